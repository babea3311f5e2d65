"""The envelope campaign: one MFC gain set against a PID retuned for every vehicle.

The question
------------
What does careful retuning buy a PID user, vehicle by vehicle, and how close
does one shipped MFC configuration, never retuned, come to it? Vehicles come
from the envelope generator (:mod:`sitl.envelope`: named corners plus a Latin
hypercube over mass, arm length, thrust-to-weight and motor time constant),
optionally with damage variants (``motor60``, ``imbalance``, ``cg10``).

Per vehicle and case (one ``multiprocessing.Pool`` job each)
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

3. **Ratios** per axis: MFC MAE over the tuned PID's MAE
   (``ratio_mfc_tuned``) and over the default PID's (``ratio_mfc_default``).

Targets (:data:`RATIO_TARGET`)
------------------------------
* MFC crashes nowhere in the envelope.
* ``ratio_mfc_tuned <= 1.25`` on every vehicle, case and axis.
* MFC better than PX4's default PID on every vehicle, case and axis
  (``ratio_mfc_default < 1``).

A (case, axis) where MFC crashed fails both comparisons; one where only the PID
crashed passes it (MFC flew, the PID did not). Ratios of crashed flights are
still recorded (MAE up to the crash) but do not decide the verdicts.

Determinism: every flight is deterministic (the scenario's seed) and the search
is seeded, records come back in case order: the same arguments give the same
records whatever the number of workers.

Outputs (:func:`write_envelope_outputs`): ``envelope.json`` (``meta``,
``verdicts``, ``records``), ``summary.md``, ``ratio.png`` and, for the worst
cases, ``worst-<vehicle>-<case>.png`` (re-flown: commanded against measured
rate for MFC and the tuned PID).
"""

from __future__ import annotations

import json
import logging
import math
import multiprocessing
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import MfcConfig, PidConfig
from companion.control import AXES
from companion.profile import VehicleProfile
from sitl.lab.pidtune import TEST_SCENARIOS, apply_params, tune_pid
from sitl.scenario import Scenario

__all__ = [
    "CASES",
    "CONTROLLERS",
    "ENVELOPE_TEST_SCENARIO",
    "RATIO_TARGET",
    "REGION_FIELDS",
    "EnvelopeCase",
    "EnvelopeSetup",
    "envelope_cases",
    "envelope_meta",
    "hard_regions",
    "load_setup",
    "plot_ratio",
    "plot_worst",
    "run_envelope",
    "summary_markdown",
    "verdicts",
    "worst_cases",
    "write_envelope_outputs",
]

_log = logging.getLogger(__name__)

_ROOT = Path(__file__).resolve().parents[2]
"""The checkout (or install) this module belongs to: bundled profiles are found from it."""

CASES: tuple[str, ...] = ("intact", "motor60", "imbalance", "cg10")
"""Vehicle cases: the intact vehicle and the generator's damage variants."""

CONTROLLERS: tuple[str, ...] = ("mfc", "pid_tuned", "pid_default")
"""The three controllers flown on the test scenario, in record order."""

RATIO_TARGET = 1.25
"""Target: MFC MAE over the tuned PID's MAE, on every vehicle, case and axis."""

ENVELOPE_TEST_SCENARIO = "envelope-test"
"""The held-out test flight of this campaign (never trained on)."""


@dataclass(frozen=True)
class EnvelopeCase:
    """One vehicle in one condition.

    Attributes
    ----------
    vehicle
        The envelope vehicle's name.
    case
        One of :data:`CASES`.
    profile
        The plant flown (damaged for a damage case).
    info
        The intact vehicle's description (``EnvelopeVehicle.to_dict()``: its
        scalars and derived figures, peak angular accelerations included), so
        a vehicle's cases share one place on the envelope plots.
    """

    vehicle: str
    case: str
    profile: VehicleProfile
    info: dict[str, Any]


