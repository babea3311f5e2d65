"""RecordWriter: the records' file I/O on one thread behind a bounded queue.

A full disk is /dev/full (a real ENOSPC); a stalled disk is a file whose
``write`` waits on a threading.Event, injected through ``opener``. Nothing here
asserts on speed: that the caller never blocked is shown by running it in a
thread joined with a timeout (it would hang otherwise).
"""

from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"  # before pymavlink is imported: encode and parse MAVLink 2

import errno
import json
import threading
import time
import tracemalloc
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pymavlink import mavutil

from companion.records import (
    FORMAT,
    ControlLog,
    EventLog,
    RecordWriter,
    TlogWriter,
    columns,
    read_control_log,
)
from tests.records.test_tlog import frames

DEV_FULL = Path("/dev/full")
needs_dev_full = pytest.mark.skipif(not DEV_FULL.exists(), reason="no /dev/full (Linux only)")
KiB = 1024


class GatedFile:
    """A real file whose writes wait until ``gate`` is set: a stalled SD card."""

    def __init__(self, path: Path) -> None:
        self._f = path.open("wb")
        self.gate = threading.Event()
        self.entered = threading.Event()

    def write(self, data: Any) -> int:
        self.entered.set()
        if not self.gate.wait(60):
            raise OSError(errno.EIO, "the test never opened the gate")
        return self._f.write(data)

    def flush(self) -> None:
        self._f.flush()

    def close(self) -> None:
        self._f.close()

    @property
    def closed(self) -> bool:
        return self._f.closed


class FailingFile:
    """Takes ``ok_writes`` writes (the header), then fails every write with ``exc``."""

    def __init__(self, path: Path, exc: Exception, ok_writes: int = 1) -> None:
        self._f = path.open("wb")
        self._exc = exc
        self._ok = ok_writes

    def write(self, data: Any) -> int:
        if self._ok <= 0:
            raise self._exc
        self._ok -= 1
        return self._f.write(data)

    def flush(self) -> None:
        self._f.flush()

    def close(self) -> None:
        self._f.close()


def opener_with(special: dict[str, Callable[[Path], Any]]) -> Callable[[Path], Any]:
    """``open(path, "wb")``, except for the file names in ``special``."""

    def opener(p: Path) -> Any:
        make = special.get(p.name)
        return make(p) if make is not None else p.open("wb")

    return opener


