"""The envelope campaign: one MFC gain set against a PID retuned for every vehicle.

The question
------------
What does careful retuning buy a PID user, vehicle by vehicle, and how close
does one shipped MFC configuration, never retuned, come to it? Vehicles come
from the envelope generator (:mod:`sitl.envelope`: named corners plus a Latin
hypercube over mass, arm length, thrust-to-weight and motor time constant),
optionally with damage variants (``motor60``, ``imbalance``, ``cg10``).

Per vehicle and case (one task each on the lab's Dask executor)
------------------------------------------------------------
1. **Tune** the PID on the *training* scenario (default ``train-acro``) with
   the vehicle's own profile: :func:`sitl.lab.pidtune.tune_pid` from PX4's
   defaults, ``tune_budget`` flights, the campaign's ``seed``. Damaged vehicles
   are retuned on the damaged plant, as a PID user would.
2. **Fly the test scenario** (default ``envelope-test``, never used for
   tuning) three times:

   ``mfc``
       The shipped MFC file, given the F450's profile (its mixer geometry):
       the controller is never told which vehicle it flies.
   ``pid_tuned``
       The tuned PID, given the vehicle's own profile.
   ``pid_default``
       PX4's default PID (``companion/data/pid_px4_default.yaml``), the floor.

3. **The oracle** (:mod:`sitl.lab.oracle`: the plant and its true state known)
   flies the test scenario too: the limit the ratios are read against. Where a
   controller crashed, the oracle that may also set the collective judges
   whether the case was feasible.
4. **Ratios** per axis: MFC MAE over the tuned PID's MAE
   (``ratio_mfc_tuned``), over the default PID's (``ratio_mfc_default``) and
   over the oracle's (``ratio_mfc_oracle``).

Targets (:data:`RATIO_TARGET`)
------------------------------
* MFC crashes nowhere in the envelope.
* ``ratio_mfc_tuned <= 1.25`` on every vehicle, case and axis.
* MFC better than PX4's default PID on every vehicle, case and axis
  (``ratio_mfc_default < 1``).
* against the tuned PID, on the worst axis of each feasible case
  (:data:`sitl.lab.envelope_setup.WORST_TARGET`, ``P90_TARGET``): the worst
  case <= 1.1, the 90th percentile <= 1.0.

A (case, axis) where MFC crashed fails both comparisons; one where only the PID
crashed passes it (MFC flew, the PID did not). Ratios of crashed flights are
still recorded (MAE up to the crash) but do not decide the verdicts.

Determinism: every flight is deterministic (the scenario's seed) and the search
is seeded, records come back in case order: the same arguments give the same
records whatever the number of workers.

Outputs (:func:`write_envelope_outputs`): ``envelope.json`` (``meta``,
``verdicts``, ``records``), ``envelope.parquet`` (the same flights, one row
each: :data:`sitl.lab.table.ENVELOPE_SCHEMA`), ``summary.md``, ``ratio.png`` and, for the worst
cases, ``worst-<vehicle>-<case>.png`` (re-flown: commanded against measured
rate for MFC and the tuned PID).

Modules: this one runs the campaign and writes its files; the cases and setup
are in :mod:`sitl.lab.envelope_setup`, the verdicts in
:mod:`sitl.lab.envelope_verdicts`, ``summary.md`` in
:mod:`sitl.lab.envelope_report` and the plots in :mod:`sitl.lab.envelope_plots`.
Their public names are importable from here too.
"""

from __future__ import annotations

import json
import logging
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from companion.config import MfcConfig, PidConfig
from companion.control import AXES
from companion.profile import VehicleProfile
from sitl.lab.envelope_plots import plot_ratio, plot_worst
from sitl.lab.envelope_report import summary_markdown
from sitl.lab.envelope_setup import (
    CONTROLLERS,
    RATIO_TARGET,
    EnvelopeCase,
    EnvelopeSetup,
)
from sitl.lab.envelope_verdicts import verdicts, worst_cases
from sitl.lab.pidtune import tune_pid
from sitl.scenario import Scenario

if TYPE_CHECKING:
    from sitl.lab.campaign_store import CampaignStore

__all__ = [
    "CASES_DIR",
    "ENVELOPE_FILES",
    "RUN_MANIFEST",
    "case_ids",
    "envelope_meta",
    "run_envelope",
    "write_envelope_outputs",
]

_log = logging.getLogger(__name__)

ENVELOPE_FILES = ("envelope.json", "envelope.parquet", "summary.md", "ratio.png", "worst-*.png")
"""What :func:`write_envelope_outputs` writes into its folder (names or patterns)."""


def _test_flight(
    plant: VehicleProfile,
    cfg: MfcConfig | PidConfig,
    scenario: Scenario,
    controller_profile: VehicleProfile | None,
) -> dict[str, Any]:
    from sitl.lab.report import compute_metrics
    from sitl.lab.simulate import simulate_flight

    m = compute_metrics(
        simulate_flight(plant, cfg, scenario, controller_profile=controller_profile)
    )
    return {k: m[k] for k in ("mae_deg_s", "crashed", "crashed_at_s", "sim_time_s")}


