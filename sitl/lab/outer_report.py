"""The outer loops' figures of a MAVLink flight (``companion fly --mode ...``).

From the SITL's log (the true position) over the companion's engaged time, and,
with a mission, against its plan: the waypoints from where the mission started
(the companion's ``mission_started`` event: its position estimate then).

``metrics.json`` gains ``outer``: ``mode``, ``engaged_s``, ``airborne_s``,
``crashed``, ``gain_scale_min`` and ``backed_off_s`` (from the companion's control
log: the least scale on the outer gains while engaged and the time it was below
1, the backoff while our rate loop saturated), and with a mission ``mission``:
``waypoints``, ``reached`` (the companion's ``mission_waypoint`` events), and
``path_error_m``, the distance from the true position to the planned path (the
straight legs between the start and the waypoints) while airborne: ``rms``,
``max``, ``horizontal_rms`` (to the legs seen from above), ``vertical_rms`` (from
the planned height at the closest point). ``path.png`` draws the path flown against the plan.
"""

from __future__ import annotations

import itertools
import json
import re
from pathlib import Path
from typing import Any

import numpy as np

from companion.mission import Mission
from sitl.flight_log import read_log
from sitl.lab.fly import FlightProcesses

__all__ = [
    "OUTER_SIMULATE_FILES",
    "mission_plan",
    "outer_metrics",
    "plot_outer_flight",
    "plot_path",
    "segment_distances",
    "write_outer_report",
]

_ORIGIN = re.compile(r"from N (-?[\d.]+) E (-?[\d.]+) D (-?[\d.]+) m")


def mission_plan(mission: Mission, events: list[dict[str, Any]]) -> np.ndarray | None:
    """The planned points (start, then the waypoints), NED (n, 3); None without a
    ``mission_started`` event."""
    for e in events:
        if e.get("kind") == "mission_started":
            m = _ORIGIN.search(str(e.get("detail", "")))
            if m is None:
                return None
            o = np.array([float(m.group(i)) for i in (1, 2, 3)])
            wps = [o + np.array([w.north_m, w.east_m, -w.up_m]) for w in mission.waypoints]
            return np.array([o, *wps])
    return None


