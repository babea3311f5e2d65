"""The laboratory: simulated flights, campaigns, the envelope, PID tuning, reports.

Everything here flies the bundled simulator (software in the loop), so it lives
beside the plant in ``sitl``; it may import the product (``companion``) and the
plant, and nothing in the product imports it. Its command-line entry points are
``companion`` subcommands (see :mod:`sitl.lab.cli`).
"""
