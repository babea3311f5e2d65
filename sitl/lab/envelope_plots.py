"""The envelope campaign's plots: the ratio over the envelope, the worst cases re-flown."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from companion.control import AXES
from sitl.lab.envelope_report import fmt
from sitl.lab.envelope_setup import RATIO_TARGET, EnvelopeCase, EnvelopeSetup, tuned_config
from sitl.lab.envelope_verdicts import vehicle_figures, worst_ratio

__all__ = ["plot_ratio", "plot_worst"]

_log = logging.getLogger(__name__)

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
    worst = np.array([worst_ratio(r) for r in records])
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
        x = np.array([vehicle_figures(r).get(field, np.nan) for r in records])
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
            case.profile, tuned_config(setup, rec["tuned_gains"]), setup.test
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
                    lw=0.7, label=f"{label} (MAE {fmt(m['mae_deg_s'][name])}{crash})")  # fmt: skip
            if m["crashed"]:
                ax.axvline(m["crashed_at_s"], color=colour, ls="--", lw=0.8)
        ax.set_ylabel(f"{name} rate (deg/s)")
        ax.set_title(
            f"{name}: ratio {fmt(rec['ratio_mfc_tuned'][name], '.2f')}", fontsize=9, loc="left"
        )
        ax.legend(loc="upper right", fontsize=7)
        ax.grid(alpha=0.3)
    axs[-1].set_xlabel("time (s)")
    fig.suptitle(f"{rec['vehicle']} / {rec['case']} on {setup.test.name}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
