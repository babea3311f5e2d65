"""Campaigns: many in-process flights over a grid, in parallel, summarised.

The grid is profiles x damage severity x wind gust sigma x seeds x controllers.
Every flight runs :func:`sitl.lab.simulate.simulate_flight` (no MAVLink) in a
``multiprocessing.Pool``; each is deterministic, so the records do not depend
on the number of workers or on the order flights finish in.

Grid axes
---------
profile
    A vehicle profile (default: every file in ``vehicle_profiles/``).
damage
    Efficiency of motor 1 (index 0, front right): its thrust and reaction-torque
    efficiencies are multiplied by this factor, on top of any damage the profile
    already has (the cut-prop F450's motor 1 is at 0.686 of thrust to begin
    with). 1.0 leaves the profile unchanged.
gust
    The scenario's wind with its gust sigma (m/s) replaced; the steady wind is
    kept.
seed
    Overrides the scenario's seed: with ``train-acro`` (pilot ``acro-random``)
    each seed is a different random acro flight, plus its own wind and noise.
controller
    A controller file, flown unchanged on every vehicle.

Outputs (:func:`write_outputs`): ``campaign.json`` (``meta`` and ``records``,
one record per flight: ``profile``, ``damage``, ``gust_sigma_m_s``, ``seed``,
``controller``, ``controller_kind``, ``mae_deg_s`` per axis, ``crashed``,
``crashed_at_s``, ``saturation_any``, ``feasible``), ``summary.md`` (median and
90th percentile MAE per controller and axis, crash counts on feasible cases and
infeasible flights) and ``mae.png`` (box plots of the per-axis MAE by
controller).
"""

from __future__ import annotations

import json
import logging
import multiprocessing
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import MfcConfig, PidConfig
from companion.control import AXES
from companion.profile import MotorDamage, VehicleProfile
from sitl.scenario import Scenario

__all__ = [
    "CAMPAIGN_FILES",
    "FlightSpec",
    "build_grid",
    "damaged_profile",
    "fly_one",
    "oracle_crashes",
    "plot_mae",
    "run_campaign",
    "summary_markdown",
    "write_outputs",
]

_log = logging.getLogger(__name__)

CAMPAIGN_FILES = ("campaign.json", "summary.md", "mae.png")
"""What :func:`write_outputs` writes into its folder."""


@dataclass(frozen=True)
class FlightSpec:
    """One flight of a campaign: what flies, how damaged, in which air, which seed."""

    profile_name: str
    profile: VehicleProfile
    damage: float
    gust_sigma_m_s: float
    seed: int
    controller_name: str
    controller: MfcConfig | PidConfig
    scenario: Scenario


def damaged_profile(profile: VehicleProfile, efficiency: float, motor: int = 0) -> VehicleProfile:
    """``profile`` with one motor's thrust and torque efficiency scaled by ``efficiency``.

    Parameters
    ----------
    profile
        The vehicle; it is not changed (profiles are frozen).
    efficiency
        Factor in (0, 1.5]; 1.0 returns ``profile`` itself.
    motor
        Index of the motor (output order).

    Returns
    -------
    VehicleProfile
        A validated copy; the factor multiplies any damage already on that motor.
    """
    if efficiency == 1.0:
        return profile
    if not 0.0 < efficiency <= 1.5:
        raise ValueError(f"efficiency must be in (0, 1.5], got {efficiency}")
    if not 0 <= motor < profile.n_motors:
        raise ValueError(f"motor index {motor} out of range 0..{profile.n_motors - 1}")
    dmg = profile.physics.damage
    motors = list(dmg.motors)
    for i, m in enumerate(motors):
        if m.motor == motor:
            motors[i] = m.model_copy(
                update={
                    "thrust_efficiency": m.thrust_efficiency * efficiency,
                    "torque_efficiency": m.torque_efficiency * efficiency,
                }
            )
            break
    else:
        motors.append(
            MotorDamage(motor=motor, thrust_efficiency=efficiency, torque_efficiency=efficiency)
        )
    physics = profile.physics.model_copy(
        update={"damage": dmg.model_copy(update={"motors": motors})}
    )
    copy = profile.model_copy(
        update={"physics": physics, "name": f"{profile.name} (motor {motor + 1} at {efficiency:g})"}
    )
    # model_copy does not validate: do it once here, at the edge.
    return VehicleProfile.model_validate(copy.model_dump())


