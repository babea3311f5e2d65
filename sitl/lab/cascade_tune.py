"""PX4's cascade retuned for each vehicle: the outer loops' per-vehicle baseline.

The outer loops are compared as the rate loop is: MFC with one config for every
vehicle, against PX4's default cascade (:mod:`sitl.lab.cascade_pid`) and against
that cascade retuned for each vehicle. This module does the retuning.

Search
------
A seeded random search over the cascade's loop gains (:data:`TUNED_FIELDS`),
each drawn log-uniformly within [1/:data:`SPAN`, :data:`SPAN`] times PX4's
default, ``budget`` candidates per vehicle, PX4's default among them; the rate
loop under it is PX4's default rate PID. The cost of a candidate is the sum, over
the training flights, of the horizontal and vertical position RMS errors (m), a
crash costing infinity. The training flights are the position hold and the
square of :data:`sitl.lab.outer_flight.SCENARIOS`, flown with
:data:`TRAIN_SEED`: another wind, other sensor and estimator errors than the
test flights' (the scenarios' own seed), so the comparison is not on the data
the gains were chosen on.

Usage::

    python -m sitl.lab.cascade_tune --profiles f450,x500 --budget 24 --out runs/cascade-tuned.json
    python -m sitl.lab.cascade_tune --compare runs/cascade-tuned.json --seeds 3 --workers 2

``--compare`` flies the test flights (the table's scenarios with their own
seed) with the MFC cascade and each vehicle's tuned PX4 cascade and prints the
ratios (below 1: MFC better; the target: at most 1.25).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from collections.abc import Sequence
from importlib.resources import files
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import PidConfig, load_controller
from sitl.lab.cascade_pid import PX4_DEFAULT_CASCADE, CascadeGains
from sitl.lab.outer_sweep import check_mfc_gyro_hz

__all__ = ["SPAN", "TRAIN_SEED", "TUNED_FIELDS", "candidates", "train_cost", "tune_vehicle"]

TUNED_FIELDS = (
    "roll_p_1_s", "pitch_p_1_s", "xy_p_1_s", "z_p_1_s", "xy_vel_p_1_s", "z_vel_p_1_s",
    "xy_vel_i_1_s2", "z_vel_i_1_s2", "xy_vel_d",
)  # fmt: skip
"""The gains searched (PX4's MC_ROLL_P, MC_PITCH_P, MPC_XY_P, MPC_Z_P, MPC_XY_VEL_P_ACC,
MPC_Z_VEL_P_ACC, MPC_XY_VEL_I_ACC, MPC_Z_VEL_I_ACC, MPC_XY_VEL_D_ACC)."""
SPAN = 2.5
"""Each gain within [default / SPAN, default * SPAN]."""
TRAIN_SEED = 4242
"""The training flights' seed (the test flights use their scenario's)."""
TRAIN_SCENARIOS = ("position-hold", "square")
TEST_SCENARIOS = (
    "altitude-steps", "position-hold", "square", "square-fast", "figure-eight", "figure-eight-fast",
)  # fmt: skip


def _px4_rates() -> PidConfig:
    cfg = load_controller(str(files("companion") / "data" / "pid_px4_default.yaml"))
    assert isinstance(cfg, PidConfig)
    return cfg


def candidates(budget: int, seed: int) -> list[CascadeGains]:
    """PX4's default, then ``budget - 1`` draws (module docstring)."""
    rng = np.random.default_rng(seed)
    out = [PX4_DEFAULT_CASCADE]
    for _ in range(max(0, budget - 1)):
        scale = np.exp(rng.uniform(-math.log(SPAN), math.log(SPAN), len(TUNED_FIELDS)))
        out.append(
            dataclasses.replace(
                PX4_DEFAULT_CASCADE,
                **{
                    f: getattr(PX4_DEFAULT_CASCADE, f) * float(s)
                    for f, s in zip(TUNED_FIELDS, scale, strict=True)
                },
            )
        )
    return out


def _fly(
    profile_name: str,
    scenario: str,
    seed: int,
    law: str,
    gains: CascadeGains,
    gyro_hz: float | None = None,
) -> dict[str, Any]:
    from companion.config import DEFAULT_CONTROLLER
    from sitl.lab.outer_flight import SCENARIOS, _profile, outer_metrics, simulate_outer_flight

    sc = SCENARIOS[scenario]
    rates = _px4_rates() if law == "px4" else load_controller(DEFAULT_CONTROLLER)
    flight = simulate_outer_flight(
        _profile(profile_name), rates, sc, seed=seed, outer_law=law, cascade_gains=gains,
        gyro_hz=gyro_hz,
    )  # fmt: skip
    return outer_metrics(flight, sc)


def train_cost(item: tuple[str, CascadeGains]) -> float:
    """A candidate's cost on the training flights (module docstring); a top-level
    function, for the workers."""
    profile_name, gains = item
    total = 0.0
    for sc in TRAIN_SCENARIOS:
        m = _fly(profile_name, sc, TRAIN_SEED, "px4", gains)
        if m["crashed"] or m["pos_rms_h_m"] is None:
            return math.inf
        total += float(m["pos_rms_h_m"]) + float(m["pos_rms_v_m"])
    return total


def tune_vehicle(profile_name: str, budget: int, seed: int, workers: int = 1) -> dict[str, Any]:
    """The best of ``budget`` candidates for one vehicle, and the default's cost."""
    from sitl.lab.executor import run_tasks

    cands = candidates(budget, seed)
    outcomes = run_tasks(
        train_cost, [(profile_name, g) for g in cands], workers=workers,
        desc=f"tune {profile_name}", unit="candidate",
    )  # fmt: skip
    costs = [o.value if o.ok else math.inf for o in outcomes]
    best = int(np.argmin(costs))
    return {
        "gains": {f: getattr(cands[best], f) for f in TUNED_FIELDS},
        "train_cost_m": costs[best],
        "default_train_cost_m": costs[0],
        "budget": budget,
        "seed": seed,
    }


