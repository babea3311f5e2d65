"""Flight metrics, plots and the markdown report.

``metrics.json`` keys (a contract other tools read; extend, never rename):

``mae_deg_s``, ``rms_deg_s``, ``max_abs_deg_s``
    Per axis (``roll``, ``pitch``, ``yaw``): the pilot's commanded rate
    against the measured rate (the gyro as the controller saw it, as the
    paper measures), over the samples where the vehicle is airborne; held
    samples (non-finite input, the controller repeated its last output) and
    samples with a non-finite rate are left out. ``null`` when no sample is left.
``mae_true_deg_s``
    The same against the simulator's true rate, over the same samples.
``mae_skipped_samples``
    Airborne samples left out of the four error metrics above.
``time_in_saturation_s``, ``saturation_fraction``
    Per axis and ``any``: time the mixer could not realise the request.
``failsafe_events``
    A list of ``{"t_s", "kind", "detail"}``.
``crashed``, ``crashed_at_s``, ``sim_time_s``, ``wall_time_s``,
``airborne_time_s``, ``samples``, ``nonfinite_events``.
"""

from __future__ import annotations

import hashlib
import json
import platform
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

import numpy as np

from companion.control import AXES
from sitl.lab.simulate import FlightRecord

__all__ = ["AXES", "REPORT_FILES", "compute_metrics", "plot_flight", "versions", "write_report"]

REPORT_FILES = ("metrics.json", "flight.npz", "report.md", "rates.png", "motors_and_estimate.png")
"""What :func:`write_report` writes into its folder."""


def _per_axis(values: np.ndarray) -> dict[str, float]:
    return {a: round(float(v), 3) for a, v in zip(AXES, values, strict=True)}


def compute_metrics(record: FlightRecord) -> dict[str, Any]:
    """Metrics of one flight (see the module docstring for the keys)."""
    c = record.columns
    meta = record.meta
    t = c["t_s"]
    n = len(t)
    air = c["airborne"].astype(bool) if n else np.zeros(0, dtype=bool)
    dt = float(np.median(np.diff(t))) if n > 1 else 0.0
    out: dict[str, Any] = {}
    none = {a: None for a in AXES}
    err = np.degrees(c["meas_rad_s"] - c["ref_rad_s"]).reshape(n, 3)
    err_true = np.degrees(c["true_rad_s"] - c["ref_rad_s"]).reshape(n, 3)
    # A held sample is one the controller did not act on (a non-finite input),
    # often with a NaN gyro: one NaN would make every error metric NaN.
    held = c["held"].astype(bool) if n else np.zeros(0, dtype=bool)
    valid = air & ~held & np.isfinite(err).all(axis=1) & np.isfinite(err_true).all(axis=1)
    if valid.any():
        err, err_true = err[valid], err_true[valid]
        out["mae_deg_s"] = _per_axis(np.mean(np.abs(err), axis=0))
        out["rms_deg_s"] = _per_axis(np.sqrt(np.mean(err**2, axis=0)))
        out["max_abs_deg_s"] = _per_axis(np.max(np.abs(err), axis=0))
        out["mae_true_deg_s"] = _per_axis(np.mean(np.abs(err_true), axis=0))
    else:  # never left the ground, or nothing valid while airborne: no tracking to speak of
        out.update(mae_deg_s=none, rms_deg_s=none, max_abs_deg_s=none, mae_true_deg_s=none)
    if air.any():
        sat = c["sat_axes"][air].astype(bool)
        sat_t = sat.sum(axis=0) * dt
        out["time_in_saturation_s"] = {
            **_per_axis(sat_t),
            "any": round(float(sat.any(axis=1).sum() * dt), 3),
        }
        out["saturation_fraction"] = {
            **_per_axis(sat.mean(axis=0)),
            "any": round(float(sat.any(axis=1).mean()), 4),
        }
    else:
        out["time_in_saturation_s"] = {**none, "any": None}
        out["saturation_fraction"] = {**none, "any": None}
    out["failsafe_events"] = list(meta.get("failsafe_events", []))
    out["crashed"] = bool(meta.get("crashed", False))
    out["crashed_at_s"] = meta.get("crashed_at_s")
    out["sim_time_s"] = round(float(meta.get("sim_time_s", t[-1] if n else 0.0)), 3)
    out["wall_time_s"] = round(float(meta.get("wall_time_s", 0.0)), 3)
    out["airborne_time_s"] = round(float(air.sum() * dt), 3)
    out["samples"] = int(n)
    out["mae_skipped_samples"] = int(np.sum(air & ~valid))
    out["nonfinite_events"] = int(meta.get("nonfinite_events", 0))
    for key in ("profile", "controller_profile", "controller", "scenario", "seed", "imu_rate_hz"):
        if key in meta:
            out[key] = meta[key]
    return out


