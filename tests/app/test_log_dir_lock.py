"""A ``--log-dir`` in use is locked for the run's life, and a run that could not
start leaves no record that looks like a flight (companion/app.py ``_open_records``,
``_close_records``; companion/records/folder.py)."""

from __future__ import annotations

import asyncio
import logging
import os
from pathlib import Path

import pytest

from companion.app import EXIT_ERROR, Companion, RunOptions
from companion.link.transport import MemoryTransport
from companion.records import LOCK_FILE, read_control_log
from tests.app.fakes import settle
from tests.app.flight import ARDUPILOT, CONTROLLER, PROFILE, Start, streams_requested


def files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}


async def test_a_second_run_on_a_log_dir_in_use_refuses_and_touches_nothing(
    start: Start, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    first = await start(engage="rc-switch", output="actuator", log_dir=tmp_path)
    await streams_requested(first)
    for _ in range(20):
        first.imu()
        await settle()
    for record in (first.companion.records.rows, first.companion.records.tlog):
        record.flush()
    await asyncio.sleep(0.1)  # the writer thread has written what it was handed
    live = files(tmp_path)

    ours, _theirs = MemoryTransport.pair()
    opts = RunOptions(connect="memory", profile=PROFILE, controller=CONTROLLER, log_dir=tmp_path)
    with caplog.at_level(logging.ERROR, logger="companion.app"):
        assert await asyncio.wait_for(Companion(opts, transport=ours).run(), 2.0) == EXIT_ERROR
    assert f"{tmp_path} is in use by another companion run (pid {os.getpid()}" in caplog.text
    assert not ours.is_open  # refused before the link opened: nothing sent
    assert not list(tmp_path.glob("earlier-*"))
    # The live run's records, where they were, as they were (its tlog may have grown).
    now = files(tmp_path)
    assert sorted(now) == sorted(live)
    assert all(now[n] == live[n] for n in ("control.mcap", "events.jsonl", LOCK_FILE))
    assert now["flight.tlog"].startswith(live["flight.tlog"])

    # The first run flies on into its own files, then ends and lets the folder go.
    for _ in range(20):
        first.imu()
        await settle()
    first.companion._stop.set()
    assert await first.finish() == 0
    rows = read_control_log(tmp_path / "control.mcap")[0]["t_s"].size
    assert rows == first.companion.counters["imu_samples"] == 40
    first_records = files(tmp_path)

    third = await start(engage="rc-switch", output="actuator", log_dir=tmp_path)
    await streams_requested(third)  # it started: the lock was free
    (earlier,) = tmp_path.glob("earlier-*")
    for name in ("control.mcap", "flight.tlog", "events.jsonl"):
        assert (earlier / name).read_bytes() == first_records[name], name
    assert (tmp_path / LOCK_FILE).read_text() == f"{os.getpid()}\n"


async def test_no_autopilot_leaves_only_the_events_that_say_why(
    start: Start, tmp_path: Path
) -> None:
    f = await start(heartbeat=False, log_dir=tmp_path, heartbeat_timeout_s=0.3)
    assert await f.finish() == EXIT_ERROR
    assert "no HEARTBEAT" in (tmp_path / "events.jsonl").read_text()
    # Our own heartbeats went out, but nothing of a flight came in: no tlog, no control.mcap.
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["events.jsonl", LOCK_FILE])


async def test_a_refused_stack_keeps_what_the_autopilot_said_and_no_empty_control_log(
    start: Start, tmp_path: Path
) -> None:
    f = await start(autopilot=ARDUPILOT, output="actuator", log_dir=tmp_path)
    assert await f.finish() == EXIT_ERROR
    assert "accepts no actuator setpoints" in (tmp_path / "events.jsonl").read_text()
    assert (tmp_path / "flight.tlog").stat().st_size > 0  # its heartbeat: why it was refused
    assert not (tmp_path / "control.mcap").exists()
