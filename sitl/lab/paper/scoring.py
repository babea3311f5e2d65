"""The paper reproduction judged: the scoreboard (MFC against the oracle and against
the PID tuned on each vehicle), whether a case is feasible at all (the oracle that
may also set the collective), and the paper's claims, each from the numbers.
"""

from __future__ import annotations

from typing import Any

from companion.control import AXES
from companion.profile import load_profile
from sitl.lab.oracle import oracle_flight
from sitl.lab.paper.flights import OWN_PID, PAPER_VEHICLES, PROFILE_DIR

TARGET_DEG_S = {"f450": 10.0, "f450_cut_props": 20.0, "tarot650": 10.0}
"""Per-axis MAE targets (deg/s) for the MFC flights: the paper's own thresholds for the F450
(IV-A, under 10) and the cut props (IV-B, under 20); the paper gives no number for the Tarot,
so it is held to the F450's 10."""
TARGET_OVER_ORACLE = 1.15
"""The target: MFC's MAE within 1.15x of the oracle's, per vehicle and axis."""
TARGET_OVER_OWN_PID = 1.0
"""The target: MFC no worse than the PID tuned on the very vehicle."""


def _ratio(num: float | None, den: float | None) -> float | None:
    if num is None or den is None or den <= 0.0:
        return None
    return round(num / den, 3)


def scoreboard(
    flights: dict[str, dict[str, Any]], feasible: dict[str, bool]
) -> dict[str, dict[str, Any]]:
    """Per paper vehicle and axis: MFC's MAE, the oracle's and the PID's tuned on that
    vehicle, MFC's ratio to each, whether each target is met, and whether the case is
    feasible (``feasible[vehicle]``: False when the oracle with the collective crashed)."""
    board: dict[str, dict[str, Any]] = {}
    for p in PAPER_VEHICLES:
        mfc = flights[f"{p}_mfc"]
        oracle = flights[f"{p}_oracle"]
        own = flights[f"{p}_{OWN_PID[p]}"]
        axes = {}
        for a in AXES:
            m, o, q = mfc["mae_deg_s"][a], oracle["mae_deg_s"][a], own["mae_deg_s"][a]
            over_oracle, over_pid = _ratio(m, o), _ratio(m, q)
            axes[a] = {
                "mfc": m,
                "oracle": o,
                "mfc_over_oracle": over_oracle,
                "pid_own": q,
                "mfc_over_pid_own": over_pid,
                "within_oracle_target": over_oracle is not None
                and over_oracle <= TARGET_OVER_ORACLE
                and not mfc["crashed"],
                "within_pid_target": over_pid is not None
                and over_pid <= TARGET_OVER_OWN_PID
                and not mfc["crashed"],
            }
        board[p] = {
            "pid_own": OWN_PID[p],
            "feasible": feasible[p],
            "crashed": {"mfc": mfc["crashed"], "oracle": oracle["crashed"],
                        "pid_own": own["crashed"]},
            "axes": axes,
        }  # fmt: skip
    return board


def case_feasible(profile: str, flights: dict[str, dict[str, Any]], sc: Any) -> bool:
    """False when a controller crashed on ``profile`` and the oracle that may also set
    the collective crashes too (the case is beyond any controller); flown only then."""
    if not any(f["crashed"] for f in flights.values() if f["profile"] == profile):
        return True
    plant = load_profile(PROFILE_DIR / f"{profile}.yaml")
    crashed: bool = oracle_flight(plant, sc, collective=True)["crashed"]
    return not crashed


def mean_mae(mae: dict[str, float | None]) -> float:
    """The mean over the axes that have a figure (NaN when none has)."""
    vals = [v for v in mae.values() if v is not None]
    return sum(vals) / len(vals) if vals else float("nan")


def fmt_mae(mae: dict[str, float | None], axes: tuple[str, ...] = AXES) -> str:
    """``"6.9 / 6.4 / 7.2"``: one decimal per axis, ``-`` for none."""
    return " / ".join("-" if mae[a] is None else f"{mae[a]:.1f}" for a in axes)