def _ratio(num: float | None, den: float | None) -> float | None:
    if num is None or den is None or den <= 0.0:
        return None
    return round(num / den, 4)


def _run_case(job: tuple[EnvelopeSetup, EnvelopeCase]) -> dict[str, Any]:
    """Tune, then fly the test scenario three times and the oracle once (a top-level
    function, for the Pool)."""
    setup, case = job
    from sitl.envelope import peak_angular_accel_rad_s2

    result, _ = tune_pid(
        case.profile,
        setup.train,
        budget=setup.tune_budget,
        seed=setup.seed,
        workers=1,
        start=setup.pid_default,
    )
    flights = {
        "mfc": _test_flight(case.profile, setup.mfc, setup.test, setup.controller_profile),
        "pid_tuned": _test_flight(case.profile, result.config, setup.test, None),
        "pid_default": _test_flight(case.profile, setup.pid_default, setup.test, None),
    }
    mae = {c: flights[c]["mae_deg_s"] for c in CONTROLLERS}
    from sitl.lab.oracle import oracle_flight

    # The limit: the oracle that knows the plant and sees its true state, on the
    # same test flight (sitl.lab.oracle).
    oracle: dict[str, Any] | None = None
    if setup.oracle:
        om = oracle_flight(case.profile, setup.test)
        oracle = {k: om[k] for k in ("mae_deg_s", "crashed", "crashed_at_s", "sim_time_s")}
    feasible = True
    if any(f["crashed"] for f in flights.values()):
        # Could any controller have flown it? The oracle that may also set the
        # collective is the judge.
        feasible = not oracle_flight(case.profile, setup.test, collective=True)["crashed"]
    return {
        "vehicle": case.vehicle,
        "case": case.case,
        "vehicle_info": case.info,
        "peak_accel_flown_rad_s2": list(peak_angular_accel_rad_s2(case.profile)),
        "flights": flights,
        "feasible": feasible,
        "ratio_mfc_tuned": {a: _ratio(mae["mfc"][a], mae["pid_tuned"][a]) for a in AXES},
        "ratio_mfc_default": {a: _ratio(mae["mfc"][a], mae["pid_default"][a]) for a in AXES},
        "oracle": oracle,
        "ratio_mfc_oracle": (
            None
            if oracle is None
            else {a: _ratio(mae["mfc"][a], oracle["mae_deg_s"][a]) for a in AXES}
        ),
        "tuned_gains": dict(result.params),
        "tune": {
            "flights": result.flights,
            "train_objective_deg_s": result.objective_deg_s,
            "start_objective_deg_s": result.start_objective_deg_s,
        },
    }


RUN_MANIFEST = "envelope-run.json"
"""The manifest of an envelope run in its folder (the cases' digest)."""
CASES_DIR = "cases"
"""Where each finished case's record is stored as it completes."""


def case_ids(cases: Sequence[EnvelopeCase], setup: EnvelopeSetup) -> list[str]:
    """Each case's id: a digest of the case (vehicle, case, plant) and of the setup
    (controllers, scenarios, budget, seed): a changed input never reuses a record."""
    from sitl.lab.campaign_store import _digest

    common = _digest(
        {
            "mfc": setup.mfc.model_dump(mode="json"),
            "pid_default": setup.pid_default.model_dump(mode="json"),
            "controller_profile": setup.controller_profile.model_dump(mode="json"),
            "train": setup.train.model_dump(mode="json"),
            "test": setup.test.model_dump(mode="json"),
            "tune_budget": setup.tune_budget,
            "seed": setup.seed,
            "oracle": setup.oracle,
        }
    )
    return [
        _digest(
            {
                "setup": common,
                "vehicle": c.vehicle,
                "case": c.case,
                "profile": c.profile.model_dump(mode="json"),
            }
        )[:20]
        for c in cases
    ]


