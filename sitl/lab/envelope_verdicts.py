"""Reading envelope records: the targets met or not, hard regions, worst cases."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from companion.control import AXES
from sitl.lab.envelope_setup import CONTROLLERS, P90_TARGET, RATIO_TARGET, WORST_TARGET

__all__ = [
    "REGION_FIELDS",
    "hard_regions",
    "vehicle_figures",
    "verdicts",
    "worst_cases",
    "worst_ratio",
]


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


def worst_ratio(rec: dict[str, Any], key: str = "ratio_mfc_tuned") -> float:
    """Largest per-axis ratio (inf when MFC crashed or a ratio is undefined)."""
    if rec["flights"]["mfc"]["crashed"]:
        return math.inf
    vals = [rec[key][a] for a in AXES]
    return math.inf if any(v is None for v in vals) else float(max(vals))


def verdicts(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The three targets, met or not, over all cases and over intact vehicles only.

    The targets are judged on feasible cases: an infeasible one (``feasible``
    False: the oracle that may also set the collective crashed there too) is
    beyond any controller and is counted apart (``infeasible``).

    Returns
    -------
    dict
        ``crashes`` (per controller, every case), ``worst_ratio_mfc_tuned`` per
        axis (with the case), and for ``all`` and ``intact``: ``cases``,
        ``infeasible``, ``no_mfc_crash``, ``ratio_within_target``,
        ``better_than_default`` (bools, over the feasible cases) with the number
        of failing (case, axis) pairs; ``worst_case_ratio`` and
        ``p90_worst_axis_ratio`` (the worst axis per feasible case over the tuned
        PID, inf where MFC crashed) against the targets: ``worst_within_target``
        (<= :data:`WORST_TARGET`) and ``p90_within_target`` (<= :data:`P90_TARGET`).
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
        scoped = [r for r in records if scope == "all" or r["case"] == "intact"]
        rs = [r for r in scoped if r.get("feasible", True)]
        fail_tuned = sum(
            not _beats(r, "pid_tuned", a, RATIO_TARGET, False) for r in rs for a in AXES
        )
        fail_default = sum(not _beats(r, "pid_default", a, 1.0, True) for r in rs for a in AXES)
        mfc_crashes = sum(r["flights"]["mfc"]["crashed"] for r in rs)
        worst = sorted(worst_ratio(r) for r in rs)
        worst_case = worst[-1] if worst else math.nan
        # "higher": a case's value, never an interpolation (an MFC crash is inf).
        p90 = float(np.percentile(worst, 90, method="higher")) if worst else math.nan
        out[scope] = {
            "cases": len(scoped),
            "infeasible": len(scoped) - len(rs),
            "no_mfc_crash": mfc_crashes == 0,
            "mfc_crashes": mfc_crashes,
            "ratio_within_target": fail_tuned == 0,
            "ratio_failures": fail_tuned,
            "better_than_default": fail_default == 0,
            "default_failures": fail_default,
            "worst_case_ratio": worst_case,
            "p90_worst_axis_ratio": p90,
            "worst_within_target": worst_case <= WORST_TARGET,
            "p90_within_target": p90 <= P90_TARGET,
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


def vehicle_figures(rec: dict[str, Any]) -> dict[str, float]:
    """The record's vehicle figures of :data:`REGION_FIELDS` that are finite numbers."""
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
    worst = np.array([worst_ratio(r) for r in rs])
    rows = []
    for f in REGION_FIELDS:
        x = np.array([vehicle_figures(r).get(f, np.nan) for r in rs])
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
        return (-worst_ratio(r), -max(recorded, default=0.0), r["vehicle"], r["case"])

    out: list[dict[str, Any]] = []
    for r in sorted(records, key=key):
        if len(out) >= k:
            break
        if all(o["vehicle"] != r["vehicle"] for o in out):
            out.append(r)
    return out
