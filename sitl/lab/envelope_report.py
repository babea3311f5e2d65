"""The envelope campaign's ``summary.md``."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from companion.control import AXES
from sitl.lab.envelope_setup import CONTROLLERS, P90_TARGET, RATIO_TARGET, WORST_TARGET
from sitl.lab.envelope_verdicts import hard_regions, verdicts, worst_ratio

__all__ = ["fmt", "summary_markdown"]

_ROOT = Path(__file__).resolve().parents[2]
"""The checkout (or install) this module belongs to: summary paths are shown from it."""


def fmt(v: float | None, spec: str = ".1f") -> str:
    """``v`` formatted with ``spec``, ``-`` for None."""
    return "-" if v is None else format(v, spec)


def _fmt_ratio(v: float) -> str:
    return "crash" if math.isinf(v) else f"{v:.2f}"


def _mae_cell(rec: dict[str, Any], axis: str) -> str:
    cells = []
    for c in CONTROLLERS:
        f = rec["flights"][c]
        cells.append(fmt(f["mae_deg_s"][axis]) + ("!" if f["crashed"] else ""))
    return " / ".join(cells)


def _met(flag: bool) -> str:
    return "**met**" if flag else "**not met**"


def _shown(path: str) -> str:
    """A file inside this checkout as a path from its root (the summary is kept in the
    repository: docs/research/envelope/), any other as given."""
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
        f"controller then flies `{te['name']}` (seed {te['seed']}, {te['duration_s']} s)"
        + (f", every flight through the `{te['link']}` link" if te.get("link") else "")
        + ". "
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
        f"| MFC never crashes on a feasible case | {_met(a['no_mfc_crash'])} "
        f"({a['mfc_crashes']} crashed of {a['cases'] - a['infeasible']}) | "
        f"{_met(i['no_mfc_crash'])} ({i['mfc_crashes']} of {i['cases'] - i['infeasible']}) |",
        f"| infeasible cases (the oracle with the collective crashes too) | "
        f"{a['infeasible']} of {a['cases']} | {i['infeasible']} of {i['cases']} |",
        f"| MFC / tuned PID MAE <= {RATIO_TARGET:g} on every axis | "
        f"{_met(a['ratio_within_target'])} ({a['ratio_failures']} case-axes fail) | "
        f"{_met(i['ratio_within_target'])} ({i['ratio_failures']} fail) |",
        f"| MFC / tuned PID, worst axis, worst case <= {WORST_TARGET:g} | "
        f"{_met(a['worst_within_target'])} ({_fmt_ratio(a['worst_case_ratio'])}) | "
        f"{_met(i['worst_within_target'])} ({_fmt_ratio(i['worst_case_ratio'])}) |",
        f"| MFC / tuned PID, worst axis, p90 <= {P90_TARGET:g} | "
        f"{_met(a['p90_within_target'])} ({_fmt_ratio(a['p90_worst_axis_ratio'])}) | "
        f"{_met(i['p90_within_target'])} ({_fmt_ratio(i['p90_worst_axis_ratio'])}) |",
        f"| MFC better than PX4's default PID on every axis | "
        f"{_met(a['better_than_default'])} ({a['default_failures']} case-axes fail) | "
        f"{_met(i['better_than_default'])} ({i['default_failures']} fail) |",
        "",
        "Crashes on the test flight: "
        + ", ".join(f"{c} {n}/{len(records)}" for c, n in v["crashes"].items())
        + ".",
        "",
    ]
    infeasible = [f"{r['vehicle']} / {r['case']}" for r in records if not r.get("feasible", True)]
    if infeasible:
        lines += [
            "Infeasible (the oracle that knows the plant and may also set the collective, "
            "sitl/lab/oracle.py, crashes too; left out of the targets): "
            + ", ".join(infeasible)
            + ".",
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
            f"| {ax} | {fmt(float(np.median(vals)) if vals else None, '.2f')} | "
            f"{fmt(float(np.percentile(vals, 90)) if vals else None, '.2f')} | "
            f"{fmt(w['ratio'] if w else None, '.2f')} | "
            f"{w['vehicle'] + ' / ' + w['case'] if w else '-'} |"
        )
    with_oracle = [r for r in records if r.get("ratio_mfc_oracle")]
    if with_oracle:
        lines += [
            "",
            "## Ratio MFC / oracle per axis",
            "",
            "The oracle knows the plant and sees its true state (sitl/lab/oracle.py), flown on "
            "the same test flight and read the same way; below 1, MFC scored better on the "
            "measured rate (see the oracle's notes: a reference, not a bound).",
            "",
            "| axis | median | p90 | worst | worst case |",
            "|---|---|---|---|---|",
        ]
        for ax in AXES:
            ranked = sorted(
                (r["ratio_mfc_oracle"][ax], r["vehicle"], r["case"])
                for r in with_oracle
                if r["ratio_mfc_oracle"][ax] is not None and not r["flights"]["mfc"]["crashed"]
            )
            vals = [x[0] for x in ranked]
            lines.append(
                f"| {ax} | {fmt(float(np.median(vals)) if vals else None, '.2f')} | "
                f"{fmt(float(np.percentile(vals, 90)) if vals else None, '.2f')} | "
                f"{fmt(ranked[-1][0] if ranked else None, '.2f')} | "
                f"{ranked[-1][1] + ' / ' + ranked[-1][2] if ranked else '-'} |"
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
            ratios = ", ".join(f"{ax} {fmt(rec['ratio_mfc_tuned'][ax], '.2f')}" for ax in AXES)
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
            cells += [_mae_cell(r, ax), fmt(r["ratio_mfc_tuned"][ax], ".2f")]
        w, wd = worst_ratio(r), worst_ratio(r, "ratio_mfc_default")
        lines.append(
            f"| {r['vehicle']} | {r['case']} | "
            + " | ".join(cells)
            + f" | {_fmt_ratio(w)} | {_fmt_ratio(wd)} |"
        )
    lines.append("")
    return "\n".join(lines)