def wait_until(cond: Callable[[], bool], what: str, timeout_s: float = 20.0) -> None:
    """Wait for the writer thread to get somewhere (not a speed assertion)."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.005)


def in_thread(fn: Callable[[], None], timeout_s: float = 60.0) -> None:
    """Run ``fn`` in a thread; fail (instead of hanging) if it blocks."""
    errors: list[BaseException] = []

    def run() -> None:
        try:
            fn()
        except BaseException as exc:
            errors.append(exc)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(timeout_s)
    assert not t.is_alive(), "the caller blocked"
    if errors:
        raise errors[0]


@pytest.fixture
def writers() -> Iterator[list[RecordWriter]]:
    """Writers made by a test; closed at the end whatever happened."""
    made: list[RecordWriter] = []
    yield made
    for w in made:
        w.close(timeout_s=10.0)


def read_tlog(path: Path) -> list[Any]:
    m = mavutil.mavlink_connection(str(path))
    got = []
    while (msg := m.recv_match()) is not None:
        got.append(msg)
    m.close()
    return got


# -- round trips ----------------------------------------------------------------


def test_round_trip_through_the_thread(tmp_path: Path, writers: list[RecordWriter]) -> None:
    w = RecordWriter()
    writers.append(w)
    data = frames()
    cols = columns(4)
    rows = np.random.default_rng(5).standard_normal((300, len(cols)))
    # flush_interval_s=0: every call hands a chunk to the thread, so order matters
    tlog = TlogWriter(tmp_path / "run" / "flight.tlog", flush_interval_s=0.0, writer=w)
    clog = ControlLog(tmp_path / "run" / "control.mcap", cols, meta={"profile": "f450"}, writer=w)
    events = EventLog(tmp_path / "run" / "events.jsonl", writer=w, flush_interval_s=0.0)
    with tlog, clog, events:
        for t, raw, outgoing, _ in data:
            tlog.write(t, raw, outgoing)
        for i, row in enumerate(rows):
            clog.append(row.tolist())
            if i % 50 == 0:
                clog.flush()
                events.append({"kind": "row", "i": i, "detail": "ü and\nnewline"})
    assert w.close() is True
    assert w.closed and w.failed == {} and w.poll_failures() == []
    assert w.counters["dropped_chunks"] == 0 and w.counters["pending_bytes"] == 0
    assert w.stats("flight.tlog").written_chunks == len(data)
    assert w.stats("control.mcap").written_chunks > 1

    got = read_tlog(tmp_path / "run" / "flight.tlog")
    assert [g.get_type() for g in got] == [typ for _, _, _, typ in data]
    for g, (t, raw, _, _) in zip(got, data):
        assert bytes(g.get_msgbuf()) == raw
        assert g._timestamp == pytest.approx(t, abs=1e-6)
    assert (tlog.written_in, tlog.written_out, tlog.dropped, tlog.failed) == (6, 5, 0, None)

    cols_got, meta = read_control_log(tmp_path / "run" / "control.mcap")
    assert meta["profile"] == "f450"
    for j, c in enumerate(cols):
        np.testing.assert_array_equal(cols_got[c], rows[:, j])

    lines = (tmp_path / "run" / "events.jsonl").read_text(encoding="utf-8").splitlines()
    assert [json.loads(s)["i"] for s in lines] == list(range(0, 300, 50))
    assert json.loads(lines[0])["detail"] == "ü and\nnewline"
    assert events.count == 6 and list(events.recent)[-1]["i"] == 250


def test_without_a_writer_logs_stay_synchronous(tmp_path: Path) -> None:
    """Offline tools (replay): no thread, the bytes are in the file when flush returns."""
    before = threading.active_count()
    with ControlLog(tmp_path / "c.mcap", ["t_s", "u_roll"], flush_interval_s=3600.0) as clog:
        clog.append((1.0, 2.0))
        clog.flush()
        got, _ = read_control_log(tmp_path / "c.mcap")
        assert got["u_roll"].tolist() == [2.0]
    with EventLog(tmp_path / "e.jsonl", flush_interval_s=3600.0) as ev:
        ev.append({"kind": "a"})  # the first event goes at once
        assert (tmp_path / "e.jsonl").read_text() == '{"kind": "a"}\n'
        ev.append({"kind": "b"})  # batched ...
        assert ev.buffered_bytes > 0
        ev.flush()  # ... until a flush
        assert (tmp_path / "e.jsonl").read_text().splitlines()[-1] == '{"kind": "b"}'
    assert threading.active_count() == before


def test_an_isolated_event_reaches_the_file_without_a_flush(
    tmp_path: Path, writers: list[RecordWriter]
) -> None:
    w = RecordWriter()
    writers.append(w)
    ev = EventLog(tmp_path / "events.jsonl", writer=w)
    ev.append({"kind": "connected", "detail": "sysid 1"})
    path = tmp_path / "events.jsonl"
    wait_until(lambda: path.read_bytes().endswith(b"\n"), "the event in the file")
    assert json.loads(path.read_text())["kind"] == "connected"


# -- a full disk ------------------------------------------------------------------


@needs_dev_full
def test_a_full_disk_stops_that_file_only(tmp_path: Path, writers: list[RecordWriter]) -> None:
    w = RecordWriter()
    writers.append(w)
    bad = TlogWriter(DEV_FULL, flush_interval_s=0.0, writer=w)  # file key "full"
    good = ControlLog(tmp_path / "control.mcap", ["t_s", "u_roll"], flush_interval_s=0.0, writer=w)
    events = EventLog(tmp_path / "events.jsonl", writer=w, flush_interval_s=0.0)
    data = frames()

    def fly(k0: int, n: int) -> None:
        for k in range(k0, k0 + n):
            t, raw, outgoing, _ = data[k % len(data)]
            bad.write(t, raw, outgoing)  # never raises
            good.append((k * 0.001, float(k)))
            events.append({"k": k})

    fly(0, 50)
    failures: list[tuple[str, OSError]] = []
    wait_until(lambda: bool(failures.extend(w.poll_failures()) or failures), "the failure")
    assert [k for k, _ in failures] == ["full"]
    err = failures[0][1]
    assert isinstance(err, OSError) and err.errno == errno.ENOSPC
    assert w.poll_failures() == []  # reported once
    assert bad.failed is err and w.failed == {"full": err} and w.failure("full") is err

    fly(50, 50)  # the tlog learns of it at its next flush and stops buffering
    assert bad.dropped > 0
    assert w.submit("full", b"more") is False
    s = w.stats("full")
    assert s.failed is err and s.written_chunks == 0 and s.dropped_chunks >= 2
    assert w.close() is True
    bad.close()
    good.close()
    events.close()

    # The other files were written, whole and in order.
    got, _ = read_control_log(tmp_path / "control.mcap")
    assert got["u_roll"].tolist() == [float(k) for k in range(100)]
    lines = (tmp_path / "events.jsonl").read_text().splitlines()
    assert [json.loads(s)["k"] for s in lines] == list(range(100))
    assert w.stats("control.mcap").dropped_chunks == 0
    assert w.counters["failed_files"] == 1


@needs_dev_full
def test_a_full_disk_without_a_writer_still_never_raises(tmp_path: Path) -> None:
    """The synchronous path keeps its behaviour: the error is kept, later rows dropped."""
    tlog = TlogWriter(DEV_FULL, flush_interval_s=0.0)
    t, raw, outgoing, _ = frames()[0]
    tlog.write(t, raw, outgoing)
    assert isinstance(tlog.failed, OSError) and tlog.failed.errno == errno.ENOSPC
    tlog.write(t, raw, outgoing)
    assert tlog.dropped == 1
    tlog.close()
    ev = EventLog(DEV_FULL)
    ev.append({"kind": "a"})
    ev.append({"kind": "b"})
    assert ev.failed is not None and ev.failed.errno == errno.ENOSPC
    assert (ev.count, ev.dropped, len(ev.recent)) == (2, 1, 2)
    ev.close()


def test_a_control_log_reflects_the_writers_failure(
    tmp_path: Path, writers: list[RecordWriter]
) -> None:
    enospc = OSError(errno.ENOSPC, "No space left on device")
    w = RecordWriter(opener=opener_with({"control.mcap": lambda p: FailingFile(p, enospc)}))
    writers.append(w)
    clog = ControlLog(tmp_path / "control.mcap", ["t_s"], flush_interval_s=0.0, writer=w)
    clog.append((1.0,))  # the header went through; this row fails in the thread
    wait_until(lambda: clog.failed is not None, "the failure")
    assert clog.failed is enospc
    clog.append((2.0,))  # noticed at this flush: recording stops
    clog.append((3.0,))
    assert (clog.rows, clog.dropped) == (2, 1)  # as before: a dropped row is not in rows
    clog.close()
    _, meta = read_control_log(tmp_path / "control.mcap")  # the header is there
    assert meta["format"] == FORMAT and meta["cut_short"] == "true"


def test_a_bug_in_a_write_stops_that_file_not_the_thread(
    tmp_path: Path, writers: list[RecordWriter]
) -> None:
    boom = RuntimeError("boom")
    w = RecordWriter(opener=opener_with({"bad.bin": lambda p: FailingFile(p, boom, 0)}))
    writers.append(w)
    w.open("bad", tmp_path / "bad.bin")
    w.open("good", tmp_path / "good.bin")
    assert w.submit("bad", b"x") and w.submit("good", b"y")
    assert w.close() is True
    [(key, err)] = w.poll_failures()
    assert key == "bad" and isinstance(err, OSError) and err.__cause__ is boom
    assert (tmp_path / "good.bin").read_bytes() == b"y"


# -- a stalled disk ---------------------------------------------------------------


def test_a_stalled_disk_never_blocks_the_caller_and_bounds_memory(
    tmp_path: Path, writers: list[RecordWriter]
) -> None:
    gated: list[GatedFile] = []

    def make(p: Path) -> GatedFile:
        gated.append(GatedFile(p))
        return gated[-1]

    w = RecordWriter(max_pending_bytes=1024 * KiB, opener=opener_with({"slow.bin": make}))
    writers.append(w)
    w.open("slow", tmp_path / "slow.bin")
    results: list[bool] = []
    chunk = 64 * KiB
    n = 2000  # 125 MiB offered
    peak = [0]

    def offer() -> None:
        for i in range(n):
            results.append(w.submit("slow", bytes([i % 251]) * chunk))
            peak[0] = max(peak[0], w.pending_bytes)

    tracemalloc.start()
    try:
        in_thread(offer)
        grown, _ = tracemalloc.get_traced_memory()
    except BaseException:
        gated[0].gate.set()
        raise
    finally:
        tracemalloc.stop()
    wait_until(gated[0].entered.is_set, "the thread inside the stalled write")
    # Exactly what fits was taken (the chunk being written still counts as pending) ...
    assert results.count(True) == 16 and results[:16] == [True] * 16
    assert peak[0] == w.pending_bytes == 16 * chunk <= w.max_pending_bytes
    # ... the rest was dropped, counted, and not kept.
    s = w.stats("slow")
    assert (s.written_chunks, s.dropped_chunks, s.dropped_bytes) == (0, n - 16, (n - 16) * chunk)
    assert grown < 4 * 1024 * KiB

    gated[0].gate.set()
    assert w.close(timeout_s=30.0) is True
    assert w.stats("slow").written_chunks == 16 and w.pending_bytes == 0
    body = (tmp_path / "slow.bin").read_bytes()
    assert body == b"".join(bytes([i % 251]) * chunk for i in range(16))  # in order


def test_the_chunk_count_is_bounded_too(tmp_path: Path, writers: list[RecordWriter]) -> None:
    gated = GatedFile(tmp_path / "slow.bin")
    w = RecordWriter(max_pending_chunks=10, opener=lambda p: gated)
    writers.append(w)
    w.open("slow", tmp_path / "slow.bin")
    try:
        results: list[bool] = []
        in_thread(lambda: results.extend(w.submit("slow", b"x") for _ in range(1000)))
        assert results.count(True) == 10 and w.pending_chunks == 10
        assert w.stats("slow").dropped_chunks == 990 and w.dropped_bytes == 990
    finally:
        gated.gate.set()


def test_close_drains_the_queue(tmp_path: Path, writers: list[RecordWriter]) -> None:
    gated = GatedFile(tmp_path / "slow.bin")
    w = RecordWriter(opener=opener_with({"slow.bin": lambda p: gated}))
    writers.append(w)
    w.open("slow", tmp_path / "slow.bin")
    w.open("other", tmp_path / "other.bin", header=b"HEAD\n")
    try:
        for i in range(100):
            assert w.submit("slow", f"{i}\n".encode())
            assert w.submit("other", f"{i}\n".encode())
        assert (tmp_path / "slow.bin").read_bytes() == b""  # all of it still queued
    finally:
        gated.gate.set()
    assert w.close(timeout_s=30.0) is True
    assert gated.closed
    want = "".join(f"{i}\n" for i in range(100))
    assert (tmp_path / "slow.bin").read_text() == want
    assert (tmp_path / "other.bin").read_text() == "HEAD\n" + want
    assert w.submit("slow", b"late") is False  # closed: dropped and counted
    assert w.stats("slow").dropped_chunks == 1
    assert w.close() is True  # twice is harmless


def test_close_gives_up_on_a_stalled_disk_and_counts_what_is_lost(
    tmp_path: Path, writers: list[RecordWriter]
) -> None:
    gated = GatedFile(tmp_path / "slow.bin")
    w = RecordWriter(opener=lambda p: gated)
    writers.append(w)
    w.open("slow", tmp_path / "slow.bin")
    try:
        for _ in range(5):
            assert w.submit("slow", b"abc")
        assert w.close(timeout_s=0.05) is False  # the gate is shut: cannot finish
        s = w.stats("slow")
        assert (s.written_chunks, s.dropped_chunks, s.dropped_bytes) == (0, 5, 15)
    finally:
        gated.gate.set()
    assert w.close(timeout_s=30.0) is True  # the thread discarded the rest and ended
    s = w.stats("slow")
    assert (s.written_chunks, s.dropped_chunks) == (0, 5)  # counted once
    assert gated.closed


# -- events -----------------------------------------------------------------------


def test_an_event_flood_keeps_memory_bounded(tmp_path: Path, writers: list[RecordWriter]) -> None:
    w = RecordWriter()
    writers.append(w)
    ev = EventLog(tmp_path / "events.jsonl", writer=w, ring_size=1000)
    n = 100_000
    peaks = [0, 0]

    def flood() -> None:
        for i in range(n):
            ev.append({"kind": "statustext", "i": i, "detail": "PreArm: Gyros inconsistent"})
            if i % 97 == 0:
                peaks[0] = max(peaks[0], ev.buffered_bytes)
                peaks[1] = max(peaks[1], w.pending_bytes)

    in_thread(flood)
    assert ev.count == n and len(ev.recent) == 1000
    assert ev.recent[0]["i"] == n - 1000 and ev.recent[-1]["i"] == n - 1
    assert peaks[0] < 64 * KiB + 200 and peaks[1] <= w.max_pending_bytes
    ev.close()
    assert w.close(timeout_s=30.0) is True
    assert w.dropped_chunks == 0 and ev.dropped == 0
    # batched: far fewer chunks than events
    assert w.stats("events.jsonl").written_chunks < n // 100
    lines = (tmp_path / "events.jsonl").read_text().splitlines()
    assert [json.loads(s)["i"] for s in lines] == list(range(n))


def test_an_event_flood_on_a_stalled_disk_drops_and_counts(
    tmp_path: Path, writers: list[RecordWriter]
) -> None:
    gated = GatedFile(tmp_path / "events.jsonl")
    w = RecordWriter(max_pending_bytes=256 * KiB, opener=lambda p: gated)
    writers.append(w)
    ev = EventLog(tmp_path / "events.jsonl", writer=w, ring_size=50)
    try:
        in_thread(lambda: [ev.append({"i": i, "detail": "x" * 40}) for i in range(100_000)])
        assert len(ev.recent) == 50 and ev.count == 100_000
        assert w.pending_bytes <= 256 * KiB and ev.buffered_bytes < 64 * KiB + 200
        assert w.stats("events.jsonl").dropped_chunks > 0
    finally:
        gated.gate.set()
    ev.close()
    assert w.close(timeout_s=30.0) is True


def test_event_log_ring_only_and_after_close(tmp_path: Path) -> None:
    ev = EventLog(ring_size=3)
    for i in range(5):
        ev.append({"i": i})
    assert [e["i"] for e in ev.recent] == [2, 3, 4]
    assert (ev.count, ev.dropped, ev.failed) == (5, 0, None)
    ev.close()

    ev = EventLog(tmp_path / "e.jsonl")
    ev.append({"i": 0})
    ev.close()
    ev.close()
    ev.append({"i": 1})  # at shutdown: kept in the ring, counted, never raises
    assert (ev.count, ev.dropped, len(ev.recent)) == (2, 1, 2)
    assert (tmp_path / "e.jsonl").read_text() == '{"i": 0}\n'


# -- arguments --------------------------------------------------------------------


def test_bad_arguments(tmp_path: Path, writers: list[RecordWriter]) -> None:
    with pytest.raises(ValueError, match="max_pending_bytes"):
        RecordWriter(max_pending_bytes=0)
    with pytest.raises(ValueError, match="max_pending_chunks"):
        RecordWriter(max_pending_chunks=-1)
    with pytest.raises(ValueError, match="ring_size"):
        EventLog(ring_size=0)
    w = RecordWriter()
    writers.append(w)
    with pytest.raises(ValueError, match="needs a path"):
        EventLog(writer=w)
    with pytest.raises(ValueError, match="no file opened"):
        w.submit("nope", b"x")
    w.open("a", tmp_path / "a.bin")
    with pytest.raises(ValueError, match="already open"):
        w.open("a", tmp_path / "b.bin")
    TlogWriter(tmp_path / "x" / "flight.tlog", writer=w)
    with pytest.raises(ValueError, match="already open"):  # the key is the file name
        TlogWriter(tmp_path / "y" / "flight.tlog", writer=w)
    with pytest.raises(ValueError, match="timeout_s"):
        w.close(timeout_s=-1.0)
    assert w.close() is True
    with pytest.raises(ValueError, match="closed"):
        w.open("b", tmp_path / "b.bin")
