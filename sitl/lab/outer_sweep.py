"""The outer loops over vehicles, damage and scenarios, with crashes classified.

Every bundled outer scenario (:data:`sitl.lab.outer_flight.SCENARIOS`) on each
vehicle, intact and with one motor degraded, flown by the MFC cascade (the
shipped config over the shipped MFC rate loop) and by PX4's default cascade
(over PX4's default rate PID), on the estimator's output as in the product.

Feasibility. Wherever either law crashes, both are flown again on the true
state (the estimator replaced by :data:`sitl.estimator_model.PERFECT`: no error,
no lag); the case is *feasible* when either of those true-state flights
survives, and then a crash of the estimator-fed MFC counts against it. A case
where both crash on the true state too is reported as infeasible, never removed.
(The true-state pair is this study's oracle: it knows the state, not the plant.)

Seeds. A vehicle at the edge of its thrust flies a different flight on every
seed, and one seed can crash where the next does not. ``--seeds N`` flies every
case on N seeds (the scenario's, or ``--seed``, and the next ones), and each
seed is a case of its own: classified, compared and counted on its own.

The flights are tasks on :class:`sitl.lab.executor.Executor` (a local Dask
cluster, or ``--scheduler``). ``python -m sitl.lab.outer_sweep --out DIR`` writes
``DIR/flights.json`` (every flight's metrics), the same as a table,
``DIR/flights.parquet`` (:data:`sitl.lab.table.OUTER_SWEEP_SCHEMA`), and
``DIR/summary.md``. Each
flight is stored in ``DIR/flights/`` as it lands, keyed by a digest of what
decides it (:func:`flight_key`): a sweep that was killed is resumed by the same
command, which flies only what is missing; a finished one (``summary.md``
written) is moved into ``DIR/earlier-<UTC time>/`` and flown afresh.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from companion.profile import VehicleProfile

__all__ = [
    "DAMAGE",
    "SweepFlight",
    "classify",
    "flight_key",
    "fly",
    "main",
    "summary_markdown",
    "sweep_flights",
    "true_state_flights",
    "verdict",
]

DAMAGE: dict[str, float] = {"intact": 1.0, "motor80": 0.8, "motor60": 0.6}
"""Damage cases: motor 0's thrust and torque efficiency (``damaged_profile``)."""

RUN_MANIFEST = "outer-sweep-run.json"
"""The manifest of a sweep in its folder (its flights' digest), for resuming."""
RECORDS_DIR = "flights"
"""Where each flight's metrics are stored as it lands."""
OUTPUTS = ("flights.parquet", "flights.json", "summary.md")
"""What a finished sweep wrote (``summary.md`` last)."""

METRICS = ("pos_rms_h_m", "pos_rms_v_m", "path_rms_m", "att_mae_deg", "yaw_mae_deg")
"""The figures compared, MFC against PX4's default (all errors: lower is better)."""

TIE_FRACTION = 0.05
"""Two figures closer than this fraction of PX4's are a tie..."""
TIE_FLOORS = {"pos_rms_v_m": "est_floor_v_m", "att_mae_deg": "est_floor_att_deg"}
"""... or closer than the estimate's own error on that metric (the mean of the two
flights' ``outer_metrics`` floor), where it is larger: on the vertical and the
attitude both laws fly the estimate's error, which neither can see."""


def verdict(metric: str, mfc: dict[str, Any], px4: dict[str, Any]) -> str | None:
    """``"better"``, ``"tie"`` or ``"worse"`` for MFC on ``metric`` (None: not
    comparable: either crashed or has no figure)."""
    a, b = mfc.get(metric), px4.get(metric)
    if mfc["crashed"] or px4["crashed"] or a is None or b is None:
        return None
    if not (math.isfinite(a) and math.isfinite(b)):
        return None
    band = TIE_FRACTION * abs(b)
    floor_key = TIE_FLOORS.get(metric)
    if floor_key is not None:
        floors = [f for f in (mfc.get(floor_key), px4.get(floor_key)) if f is not None]
        if floors:
            band = max(band, sum(floors) / len(floors))
    if abs(a - b) < band:
        return "tie"
    return "better" if a < b else "worse"