def build_grid(
    profiles: dict[str, VehicleProfile],
    controllers: dict[str, MfcConfig | PidConfig],
    scenario: Scenario,
    *,
    damages: Sequence[float] = (1.0, 0.8, 0.6),
    gusts_m_s: Sequence[float] = (0.0, 2.0),
    seeds: Sequence[int] = (1000, 1001, 1002),
    duration_s: float | None = None,
) -> list[FlightSpec]:
    """Every combination, in a fixed order (profile, damage, gust, seed, controller).

    ``duration_s`` flies only the first seconds of the scenario.
    """
    base = (
        scenario if duration_s is None else scenario.model_copy(update={"duration_s": duration_s})
    )
    specs = []
    for pname, prof in profiles.items():
        for dmg in damages:
            vehicle = damaged_profile(prof, dmg)
            for gust in gusts_m_s:
                # Validated (model_copy is not): a bad gust is a ValueError here,
                # not a failure inside a worker's flight.
                wind = type(base.wind).model_validate(
                    {**base.wind.model_dump(), "gust_sigma_m_s": float(gust)}
                )
                sc = base.model_copy(update={"wind": wind})
                for seed in seeds:
                    for cname, cfg in controllers.items():
                        specs.append(
                            FlightSpec(
                                pname, vehicle, float(dmg), float(gust), int(seed), cname, cfg, sc
                            )
                        )
    return specs


def fly_one(spec: FlightSpec) -> dict[str, Any]:
    """Fly one spec and return its record (a top-level function, for the Pool)."""
    from sitl.lab.report import compute_metrics
    from sitl.lab.simulate import simulate_flight

    m = compute_metrics(
        simulate_flight(spec.profile, spec.controller, spec.scenario, seed=spec.seed)
    )
    return {
        "profile": spec.profile_name,
        "damage": spec.damage,
        "gust_sigma_m_s": spec.gust_sigma_m_s,
        "seed": spec.seed,
        "controller": spec.controller_name,
        "controller_kind": spec.controller.kind,
        "mae_deg_s": m["mae_deg_s"],
        "crashed": m["crashed"],
        "crashed_at_s": m["crashed_at_s"],
        "saturation_any": m["saturation_fraction"]["any"],
        "sim_time_s": m["sim_time_s"],
    }


def _case(spec: FlightSpec) -> tuple[str, float, float, int]:
    """The case a flight belongs to: everything but the controller."""
    return (spec.profile_name, spec.damage, spec.gust_sigma_m_s, spec.seed)


def oracle_crashes(spec: FlightSpec) -> bool:
    """Whether the oracle that may also set the collective (sitl.lab.oracle) crashes
    in ``spec``'s case: if it does, no controller could have flown it (a top-level
    function, for the Pool)."""
    from sitl.lab.oracle import oracle_flight

    crashed: bool = oracle_flight(spec.profile, spec.scenario, seed=spec.seed, collective=True)[
        "crashed"
    ]
    return crashed


def _map(fn: Any, items: Sequence[Any], workers: int, desc: str, progress: bool) -> list[Any]:
    """``fn`` over ``items`` on ``workers`` processes, in order, with a tqdm bar."""
    from tqdm import tqdm

    if workers <= 1 or len(items) <= 1:
        return [fn(x) for x in tqdm(items, desc=desc, unit="flight", disable=not progress)]
    with multiprocessing.Pool(min(workers, len(items))) as pool:
        it = pool.imap(fn, items, chunksize=1)
        return list(tqdm(it, total=len(items), desc=desc, unit="flight", disable=not progress))


def run_campaign(
    specs: Sequence[FlightSpec], *, workers: int = 2, progress: bool = True
) -> list[dict[str, Any]]:
    """Fly every spec on ``workers`` processes with a tqdm bar; records in spec order.

    Then, for each case (a vehicle, its damage, the gust and the seed) where any
    controller crashed, the oracle that may also set the collective flies it: each
    record's ``feasible`` is False when that oracle crashes too (the case is beyond
    any controller, reported apart and left out of the crash counts), True
    otherwise."""
    records: list[dict[str, Any]] = _map(fly_one, specs, workers, "campaign", progress)
    crashed: dict[tuple[str, float, float, int], FlightSpec] = {}
    for spec, rec in zip(specs, records):
        if rec["crashed"]:
            crashed.setdefault(_case(spec), spec)
    verdicts = _map(oracle_crashes, list(crashed.values()), workers, "oracle", progress)
    infeasible = {case for case, bad in zip(crashed, verdicts) if bad}
    for spec, rec in zip(specs, records):
        rec["feasible"] = _case(spec) not in infeasible
    return records


def _stats(records: list[dict[str, Any]], axis: str) -> tuple[float, float, int]:
    vals = [r["mae_deg_s"][axis] for r in records if r["mae_deg_s"][axis] is not None]
    if not vals:
        return float("nan"), float("nan"), 0
    return float(np.median(vals)), float(np.percentile(vals, 90)), len(vals)


