"""A fair, documented auto-tuner for the rate PID: a seeded pattern search.

What it does
------------
It tunes the PID that the paper compares MFC with (Section IV-D: "a PID
controller was properly tuned and deployed on the large Tarot"). The procedure
is meant to be one a careful user could run, with the same information the MFC
gain search had:

* **One vehicle, one training flight.** Every candidate flies ``scenario`` (by
  default ``train-acro``: seeded random acro, the MFC search's training flight)
  on ``profile``, in process (:func:`sitl.lab.simulate.simulate_flight`). The
  test flight ``paper-acro`` is refused, so tuning never sees it.
* **Objective** (deg/s, lower is better): the mean (``"mean"``, default) or the
  worst (``"worst"``) of the per-axis rate MAE (pilot command against measured
  rate, while airborne; :func:`sitl.lab.report.compute_metrics`). A crash costs
  :data:`CRASH_PENALTY_DEG_S` plus the MAE flown until then, so every crash is
  worse than every flight that lands.
* **Parameters** (five, in log10 space, within :data:`BOUNDS`): roll and pitch
  share ``kp``, ``ki``, ``kd`` (the frame is symmetric, as the MFC search
  assumed); yaw has ``kp`` and ``ki`` (a PI on yaw, as the paper notes is
  usual). ``kff``, ``i_limit``, ``d_lpf_hz``, yaw ``kd`` and the stick curves
  stay as in the start file (PX4's defaults, ``companion/data/pid_px4_default.yaml``).
  Values are rounded to three significant digits before they fly, so the file
  written holds exactly the gains that were scored.
* **Search**: a compass (pattern) search from the start file. Each round flies,
  in parallel, the 2 x 5 points one step up and down each coordinate (order
  shuffled by the seeded generator) plus ``n_random`` points one step away in
  seeded random directions. The best point moves the centre if it beats the
  centre; otherwise the step halves (the first step is a factor of 2, the last
  a factor of about 1.09). Points already flown are not flown again. It stops
  when ``budget`` flights are spent or the step is below ``min_step``.
* **Deterministic** given ``seed``: flights are deterministic (the scenario's
  seed), results are gathered in submission order, and the only other
  randomness is the seeded :class:`numpy.random.Generator` of the search. The
  number of workers changes the wall time, never the answer.

Run it (this is how ``companion/data/pid_tarot_tuned.yaml`` was made)::

    python -m sitl.lab.pidtune --profile vehicle_profiles/tarot650.yaml \\
        --scenario train-acro --budget 120 --seed 1 --workers 2 \\
        --out companion/data/pid_tarot_tuned.yaml
"""

from __future__ import annotations

import argparse
import logging
import math
import multiprocessing
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from companion.config import PID_DEFAULT_CONTROLLER, PidAxes, PidConfig, load_controller
from companion.control import AXES
from companion.profile import VehicleProfile, load_profile
from sitl.scenario import Scenario, load_scenario

__all__ = [
    "BOUNDS",
    "CRASH_PENALTY_DEG_S",
    "PARAMS",
    "TEST_SCENARIOS",
    "TuneResult",
    "apply_params",
    "params_of",
    "tune_pid",
    "write_pid_yaml",
]

_log = logging.getLogger(__name__)


PARAMS: tuple[str, ...] = ("rp_kp", "rp_ki", "rp_kd", "yaw_kp", "yaw_ki")
"""Searched parameters: roll+pitch (shared) kp, ki, kd; yaw kp, ki."""

BOUNDS: dict[str, tuple[float, float]] = {
    # Normalised torque per rad/s (kp), per rad (ki), per rad/s^2 (kd). PX4's
    # defaults sit inside, about a factor of 5-10 from either edge: MC_ROLLRATE_P
    # 0.15, I 0.2, D 0.003; MC_YAWRATE_P 0.2, I 0.1.
    "rp_kp": (0.02, 1.0),
    "rp_ki": (0.02, 2.0),
    "rp_kd": (0.0003, 0.03),
    "yaw_kp": (0.02, 2.0),
    "yaw_ki": (0.01, 1.0),
}
"""Search bounds (inclusive) for each parameter in :data:`PARAMS`."""

CRASH_PENALTY_DEG_S = 1000.0
"""Added to the objective of a flight that crashed (deg/s)."""

TEST_SCENARIOS = frozenset({"paper-acro", "envelope-test"})
"""Scenarios kept as test flights: the tuner refuses to train on them."""

Objective = Literal["mean", "worst"]