@dataclass(frozen=True)
class SweepFlight:
    """One flight of the sweep: everything its task needs (it is pickled to a worker)."""

    vehicle: str
    damage: str
    scenario: str
    law: str
    """``mfc`` or ``px4``."""
    true_state: bool
    profile: VehicleProfile
    duration_s: float | None = None
    seed: int | None = None
    mfc_gyro_hz: float | None = None
    """When set, the MFC cascade flies the gyro as PX4 sends it to a companion at
    this rate (:func:`sitl.lab.simulate.simulate_flight`'s ``gyro_hz``); PX4's
    cascade always flies every IMU sample, as PX4 runs its own loops."""


def fly(f: SweepFlight) -> dict[str, Any]:
    """Fly one :class:`SweepFlight`; its metrics with the flight's identity."""
    from companion.config import PID_DEFAULT_CONTROLLER, load_controller
    from sitl.estimator_model import PERFECT
    from sitl.lab.outer_flight import SCENARIOS, outer_metrics, simulate_outer_flight

    sc = SCENARIOS[f.scenario]
    if f.duration_s is not None:
        sc = sc.with_duration(f.duration_s)
    if f.true_state:
        sc = replace(sc, estimator=PERFECT)
    cfg = load_controller(PID_DEFAULT_CONTROLLER) if f.law == "px4" else load_controller()
    t0 = time.perf_counter()
    gyro_hz = f.mfc_gyro_hz if f.law == "mfc" else None
    fl = simulate_outer_flight(f.profile, cfg, sc, seed=f.seed, outer_law=f.law, gyro_hz=gyro_hz)
    m = outer_metrics(fl, sc)
    m.update(
        vehicle=f.vehicle, damage=f.damage, law=f.law, true_state=f.true_state,
        wall_s=round(time.perf_counter() - t0, 2),
    )  # fmt: skip
    if gyro_hz is not None:
        m["gyro_hz"] = fl.meta["gyro_hz"]
    return m


def flight_key(f: SweepFlight) -> str:
    """The flight's key: a digest of everything that decides it (the profile by its
    content), so a changed input never reuses a stored record."""
    from sitl.lab.campaign_store import _digest

    return _digest(
        {
            "vehicle": f.vehicle,
            "damage": f.damage,
            "scenario": f.scenario,
            "law": f.law,
            "true_state": f.true_state,
            "profile": f.profile.model_dump(mode="json"),
            "duration_s": f.duration_s,
            "seed": f.seed,
            # Only where it decides the flight: the rest keep the keys they had.
            **({"gyro_hz": f.mfc_gyro_hz} if f.mfc_gyro_hz is not None and f.law == "mfc" else {}),
        }
    )[:20]


def _fly_stored(
    flights: Sequence[SweepFlight], store: Any, desc: str, run: dict[str, Any]
) -> tuple[list[dict[str, Any]], list[str]]:
    """Fly those of ``flights`` not in ``store`` yet, storing each as it lands; every
    flight's record that exists (in order), and what raised."""
    keys = [flight_key(f) for f in flights]
    done, outcomes = store.run_missing(RECORDS_DIR, keys, fly, flights, desc=desc, **run)
    errors = [f"{o.item.vehicle}/{o.item.damage}/{o.item.scenario}/{o.item.law}"
              f"{' (true state)' if o.item.true_state else ''}: {o.error}"
              for o in outcomes if not o.ok]  # fmt: skip
    return [done[k] for k in keys if k in done], errors


def vehicles(names: Sequence[str], corners: bool) -> dict[str, VehicleProfile]:
    """The vehicles by name: bundled profiles, then (``corners``) the envelope's corners."""
    from sitl.envelope import corners as envelope_corners
    from sitl.lab.outer_flight import _profile

    out = {n: _profile(n) for n in names}
    if corners:
        out.update({v.name: v.profile() for v in envelope_corners()})
    return out


def _flown_seed(scenario: str, seed: int | None) -> int:
    """The seed ``scenario`` is flown on given ``seed`` (None: the scenario's own)."""
    from sitl.lab.outer_flight import SCENARIOS

    return SCENARIOS[scenario].seed if seed is None else seed


