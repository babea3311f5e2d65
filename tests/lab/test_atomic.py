"""The lab's files are written whole or not at all."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sitl.lab.atomic import replacing, write_json_atomic


def test_json_is_written_whole_and_replaces_the_old(tmp_path: Path) -> None:
    path = tmp_path / "deep" / "er" / "x.json"  # folders made on the way
    write_json_atomic(path, {"a": 1})
    write_json_atomic(path, {"b": [1, 2]})
    assert json.loads(path.read_text(encoding="utf-8")) == {"b": [1, 2]}
    assert [p.name for p in path.parent.iterdir()] == ["x.json"]  # no temporary left


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path: Path) -> None:
    path = tmp_path / "x.txt"
    path.write_text("old", encoding="utf-8")
    with pytest.raises(RuntimeError), replacing(path) as tmp:
        assert tmp.parent == path.parent and tmp != path
        tmp.write_text("half", encoding="utf-8")
        raise RuntimeError("killed mid-write")
    assert path.read_text(encoding="utf-8") == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["x.txt"]