@dataclass(frozen=True)
class TuneResult:
    """Best point of a search.

    Attributes
    ----------
    config
        The tuned controller (the start file with the five gains replaced).
    params
        The tuned values of :data:`PARAMS`.
    objective_deg_s
        Its objective on the training flight (deg/s).
    start_objective_deg_s
        The start file's objective on the same flight.
    flights
        Flights flown (at most the budget).
    """

    config: PidConfig
    params: dict[str, float]
    objective_deg_s: float
    start_objective_deg_s: float
    flights: int


def _round_sig(x: float, digits: int = 3) -> float:
    if x == 0.0:
        return 0.0
    return round(x, digits - 1 - math.floor(math.log10(abs(x))))


def params_of(cfg: PidConfig) -> dict[str, float]:
    """The searched parameters of a PID config (roll's values stand for roll+pitch)."""
    a = cfg.axes
    return {
        "rp_kp": a.roll.kp,
        "rp_ki": a.roll.ki,
        "rp_kd": a.roll.kd,
        "yaw_kp": a.yaw.kp,
        "yaw_ki": a.yaw.ki,
    }


def apply_params(cfg: PidConfig, params: dict[str, float]) -> PidConfig:
    """A copy of ``cfg`` with roll and pitch (shared) and yaw gains from ``params``."""
    rp = {"kp": params["rp_kp"], "ki": params["rp_ki"], "kd": params["rp_kd"]}
    axes = PidAxes(
        roll=cfg.axes.roll.model_copy(update=rp),
        pitch=cfg.axes.pitch.model_copy(update=rp),
        yaw=cfg.axes.yaw.model_copy(update={"kp": params["yaw_kp"], "ki": params["yaw_ki"]}),
    )
    # Re-validate: model_copy skips validation, and the bounds of PidAxisConfig apply.
    return PidConfig.model_validate({**cfg.model_dump(), "axes": axes.model_dump()})


def _objective(mae: dict[str, float], crashed: bool, kind: Objective) -> float:
    vals = [mae[a] if mae[a] is not None else CRASH_PENALTY_DEG_S for a in AXES]
    score = max(vals) if kind == "worst" else float(np.mean(vals))
    return score + (CRASH_PENALTY_DEG_S if crashed else 0.0)


def _fly(job: tuple[VehicleProfile, PidConfig, Scenario, Objective]) -> dict[str, Any]:
    """Fly one candidate and score it (a top-level function, so a Pool can run it)."""
    from sitl.lab.report import compute_metrics
    from sitl.lab.simulate import simulate_flight

    profile, cfg, scenario, kind = job
    m = compute_metrics(simulate_flight(profile, cfg, scenario))
    mae = dict(m["mae_deg_s"])
    return {
        "mae_deg_s": mae,
        "crashed": m["crashed"],
        "crashed_at_s": m["crashed_at_s"],
        "objective_deg_s": round(_objective(mae, m["crashed"], kind), 4),
    }


def _to_params(x: np.ndarray) -> dict[str, float]:
    return {n: _round_sig(10.0 ** float(v)) for n, v in zip(PARAMS, x, strict=True)}


def _clip(x: np.ndarray) -> np.ndarray:
    lo = np.log10([BOUNDS[n][0] for n in PARAMS])
    hi = np.log10([BOUNDS[n][1] for n in PARAMS])
    return np.asarray(np.clip(x, lo, hi), dtype=float)