def _seeds(scenario: str, seed: int | None, seeds: int) -> list[int | None]:
    """The seeds a scenario is flown on: ``seed`` (None: the scenario's own) and the
    next ``seeds - 1``; one seed stays ``seed`` as given, so its flights' keys are
    those of a sweep flown before ``--seeds``."""
    if seeds == 1:
        return [seed]
    first = _flown_seed(scenario, seed)
    return [first + k for k in range(seeds)]


def sweep_flights(
    fleet: dict[str, VehicleProfile],
    scenarios: Sequence[str],
    damage: Sequence[str],
    *,
    true_state: bool = False,
    laws: Sequence[str] = ("mfc", "px4"),
    duration_s: float | None = None,
    seed: int | None = None,
    seeds: int = 1,
    mfc_gyro_hz: float | None = None,
) -> list[SweepFlight]:
    """Every (vehicle, damage, scenario, seed, law), damage applied to motor 0."""
    from sitl.lab.campaign import damaged_profile

    if seeds < 1:
        raise ValueError(f"seeds: expected at least 1, got {seeds}")
    out = []
    for name, prof in fleet.items():
        for d in damage:
            p = damaged_profile(prof, DAMAGE[d])
            for sc in scenarios:
                for s in _seeds(sc, seed, seeds):
                    for law in laws:
                        out.append(
                            SweepFlight(name, d, sc, law, true_state, p, duration_s, s, mfc_gyro_hz)
                        )
    return out


def true_state_flights(
    records: Sequence[dict[str, Any]],
    fleet: dict[str, VehicleProfile],
    scenarios: Sequence[str],
    damage: Sequence[str],
    **kw: Any,
) -> list[SweepFlight]:
    """Both laws on the true state, for every case (and seed) where either crashed in
    ``records``."""
    crashed = {_key(r) for r in records if r["crashed"] and not r["true_state"]}
    return [
        f
        for f in sweep_flights(fleet, scenarios, damage, true_state=True, **kw)
        if (f.vehicle, f.damage, f.scenario, _flown_seed(f.scenario, f.seed)) in crashed
    ]


Case = tuple[str, str, str, int | None]
"""A case: vehicle, damage, scenario and the seed flown (None: a record without one)."""


def _key(r: dict[str, Any]) -> Case:
    return (r["vehicle"], r["damage"], r["scenario"], r.get("seed"))


def _case_name(k: Case, *, seeded: bool = False) -> str:
    """``vehicle/damage/scenario``, and ``(seed N)`` when ``seeded``."""
    name = "/".join(k[:3])
    return f"{name} (seed {k[3]})" if seeded else name


def classify(records: Sequence[dict[str, Any]]) -> dict[Case, dict[str, Any]]:
    """Per case: each law's crash on the estimate and on the true state, and feasibility."""
    cases: dict[Case, dict[tuple[str, bool], dict[str, Any]]] = {}
    for r in records:
        c = cases.setdefault(_key(r), {})
        c[(r["law"], r["true_state"])] = r
    out = {}
    for k, c in cases.items():
        crashed: dict[tuple[str, bool], bool] = {lt: bool(r["crashed"]) for lt, r in c.items()}
        any_crash = crashed.get(("mfc", False), False) or crashed.get(("px4", False), False)
        truth = [v for (_, ts), v in crashed.items() if ts]
        feasible = True if not any_crash else (not all(truth) if truth else None)
        out[k] = {"flights": c, "crashed": crashed, "feasible": feasible}
    return out


def _ratio(a: float | None, b: float | None) -> float | None:
    if a is None or b is None or not math.isfinite(a) or not math.isfinite(b):
        return None
    if b == 0.0:
        return None if a == 0.0 else math.inf
    return float(a / b)


