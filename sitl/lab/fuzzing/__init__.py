"""Fuzzing the product with the bundled simulator: malformed MAVLink in flight
(:mod:`sitl.lab.fuzzing.mavlink`) and mutated controller configs
(:mod:`sitl.lab.fuzzing.config`).

Lab equipment, as the rest of :mod:`sitl.lab`: it flies ``companion`` against the
SITL and the product imports nothing of it. ``scripts/fuzz.py`` is its command line;
the tests import it from here.
"""