def run_envelope(
    cases: Sequence[EnvelopeCase],
    setup: EnvelopeSetup,
    *,
    workers: int | None = 1,
    progress: bool = True,
    scheduler: str | None = None,
    store: CampaignStore | None = None,
) -> list[dict[str, Any]]:
    """Tune and fly every case on a Dask cluster (:mod:`sitl.lab.executor`), with a
    tqdm bar on stderr.

    Parameters
    ----------
    cases
        From :func:`envelope_cases`.
    setup
        Controllers, scenarios, tuning budget and seed.
    workers, scheduler
        ``workers`` local worker processes (at most one per case), or the running
        cluster at ``scheduler``.
    progress
        Show the bar.
    store
        Each finished case's record is written there as it completes
        (``cases/<case id>.json``, :func:`case_ids`); cases already there are not
        flown again. None keeps them in memory only.

    Returns
    -------
    list of dict
        One record per case, in case order: ``vehicle``, ``case``,
        ``vehicle_info``, ``peak_accel_flown_rad_s2``, ``flights`` (per
        controller of :data:`CONTROLLERS`: ``mae_deg_s`` per axis, ``crashed``,
        ``crashed_at_s``, ``sim_time_s``), ``feasible`` (False when a controller
        crashed and the oracle that may also set the collective crashes too:
        no controller could fly the case), ``oracle`` (the oracle's flight:
        ``mae_deg_s``, ``crashed``, ``crashed_at_s``, ``sim_time_s``),
        ``ratio_mfc_tuned``, ``ratio_mfc_default`` and ``ratio_mfc_oracle`` per
        axis (None when undefined), ``tuned_gains``
        (:data:`sitl.lab.pidtune.PARAMS`) and ``tune`` (flights, training
        objective before and after, deg/s).
    """
    from sitl.lab.executor import Executor, TaskOutcome

    ids = case_ids(cases, setup)
    done: dict[str, dict[str, Any]] = store.load(CASES_DIR, ids) if store else {}
    todo = [i for i, cid in enumerate(ids) if cid not in done]

    def keep(o: TaskOutcome) -> None:
        i = todo[o.index]
        if not o.ok:  # a case is many flights: one that raised stops the campaign
            raise RuntimeError(f"envelope case {cases[i].vehicle} / {cases[i].case}: {o.error}")
        if store:
            store.save(CASES_DIR, ids[i], o.value)
        done[ids[i]] = o.value

    if todo:
        n = min(workers or os.cpu_count() or 1, len(todo))
        with Executor(scheduler, n) as ex:
            if scheduler is not None:
                _log.info("envelope on %s: dashboard %s", scheduler, ex.dashboard_link)
            ex.run(
                _run_case, ((setup, cases[i]) for i in todo), on_result=keep, total=len(todo),
                tally=lambda r: "mfc crashed" if r["flights"]["mfc"]["crashed"] else None,
                desc="envelope", unit="case", progress=progress,
            )  # fmt: skip
    return [done[cid] for cid in ids]


def _scenario_meta(sc: Scenario) -> dict[str, Any]:
    return {
        "name": sc.name,
        "seed": sc.seed,
        "duration_s": sc.duration_s,
        "pilot": sc.pilot,
        "link": sc.link.describe(),
    }


def envelope_meta(
    cases: Sequence[EnvelopeCase], setup: EnvelopeSetup, **extra: Any
) -> dict[str, Any]:
    """The ``meta`` block of ``envelope.json``: what was flown, how, and ``extra`` keys."""
    vehicles = list(dict.fromkeys(c.vehicle for c in cases))
    damaged = list(dict.fromkeys(c.vehicle for c in cases if c.case != "intact"))
    return {
        "vehicles": len(vehicles),
        "cases": len(cases),
        "damaged_vehicles": damaged,
        "damage_retuned": True,
        "train_scenario": _scenario_meta(setup.train),
        "test_scenario": _scenario_meta(setup.test),
        "tune_budget": setup.tune_budget,
        "tune_seed": setup.seed,
        "mfc_controller_profile": setup.controller_profile.name,
        "ratio_target": RATIO_TARGET,
        **extra,
    }


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_") or "case"


def write_envelope_outputs(
    records: Sequence[dict[str, Any]],
    out_dir: str | Path,
    meta: dict[str, Any],
    *,
    setup: EnvelopeSetup | None = None,
    cases: Sequence[EnvelopeCase] = (),
    worst_k: int = 3,
) -> dict[str, Path]:
    """Write ``envelope.parquet``, ``envelope.json``, ``summary.md``, ``ratio.png`` and
    the worst-case plots (``envelope.json`` last: its presence marks a finished run).

    Parameters
    ----------
    records
        From :func:`run_envelope`.
    out_dir
        Created if missing.
    meta
        From :func:`envelope_meta` (plus wall time, workers, ...).
    setup, cases
        Needed to re-fly the worst cases; without them no ``worst-*.png`` is drawn.
    worst_k
        How many worst cases (by worst-axis ratio, MFC crashes first) to plot.

    Returns
    -------
    dict
        ``json``, ``table``, ``summary``, ``plot`` and ``worst-<vehicle>-<case>`` paths.
    """
    from sitl.lab.table import envelope_table, write_table

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "json": out / "envelope.json",
        "table": write_table(envelope_table(records), out / "envelope.parquet"),
        "summary": out / "summary.md",
        "plot": out / "ratio.png",
    }
    images: dict[tuple[str, str], str] = {}
    if setup is not None and worst_k > 0:
        by_key = {(c.vehicle, c.case): c for c in cases}
        for rec in worst_cases(records, worst_k):
            k = (rec["vehicle"], rec["case"])
            if k not in by_key:
                _log.warning("no profile for worst case %s / %s; not plotted", *k)
                continue
            name = f"worst-{_slug(rec['vehicle'])}-{_slug(rec['case'])}"
            paths[name] = plot_worst(rec, by_key[k], setup, out / f"{name}.png")
            images[k] = f"{name}.png"
    paths["summary"].write_text(
        summary_markdown(records, meta, worst_images=images), encoding="utf-8"
    )
    plot_ratio(records, paths["plot"])
    doc = {"meta": meta, "verdicts": verdicts(records), "records": list(records)}
    paths["json"].write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    return paths