COMPARED = ("pos_rms_h_m", "pos_rms_v_m", "pos_max_h_m", "path_rms_m", "att_mae_deg")
"""The test flights' figures compared (each an error: lower is better)."""


def compare(
    tuned: dict[str, Any],
    *,
    seeds: int = 1,
    workers: int = 1,
    mfc_gyro_hz: float | None = None,
) -> list[dict[str, Any]]:
    """MFC's and each vehicle's tuned PX4 cascade's test flights, with their ratios:
    every test scenario on ``seeds`` seeds (its own and the next ones), the MFC on
    the gyro as PX4 sends it at ``mfc_gyro_hz`` where given (the outer sweep's
    ``--mfc-gyro-hz``)."""
    from sitl.lab.executor import run_tasks
    from sitl.lab.outer_flight import SCENARIOS

    if seeds < 1:
        raise ValueError(f"seeds: expected at least 1, got {seeds}")
    cases = [
        (vehicle, sc, SCENARIOS[sc].seed + i, t["gains"], mfc_gyro_hz)
        for vehicle, t in tuned["vehicles"].items()
        for sc in TEST_SCENARIOS
        for i in range(seeds)
    ]
    outcomes = run_tasks(compare_case, cases, workers=workers, desc="compare", unit="case")
    outcomes = sorted(outcomes, key=lambda o: o.index)
    failed = [f"{o.item[0]}/{o.item[1]}/{o.item[2]}: {o.error}" for o in outcomes if not o.ok]
    if failed:
        raise RuntimeError("compare: flights raised: " + "; ".join(failed))
    return [o.value for o in outcomes]


def compare_case(case: tuple[str, str, int, dict[str, float], float | None]) -> dict[str, Any]:
    """One test case of :func:`compare`, both laws (a top-level function, for the workers)."""
    vehicle, sc, seed, tuned_gains, gyro_hz = case
    gains = dataclasses.replace(PX4_DEFAULT_CASCADE, **tuned_gains)
    mfc = _fly(vehicle, sc, seed, "mfc", PX4_DEFAULT_CASCADE, gyro_hz)
    px4 = _fly(vehicle, sc, seed, "px4", gains)
    row: dict[str, Any] = {"vehicle": vehicle, "scenario": sc, "seed": seed}
    for k in COMPARED:
        a, b = mfc[k], px4[k]
        row[k] = (a, b, None if a is None or not b else a / b)
    row["crashed"] = (mfc["crashed"], px4["crashed"])
    return row


def _table(rows: Sequence[dict[str, Any]]) -> str:
    keys = COMPARED
    lines = [
        "| vehicle | scenario | seed | " + " | ".join(keys) + " | crash MFC / tuned |",
        "|---|---|---|" + "---|" * len(keys) + "---|",
    ]

    def cell(v: tuple[Any, Any, Any]) -> str:
        a, b, r = v
        if a is None:
            return "-"
        return f"{a:.2f} / {b:.2f} ({r:.2f})" if r is not None else f"{a:.2f} / {b:.2f}"

    for r in rows:
        crash = " / ".join("yes" if c else "no" for c in r["crashed"])
        lines.append(
            f"| {r['vehicle']} | {r['scenario']} | {r['seed']} | "
            + " | ".join(cell(r[k]) for k in keys)
            + f" | {crash} |"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--profiles", default="f450,f450_cut_props,tarot650,x500")
    ap.add_argument("--budget", type=int, default=24, help="candidates per vehicle")
    ap.add_argument("--seed", type=int, default=1, help="seeds the search")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("runs/cascade-tuned.json"))
    ap.add_argument("--compare", type=Path, default=None, help="a tuned file: fly the test")
    ap.add_argument(
        "--seeds", type=int, default=1, help="--compare: each test case on this many seeds"
    )
    ap.add_argument(
        "--mfc-gyro-hz",
        type=float,
        default=None,
        metavar="HZ",
        help="--compare: the MFC flies the gyro as PX4 sends it at HZ (as the outer sweep's)",
    )
    args = ap.parse_args(argv)
    if args.seeds < 1:
        ap.error(f"--seeds: expected at least 1, got {args.seeds}")
    check_mfc_gyro_hz(ap, args.mfc_gyro_hz)
    if args.compare is not None:
        tuned = json.loads(args.compare.read_text(encoding="utf-8"))
        rows = compare(tuned, seeds=args.seeds, workers=args.workers, mfc_gyro_hz=args.mfc_gyro_hz)
        print(_table(rows))
        return 0
    if args.budget < 1:
        ap.error("--budget: at least 1")
    vehicles = {}
    for name in [p.strip() for p in args.profiles.split(",") if p.strip()]:
        vehicles[name] = tune_vehicle(name, args.budget, args.seed, args.workers)
        v = vehicles[name]
        print(
            f"{name}: train cost {v['train_cost_m']:.3f} m (PX4 default "
            f"{v['default_train_cost_m']:.3f} m); gains "
            + ", ".join(f"{k} {x:.3g}" for k, x in v["gains"].items()),
            flush=True,
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    doc = {"train_seed": TRAIN_SEED, "train_scenarios": list(TRAIN_SCENARIOS), "vehicles": vehicles}
    args.out.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