def summary_markdown(records: Sequence[dict[str, Any]]) -> str:
    """The verdicts, then one row per case (MFC / PX4 on each metric)."""
    cases = classify(records)
    feasible = [c for c in cases.values() if c["feasible"]]
    mfc_crash = [k for k, c in cases.items() if c["feasible"] and c["crashed"].get(("mfc", False))]
    px4_crash = [k for k, c in cases.items() if c["feasible"] and c["crashed"].get(("px4", False))]
    infeasible = [k for k, c in cases.items() if c["feasible"] is False]
    seeded = len({k[3] for k in cases}) > 1

    def names(ks: list[Case]) -> str:
        return ", ".join(_case_name(k, seeded=seeded) for k in ks)

    lines = [
        f"{len(cases)} cases, {len(records)} flights; {len(feasible)} feasible, "
        f"{len(infeasible)} infeasible (both laws crash on the true state too).",
        "",
        f"- **MFC crashes on a feasible case: {len(mfc_crash)}**"
        + (": " + names(mfc_crash) if mfc_crash else ""),
        f"- PX4's default cascade crashes on a feasible case: {len(px4_crash)}"
        + (": " + names(px4_crash) if px4_crash else ""),
    ]
    if infeasible:
        lines.append("- Infeasible: " + names(infeasible))
    gyro = sorted({r["gyro_hz"] for r in records if r.get("gyro_hz") is not None})
    if gyro:
        lines.append(
            "- The MFC flew the gyro as PX4 sends it to a companion, at "
            + ", ".join(f"{g:g}" for g in gyro)
            + " Hz (every n-th IMU sample, the mean of the last n); PX4's cascade flew"
            " every sample"
        )
    better: dict[str, list[int]] = {m: [0, 0] for m in METRICS}
    verdicts: dict[str, dict[str, int]] = {m: {"better": 0, "tie": 0, "worse": 0} for m in METRICS}
    rows = []
    for k, c in sorted(cases.items()):
        mf, px = c["flights"].get(("mfc", False)), c["flights"].get(("px4", False))
        if mf is None or px is None:
            continue
        cells = []
        for m in METRICS:
            r = None if mf["crashed"] or px["crashed"] else _ratio(mf.get(m), px.get(m))
            if r is not None:
                better[m][0] += r < 1.0
                better[m][1] += 1
            v = verdict(m, mf, px)
            if v is not None:
                verdicts[m][v] += 1
            cells.append("-" if r is None else f"{r:.2f}")
        crash = "MFC" if mf["crashed"] else ""
        crash += ("+" if crash and px["crashed"] else "") + ("PX4" if px["crashed"] else "")
        feas = {True: "yes", False: "no", None: "?"}[c["feasible"]]
        case = " | ".join(k[:3]) + (f" | {k[3]}" if seeded else "")
        rows.append(f"| {case} | {' | '.join(cells)} | {crash or '-'} | {feas} |")
    lines += ["", "MFC better than PX4's default (ratio below 1), cases per metric:", ""]
    lines += [f"- {m}: {b} of {n}" for m, (b, n) in better.items()]
    lines += [
        "",
        f"Better, tied (within {TIE_FRACTION:.0%} of PX4's, or the estimate's own error "
        "on the vertical and the attitude) and worse, cases per metric:",
        "",
    ]
    lines += [
        f"- {m}: {v['better']} better, {v['tie']} tied, {v['worse']} worse"
        for m, v in verdicts.items()
    ]
    lines += [
        "",
        "| vehicle | damage | scenario | "
        + ("seed | " if seeded else "")
        + " | ".join(METRICS)
        + " | crashed | feasible |",
        "|" + "---|" * (len(METRICS) + 5 + seeded),
        *rows,
    ]
    return "\n".join(lines) + "\n"