@dataclass(frozen=True)
class EnvelopeSetup:
    """What every case of a campaign shares.

    Attributes
    ----------
    mfc
        The MFC configuration, flown unchanged on every vehicle.
    pid_default
        PX4's default PID: the floor, and the tuner's start point.
    controller_profile
        The profile MFC is given (its geometry makes the mixer): the F450's.
    train
        The tuning scenario.
    test
        The test scenario (never tuned on).
    tune_budget
        Flights per tuning run, the start point's included.
    seed
        Seeds every tuning search.
    """

    mfc: MfcConfig
    pid_default: PidConfig
    controller_profile: VehicleProfile
    train: Scenario
    test: Scenario
    tune_budget: int = 40
    seed: int = 1

    def __post_init__(self) -> None:
        held_out = TEST_SCENARIOS | {ENVELOPE_TEST_SCENARIO, self.test.name}
        if self.train.name in held_out:
            raise ValueError(
                f"training scenario {self.train.name!r} is a test flight; "
                f"tune on one that is not in {sorted(held_out)}"
            )
        if self.tune_budget < 1:
            raise ValueError(f"tune_budget must be at least 1 flight, got {self.tune_budget}")


def load_setup(
    *,
    controller: str | Path | None = None,
    controller_profile: str | Path = "vehicle_profiles/f450.yaml",
    train_scenario: str | Path = "train-acro",
    test_scenario: str | Path = ENVELOPE_TEST_SCENARIO,
    tune_budget: int = 40,
    seed: int = 1,
) -> EnvelopeSetup:
    """Load the files of an :class:`EnvelopeSetup` (the PID floor is PX4's defaults).

    Parameters
    ----------
    controller
        MFC file; default the shipped one (:data:`~companion.config.DEFAULT_CONTROLLER`).
    controller_profile
        The profile MFC is given; a relative path missing from the working
        directory is looked up in the repository.
    train_scenario, test_scenario
        Scenario names or files.
    tune_budget, seed
        As in :class:`EnvelopeSetup`.

    Raises
    ------
    companion.errors.ConfigError
        A file that does not load.
    ValueError
        A controller that is not MFC, or a setup :class:`EnvelopeSetup` refuses.
    """
    from companion.config import DEFAULT_CONTROLLER, PID_DEFAULT_CONTROLLER, load_controller
    from companion.profile import load_profile
    from sitl.scenario import load_scenario

    prof_path = Path(controller_profile)
    if not prof_path.exists() and not prof_path.is_absolute():
        prof_path = _ROOT / prof_path
    mfc_path = Path(controller) if controller is not None else DEFAULT_CONTROLLER
    mfc = load_controller(mfc_path)
    if not isinstance(mfc, MfcConfig):
        raise ValueError(f"{mfc_path} is a {mfc.kind} file; the envelope campaign flies MFC")
    pid_default = load_controller(PID_DEFAULT_CONTROLLER)
    if not isinstance(pid_default, PidConfig):
        raise ValueError(f"{PID_DEFAULT_CONTROLLER} is not a PID file")
    return EnvelopeSetup(
        mfc=mfc,
        pid_default=pid_default,
        controller_profile=load_profile(prof_path),
        train=load_scenario(train_scenario),
        test=load_scenario(test_scenario),
        tune_budget=tune_budget,
        seed=seed,
    )


def envelope_cases(
    n: int = 30,
    seed: int = 1,
    *,
    corners_only: bool = False,
    damage: bool = True,
    damage_on: int = 8,
) -> list[EnvelopeCase]:
    """The campaign's cases: the corners, ``n`` sampled vehicles, damage on some.

    Parameters
    ----------
    n
        Latin-hypercube vehicles (:func:`sitl.envelope.sample_envelope`).
    seed
        The sample's seed.
    corners_only
        Only the named corner vehicles (:func:`sitl.envelope.corners`).
    damage
        Add the damage variants (``motor60``, ``imbalance``, ``cg10``).
    damage_on
        How many vehicles get them: the first ``damage_on`` of the list, which
        starts with the corners, then the sampled vehicles in sample order.

    Returns
    -------
    list of EnvelopeCase
        Vehicle by vehicle, each vehicle's intact case first.
    """
    from sitl.envelope import corners, damage_variants, sample_envelope

    if n < 0 or damage_on < 0:
        raise ValueError(f"n and damage_on must be >= 0, got {n} and {damage_on}")
    vehicles = list(corners()) + ([] if corners_only else list(sample_envelope(n, seed)))
    names = [v.name for v in vehicles]
    if len(set(names)) != len(names):
        raise ValueError(f"envelope vehicle names are not unique: {names}")
    cases: list[EnvelopeCase] = []
    for i, v in enumerate(vehicles):
        info = dict(v.to_dict())
        cases.append(EnvelopeCase(v.name, "intact", v.profile(), info))
        if damage and i < damage_on:
            variants = damage_variants(v)
            for case in CASES[1:]:
                cases.append(EnvelopeCase(v.name, case, variants[case], info))
    return cases


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