def tune_pid(
    profile: VehicleProfile,
    scenario: Scenario,
    *,
    budget: int,
    seed: int,
    workers: int = 2,
    start: PidConfig | None = None,
    objective: Objective = "mean",
    n_random: int = 2,
    min_step: float = math.log10(1.09),
    progress: Callable[[int], None] | None = None,
) -> tuple[TuneResult, list[dict[str, Any]]]:
    """Tune roll/pitch and yaw PID gains on one vehicle by a seeded pattern search.

    Parameters
    ----------
    profile
        The vehicle to tune on (its physics fly; its geometry makes the mixer).
    scenario
        The training flight. Its name must not be in :data:`TEST_SCENARIOS`.
    budget
        Maximum number of flights, the start point's included (>= 1).
    seed
        Seeds the search's generator (coordinate order and random directions).
    workers
        Parallel flights (``multiprocessing.Pool``); 1 flies in this process.
    start
        Start point; default PX4's defaults (:data:`~companion.config.PID_DEFAULT_CONTROLLER`).
        Its values are clipped into :data:`BOUNDS` first.
    objective
        ``"mean"`` or ``"worst"`` of the per-axis MAE (deg/s).
    n_random
        Points in random directions added to each round's 2 x 5 coordinate points.
    min_step
        Smallest step, in log10 units, before the search stops.
    progress
        Called with the number of flights just finished.

    Returns
    -------
    result : TuneResult
        The best point found.
    history : list of dict
        One entry per flight, in order: ``flight``, ``round``, ``step_factor``,
        ``params``, ``mae_deg_s``, ``crashed``, ``crashed_at_s``,
        ``objective_deg_s`` and ``best_so_far_deg_s``.

    Raises
    ------
    ValueError
        A test scenario, a budget below 1, or a start file that is not a PID.
    """
    if scenario.name in TEST_SCENARIOS:
        raise ValueError(f"scenario {scenario.name!r} is a test flight; tune on a training one")
    if budget < 1:
        raise ValueError(f"budget must be at least 1 flight, got {budget}")
    if start is None:
        loaded = load_controller(PID_DEFAULT_CONTROLLER)
        if not isinstance(loaded, PidConfig):
            raise ValueError(f"{PID_DEFAULT_CONTROLLER} is not a PID controller file")
        start = loaded
    if objective not in ("mean", "worst"):
        raise ValueError(f"objective must be 'mean' or 'worst', got {objective!r}")

    rng = np.random.default_rng(seed)
    n = len(PARAMS)
    x = _clip(np.log10([params_of(start)[p] for p in PARAMS]))
    step = math.log10(2.0)
    history: list[dict[str, Any]] = []
    scored: dict[tuple[float, ...], dict[str, Any]] = {}

    def key(p: dict[str, float]) -> tuple[float, ...]:
        return tuple(p[name] for name in PARAMS)

    pool = multiprocessing.Pool(workers) if workers > 1 else None
    try:

        def evaluate(points: list[np.ndarray], round_no: int) -> list[dict[str, Any]]:
            params = [_to_params(p) for p in points]
            jobs = [(profile, apply_params(start, p), scenario, objective) for p in params]
            if pool is not None:
                results = pool.map(_fly, jobs, chunksize=1)
            else:
                results = [_fly(j) for j in jobs]
            out = []
            for p, r in zip(params, results, strict=True):
                best = min([e["objective_deg_s"] for e in history] + [r["objective_deg_s"]])
                entry = {
                    "flight": len(history) + 1,
                    "round": round_no,
                    "step_factor": round(10.0**step, 4),
                    "params": p,
                    **r,
                    "best_so_far_deg_s": best,
                }
                history.append(entry)
                scored[key(p)] = entry
                out.append(entry)
            if progress is not None:
                progress(len(results))
            return out

        centre = evaluate([x], 0)[0]
        start_obj = centre["objective_deg_s"]
        round_no = 0
        while len(history) < budget and step >= min_step - 1e-12:
            round_no += 1
            cands: list[np.ndarray] = []
            seen: set[tuple[float, ...]] = {key(_to_params(x))}
            for i in rng.permutation(n):
                for sign in (1.0, -1.0):
                    e = np.zeros(n)
                    e[i] = sign * step
                    cands.append(_clip(x + e))
            for _ in range(n_random):
                d = rng.normal(size=n)
                cands.append(_clip(x + step * d / np.linalg.norm(d)))
            fresh: list[np.ndarray] = []
            for c in cands:
                k = key(_to_params(c))
                if k in seen:
                    continue
                seen.add(k)
                if k in scored:  # flown before: reuse the score, spend no flight
                    continue
                fresh.append(c)
            fresh = fresh[: budget - len(history)]
            if fresh:
                evaluate(fresh, round_no)
            # Best among this round's neighbours, flown now or before.
            neighbours = [scored[k] for k in seen if k in scored and k != key(_to_params(x))]
            best = min(neighbours, key=lambda e: e["objective_deg_s"], default=None)
            if best is not None and best["objective_deg_s"] < centre["objective_deg_s"] - 1e-9:
                centre = best
                x = _clip(np.log10([best["params"][p] for p in PARAMS]))
                _log.info(
                    "round %d: moved to %s, objective %.2f deg/s",
                    round_no,
                    best["params"],
                    best["objective_deg_s"],
                )
            else:
                step /= 2.0
                _log.info("round %d: no better neighbour; step factor now %.3f", round_no, 10**step)
    finally:
        if pool is not None:
            pool.close()
            pool.join()

    result = TuneResult(
        config=apply_params(start, centre["params"]),
        params=dict(centre["params"]),
        objective_deg_s=centre["objective_deg_s"],
        start_objective_deg_s=start_obj,
        flights=len(history),
    )
    return result, history


