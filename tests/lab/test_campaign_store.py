"""A campaign's folder resumes only a run of the same grid, and the grid includes the code."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

from sitl.lab import campaign_store
from sitl.lab.campaign_store import CampaignStore, code_digest, grid_digest, sources_digest

ROOT = Path(__file__).resolve().parents[2]


def test_the_code_digest_follows_every_python_source(tmp_path: Path) -> None:
    tree = tmp_path / "sitl"
    shutil.copytree(ROOT / "sitl", tree, ignore=shutil.ignore_patterns("__pycache__"))
    before = sources_digest([("sitl", tree)])
    assert re.fullmatch(r"[0-9a-f]{20}", before)
    assert sources_digest([("sitl", tree)]) == before
    physics = tree / "physics.py"
    physics.write_text(physics.read_text() + "\n# an edit\n")
    edited = sources_digest([("sitl", tree)])
    (tree / "lab" / "new_module.py").write_text("")
    added = sources_digest([("sitl", tree)])
    (tree / "scenarios" / "notes.txt").write_text("not code")
    assert len({before, edited, added}) == 3
    assert sources_digest([("sitl", tree)]) == added  # only Python sources count


def test_an_unfinished_run_of_other_code_is_not_resumed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert code_digest() == code_digest()
    ids = ["a" * 20, "b" * 20]
    store = CampaignStore(tmp_path)
    store.start(grid_digest(ids), len(ids))
    assert store.can_resume(grid_digest(ids))
    monkeypatch.setattr(campaign_store, "code_digest", lambda: "0" * 20)
    assert not store.can_resume(grid_digest(ids))
