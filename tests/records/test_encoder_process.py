"""The control log's encoder in a child process (companion/records/encoder_process.py)."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from companion.child_process import ChildObject
from companion.records import ControlLog, RecordWriter, columns, read_control_log
from companion.records.encoder_process import ProcessEncoder

from .test_control_log import flight_rows


def _encoder(log: ControlLog) -> ProcessEncoder:
    enc = log._sink._encoder  # type: ignore[attr-defined]
    assert isinstance(enc, ProcessEncoder)
    return enc


def _wait(cond: object, timeout_s: float = 20.0) -> None:
    end = time.monotonic() + timeout_s
    while not cond():  # type: ignore[operator]
        assert time.monotonic() < end, "timed out"
        time.sleep(0.01)


def test_a_log_through_the_writer_is_encoded_in_another_process(tmp_path: Path) -> None:
    cols = columns(4)
    data = flight_rows(50, cols)
    w = RecordWriter()
    try:
        log = ControlLog(tmp_path / "a.mcap", cols, flush_interval_s=0.0, writer=w)
        log.append(data[0].tolist())
        enc = _encoder(log)
        _wait(lambda: enc.pid is not None and w.pending_chunks == 0)
        assert enc.pid != os.getpid()
        for row in data[1:].tolist():
            log.append(row)
        log.close()
    finally:
        assert w.close() is True
    assert enc._child is not None and enc._child.close() == 0  # ended with the file
    got, meta = read_control_log(tmp_path / "a.mcap")
    assert "cut_short" not in meta
    np.testing.assert_array_equal(got["t_s"], data[:, cols.index("t_s")])


def test_an_encoder_process_that_dies_stops_the_record_not_the_caller(tmp_path: Path) -> None:
    cols = columns(4)
    data = flight_rows(40, cols)
    w = RecordWriter()
    try:
        log = ControlLog(tmp_path / "a.mcap", cols, flush_interval_s=0.0, writer=w)
        for row in data[:20].tolist():
            log.append(row)
        enc = _encoder(log)
        _wait(lambda: enc.pid is not None and w.pending_chunks == 0)
        assert enc.pid is not None
        os.kill(enc.pid, signal.SIGKILL)
        for row in data[20:].tolist():
            log.append(row)  # never raises: the record stops, counted
        _wait(lambda: w.failure("a.mcap") is not None)
        log.close()
    finally:
        assert w.close() is True
    err = w.failure("a.mcap")
    assert isinstance(err, OSError) and "child process ended" in str(err)
    got, meta = read_control_log(tmp_path / "a.mcap")
    assert meta["cut_short"] == "true"
    np.testing.assert_array_equal(got["t_s"], data[:20, cols.index("t_s")])


def test_an_encoder_process_that_cannot_start_leaves_the_encoding_here(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def refuse(*args: object, **kwargs: object) -> subprocess.Popen[bytes]:
        raise OSError(11, "Resource temporarily unavailable")

    monkeypatch.setattr(subprocess, "Popen", refuse)
    cols = columns(4)
    data = flight_rows(30, cols)
    w = RecordWriter()
    try:
        log = ControlLog(tmp_path / "a.mcap", cols, flush_interval_s=0.0, writer=w)
        for row in data.tolist():
            log.append(row)
        log.close()
    finally:
        assert w.close() is True
    assert _encoder(log).pid is None and w.failure("a.mcap") is None
    got, meta = read_control_log(tmp_path / "a.mcap")
    assert "cut_short" not in meta
    np.testing.assert_array_equal(got["t_s"], data[:, cols.index("t_s")])


def test_the_child_outlives_a_signal_to_the_group_and_ends_with_its_input() -> None:
    """Ctrl-C reaches every process of the terminal's group: the companion hands
    back and finishes its records through the child, so the child must not die
    of it; it ends when its input closes."""
    child = ChildObject("companion.records.topics:event_schema", ())
    assert child.pid is not None
    os.kill(child.pid, signal.SIGINT)
    os.kill(child.pid, signal.SIGTERM)
    time.sleep(0.2)
    assert child.call("__len__") > 0  # still answering
    assert child.close() == 0


@pytest.mark.parametrize("reaped", [False, True], ids=["dying", "reaped"])
def test_a_call_into_a_killed_child_says_it_ended(reaped: bool) -> None:
    """Whether the write finds the pipe broken or the read finds it empty, and
    whether or not the child has been reaped yet, the caller learns the same."""
    child = ChildObject("companion.records.topics:event_schema", ())
    assert child.pid is not None
    os.kill(child.pid, signal.SIGKILL)
    if reaped:
        os.waitpid(child.pid, 0)
    else:
        time.sleep(0.2)  # dead, so a write meets a broken pipe
    with pytest.raises(OSError, match="child process ended"):
        child.call("__len__", b"x" * 200_000)  # more than the pipe holds
    assert child.pid is None