def write_pid_yaml(
    cfg: PidConfig, path: str | Path, *, comments: Sequence[str] = (), **provenance: Any
) -> Path:
    """Write a PID controller file with a comment header saying how it was produced.

    Parameters
    ----------
    cfg
        The controller to write.
    path
        Output file.
    comments
        Free lines for the header (written as ``# line``).
    **provenance
        ``key: value`` lines for the header (e.g. ``budget=96, seed=1``).

    Returns
    -------
    Path
        The file written; it loads back with :func:`companion.config.load_controller`.
    """
    import yaml

    lines = [f"# {c}".rstrip() for c in comments]
    lines += [f"#   {k}: {v}" for k, v in provenance.items()]
    lines += [
        "# Gains in normalised torque per rad/s (kp), per rad (ki), per rad/s^2 (kd).",
        "kind: pid",
        f"dt_min_s: {cfg.dt_min_s}",
        f"dt_max_s: {cfg.dt_max_s}",
        "axes:",
    ]
    for name in AXES:
        a = getattr(cfg.axes, name)
        lines.append(
            f"  {name + ':':<7}{{kp: {a.kp}, ki: {a.ki}, kd: {a.kd}, kff: {a.kff}, "
            f"i_limit: {a.i_limit}, d_lpf_hz: {a.d_lpf_hz}}}"
        )
    sticks = yaml.safe_dump(
        {"sticks": cfg.sticks.model_dump(mode="json")}, sort_keys=False, default_flow_style=None
    )
    p = Path(path)
    p.write_text("\n".join(lines) + "\n" + sticks, encoding="utf-8")
    loaded = load_controller(p)
    if loaded != cfg:
        raise RuntimeError(f"{p} does not load back to the configuration written")
    return p


def _main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m sitl.lab.pidtune", description=__doc__)
    ap.add_argument("--profile", type=Path, required=True, help="vehicle profile YAML")
    ap.add_argument("--scenario", default="train-acro", help="training scenario name or file")
    ap.add_argument("--budget", type=int, default=120, help="flights, the start point's included")
    ap.add_argument("--seed", type=int, default=1, help="the search's seed")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--objective", choices=("mean", "worst"), default="mean")
    ap.add_argument("--start", type=Path, default=PID_DEFAULT_CONTROLLER, help="start PID file")
    ap.add_argument("--out", type=Path, required=True, help="tuned PID YAML to write")
    ap.add_argument("--history", type=Path, default=None, help="also write the history as JSON")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")

    import json
    import time

    from tqdm import tqdm

    profile = load_profile(args.profile)
    scenario = load_scenario(args.scenario)
    start = load_controller(args.start)
    if not isinstance(start, PidConfig):
        ap.error(f"--start {args.start} is not a PID controller file")
    t0 = time.perf_counter()
    with tqdm(total=args.budget, desc="tuning", unit="flight") as bar:
        res, hist = tune_pid(
            profile,
            scenario,
            budget=args.budget,
            seed=args.seed,
            workers=args.workers,
            start=start,
            objective=args.objective,
            progress=bar.update,
        )
    wall = time.perf_counter() - t0
    best = next(e for e in hist if e["params"] == res.params)
    mae = best["mae_deg_s"]
    write_pid_yaml(
        res.config,
        args.out,
        comments=[
            f"Rate PID tuned on {profile.name} by sitl/lab/pidtune.py (a seeded pattern",
            "search; procedure in that module's docstring and docs/research/paper.md). "
            "Produced by:",
            f"  python -m sitl.lab.pidtune --profile {args.profile} --scenario {args.scenario} \\",
            f"      --budget {args.budget} --seed {args.seed} --workers {args.workers} "
            f"--objective {args.objective} --out {args.out}",
            "Trained on the scenario below only; paper-acro (the test flight) was never flown.",
            "Searched: roll+pitch (shared) kp, ki, kd and yaw kp, ki, from PX4's defaults",
            "(companion/data/pid_px4_default.yaml); kff, i_limit, d_lpf_hz, yaw kd and sticks",
            "are PX4's. Not re-tuned for any other vehicle.",
        ],
        profile=f"{args.profile} ({profile.name})",
        scenario=f"{scenario.name} (seed {scenario.seed}, {scenario.duration_s} s)",
        objective=f"{args.objective} of per-axis rate MAE, crash +{CRASH_PENALTY_DEG_S:g}",
        budget=f"{args.budget} flights ({res.flights} flown)",
        seed=args.seed,
        start_objective_deg_s=res.start_objective_deg_s,
        tuned_objective_deg_s=res.objective_deg_s,
        tuned_mae_deg_s=f"roll {mae['roll']}, pitch {mae['pitch']}, yaw {mae['yaw']}",
    )
    if args.history is not None:
        args.history.write_text(json.dumps(hist, indent=1) + "\n", encoding="utf-8")
    _log.info(
        "objective %.2f -> %.2f deg/s in %d flights (%.0f s wall); wrote %s",
        res.start_objective_deg_s,
        res.objective_deg_s,
        res.flights,
        wall,
        args.out,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(_main())