def check_mfc_gyro_hz(ap: argparse.ArgumentParser, hz: float | None) -> None:
    """``--mfc-gyro-hz`` (here and in ``cascade_tune --compare``): a rate in 1-1000 Hz."""
    if hz is not None and not 1.0 <= hz <= 1000.0:
        ap.error(f"--mfc-gyro-hz: expected a rate in 1-1000 Hz, got {hz:g}")


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m sitl.lab.outer_sweep``: the sweep, its flights and summary."""
    from companion.options import keep_earlier
    from sitl.lab.campaign_store import CampaignStore, grid_digest
    from sitl.lab.outer_flight import SCENARIOS, TABLE_PROFILES

    ap = argparse.ArgumentParser(
        prog="python -m sitl.lab.outer_sweep", description=__doc__.split("\n")[0]
    )
    ap.add_argument("--out", required=True, type=Path, help="output folder")
    ap.add_argument("--profiles", default=",".join(TABLE_PROFILES), help="comma-separated")
    ap.add_argument("--corners", action="store_true", help="add the envelope's five corners")
    ap.add_argument(
        "--scenarios", default=",".join(SCENARIOS), help="comma-separated (default: all)"
    )
    ap.add_argument("--damage", default=",".join(DAMAGE), help="comma-separated")
    ap.add_argument("--duration", type=float, default=None, help="flight time, s")
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument(
        "--seeds",
        type=int,
        default=1,
        help="fly each case on this many seeds, the scenario's (or --seed) and the next "
        "ones; each seed is a case of its own (default 1)",
    )
    ap.add_argument(
        "--mfc-gyro-hz",
        type=float,
        default=None,
        metavar="HZ",
        help="the MFC cascade flies the gyro as PX4 sends it to a companion at HZ: every "
        "n-th IMU sample, the mean of the last n (IMU_INTEG_RATE at HZ); the IMU, the "
        "estimator and PX4's cascade keep every sample (default: the MFC too)",
    )
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--scheduler", default=None, help="tcp://HOST:PORT of a Dask scheduler")
    args = ap.parse_args(argv)
    scenarios = [s for s in args.scenarios.split(",") if s]
    damage = [d for d in args.damage.split(",") if d]
    for s in scenarios:
        if s not in SCENARIOS:
            ap.error(f"--scenarios: {s!r} is not one of {', '.join(SCENARIOS)}")
    for d in damage:
        if d not in DAMAGE:
            ap.error(f"--damage: {d!r} is not one of {', '.join(DAMAGE)}")
    if args.seeds < 1:
        ap.error(f"--seeds: expected at least 1, got {args.seeds}")
    check_mfc_gyro_hz(ap, args.mfc_gyro_hz)
    try:
        fleet = vehicles([p for p in args.profiles.split(",") if p], args.corners)
    except (OSError, ValueError) as exc:
        ap.error(f"--profiles: {exc}")
    args.out.mkdir(parents=True, exist_ok=True)
    kw = {
        "duration_s": args.duration,
        "seed": args.seed,
        "seeds": args.seeds,
        "mfc_gyro_hz": args.mfc_gyro_hz,
    }
    run = {"scheduler": args.scheduler, "workers": args.workers, "unit": "flight"}
    flights = sweep_flights(fleet, scenarios, damage, **kw)
    store = CampaignStore(args.out, manifest=RUN_MANIFEST, finished=OUTPUTS[-1])
    keys = [flight_key(f) for f in flights]
    grid = grid_digest(keys)
    if store.can_resume(grid):
        n = len(store.load(RECORDS_DIR, keys))
        print(f"resuming: {n} of {len(flights)} flights done", file=sys.stderr)
    else:
        keep_earlier(f"--out {args.out}", args.out, (*OUTPUTS, RUN_MANIFEST, RECORDS_DIR))
    store.start(grid, len(flights))
    records, errors = _fly_stored(flights, store, "outer sweep", run)
    again = true_state_flights(records, fleet, scenarios, damage, **kw)
    if again:
        more, more_errors = _fly_stored(again, store, "true state", run)
        records += more
        errors += more_errors
    from sitl.lab.table import outer_sweep_table, write_table

    feasible = {k: c["feasible"] for k, c in classify(records).items()}
    write_table(outer_sweep_table(records, feasible), args.out / "flights.parquet")
    (args.out / "flights.json").write_text(json.dumps(records, indent=1) + "\n")
    text = summary_markdown(records)
    if errors:
        text += "\nErrors:\n\n" + "".join(f"- {e}\n" for e in errors)
    (args.out / "summary.md").write_text(text)
    sys.stdout.write(text)
    return 1 if errors else 0


if __name__ == "__main__":
    raise SystemExit(main())