def summary_markdown(records: list[dict[str, Any]], meta: dict[str, Any]) -> str:
    """The ``summary.md`` text: per controller and axis, median and p90 MAE, crashes."""
    controllers = list(dict.fromkeys(r["controller"] for r in records))
    lines = [
        "# Campaign summary",
        "",
        f"{len(records)} flights: scenario `{meta['scenario']}` (first {meta['duration_s']} s), "
        f"profiles {', '.join(meta['profiles'])}; motor 1 efficiency {meta['damages']}; "
        f"gust sigma {meta['gusts_m_s']} m/s; seeds {meta['seeds']}; "
        f"{meta['workers']} workers, {meta['wall_time_s']:.0f} s wall.",
        "",
        "Per-axis rate MAE (deg/s, pilot command against measured rate while airborne; "
        "crashed flights included up to the crash):",
        "",
        "| controller | kind | flights | crashes | infeasible | roll median | roll p90 "
        "| pitch median | pitch p90 | yaw median | yaw p90 |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in controllers:
        rs = [r for r in records if r["controller"] == c]
        cells = []
        for a in AXES:
            med, p90, _ = _stats(rs, a)
            cells += [f"{med:.1f}", f"{p90:.1f}"]
        crashes = sum(r["crashed"] and r.get("feasible", True) for r in rs)
        infeasible = sum(not r.get("feasible", True) for r in rs)
        lines.append(
            f"| {c} | {rs[0]['controller_kind']} | {len(rs)} | {crashes} | {infeasible} | "
            + " | ".join(cells)
            + " |"
        )
    lines += [
        "",
        "Crashes count feasible cases only. A case (vehicle, damage, gust, seed) is "
        "infeasible when the oracle that knows the plant and may also set the collective "
        "(sitl/lab/oracle.py) crashes in it too; its flights are counted under infeasible, "
        "whatever they did.",
        "",
        "Crashes by profile and damage (crashed / flown, infeasible cases included):",
        "",
    ]
    profiles = list(dict.fromkeys(r["profile"] for r in records))
    damages = list(dict.fromkeys(r["damage"] for r in records))
    lines.append("| profile | damage | " + " | ".join(controllers) + " |")
    lines.append("|---|---|" + "---|" * len(controllers))
    for p in profiles:
        for d in damages:
            cells = []
            for c in controllers:
                rs = [
                    r for r in records if (r["profile"], r["damage"], r["controller"]) == (p, d, c)
                ]
                cells.append(f"{sum(r['crashed'] for r in rs)}/{len(rs)}")
            lines.append(f"| {p} | {d:g} | " + " | ".join(cells) + " |")
    lines += ["", "Median worst-axis MAE by profile (deg/s):", ""]
    lines.append("| profile | " + " | ".join(controllers) + " |")
    lines.append("|---|" + "---|" * len(controllers))
    for p in profiles:
        cells = []
        for c in controllers:
            worst = [
                max(v for v in r["mae_deg_s"].values() if v is not None)
                for r in records
                if r["profile"] == p and r["controller"] == c and r["mae_deg_s"]["roll"] is not None
            ]
            cells.append(f"{np.median(worst):.1f}" if worst else "-")
        lines.append(f"| {p} | " + " | ".join(cells) + " |")
    lines += ["", "![MAE distributions](mae.png)", ""]
    return "\n".join(lines)


def plot_mae(records: list[dict[str, Any]], path: Path) -> Path:
    """Box plots of per-axis MAE for each controller (one panel per axis)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    controllers = list(dict.fromkeys(r["controller"] for r in records))
    fig, axs = plt.subplots(1, 3, figsize=(12, 4.5), sharey=False)
    for ax, a in zip(axs, AXES, strict=True):
        data = [
            [
                r["mae_deg_s"][a]
                for r in records
                if r["controller"] == c and r["mae_deg_s"][a] is not None
            ]
            for c in controllers
        ]
        ax.boxplot(data, whis=(5, 95), showfliers=True)
        ax.set_xticks(range(1, len(controllers) + 1), controllers, rotation=15, fontsize=8)
        for i, c in enumerate(controllers, start=1):
            crashed = [
                r["mae_deg_s"][a]
                for r in records
                if r["controller"] == c and r["crashed"] and r["mae_deg_s"][a] is not None
            ]
            ax.plot([i] * len(crashed), crashed, "x", color="tab:red")
        ax.set_title(f"{a} rate MAE")
        ax.set_ylabel("deg/s")
        ax.grid(alpha=0.3, axis="y")
    fig.suptitle(f"MAE distribution over {len(records)} flights (whiskers 5-95 %, x = crashed)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_outputs(
    records: list[dict[str, Any]], out_dir: str | Path, meta: dict[str, Any]
) -> dict[str, Path]:
    """Write ``campaign.json``, ``summary.md`` and ``mae.png`` into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "json": out / "campaign.json",
        "summary": out / "summary.md",
        "plot": out / "mae.png",
    }
    paths["json"].write_text(
        json.dumps({"meta": meta, "records": records}, indent=1) + "\n", encoding="utf-8"
    )
    paths["summary"].write_text(summary_markdown(records, meta), encoding="utf-8")
    plot_mae(records, paths["plot"])
    return paths
