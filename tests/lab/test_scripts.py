"""Smoke-run the scripts in ``scripts/`` as subprocesses."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from companion.control import AXES

ROOT = Path(__file__).resolve().parents[2]
PAPER_FLIGHTS = {
    "f450_mfc",
    "f450_cut_props_mfc",
    "tarot650_mfc",
    "tarot650_pid_tuned",
    "f450_pid_tuned",
}


def _reproduce_quick(out: Path, workers: int) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "reproduce_paper.py"), "--quick", "--out", str(out),
         "--workers", str(workers), "--no-progress"],
        cwd=out.parent, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip


@pytest.mark.slow  # about 30 s alone: fourteen 15 s flights and their plots, two again
@pytest.mark.long
def test_reproduce_paper_quick(tmp_path: Path) -> None:
    out = tmp_path / "paper"
    proc = _reproduce_quick(out, workers=2)
    assert proc.returncode == 0, proc.stderr[-2000:]
    doc = json.loads((out / "results.json").read_text(encoding="utf-8"))
    for key in ("scenario", "seed", "quick", "duration_s", "controllers", "paper", "flights",
                "claims", "why", "input_gains", "command", "versions"):  # fmt: skip
        assert key in doc, key
    assert doc["scenario"] == "paper-acro" and doc["quick"] is True and doc["duration_s"] == 15.0
    assert set(doc["flights"]) >= PAPER_FLIGHTS
    for name, f in doc["flights"].items():
        for a in AXES:
            v = f["mae_deg_s"][a]
            assert v is not None and math.isfinite(v) and v >= 0.0, (name, a, v)
        assert isinstance(f["crashed"], bool)
        for plot in f["plots"]:
            assert (out / plot).stat().st_size > 0
    for name in ("f450_mfc", "f450_cut_props_mfc", "tarot650_mfc"):
        floor = doc["flights"][name]["acceleration_floor_deg_s"]
        ideal = doc["flights"][name]["ideal_tracker_deg_s"]
        measured = doc["flights"][name]["ideal_tracker_measured_deg_s"]
        for a in ("roll", "pitch"):  # a lower bound: never above what was flown
            assert 0.0 <= floor[a] <= doc["flights"][name]["mae_deg_s"][a], (name, a, floor)
            assert floor[a] <= ideal[a], (name, a, floor, ideal)
            # the filtered rate changes no faster than the rate: the floor holds for it too
            assert floor[a] <= measured[a], (name, a, floor, measured)
    assert {c["id"] for c in doc["claims"]} >= {"f450_under_10", "pid_degrades_when_moved"}
    assert all(c["holds"] in (True, False, None) for c in doc["claims"])
    for p, row in doc["scoreboard"].items():  # each vehicle against its limit and its own PID
        assert isinstance(row["feasible"], bool)
        for a in AXES:
            x = row["axes"][a]
            assert x["oracle"] == doc["flights"][f"{p}_oracle"]["mae_deg_s"][a]
            assert x["mfc_over_oracle"] == pytest.approx(x["mfc"] / x["oracle"], abs=1e-3)
            assert x["mfc_over_pid_own"] == pytest.approx(x["mfc"] / x["pid_own"], abs=1e-3)
    assert set(doc["scoreboard"]) == {"f450", "f450_cut_props", "tarot650"}
    md = (out / "results.md").read_text(encoding="utf-8")
    assert "| flight |" in md and "f450_pid_tuned" in md
    assert md.index("## Scoreboard") < md.index("## The paper's flights") < md.index("| flight |")
    assert doc["controllers"]["pid_tuned"]["path"].endswith("pid_tarot_tuned.yaml")
    # As if killed before its last two flights landed: the same command flies only them.
    records = sorted((out / "records").glob("*.json"))
    assert len(records) == len(doc["flights"])
    for r in records[:2]:
        r.unlink()
    (out / "results.json").unlink()
    kept = {r: r.stat().st_mtime_ns for r in records[2:]}
    again = _reproduce_quick(out, workers=1)
    assert again.returncode == 0, again.stderr[-2000:]
    assert f"resuming: {len(records) - 2} of {len(records)} flights done" in again.stderr
    assert {r: r.stat().st_mtime_ns for r in records[2:]} == kept
    resumed = json.loads((out / "results.json").read_text(encoding="utf-8"))
    assert resumed["flights"] == doc["flights"] and resumed["scoreboard"] == doc["scoreboard"]


def test_reproduce_paper_refuses_an_unknown_link(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "reproduce_paper.py"), "--quick", "--out",
         str(tmp_path / "paper"), "--link", "carrier-pigeon"],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert proc.returncode == 2 and "--link" in proc.stderr and "carrier-pigeon" in proc.stderr
    assert not (tmp_path / "paper").exists()  # nothing half-started