def versions() -> dict[str, str]:
    """Versions that shape a result, for the report."""
    out = {"python": platform.python_version()}
    for pkg in ("mfc-companion", "numpy", "pymavlink"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def plot_flight(record: FlightRecord, out_dir: Path, *, title: str = "") -> list[Path]:
    """Write the paper-style figures; returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    c = record.columns
    t = c["t_s"]
    written = []

    fig, axs = plt.subplots(3, 1, figsize=(11, 8), sharex=True)
    for i, (ax, name) in enumerate(zip(axs, AXES, strict=True)):
        ax.plot(t, np.degrees(c["ref_rad_s"][:, i]), lw=1.0, color="k", label="commanded (pilot)")
        ax.plot(t, np.degrees(c["meas_rad_s"][:, i]), lw=0.7, color="tab:red", label="measured")
        ax.set_ylabel(f"{name} rate (deg/s)")
        ax.grid(alpha=0.3)
    axs[0].legend(loc="upper right", fontsize=8)
    axs[-1].set_xlabel("time (s)")
    fig.suptitle(title or "Rate tracking")
    fig.tight_layout()
    p = out_dir / "rates.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    written.append(p)

    fig, axs = plt.subplots(2, 1, figsize=(11, 6), sharex=True)
    motors = c["motors"]
    for j in range(motors.shape[1]):
        axs[0].plot(t, motors[:, j], lw=0.6, label=f"motor {j + 1}")
    axs[0].set_ylabel("motor command (0-1)")
    axs[0].legend(loc="upper right", fontsize=8, ncol=4)
    axs[0].grid(alpha=0.3)
    is_mfc = bool(np.any(c["f_hat"]))
    series = c["f_hat"] if is_mfc else c["u"]
    for i, name in enumerate(AXES):
        axs[1].plot(t, series[:, i], lw=0.6, label=name)
    axs[1].set_ylabel("F_hat (rad/s^m)" if is_mfc else "PID output (normalised)")
    axs[1].legend(loc="upper right", fontsize=8)
    axs[1].grid(alpha=0.3)
    axs[1].set_xlabel("time (s)")
    fig.tight_layout()
    p = out_dir / "motors_and_estimate.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    written.append(p)
    return written


def _digest(path: str) -> str:
    """``sha256 <first 12 hex digits>`` of the file, to tell which version flew."""
    try:
        return "sha256 " + hashlib.sha256(Path(path).read_bytes()).hexdigest()[:12]
    except OSError:
        return "file not readable"


def write_report(
    record: FlightRecord,
    out_dir: str | Path,
    *,
    controller_path: str,
    profile_path: str,
    scenario_desc: str = "",
    passthrough: FlightRecord | None = None,
) -> dict[str, Any]:
    """Write ``metrics.json``, the plots, ``flight.npz`` and ``report.md`` into ``out_dir``.

    With ``passthrough`` (the same scenario flown sending the pilot's rates
    straight to the autopilot), its metrics go under ``metrics["passthrough"]``
    and the report compares the two.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    metrics = compute_metrics(record)
    if passthrough is not None:
        metrics["passthrough"] = compute_metrics(passthrough)
    metrics["versions"] = versions()
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n", encoding="utf-8")
    record.save(str(out / "flight.npz"))
    meta = record.meta
    title = f"{meta.get('profile')} / {meta.get('controller')} / {meta.get('scenario')}"
    images = plot_flight(record, out, title=title)

    def row(key: str, m: dict[str, Any] = metrics) -> str:
        vals = m[key]
        return " | ".join("-" if vals[a] is None else f"{vals[a]:.1f}" for a in AXES)

    compare: list[str] = []
    if passthrough is not None:
        pt = metrics["passthrough"]
        pt_end = (
            f" (ended at {pt['sim_time_s']:.1f} s by: "
            + ", ".join(str(e["kind"]) for e in pt["failsafe_events"]) + ")"
            if pt["failsafe_events"] else ""
        )  # fmt: skip
        compare = [
            "MFC on top of the autopilot's rate loop against the pilot's rates sent straight "
            "through (same scenario, seed and SITL; logs in `passthrough/`), MAE deg/s:",
            "",
            "| flight | roll | pitch | yaw |",
            "|---|---|---|---|",
            f"| MFC on top | {row('mae_deg_s')} |",
            f"| pass-through{pt_end} | {row('mae_deg_s', pt)} |",
            "",
        ]

    status = f"CRASHED at {metrics['crashed_at_s']:.2f} s" if metrics["crashed"] else "no crash"
    lines = [
        f"# Flight report: {title}",
        "",
        f"- vehicle profile: `{profile_path}` ({meta.get('profile')}; {_digest(profile_path)})",
        f"- controller given the profile of: {meta.get('controller_profile')}",
        f"- controller config: `{controller_path}` (kind `{meta.get('controller')}`; "
        f"{_digest(controller_path)})",
        f"- scenario: `{meta.get('scenario')}`, seed {meta.get('seed')}. {scenario_desc}".rstrip(),
        f"- outcome: {status}; simulated {metrics['sim_time_s']:.1f} s "
        f"(airborne {metrics['airborne_time_s']:.1f} s) in {metrics['wall_time_s']:.1f} s wall",
        f"- failsafe events: {len(metrics['failsafe_events'])}; non-finite inputs held: "
        f"{metrics['nonfinite_events']}",
        "",
        "Rate tracking, pilot's command against the measured rate, while airborne (deg/s):",
        "",
        "| metric | roll | pitch | yaw |",
        "|---|---|---|---|",
        f"| mean absolute error | {row('mae_deg_s')} |",
        f"| RMS error | {row('rms_deg_s')} |",
        f"| max abs error | {row('max_abs_deg_s')} |",
        f"| MAE against the true rate | {row('mae_true_deg_s')} |",
        f"| time in saturation (s) | {row('time_in_saturation_s')} |",
        "",
        *compare,
        *[f"![{p.stem}]({p.name})" for p in images],
        "",
        "Versions: " + ", ".join(f"{k} {v}" for k, v in metrics["versions"].items()),
        "",
    ]
    (out / "report.md").write_text("\n".join(lines), encoding="utf-8")
    return metrics