def assess(
    flights: dict[str, dict[str, Any]], gains: dict[str, dict[str, float]]
) -> list[dict[str, Any]]:
    """The paper's claims, each judged from the measured numbers.

    Returns a list of ``{"id", "paper", "holds", "detail"}``; ``holds`` is
    ``True``, ``False`` or ``None`` (not decidable from a number).
    """
    F = {k: v for k, v in flights.items()}
    claims: list[dict[str, Any]] = []

    def mae(name: str) -> dict[str, float | None]:
        m: dict[str, float | None] = F[name]["mae_deg_s"]
        return m

    def under(name: str, limit: float) -> tuple[bool, list[str]]:
        m = mae(name)
        bad = [a for a in AXES if m[a] is None or m[a] >= limit]  # type: ignore[operator]
        return (not bad and not F[name]["crashed"]), bad

    for cid, name, limit, sec in (
        ("f450_under_10", "f450_mfc", TARGET_DEG_S["f450"], "IV-A"),
        ("cut_props_under_20", "f450_cut_props_mfc", TARGET_DEG_S["f450_cut_props"], "IV-B"),
    ):
        ok, bad = under(name, limit)
        detail = f"measured {fmt_mae(mae(name))} deg/s (roll / pitch / yaw)"
        if F[name]["crashed"]:
            detail += f"; crashed at {F[name]['crashed_at_s']:.1f} s"
        if bad:
            detail += f"; at or above {limit:g} on: {', '.join(bad)}"
        claims.append(
            {"id": cid, "section": sec, "paper": f"MFC MAE < {limit:g} deg/s on every axis",
             "holds": ok, "detail": detail}
        )  # fmt: skip

    t_mfc, t_pid = F["tarot650_mfc"], F["tarot650_pid_tuned"]
    claims.append(
        {
            "id": "tarot_mfc_flies",
            "section": "IV-C",
            "paper": "the same MFC gains fly the Tarot 650 with its stuck gear",
            "holds": not t_mfc["crashed"],
            "detail": f"{'crashed' if t_mfc['crashed'] else 'no crash'}; MAE "
            f"{fmt_mae(mae('tarot650_mfc'))} deg/s (the paper gives no figure); the Tarot-tuned "
            f"PID measured {fmt_mae(mae('tarot650_pid_tuned'))}",
        }
    )
    claims.append(
        {
            "id": "tarot_pid_flies",
            "section": "IV-D",
            "paper": "the PID tuned on the Tarot flies it successfully",
            "holds": not t_pid["crashed"],
            "detail": f"{'crashed' if t_pid['crashed'] else 'no crash'}; MAE "
            f"{fmt_mae(mae('tarot650_pid_tuned'))} deg/s",
        }
    )
    f_pid, f_mfc = F["f450_pid_tuned"], F["f450_mfc"]
    m_pid_t, m_pid_f = mean_mae(mae("tarot650_pid_tuned")), mean_mae(mae("f450_pid_tuned"))
    worse_axes = [
        a for a in AXES if (mae("f450_pid_tuned")[a] or 0.0) > (mae("tarot650_pid_tuned")[a] or 0.0)
    ]
    degrades = f_pid["crashed"] or m_pid_f > m_pid_t
    claims.append(
        {
            "id": "pid_degrades_when_moved",
            "section": "IV-D",
            "paper": "the Tarot-tuned PID degrades when moved, unchanged, to the F450",
            "holds": bool(degrades),
            "detail": f"axis-mean MAE {m_pid_t:.1f} on the Tarot -> {m_pid_f:.1f} deg/s on the F450"
            f"{' (crashed)' if f_pid['crashed'] else ''}; worse on: "
            f"{', '.join(worse_axes) if worse_axes else 'no axis'}",
        }
    )
    m_mfc_f = mean_mae(mae("f450_mfc"))
    mfc_beats = (not f_mfc["crashed"]) and (f_pid["crashed"] or m_mfc_f < m_pid_f)
    claims.append(
        {
            "id": "mfc_beats_moved_pid_on_f450",
            "section": "IV-D",
            "paper": "on the F450, MFC is better than the PID moved from the Tarot",
            "holds": bool(mfc_beats),
            "detail": f"axis-mean MAE on the F450: MFC {m_mfc_f:.1f}, moved PID "
            f"{m_pid_f:.1f} deg/s "
            f"(MFC {fmt_mae(mae('f450_mfc'))}; PID {fmt_mae(mae('f450_pid_tuned'))})",
        }
    )
    # Robustness across vehicles. Each vehicle is a different task, so compare each
    # controller with the other on the same vehicle: how much of the tuned PID's edge
    # over MFC on its own vehicle survives the move?
    m_mfc_t = mean_mae(mae("tarot650_mfc"))
    edge_t = 1.0 - m_pid_t / m_mfc_t
    edge_f = 1.0 - m_pid_f / m_mfc_f
    claims.append(
        {
            "id": "mfc_more_robust_across_vehicles",
            "section": "IV-D",
            "paper": "MFC is much more robust across vehicles than PID",
            "holds": bool(degrades and mfc_beats),
            "detail": f"in absolute terms both controllers track better on the F450 than on the "
            f"Tarot (axis-mean MAE MFC {m_mfc_t:.1f} -> {m_mfc_f:.1f}, tuned PID {m_pid_t:.1f} -> "
            f"{m_pid_f:.1f} deg/s); relative to MFC on the same vehicle, the tuned PID's MAE is "
            f"{_rel(edge_t)} on the Tarot and {_rel(edge_f)} on the F450: "
            f"{_edge_story(edge_t, edge_f)}",
        }
    )
    return claims


def _rel(edge: float) -> str:
    """``edge`` = 1 - PID MAE / MFC MAE, as words."""
    return f"{abs(100 * edge):.0f} % {'lower' if edge > 0 else 'higher'} than MFC's"


def _edge_story(edge_tarot: float, edge_f450: float) -> str:
    if edge_tarot <= 0.0:
        return "the PID has no edge over MFC even on the vehicle it was tuned on, and " + (
            "MFC's lead grows on the F450" if edge_f450 < edge_tarot else "MFC's lead shrinks"
        )
    shrink = "shrinks" if edge_f450 < edge_tarot else "does not shrink"
    reverse = "but does not reverse it" if edge_f450 > 0 else "and reverses it"
    return f"the move {shrink} the PID's edge {reverse}"
