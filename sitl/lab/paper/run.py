"""One run of the paper reproduction: resume what an earlier run left, fly what is
missing, judge it and write ``results.json`` and ``results.md`` in the output folder.

Each flight's metrics are stored in ``OUT/records/`` as it lands (keyed by
:func:`sitl.lab.paper.flights.flight_keys`); a run that was killed is resumed by
the same command, which flies only what is missing. A finished run
(``results.json`` written) is flown afresh.
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path
from typing import Any

from companion.profile import load_profile
from sitl.lab.campaign_store import CampaignStore, grid_digest
from sitl.lab.paper.analysis import MOTION_KEYS, input_gains
from sitl.lab.paper.flights import (
    CONTROLLERS,
    DATA_DIR,
    FLIGHTS,
    PAPER_VEHICLES,
    PROFILE_DIR,
    QUICK_S,
    RECORDS_DIR,
    ROOT,
    RUN_MANIFEST,
    SCENARIO,
    flight_keys,
    fly_flight,
    paper_scenario,
    sha256_file,
)
from sitl.lab.paper.prose import explain, print_summary, write_markdown
from sitl.lab.paper.scoring import assess, case_feasible, scoreboard
from sitl.lab.report import versions


class SchedulerError(ValueError):
    """No Dask scheduler answered at the address given."""


def run(
    out: Path,
    *,
    quick: bool,
    workers: int,
    scheduler: str | None = None,
    link: str | None = None,
    progress: bool = True,
) -> int:
    """Fly the reproduction into ``out``; 0 when every flight flew, 1 when one raised
    (listed on stderr, nothing written). ``quick`` flies the first :data:`QUICK_S`
    seconds only; ``link`` is a companion link (:func:`sitl.link_model.parse_link`).

    Raises :class:`SchedulerError` when ``scheduler`` is given and does not answer.
    """
    out.mkdir(parents=True, exist_ok=True)
    duration = QUICK_S if quick else None
    sc = paper_scenario(None, link)
    t0 = time.perf_counter()
    keys = flight_keys(duration, link)
    store = CampaignStore(out, manifest=RUN_MANIFEST, finished="results.json")
    grid = grid_digest(keys)
    if store.can_resume(grid):
        n = len(store.load(RECORDS_DIR, keys))
        print(f"resuming: {n} of {len(keys)} flights done", file=sys.stderr)
    else:
        shutil.rmtree(out / RECORDS_DIR, ignore_errors=True)  # an earlier run's
    store.start(grid, len(keys))
    jobs = [(f, duration, str(out), link) for f in FLIGHTS]
    try:
        done, outcomes = store.run_missing(
            RECORDS_DIR, keys, fly_flight, jobs, scheduler=scheduler, workers=workers,
            desc="paper flights", unit="flight", progress=progress,
        )  # fmt: skip
    except ValueError as exc:  # no scheduler answered
        raise SchedulerError(str(exc)) from exc
    failed = [f"{o.item[0].name}: {o.error}" for o in outcomes if not o.ok]
    if failed:
        print("flights that raised:\n" + "\n".join(failed), file=sys.stderr)
        return 1
    metrics = [done[k] for k in keys]
    wall = time.perf_counter() - t0

    flights: dict[str, dict[str, Any]] = {}
    for f, m in zip(FLIGHTS, metrics, strict=True):
        flights[f.name] = {
            "profile": f.profile,
            "controller": f.controller,
            "role": f.role,
            "section": f.section,
            "paper_says": f.paper_says,
            "mae_deg_s": m["mae_deg_s"],
            "rms_deg_s": m["rms_deg_s"],
            "mae_true_deg_s": m["mae_true_deg_s"],
            "saturation_fraction": m["saturation_fraction"],
            "crashed": m["crashed"],
            "crashed_at_s": m["crashed_at_s"],
            "sim_time_s": m["sim_time_s"],
            "airborne_time_s": m["airborne_time_s"],
            "after_fast_changes": m["after_fast_changes"],
            "report": f"{f.name}/report.md",
            "plots": [f"{f.name}/rates.png", f"{f.name}/motors_and_estimate.png"],
        }
        for key in MOTION_KEYS:
            if key in m:
                flights[f.name][key] = m[key]
    gains = {p: input_gains(load_profile(PROFILE_DIR / f"{p}.yaml")) for p in PAPER_VEHICLES}
    flown = paper_scenario(duration, link)
    feasible = {p: case_feasible(p, flights, flown) for p in PAPER_VEHICLES}
    ctrl = {}
    for k, fname in CONTROLLERS.items():
        p = DATA_DIR / fname
        shown = p.relative_to(ROOT) if p.is_relative_to(ROOT) else p
        ctrl[k] = {"path": str(shown), "sha256": sha256_file(p)}

    result: dict[str, Any] = {
        "scenario": SCENARIO,
        "seed": sc.seed,
        "quick": bool(quick),
        "duration_s": duration if duration is not None else round(metrics[0]["sim_time_s"], 1),
        "controllers": ctrl,
        "paper": {
            "f450_mfc_mae_below_deg_s": 10.0,
            "f450_cut_props_mfc_mae_below_deg_s": 20.0,
            "pid_moved_to_f450": "degrades",
        },
        "scoreboard": scoreboard(flights, feasible),
        "flights": flights,
        "claims": assess(flights, gains),
        "why": explain(flights, gains),
        "input_gains": gains,
        "link": sc.link.describe(),
        "command": "python scripts/reproduce_paper.py --out "
        + str(out)
        + (" --quick" if quick else "")
        + (f" --link {link}" if link else ""),
        "workers": workers,
        "wall_time_s": round(wall, 1),
        "versions": versions(),
    }
    (out / "results.json").write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    write_markdown(result, out / "results.md")
    print_summary(result, out, wall)
    return 0