def _tuned_config(setup: EnvelopeSetup, gains: dict[str, float]) -> PidConfig:
    return apply_params(setup.pid_default, gains)


def _run_case(job: tuple[EnvelopeSetup, EnvelopeCase]) -> dict[str, Any]:
    """Tune, then fly the test scenario three times (a top-level function, for the Pool)."""
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
    return {
        "vehicle": case.vehicle,
        "case": case.case,
        "vehicle_info": case.info,
        "peak_accel_flown_rad_s2": list(peak_angular_accel_rad_s2(case.profile)),
        "flights": flights,
        "ratio_mfc_tuned": {a: _ratio(mae["mfc"][a], mae["pid_tuned"][a]) for a in AXES},
        "ratio_mfc_default": {a: _ratio(mae["mfc"][a], mae["pid_default"][a]) for a in AXES},
        "tuned_gains": dict(result.params),
        "tune": {
            "flights": result.flights,
            "train_objective_deg_s": result.objective_deg_s,
            "start_objective_deg_s": result.start_objective_deg_s,
        },
    }


def run_envelope(
    cases: Sequence[EnvelopeCase],
    setup: EnvelopeSetup,
    *,
    workers: int = 1,
    progress: bool = True,
) -> list[dict[str, Any]]:
    """Tune and fly every case, ``workers`` cases at a time, with a tqdm bar on stderr.

    Parameters
    ----------
    cases
        From :func:`envelope_cases`.
    setup
        Controllers, scenarios, tuning budget and seed.
    workers
        Parallel cases (processes); 1 runs in this process.
    progress
        Show the bar.

    Returns
    -------
    list of dict
        One record per case, in case order: ``vehicle``, ``case``,
        ``vehicle_info``, ``peak_accel_flown_rad_s2``, ``flights`` (per
        controller of :data:`CONTROLLERS`: ``mae_deg_s`` per axis, ``crashed``,
        ``crashed_at_s``, ``sim_time_s``), ``ratio_mfc_tuned`` and
        ``ratio_mfc_default`` per axis (None when undefined), ``tuned_gains``
        (:data:`sitl.lab.pidtune.PARAMS`) and ``tune`` (flights, training
        objective before and after, deg/s).
    """
    from tqdm import tqdm

    jobs = [(setup, c) for c in cases]
    bar = tqdm(total=len(jobs), desc="envelope", unit="case", disable=not progress)
    records: list[dict[str, Any]] = []
    try:
        if workers <= 1:
            for j in jobs:
                records.append(_run_case(j))
                bar.update(1)
        else:
            with multiprocessing.Pool(workers) as pool:
                for r in pool.imap(_run_case, jobs, chunksize=1):
                    records.append(r)
                    bar.update(1)
    finally:
        bar.close()
    return records


def _scenario_meta(sc: Scenario) -> dict[str, Any]:
    return {"name": sc.name, "seed": sc.seed, "duration_s": sc.duration_s, "pilot": sc.pilot}


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


# ------------------------------------------------------------------ verdicts and tables


def _beats(rec: dict[str, Any], other: str, axis: str, bound: float, strict: bool) -> bool:
    """MFC meets the bound against ``other`` on this (case, axis)."""
    f = rec["flights"]
    if f["mfc"]["crashed"]:
        return False
    if f[other]["crashed"]:
        return True
    r = rec["ratio_mfc_tuned" if other == "pid_tuned" else "ratio_mfc_default"][axis]
    if r is None:
        return False
    return bool(r < bound if strict else r <= bound)