def segment_distances(points: np.ndarray, plan: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per point: the distance to the closest leg of ``plan`` and that closest
    point on it (both for points (n, d) and a polyline (m, d), any d)."""
    best = np.full(len(points), np.inf)
    closest = np.zeros_like(points)
    legs = list(itertools.pairwise(plan)) or [(plan[0], plan[0])]
    for a, b in legs:
        ab = b - a
        den = float(ab @ ab)
        s = np.zeros(len(points)) if den == 0.0 else np.clip((points - a) @ ab / den, 0.0, 1.0)
        c = a + s[:, None] * ab
        d = np.linalg.norm(points - c, axis=1)
        better = d < best
        best[better] = d[better]
        closest[better] = c[better]
    return best, closest


def _backoff(flight: FlightProcesses) -> dict[str, float | None]:
    """The outer gains' backoff while engaged, from the companion's control log
    (None where the log or its column is missing)."""
    from companion.records import read_control_log

    none: dict[str, float | None] = {"gain_scale_min": None, "backed_off_s": None}
    if not flight.control_log.exists():
        return none
    cols, _ = read_control_log(flight.control_log)
    scale = cols.get("outer_gain_scale")
    if scale is None:
        return none
    eng = (cols["engaged"] > 0.5) & np.isfinite(scale)
    if not eng.any():
        return none
    t = cols["t_s"][eng]
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    s = scale[eng]
    return {
        "gain_scale_min": round(float(s.min()), 3),
        "backed_off_s": round(float((s < 1.0).sum()) * dt, 2),
    }


def _engaged(flight: FlightProcesses) -> tuple[float, float] | None:
    ev = flight.companion_events
    t0 = next((float(e["t_s"]) for e in ev if e.get("kind") == "engaged"), None)
    if t0 is None:
        return None
    ends = [float(e["t_s"]) for e in ev if e.get("kind") in ("duration", "signal")]
    ends += [float(e["t_s"]) for e in ev if str(e.get("kind", "")).startswith("failsafe")]
    return t0, min(ends) if ends else np.inf


def outer_metrics(
    flight: FlightProcesses, mode: str, mission: Mission | None = None
) -> dict[str, Any]:
    """``metrics["outer"]`` of a flight (module docstring)."""
    log = read_log(flight.sitl_log)
    t, pos = log["t_s"], log["pos_ned_m"]
    span = _engaged(flight)
    out: dict[str, Any] = {"mode": mode, "crashed": bool(log.summary.get("crashed", False))}
    if span is None:
        return {**out, "engaged_s": 0.0, "airborne_s": 0.0}
    sel = (t >= span[0]) & (t <= span[1])
    airborne = sel & (pos[:, 2] < -0.3)
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    out["engaged_s"] = round(float(sel.sum()) * dt, 2)
    out["airborne_s"] = round(float(airborne.sum()) * dt, 2)
    out.update(_backoff(flight))
    if mission is None:
        return out
    events = flight.companion_events
    reached = [e for e in events if e.get("kind") == "mission_waypoint"]
    m: dict[str, Any] = {
        "waypoints": len(mission.waypoints),
        "reached": int(str(reached[-1]["detail"]).split(" of ")[0]) if reached else 0,
    }
    plan = mission_plan(mission, events)
    if plan is not None and airborne.any():
        p = pos[airborne]
        d3, c3 = segment_distances(p, plan)
        dh, _ = segment_distances(p[:, :2], plan[:, :2])
        dv = np.abs(p[:, 2] - c3[:, 2])
        m["path_error_m"] = {
            "rms": round(float(np.sqrt(np.mean(d3**2))), 3),
            "max": round(float(d3.max()), 3),
            "horizontal_rms": round(float(np.sqrt(np.mean(dh**2))), 3),
            "vertical_rms": round(float(np.sqrt(np.mean(dv**2))), 3),
        }
    out["mission"] = m
    return out


def plot_path(
    flight: FlightProcesses, out_dir: Path, mission: Mission | None = None, *, title: str = ""
) -> Path:
    """``path.png``: the path flown seen from above (east right, north up) and the
    height in time, with the mission's plan when there is one."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    log = read_log(flight.sitl_log)
    t, pos = log["t_s"], log["pos_ned_m"]
    span = _engaged(flight)
    sel = np.ones(len(t), bool) if span is None else (t >= span[0]) & (t <= span[1])
    fig, (ax, az) = plt.subplots(1, 2, figsize=(11, 5), gridspec_kw={"width_ratios": [1, 1.3]})
    ax.plot(pos[sel, 1], pos[sel, 0], lw=1.2, label="flown (true position)")
    az.plot(t[sel] - t[sel][0] if sel.any() else t, -pos[sel, 2], lw=1.2, label="flown")
    plan = mission_plan(mission, flight.companion_events) if mission is not None else None
    if plan is not None:
        ax.plot(plan[:, 1], plan[:, 0], "k--", lw=1.0, label="plan")
        ax.plot(plan[1:, 1], plan[1:, 0], "ko", ms=5)
        for k, (n, e) in enumerate(plan[1:, :2], start=1):
            ax.annotate(str(k), (e, n), textcoords="offset points", xytext=(5, 5))
        for up in sorted(set(np.round(-plan[1:, 2], 2))):
            az.axhline(up, color="k", ls=":", lw=0.8)
    ax.set_xlabel("east, m")
    ax.set_ylabel("north, m")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    az.set_xlabel("time engaged, s")
    az.set_ylabel("height, m (up)")
    az.grid(True, alpha=0.3)
    fig.suptitle(title or "path")
    fig.tight_layout()
    path = Path(out_dir) / "path.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


OUTER_SIMULATE_FILES = ("metrics.json", "report.md", "path.png")
"""What :func:`write_outer_report` writes into its folder (``companion simulate --mode``)."""


def plot_outer_flight(columns: dict[str, np.ndarray], out_dir: Path, *, title: str) -> Path:
    """``path.png`` of an in-process outer flight: the path flown (true position)
    and the setpoint seen from above, and the height against its setpoint in time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t, pos, sp = columns["t_s"], columns["pos_ned_m"], columns["sp_pos_ne_m"]
    fig, (ax, az) = plt.subplots(1, 2, figsize=(11, 5), gridspec_kw={"width_ratios": [1, 1.3]})
    ax.plot(sp[:, 1], sp[:, 0], "k--", lw=1.0, label="setpoint")
    ax.plot(pos[:, 1], pos[:, 0], lw=1.2, label="flown (true position)")
    az.plot(t, columns["sp_up_m"], "k--", lw=1.0, label="setpoint")
    az.plot(t, -pos[:, 2], lw=1.2, label="flown")
    ax.set_xlabel("east, m")
    ax.set_ylabel("north, m")
    ax.set_aspect("equal", adjustable="datalim")
    az.set_xlabel("time, s")
    az.set_ylabel("height, m (up)")
    for a in (ax, az):
        a.grid(True, alpha=0.3)
        a.legend(loc="best", fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    path = Path(out_dir) / "path.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_outer_report(
    columns: dict[str, np.ndarray],
    figures: dict[str, Any],
    out_dir: Path,
    *,
    description: str,
    controller_path: str,
    profile_path: str,
    wall_time_s: float,
) -> dict[str, Any]:
    """``metrics.json`` (``outer``: the figures of
    :func:`sitl.lab.outer_flight.outer_metrics`), ``path.png`` and ``report.md``
    of an in-process outer flight; returns the metrics."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t = columns["t_s"]
    metrics = {
        "scenario": figures["scenario"],
        "mode": figures["mode"],
        "profile": profile_path,
        "controller": controller_path,
        "seed": figures["seed"],
        "crashed": figures["crashed"],
        "sim_time_s": round(float(t[-1]), 3) if len(t) else 0.0,
        "wall_time_s": round(wall_time_s, 2),
        "outer": figures,
    }
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    plot_outer_flight(columns, out_dir, title=f"{figures['scenario']} on {figures['profile']}")
    rows = [
        ("horizontal position RMS, m", figures.get("pos_rms_h_m")),
        ("vertical position RMS, m", figures.get("pos_rms_v_m")),
        ("path error RMS, m", figures.get("path_rms_m")),
        ("path error max, m", figures.get("path_max_m")),
        ("attitude MAE (roll, pitch), deg", figures.get("att_mae_deg")),
        ("heading MAE, deg", figures.get("yaw_mae_deg")),
        ("rate loop saturated, s", figures.get("rate_sat_s")),
        ("tilt limited, s", figures.get("tilt_limited_s")),
    ]
    lift = "-" if figures.get("lift_off_s") is None else f"{figures['lift_off_s']:.2f}"
    lines = [
        f"# {figures['scenario']} ({figures['mode']} mode) on {figures['profile']}",
        "",
        description,
        "",
        f"{'CRASHED' if figures['crashed'] else 'Flew'} {metrics['sim_time_s']} s simulated "
        f"in {metrics['wall_time_s']} s; lift-off at {lift} s. "
        "Scored from the true state against the setpoints (`metrics.json`, key `outer`).",
        "",
        "| figure | value |",
        "|---|---|",
        *(f"| {k} | {'-' if v is None else round(v, 3)} |" for k, v in rows),
        "",
        "![path](path.png)",
        "",
    ]
    (out_dir / "report.md").write_text("\n".join(lines))
    return metrics
