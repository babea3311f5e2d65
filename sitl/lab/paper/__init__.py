"""Reproduce the paper's Section IV in simulation: four flights and the PID comparison.

Usage::

    python scripts/reproduce_paper.py --out runs/paper          # full 60 s flights
    python scripts/reproduce_paper.py --out /tmp/paper --quick  # 15 s slices (smoke test)

Every flight is ``paper-acro`` (the frozen test flight), flown in process
(:func:`sitl.lab.simulate.simulate_flight`, no MAVLink). The controllers are the
shipped files, loaded as they are; nothing is tuned here:

* MFC: ``companion/data/mfc_default.yaml`` (one gain set, never retuned), on the
  F450 (IV-A), the F450 with cut propellers (IV-B) and the Tarot 650 with the
  stuck landing gear (IV-C);
* the Tarot-tuned PID: ``companion/data/pid_tarot_tuned.yaml``, made by
  ``sitl/lab/pidtune.py`` on ``train-acro`` (never on ``paper-acro``), flown on
  the Tarot and then, unchanged, on the F450 (IV-D);
* the scoreboard: on each paper vehicle, a PID tuned on that very vehicle by the
  same tuner on ``train-acro`` (``pid_f450_tuned.yaml``, ``pid_f450_cut_props_tuned.yaml``;
  the Tarot's is the Tarot-tuned one) and the oracle (:mod:`sitl.lab.oracle`: the
  plant and its true state known), flown on the same scenario and measured the
  same way; MFC's MAE over each, per axis, leads ``results.md``. Where any
  controller crashed, the oracle that may also set the collective judges whether
  the case was feasible at all;
* as context: PX4's default PID on each vehicle, and the tuned PID on the
  cut-prop F450.

Writes ``OUT/results.json``, ``OUT/results.md`` (the per-axis MAE table beside
the paper's figures and a comparison text generated from the numbers) and, per
flight, ``OUT/<flight>/`` (``metrics.json``, ``report.md``, ``rates.png``,
``motors_and_estimate.png``, ``flight.npz``).

Each flight's metrics are stored in ``OUT/records/`` as it lands, keyed by a
digest of what decides it (the flight, the profile's and the controller's
content, the scenario, ``--quick`` and ``--link``); a run that was killed is
resumed by the same command, which flies only what is missing. A finished run
(``results.json`` written) is flown afresh.
"""

# The modules, by concern:
#   flights   the fourteen flights, their scenario, their keys, and flying one (a worker)
#   analysis  what the motion allows: the acceleration floor, the ideal tracker, the gyro
#             filter, the link's round trip, the error after fast stick changes, input gains
#   scoring   the scoreboard against the oracle and the vehicle's own PID, feasibility (the
#             oracle with the collective), and the paper's claims judged from the numbers
#   prose     results.md and the console summary, the explanations generated from the numbers
#   run       one run: resume, fly what is missing, assemble and write the results
# scripts/reproduce_paper.py is the command line; the tests import these modules.