def _worst_ratio(rec: dict[str, Any], key: str = "ratio_mfc_tuned") -> float:
    """Largest per-axis ratio (inf when MFC crashed or a ratio is undefined)."""
    if rec["flights"]["mfc"]["crashed"]:
        return math.inf
    vals = [rec[key][a] for a in AXES]
    return math.inf if any(v is None for v in vals) else float(max(vals))


def verdicts(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The three targets, met or not, over all cases and over intact vehicles only.

    Returns
    -------
    dict
        ``crashes`` (per controller), ``worst_ratio_mfc_tuned`` per axis (with
        the case), and for ``all`` and ``intact``: ``no_mfc_crash``,
        ``ratio_within_target``, ``better_than_default`` (bools) with the number
        of failing (case, axis) pairs.
    """
    out: dict[str, Any] = {
        "crashes": {c: sum(r["flights"][c]["crashed"] for r in records) for c in CONTROLLERS},
        "worst_ratio_mfc_tuned": {},
    }
    for a in AXES:
        ranked = [
            (r["ratio_mfc_tuned"][a], r["vehicle"], r["case"])
            for r in records
            if r["ratio_mfc_tuned"][a] is not None
        ]
        if ranked:
            v, name, case = max(ranked)
            out["worst_ratio_mfc_tuned"][a] = {"ratio": v, "vehicle": name, "case": case}
    for scope in ("all", "intact"):
        rs = [r for r in records if scope == "all" or r["case"] == "intact"]
        fail_tuned = sum(
            not _beats(r, "pid_tuned", a, RATIO_TARGET, False) for r in rs for a in AXES
        )
        fail_default = sum(not _beats(r, "pid_default", a, 1.0, True) for r in rs for a in AXES)
        mfc_crashes = sum(r["flights"]["mfc"]["crashed"] for r in rs)
        out[scope] = {
            "cases": len(rs),
            "no_mfc_crash": mfc_crashes == 0,
            "mfc_crashes": mfc_crashes,
            "ratio_within_target": fail_tuned == 0,
            "ratio_failures": fail_tuned,
            "better_than_default": fail_default == 0,
            "default_failures": fail_default,
        }
    return out


REGION_FIELDS: tuple[str, ...] = (
    "mass_kg",
    "thrust_to_weight",
    "motor_tau_s",
    "arm_factor",
    "peak_roll_accel_rad_s2",
    "peak_yaw_accel_rad_s2",
    "roll_rate_per_motor_lag_rad_s",
    "hover_command",
    "disk_loading_n_m2",
)
"""Vehicle figures the hard-region table ranks: keys of ``EnvelopeVehicle.to_dict()``
and ``roll_rate_per_motor_lag_rad_s`` = peak roll acceleration x motor time constant
(the roll rate full authority builds up within one motor lag)."""


def _numeric_info(rec: dict[str, Any]) -> dict[str, float]:
    info = dict(rec["vehicle_info"])
    acc, tau = info.get("peak_roll_accel_rad_s2"), info.get("motor_tau_s")
    if isinstance(acc, (int, float)) and isinstance(tau, (int, float)):
        info["roll_rate_per_motor_lag_rad_s"] = acc * tau
    return {
        k: float(info[k])
        for k in REGION_FIELDS
        if isinstance(info.get(k), (int, float)) and math.isfinite(info[k])
    }


def _ranks(x: np.ndarray) -> np.ndarray:
    order = np.argsort(x, kind="stable")
    r = np.empty(len(x))
    r[order] = np.arange(len(x))
    return r


def hard_regions(records: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """How the worst-axis ratio of the intact vehicles varies with each envelope figure.

    For every figure of :data:`REGION_FIELDS`: the Spearman rank correlation
    with the worst-axis ``ratio_mfc_tuned`` (an MFC crash ranks worst, as
    ``inf``) and the median worst ratio in the lower and upper third of that
    figure (``inf`` when most of that third crashed). Sorted by the size of the
    correlation; empty below 4 intact vehicles.
    """
    rs = [r for r in records if r["case"] == "intact"]
    if len(rs) < 4:
        return []
    worst = np.array([_worst_ratio(r) for r in rs])
    rows = []
    for f in REGION_FIELDS:
        x = np.array([_numeric_info(r).get(f, np.nan) for r in rs])
        if not np.all(np.isfinite(x)) or np.ptp(x) == 0.0:
            continue
        rho = float(np.corrcoef(_ranks(x), _ranks(worst))[0, 1])
        lo, hi = np.percentile(x, [100 / 3, 200 / 3])
        rows.append(
            {
                "field": f,
                "spearman": round(rho, 3),
                "median_worst_low_third": float(np.median(worst[x <= lo])),
                "median_worst_high_third": float(np.median(worst[x >= hi])),
            }
        )
    return sorted(rows, key=lambda r: -abs(r["spearman"]))


def worst_cases(records: Sequence[dict[str, Any]], k: int = 3) -> list[dict[str, Any]]:
    """The ``k`` worst cases, at most one per vehicle.

    Ranked by worst-axis MFC / tuned-PID ratio, an MFC crash first (among
    crashes, the larger ratio recorded up to the crash first). A vehicle's
    other cases are skipped once one of them is in, so the plots show ``k``
    different vehicles.
    """

    def key(r: dict[str, Any]) -> tuple[float, float, str, str]:
        recorded = [v for v in r["ratio_mfc_tuned"].values() if v is not None]
        return (-_worst_ratio(r), -max(recorded, default=0.0), r["vehicle"], r["case"])

    out: list[dict[str, Any]] = []
    for r in sorted(records, key=key):
        if len(out) >= k:
            break
        if all(o["vehicle"] != r["vehicle"] for o in out):
            out.append(r)
    return out


def _fmt(v: float | None, spec: str = ".1f") -> str:
    return "-" if v is None else format(v, spec)


def _fmt_ratio(v: float) -> str:
    return "crash" if math.isinf(v) else f"{v:.2f}"


def _mae_cell(rec: dict[str, Any], axis: str) -> str:
    cells = []
    for c in CONTROLLERS:
        f = rec["flights"][c]
        cells.append(_fmt(f["mae_deg_s"][axis]) + ("!" if f["crashed"] else ""))
    return " / ".join(cells)


def _met(flag: bool) -> str:
    return "**met**" if flag else "**not met**"


def _shown(path: str) -> str:
    """A file inside this checkout as a path from its root (the summary is kept in the
    repository: docs/envelope/), any other as given."""
    p = Path(path)
    return str(p.relative_to(_ROOT)) if p.is_absolute() and p.is_relative_to(_ROOT) else path


def summary_markdown(
    records: Sequence[dict[str, Any]],
    meta: dict[str, Any],
    *,
    worst_images: dict[tuple[str, str], str] | None = None,
) -> str:
    """The ``summary.md`` text: verdicts, headline numbers, hard regions, the full table."""
    v = verdicts(records)
    tr, te = meta["train_scenario"], meta["test_scenario"]
    lines = [
        "# Envelope campaign: one MFC configuration against a PID retuned per vehicle",
        "",
        f"{meta['vehicles']} vehicles, {meta['cases']} cases (damage variants on "
        f"{len(meta['damaged_vehicles'])} vehicles, PID retuned on each damaged plant). "
        f"PID tuned on `{tr['name']}` (seed {tr['seed']}, {tr['duration_s']} s), "
        f"{meta['tune_budget']} flights per case, search seed {meta['tune_seed']}; every "
        f"controller then flies `{te['name']}` (seed {te['seed']}, {te['duration_s']} s). "
        f"MFC is `{_shown(meta.get('mfc_controller', 'the shipped file'))}`, given the profile of "
        f"{meta['mfc_controller_profile']}, never retuned. "
        f"{meta.get('workers', '?')} workers, {meta.get('wall_time_s', float('nan')):.0f} s wall.",
        "",
        "## Targets",
        "",
        "| target | all cases | intact vehicles only |",
        "|---|---|---|",
    ]
    a, i = v["all"], v["intact"]
    lines += [
        f"| MFC never crashes | {_met(a['no_mfc_crash'])} ({a['mfc_crashes']} crashed of "
        f"{a['cases']}) | {_met(i['no_mfc_crash'])} ({i['mfc_crashes']} of {i['cases']}) |",
        f"| MFC / tuned PID MAE <= {RATIO_TARGET:g} on every axis | "
        f"{_met(a['ratio_within_target'])} ({a['ratio_failures']} case-axes fail) | "
        f"{_met(i['ratio_within_target'])} ({i['ratio_failures']} fail) |",
        f"| MFC better than PX4's default PID on every axis | "
        f"{_met(a['better_than_default'])} ({a['default_failures']} case-axes fail) | "
        f"{_met(i['better_than_default'])} ({i['default_failures']} fail) |",
        "",
        "Crashes on the test flight: "
        + ", ".join(f"{c} {n}/{len(records)}" for c, n in v["crashes"].items())
        + ".",
        "",
    ]
    all_crashed = [
        f"{r['vehicle']} / {r['case']}"
        for r in records
        if all(r["flights"][c]["crashed"] for c in CONTROLLERS)
    ]
    if all_crashed:
        lines += [
            "Every controller crashed on: " + ", ".join(all_crashed) + " (probably beyond "
            "the vehicle's authority; still counted as an MFC crash above).",
            "",
        ]
    lines += [
        "## Ratio MFC / tuned PID per axis",
        "",
        "| axis | median | p90 | worst | worst case |",
        "|---|---|---|---|---|",
    ]
    for ax in AXES:
        vals = [r["ratio_mfc_tuned"][ax] for r in records if r["ratio_mfc_tuned"][ax] is not None]
        w = v["worst_ratio_mfc_tuned"].get(ax)
        lines.append(
            f"| {ax} | {_fmt(float(np.median(vals)) if vals else None, '.2f')} | "
            f"{_fmt(float(np.percentile(vals, 90)) if vals else None, '.2f')} | "
            f"{_fmt(w['ratio'] if w else None, '.2f')} | "
            f"{w['vehicle'] + ' / ' + w['case'] if w else '-'} |"
        )
    regions = hard_regions(records)
    if regions:
        lines += [
            "",
            "## Where the envelope is hard (intact vehicles)",
            "",
            "Spearman rank correlation of the worst-axis ratio with each vehicle figure, "
            "and the median worst-axis ratio in the lower and upper third of that figure "
            "(an MFC crash counts as the worst ratio):",
            "",
            "| figure | Spearman | median worst ratio, low third | high third |",
            "|---|---|---|---|",
        ]
        lines += [
            f"| {r['field']} | {r['spearman']:+.2f} | {_fmt_ratio(r['median_worst_low_third'])} "
            f"| {_fmt_ratio(r['median_worst_high_third'])} |"
            for r in regions
        ]
    lines += ["", "![worst-axis ratio over the envelope](ratio.png)", ""]
    if worst_images:
        lines += ["## Worst cases", ""]
        for (name, case), img in worst_images.items():
            rec = next(r for r in records if (r["vehicle"], r["case"]) == (name, case))
            ratios = ", ".join(f"{ax} {_fmt(rec['ratio_mfc_tuned'][ax], '.2f')}" for ax in AXES)
            crashes = "; ".join(
                f"{c} crashed at {rec['flights'][c]['crashed_at_s']:.1f} s"
                for c in CONTROLLERS
                if rec["flights"][c]["crashed"]
            )
            lines += [
                f"- {name} / {case}: ratio {ratios}" + (f" ({crashes})" if crashes else ""),
                "",
                f"  ![{name} {case}]({img})",
                "",
            ]
    lines += [
        "## Every case",
        "",
        "MAE in deg/s on the test flight, MFC / tuned PID / PX4-default PID "
        "(`!` = crashed, MAE up to the crash); ratio = MFC / tuned PID.",
        "",
        "| vehicle | case | roll MAE | roll ratio | pitch MAE | pitch ratio | yaw MAE "
        "| yaw ratio | worst ratio | worst vs default |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in records:
        cells = []
        for ax in AXES:
            cells += [_mae_cell(r, ax), _fmt(r["ratio_mfc_tuned"][ax], ".2f")]
        w, wd = _worst_ratio(r), _worst_ratio(r, "ratio_mfc_default")
        lines.append(
            f"| {r['vehicle']} | {r['case']} | "
            + " | ".join(cells)
            + f" | {_fmt_ratio(w)} | {_fmt_ratio(wd)} |"
        )
    lines.append("")
    return "\n".join(lines)


# ------------------------------------------------------------------ plots


_MARKERS = {"intact": "o", "motor60": "v", "imbalance": "^", "cg10": "s"}


def plot_ratio(records: Sequence[dict[str, Any]], path: Path) -> Path:
    """Worst-axis ratio over the envelope: one panel per vehicle figure, line at the target.

    x: peak roll angular acceleration, motor time constant, their product and
    mass of the intact vehicle; y (log): the worst-axis MFC / tuned-PID ratio.
    An MFC crash is drawn above every finite ratio with a red edge. Colour is
    the ratio (diverging at the target); marker shape is the case.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm
    from matplotlib.lines import Line2D
    from matplotlib.ticker import FuncFormatter, NullFormatter

    panels = [
        ("peak_roll_accel_rad_s2", "peak roll angular acceleration (rad/s^2)"),
        ("motor_tau_s", "motor time constant (s)"),
        ("roll_rate_per_motor_lag_rad_s", "peak roll acceleration x motor tau (rad/s)"),
        ("mass_kg", "mass (kg)"),
    ]
    worst = np.array([_worst_ratio(r) for r in records])
    finite = worst[np.isfinite(worst)]
    top = 1.5 * max(3.0, float(finite.max(initial=1.0)))
    crashed = ~np.isfinite(worst)
    y = np.where(crashed, top, np.maximum(worst, 1e-3))
    log_y = np.log10(y)
    # Diverging at the target, on log10 of the ratio: green below, red above.
    c_lo = min(math.log10(0.5), float(log_y.min(initial=0.0)) - 0.01)
    c_hi = max(math.log10(3.0), float(log_y.max(initial=0.0)) + 0.01)
    norm = TwoSlopeNorm(vmin=c_lo, vcenter=math.log10(RATIO_TARGET), vmax=c_hi)
    cases = np.array([r["case"] for r in records])
    fig, axs = plt.subplots(2, 2, figsize=(12, 8.5))
    sc = None
    for ax, (field, label) in zip(axs.flat, panels, strict=True):
        x = np.array([_numeric_info(r).get(field, np.nan) for r in records])
        for case, marker in _MARKERS.items():
            m = (cases == case) & np.isfinite(x)
            if not m.any():
                continue
            sc = ax.scatter(x[m], y[m], c=log_y[m], cmap="RdYlGn_r", norm=norm, s=42,
                            marker=marker, edgecolors=np.where(crashed[m], "red", "k"),
                            linewidths=np.where(crashed[m], 2.0, 0.4))  # fmt: skip
        ax.axhline(RATIO_TARGET, color="k", ls="--", lw=1.0)
        ax.axhline(1.0, color="0.5", ls=":", lw=0.8)
        if crashed.any():
            ax.axhline(top, color="red", ls="-", lw=0.5, alpha=0.5)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_minor_formatter(NullFormatter())
        plain = FuncFormatter(lambda v, _: f"{v:g}")
        ax.yaxis.set_major_formatter(plain)
        # Label the minor ticks only when the plot spans too few decades to show majors.
        few_decades = math.log10(top) - math.log10(max(float(y.min(initial=1.0)), 1e-3)) < 1.5
        ax.yaxis.set_minor_formatter(plain if few_decades else NullFormatter())
        ax.set_xlabel(label)
        ax.set_ylabel("worst-axis MAE ratio MFC / tuned PID")
        ax.grid(alpha=0.3, which="both")
    handles = [
        Line2D([], [], ls="", marker=mk, mfc="0.8", mec="k", label=case)
        for case, mk in _MARKERS.items()
        if (cases == case).any()
    ]
    if crashed.any():
        handles.append(Line2D([], [], ls="", marker="o", mfc="0.8", mec="red", mew=2.0,
                              label="MFC crashed (top line)"))  # fmt: skip
    axs.flat[0].legend(handles=handles, fontsize=8, loc="best")
    if sc is not None:
        ticks = [t for t in (0.5, 1.0, RATIO_TARGET, 2.0, 5.0, 10.0, 100.0, 1000.0)
                 if c_lo <= math.log10(t) <= c_hi]  # fmt: skip
        cb = fig.colorbar(sc, ax=axs, shrink=0.8, label="worst-axis ratio")
        cb.set_ticks([math.log10(t) for t in ticks], labels=[f"{t:g}" for t in ticks])
    fig.suptitle(
        f"Worst-axis ratio over the envelope ({len(records)} cases; dashed: target "
        f"{RATIO_TARGET:g}, dotted: parity)"
    )
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_worst(rec: dict[str, Any], case: EnvelopeCase, setup: EnvelopeSetup, path: Path) -> Path:
    """Re-fly one case and plot commanded vs measured rate per axis, MFC and tuned PID.

    Flights are deterministic, so the re-flown MAE equals the record's unless
    the code changed in between; the legend gives the re-flown MAE and a
    warning is logged when it differs from the record by more than 1 %.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sitl.lab.report import compute_metrics
    from sitl.lab.simulate import simulate_flight

    flights = {
        "mfc": simulate_flight(
            case.profile, setup.mfc, setup.test, controller_profile=setup.controller_profile
        ),
        "pid_tuned": simulate_flight(
            case.profile, _tuned_config(setup, rec["tuned_gains"]), setup.test
        ),
    }
    metrics = {c: compute_metrics(fr) for c, fr in flights.items()}
    for c, m in metrics.items():
        for a in AXES:
            old, new = rec["flights"][c]["mae_deg_s"][a], m["mae_deg_s"][a]
            if old is not None and new is not None and abs(new - old) > 0.01 * max(old, 1e-9):
                _log.warning(
                    "%s / %s %s %s: re-flown MAE %.2f, recorded %.2f (has the code changed?)",
                    rec["vehicle"], rec["case"], c, a, new, old,
                )  # fmt: skip
    style = {"mfc": ("MFC", "tab:red"), "pid_tuned": ("tuned PID", "tab:blue")}
    ref = max(flights.values(), key=lambda fr: len(fr.columns["t_s"])).columns
    fig, axs = plt.subplots(3, 1, figsize=(12, 8.5), sharex=True)
    for i, (ax, name) in enumerate(zip(axs, AXES, strict=True)):
        ax.plot(ref["t_s"], np.degrees(ref["ref_rad_s"][:, i]), color="k", lw=1.0,
                label="commanded")  # fmt: skip
        for c, fr in flights.items():
            label, colour = style[c]
            m = metrics[c]
            crash = f", crashed at {m['crashed_at_s']:.1f} s" if m["crashed"] else ""
            ax.plot(fr.columns["t_s"], np.degrees(fr.columns["meas_rad_s"][:, i]), color=colour,
                    lw=0.7, label=f"{label} (MAE {_fmt(m['mae_deg_s'][name])}{crash})")  # fmt: skip
            if m["crashed"]:
                ax.axvline(m["crashed_at_s"], color=colour, ls="--", lw=0.8)
        ax.set_ylabel(f"{name} rate (deg/s)")
        ax.set_title(
            f"{name}: ratio {_fmt(rec['ratio_mfc_tuned'][name], '.2f')}", fontsize=9, loc="left"
        )
        ax.legend(loc="upper right", fontsize=7)
        ax.grid(alpha=0.3)
    axs[-1].set_xlabel("time (s)")
    fig.suptitle(f"{rec['vehicle']} / {rec['case']} on {setup.test.name}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


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
    """Write ``envelope.json``, ``summary.md``, ``ratio.png`` and the worst-case plots.

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
        ``json``, ``summary``, ``plot`` and ``worst-<vehicle>-<case>`` paths.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "json": out / "envelope.json",
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
    doc = {"meta": meta, "verdicts": verdicts(records), "records": list(records)}
    paths["json"].write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    paths["summary"].write_text(
        summary_markdown(records, meta, worst_images=images), encoding="utf-8"
    )
    plot_ratio(records, paths["plot"])
    return paths
