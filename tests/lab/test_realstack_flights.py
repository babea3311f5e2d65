"""The real-stack session's pieces that need no stack."""

from __future__ import annotations

import json
from pathlib import Path

from sitl.lab.realstack.flights import new_log_dir


def test_a_flight_flown_again_under_its_name_gets_a_folder_of_its_own(tmp_path: Path) -> None:
    """The session judges a companion ready by the events in its folder: an earlier
    flight's ``imu_stream`` there would start the pilot before the new companion saw
    the switch low (the real-stack tier failed so on 2026-11-30)."""
    first = new_log_dir(tmp_path, "rates-mfc")
    assert first == tmp_path / "rates-mfc" and first.is_dir()
    event = {"t_s": 0.0, "kind": "imu_stream", "detail": "message 105 at 250 Hz"}
    (first / "events.jsonl").write_text(json.dumps(event) + "\n", encoding="utf-8")
    first.with_suffix(".stderr").write_text("", encoding="utf-8")

    second = new_log_dir(tmp_path, "rates-mfc")
    assert second == tmp_path / "rates-mfc-2" and list(second.iterdir()) == []
    assert new_log_dir(tmp_path, "rates-mfc") == tmp_path / "rates-mfc-3"


def test_a_stderr_file_left_without_its_folder_still_counts_as_used(tmp_path: Path) -> None:
    (tmp_path / "hold.stderr").write_text("", encoding="utf-8")
    assert new_log_dir(tmp_path, "hold") == tmp_path / "hold-2"
