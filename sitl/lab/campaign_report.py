"""A campaign's final outputs: ``flights.parquet``, then from it ``summary.md``,
``mae.png`` and ``campaign.json`` (the keys are in :mod:`sitl.lab.campaign`'s
docstring, the table's columns in :mod:`sitl.lab.table`).

``campaign.json`` is written last: its presence marks a finished run
(:mod:`sitl.lab.campaign_store`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from companion.control import AXES

__all__ = ["CAMPAIGN_FILES", "plot_mae", "summary_markdown", "write_outputs"]

CAMPAIGN_FILES = ("campaign.json", "summary.md", "mae.png", "flights.parquet")
"""What :func:`write_outputs` writes into its folder."""


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
        crashes = sum(r["crashed"] is True and r.get("feasible") is not False for r in rs)
        infeasible = sum(r.get("feasible") is False for r in rs)
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
        *_failures(records),
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
                cells.append(f"{sum(r['crashed'] is True for r in rs)}/{len(rs)}")
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
    lines += _against_the_limit(records, profiles, controllers)
    lines += ["", "![MAE distributions](mae.png)", ""]
    return "\n".join(lines)


def _median(vals: list[float]) -> str:
    return f"{np.median(vals):.2f}" if vals else "-"


def _against_the_limit(
    records: list[dict[str, Any]], profiles: list[str], controllers: list[str]
) -> list[str]:
    """Per profile and axis: the oracle's median MAE, each controller's median MAE
    and its median ratio to the oracle in the same case, and the first MFC
    controller's median ratio to each PID in the same flight's case."""
    if not any(r.get("oracle_mae_deg_s") for r in records):
        return []
    kind = {r["controller"]: r["controller_kind"] for r in records}
    mfc = next((c for c in controllers if kind[c] == "mfc"), None)
    pids = [c for c in controllers if kind[c] == "pid"] if mfc else []
    head = ["profile", "axis", "oracle"]
    for c in controllers:
        head += [c, f"{c} / oracle"]
    head += [f"{mfc} / {p}" for p in pids]
    lines = [
        "",
        "## Against the limit",
        "",
        "Medians over each profile's flights (all damages, gusts and seeds; crashed and "
        "raised flights left out) of the MAE (deg/s) and of the per-case ratio to the "
        "oracle that knows the plant (sitl/lab/oracle.py; below 1, the controller scored "
        "better on the measured rate) and, for MFC, to each PID flown in the same case:",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]

    def flown(r: dict[str, Any]) -> bool:
        return r["crashed"] is False and r["mae_deg_s"]["roll"] is not None

    case_keys = ("profile", "damage", "gust_sigma_m_s", "seed")
    by_case = {(tuple(r[k] for k in case_keys), r["controller"]): r for r in records if flown(r)}
    for p in profiles:
        rs = [r for r in records if r["profile"] == p and flown(r)]
        for a in AXES:
            limit = [r["oracle_mae_deg_s"][a] for r in rs if r.get("oracle_mae_deg_s")]
            cells = [p, a, _median(limit)]
            for c in controllers:
                own = [r for r in rs if r["controller"] == c]
                ratios = [
                    r["mae_deg_s"][a] / r["oracle_mae_deg_s"][a]
                    for r in own
                    if r.get("oracle_mae_deg_s") and r["oracle_mae_deg_s"][a]
                ]
                cells += [_median([r["mae_deg_s"][a] for r in own]), _median(ratios)]
            for pid in pids:
                ratios = []
                for r in rs:
                    other = by_case.get((tuple(r[k] for k in case_keys), pid))
                    if r["controller"] == mfc and other and other["mae_deg_s"][a]:
                        ratios.append(r["mae_deg_s"][a] / other["mae_deg_s"][a])
                cells.append(_median(ratios))
            lines.append("| " + " | ".join(cells) + " |")
    return lines


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
                if r["controller"] == c and r["crashed"] is True and r["mae_deg_s"][a] is not None
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


def _failures(records: list[dict[str, Any]]) -> list[str]:
    """Lines naming the flights that raised, and cases the oracle could not judge."""
    lines = []
    failed = [r for r in records if r.get("error")]
    if failed:
        lines += ["", f"{len(failed)} flights raised (no figures; the `error` column of "
                  "flights.parquet says what):", ""]  # fmt: skip
        lines += [
            f"- {r['profile']} damage {r['damage']:g} gust {r['gust_sigma_m_s']:g} seed "
            f"{r['seed']} {r['controller']}: {r['error']}"
            for r in failed[:20]
        ]
        if len(failed) > 20:
            lines.append(f"- ... and {len(failed) - 20} more")
    unjudged = sum(r.get("feasible", True) is None for r in records)
    if unjudged:
        lines += ["", f"{unjudged} flights are in cases whose oracle flight raised: their "
                  "feasibility is unknown (null) and their crashes are counted."]  # fmt: skip
    return lines


def _versions(records: list[dict[str, Any]]) -> list[dict[str, str]]:
    """The distinct version sets the flights were flown with (usually one)."""
    seen = {tuple(sorted(r["versions"].items())) for r in records if r.get("versions")}
    return [dict(v) for v in sorted(seen)]


def write_outputs(
    records: list[dict[str, Any]], out_dir: str | Path, meta: dict[str, Any]
) -> dict[str, Path]:
    """Write ``flights.parquet``, then from it ``summary.md``, ``mae.png`` and
    ``campaign.json`` into ``out_dir``.

    ``records`` are :func:`sitl.lab.campaign.run_campaign`'s; ``meta`` gains
    ``versions`` (:func:`_versions`).
    """
    from sitl.lab.atomic import write_json_atomic
    from sitl.lab.table import read_table, to_records, to_table, write_table

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "table": out / "flights.parquet",
        "summary": out / "summary.md",
        "plot": out / "mae.png",
        "json": out / "campaign.json",
    }
    write_table(to_table(records), paths["table"])
    rows = to_records(read_table(paths["table"]))
    meta = {**meta, "versions": _versions(records)}
    paths["summary"].write_text(summary_markdown(rows, meta), encoding="utf-8")
    plot_mae(rows, paths["plot"])
    write_json_atomic(paths["json"], {"meta": meta, "records": rows})
    return paths
