"""Flight records: a MAVLink telemetry log (``.tlog``), a binary columnar log and an event log.

The logs are fed from the control path (once per MAVLink message, once per
control sample, once per event), so appending is a cheap copy into an
in-memory buffer; the buffer is handed on, in one piece, on the first append
at least ``flush_interval_s`` after the last hand-over (or on :meth:`flush`,
:meth:`close`).

Where it goes depends on the ``writer`` a log is given:

* with a :class:`RecordWriter` (the app: one per run, for all its records),
  the buffer is swapped for an empty one and queued to the writer's thread,
  which does every ``write``, ``flush`` and ``close``. A slow or stalled disk
  never blocks the caller: the queue is bounded (``max_pending_bytes``,
  ``max_pending_chunks``) and a chunk that does not fit is dropped and
  counted. A write error (``ENOSPC``, ``EIO``) stops that file only; the
  thread keeps writing the others and reports the failure through
  :meth:`RecordWriter.poll_failures`;
* without one (offline tools such as ``companion replay``), the log writes the
  buffer to its own file synchronously, from the caller.

Nothing calls ``fsync`` (it can block for tens of milliseconds on an SD card):
a killed process loses what was buffered or queued (normally the last
``flush_interval_s``); a power cut may also lose what the kernel had not
written back. Opening a file and writing its header are synchronous, at
start-up, and raise ``OSError`` as ``open`` does.

A write error never reaches the caller: it is logged once, the log stops
recording (``failed`` holds the error) and later rows are counted in
``dropped``.

Formats are described in ``docs/logs.md``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import queue
import struct
import sys
import threading
import time
from array import array
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from companion.control import AXES

__all__ = [
    "FORMAT",
    "RECORD_FILES",
    "ColumnarLog",
    "EventLog",
    "RecordFileStats",
    "RecordWriter",
    "TlogWriter",
    "columns",
    "last_row",
    "prepare_log_dir",
    "read_columnar",
]

log = logging.getLogger(__name__)


FORMAT = "companion-columnar 2 (binary float64 rows)"
_MARKER = b"# float64 rows follow\n"

_pack_usec = struct.Struct(">Q").pack


RECORD_FILES = ("flight.tlog", "control.bin", "events.jsonl")
"""What ``companion run --log-dir DIR`` writes into DIR."""

Chunk = bytes | bytearray | memoryview
"""Bytes for :meth:`RecordWriter.submit`; ``len()`` must be the size in bytes."""


def prepare_log_dir(path: str | Path) -> Path | None:
    """Make ``path`` ready for one run's records; never overwrite an earlier run's.

    Creates the folder if needed. Records already in it (an earlier run's, or a
    start-up that failed: a service restarting into the same folder) are moved,
    untouched, into a subfolder ``earlier-<UTC time of their last write>`` first.
    Returns that subfolder, or None when there was nothing to move.

    Raises
    ------
    ValueError
        If the folder cannot be created or written, naming it.
    """
    d = Path(path)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"--log-dir {d}: cannot create the folder: {exc.strerror}") from None
    if not os.access(d, os.W_OK | os.X_OK):
        raise ValueError(f"--log-dir {d}: the folder is not writable")
    held = [d / n for n in RECORD_FILES if (d / n).exists()]
    if not held:
        return None
    when = datetime.fromtimestamp(max(p.stat().st_mtime for p in held), tz=timezone.utc)
    base = d / f"earlier-{when:%Y%m%dT%H%M%SZ}"
    dest, n = base, 1
    while dest.exists():
        dest, n = base.with_name(f"{base.name}-{n}"), n + 1
    try:
        dest.mkdir()
        for p in held:
            p.rename(dest / p.name)
    except OSError as exc:
        raise ValueError(f"--log-dir {d}: cannot move the earlier records aside: {exc}") from None
    return dest


def columns(n_motors: int) -> list[str]:
    """The columnar flight log's columns, in order, for a vehicle with ``n_motors``.

    ``t_s`` (IMU sample time, s), ``wall_s`` (monotonic clock, s),
    ``latency_us`` (datagram arrival to command sent), ``engaged`` and
    ``held`` (0/1); per axis (roll, pitch, yaw): ``ref_<axis>_rad_s``,
    ``meas_<axis>_rad_s``, ``err_<axis>_rad_s``, ``f_hat_<axis>``,
    ``u_<axis>``, ``torque_<axis>``, ``sat_<axis>`` (0/1); then ``thrust``
    (pilot's collective, 0..1), ``thrust_out`` (realised),
    ``motor_1`` .. ``motor_<n_motors>``, ``sent_<axis>_rad_s``, the body
    rates sent with ``--output rates`` (NaN when none were sent), and
    ``on_ground`` (0/1: the autopilot said ON_GROUND, so nothing was learnt).
    """
    if not isinstance(n_motors, int) or isinstance(n_motors, bool) or n_motors < 1:
        raise ValueError(f"n_motors must be a positive integer, got {n_motors!r}")
    cols = ["t_s", "wall_s", "latency_us", "engaged", "held"]
    for a in AXES:
        cols += [
            f"ref_{a}_rad_s",
            f"meas_{a}_rad_s",
            f"err_{a}_rad_s",
            f"f_hat_{a}",
            f"u_{a}",
            f"torque_{a}",
            f"sat_{a}",
        ]
    cols += ["thrust", "thrust_out"]
    cols += [f"motor_{i}" for i in range(1, n_motors + 1)]
    cols += [f"sent_{a}_rad_s" for a in AXES]
    cols.append("on_ground")
    return cols


_MIB = 1 << 20


@dataclass(frozen=True)
class RecordFileStats:
    """What a :class:`RecordWriter` has done with one file's chunks (a snapshot)."""

    path: Path
    written_chunks: int
    """Chunks handed to the OS (``write`` and ``flush`` returned)."""
    written_bytes: int
    dropped_chunks: int
    """Chunks not written: refused (the queue was full, the file had failed or
    the writer was closed), lost (queued when the file failed) or abandoned
    (still queued when :meth:`RecordWriter.close` stopped waiting)."""
    dropped_bytes: int
    failed: OSError | None
    """The error that stopped this file, or None."""


class _File:
    """One file of a :class:`RecordWriter`. Each group of counters has one writing thread."""

    __slots__ = (
        "abandoned_bytes",
        "abandoned_chunks",
        "accepted_bytes",
        "accepted_chunks",
        "f",
        "failed",
        "key",
        "lost_bytes",
        "lost_chunks",
        "path",
        "refused_bytes",
        "refused_chunks",
        "written_bytes",
        "written_chunks",
    )

    def __init__(self, key: str, path: Path, f: BinaryIO) -> None:
        self.key = key
        self.path = path
        self.f = f
        self.failed: OSError | None = None  # set once, by the writer thread
        # submitters, under RecordWriter._submit_lock
        self.accepted_chunks = self.accepted_bytes = 0
        self.refused_chunks = self.refused_bytes = 0
        # the writer thread, under RecordWriter._account_lock
        self.written_chunks = self.written_bytes = 0
        self.lost_chunks = self.lost_bytes = 0
        # close(), under RecordWriter._account_lock, when it stops waiting
        self.abandoned_chunks = self.abandoned_bytes = 0


def _open_binary(path: Path) -> BinaryIO:
    return open(path, "wb")


class RecordWriter:
    """One thread doing all the file I/O of one run's records, fed through a bounded queue.

    :meth:`open` each file (synchronously, before the flight: it creates the
    file and writes its header), then :meth:`submit` chunks of bytes for it
    from any thread; the writer's thread appends them, in submit order, with
    one ``write`` and one ``flush`` (no ``fsync``) per chunk. :meth:`close`
    writes what is queued, closes the files and ends the thread. Usable as a
    context manager (``close()`` on exit). The thread (a daemon) starts in the
    constructor, so nothing can be submitted to a writer that nobody started.

    :meth:`submit` never blocks and never raises on a disk problem:

    * the queue holds at most ``max_pending_bytes`` bytes and
      ``max_pending_chunks`` chunks (queued or being written); a chunk that
      does not fit is dropped and counted (:meth:`stats`, :attr:`counters`),
      so a stalled disk costs records, never control-loop time or unbounded
      memory;
    * a write error (``ENOSPC``, ``EIO``, ...) stops that file only: it is
      logged once, the file is closed, its later chunks are dropped and
      counted, and the thread keeps writing the other files. The supervisor
      learns of it through :meth:`poll_failures` (or :attr:`failed`).

    Parameters
    ----------
    max_pending_bytes
        Bytes queued or being written, at most. The default, 32 MiB, holds
        about a minute of a 1 kHz flight's records (the columnar log and the
        tlog take ~0.45 MB/s together) while the disk stalls.
    max_pending_chunks
        Chunks queued or being written, at most (default 4096): bounds the
        per-item overhead of many small chunks. A flight submits ~15 per second.
    opener
        ``opener(path)`` returns the binary file object :meth:`open` writes to;
        the default is ``open(path, "wb")``. The seam for tests that need a file
        whose writes block (a stalled SD card).
    name
        The thread's name.

    Notes
    -----
    The queue is a :class:`queue.SimpleQueue` bounded by counters rather than
    a ``queue.Queue(maxsize)``: the bound is in bytes as well as items, and a
    ``SimpleQueue.put`` is one C call that never blocks. The byte and chunk
    counts are pairs of monotonic counters, "in" written only by submitters
    (under a lock the writer thread never takes) and "out" written only by the
    writer thread after it has let go of a chunk; pending is their difference,
    so no counter is updated from two threads. The lock the thread does take
    (``_account_lock``, for its per-file counters) is never held during I/O,
    and :meth:`submit` does not take it.
    """

    def __init__(
        self,
        *,
        max_pending_bytes: int = 32 * _MIB,
        max_pending_chunks: int = 4096,
        opener: Callable[[Path], BinaryIO] | None = None,
        name: str = "record-writer",
    ) -> None:
        for what, v in (
            ("max_pending_bytes", max_pending_bytes),
            ("max_pending_chunks", max_pending_chunks),
        ):
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"{what} must be a positive integer, got {v!r}")
        self.max_pending_bytes = max_pending_bytes
        self.max_pending_chunks = max_pending_chunks
        self._opener = opener or _open_binary
        self._files: dict[str, _File] = {}
        self._queue: queue.SimpleQueue[tuple[_File, Chunk] | None] = queue.SimpleQueue()
        self._submit_lock = threading.Lock()  # submitters and open/close; never the thread
        self._account_lock = threading.Lock()  # the thread's counters against close()
        self._in_chunks = self._in_bytes = 0  # submitters
        self._out_chunks = self._out_bytes = 0  # the writer thread
        self._refused_full = 0  # submitters: chunks refused by a full queue
        self._failures: deque[tuple[str, OSError]] = deque()
        self._closed = False
        self._abandon = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    # ------------------------------------------------------------ the caller's side
    def open(self, file_key: str, path: str | Path, *, header: bytes = b"") -> None:
        """Create ``path`` (replacing a file there), write ``header``, and accept chunks for it.

        Synchronous, on the caller's thread (at start-up, before the flight);
        parent folders are created.

        Raises
        ------
        ValueError
            If ``file_key`` is taken or the writer is closed.
        OSError
            As ``open`` and ``write`` raise them.
        """
        if self._closed:
            raise ValueError("RecordWriter is closed")
        if file_key in self._files:
            raise ValueError(f"RecordWriter: {file_key!r} is already open")
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        f = self._opener(p)
        try:
            if header:
                f.write(header)
                f.flush()  # a killed process leaves a file with its header
            with self._submit_lock:
                if self._closed or file_key in self._files:
                    raise ValueError(f"RecordWriter: cannot open {file_key!r} (closed or taken)")
                self._files[file_key] = _File(file_key, p, f)
        except BaseException:
            with contextlib.suppress(Exception):
                f.close()
            raise

    def submit(self, file_key: str, data: Chunk) -> bool:
        """Queue ``data`` to be appended to ``file_key``'s file. O(1); never blocks.

        Returns False, counting the chunk as dropped, when it does not fit in
        the bounds, when the file has failed, or when the writer is closed. The
        writer keeps a reference to ``data``: do not modify it afterwards.

        Raises
        ------
        ValueError
            If no file was opened as ``file_key`` (a programming error).
        """
        t = self._files.get(file_key)
        if t is None:
            raise ValueError(f"RecordWriter: no file opened as {file_key!r}")
        n = len(data)
        if n == 0:
            return True
        with self._submit_lock:
            if self._closed or t.failed is not None:
                t.refused_chunks += 1
                t.refused_bytes += n
                return False
            if (
                self._in_bytes - self._out_bytes + n > self.max_pending_bytes
                or self._in_chunks - self._out_chunks >= self.max_pending_chunks
            ):
                t.refused_chunks += 1
                t.refused_bytes += n
                self._refused_full += 1
                return False
            self._in_chunks += 1
            self._in_bytes += n
            t.accepted_chunks += 1
            t.accepted_bytes += n
            self._queue.put((t, data))
        return True

    def poll_failures(self) -> list[tuple[str, OSError]]:
        """Files that failed since the last call, as ``(file_key, error)``; cheap, thread-safe."""
        out = []
        pop = self._failures.popleft
        while True:
            try:
                out.append(pop())
            except IndexError:
                return out

    def failure(self, file_key: str) -> OSError | None:
        """The error that stopped ``file_key``'s file, or None (also for an unknown key)."""
        t = self._files.get(file_key)
        return None if t is None else t.failed

    @property
    def failed(self) -> dict[str, OSError]:
        """``{file_key: error}`` for every file that has stopped recording."""
        return {k: t.failed for k, t in list(self._files.items()) if t.failed is not None}

    @property
    def pending_bytes(self) -> int:
        """Bytes queued or being written (at most ``max_pending_bytes``)."""
        return self._in_bytes - self._out_bytes

    @property
    def pending_chunks(self) -> int:
        """Chunks queued or being written (at most ``max_pending_chunks``)."""
        return self._in_chunks - self._out_chunks

    @property
    def closed(self) -> bool:
        return self._closed

    def stats(self, file_key: str) -> RecordFileStats:
        """What has been done with ``file_key``'s chunks so far.

        Raises
        ------
        KeyError
            If no file was opened as ``file_key``.
        """
        t = self._files[file_key]
        with self._account_lock:
            return RecordFileStats(
                path=t.path,
                written_chunks=t.written_chunks,
                written_bytes=t.written_bytes,
                dropped_chunks=t.refused_chunks + t.lost_chunks + t.abandoned_chunks,
                dropped_bytes=t.refused_bytes + t.lost_bytes + t.abandoned_bytes,
                failed=t.failed,
            )

    @property
    def dropped_chunks(self) -> int:
        """Chunks not written, all files together (see :class:`RecordFileStats`)."""
        return sum(self.stats(k).dropped_chunks for k in list(self._files))

    @property
    def dropped_bytes(self) -> int:
        """Bytes not written, all files together."""
        return sum(self.stats(k).dropped_bytes for k in list(self._files))

    @property
    def counters(self) -> dict[str, int]:
        """``written_chunks``, ``written_bytes``, ``dropped_chunks``, ``dropped_bytes``,
        ``pending_chunks``, ``pending_bytes`` and ``failed_files``, all files together."""
        all_stats = [self.stats(k) for k in list(self._files)]
        return {
            "written_chunks": sum(s.written_chunks for s in all_stats),
            "written_bytes": sum(s.written_bytes for s in all_stats),
            "dropped_chunks": sum(s.dropped_chunks for s in all_stats),
            "dropped_bytes": sum(s.dropped_bytes for s in all_stats),
            "pending_chunks": self.pending_chunks,
            "pending_bytes": self.pending_bytes,
            "failed_files": sum(s.failed is not None for s in all_stats),
        }

    def close(self, timeout_s: float = 2.0) -> bool:
        """Write what is queued, close the files and end the thread; wait at most ``timeout_s``.

        Returns True when all that was done in time. Otherwise (a stalled disk)
        what is still queued or being written is counted as dropped
        ("abandoned", even a chunk whose ``write`` completes later) and logged;
        the thread discards the rest when it wakes, then closes the files, and a
        later ``close`` waits for that again. Once closed, :meth:`submit` drops.
        Closing twice is harmless.
        """
        if not (math.isfinite(timeout_s) and timeout_s >= 0.0):
            raise ValueError(f"timeout_s must be >= 0, got {timeout_s!r}")
        with self._submit_lock:
            if not self._closed:
                self._closed = True
                self._queue.put(None)  # after every accepted chunk
        self._thread.join(timeout_s)
        if not self._thread.is_alive():
            return True
        with self._account_lock:
            if not self._abandon:
                self._abandon = True
                n = b = 0
                for t in list(self._files.values()):
                    t.abandoned_chunks = t.accepted_chunks - t.written_chunks - t.lost_chunks
                    t.abandoned_bytes = t.accepted_bytes - t.written_bytes - t.lost_bytes
                    n += t.abandoned_chunks
                    b += t.abandoned_bytes
                log.error(
                    "records: the disk did not take the last %d chunks (%d bytes) within "
                    "%.1f s; they are dropped",
                    n,
                    b,
                    timeout_s,
                )
        return False

    def __enter__(self) -> RecordWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------ the writer thread
    def _run(self) -> None:
        get = self._queue.get
        reported_full = 0
        next_report = 0.0
        while True:
            item = get()
            if item is None:
                break
            t, data = item
            n = len(data)
            ok = False
            if t.failed is None and not self._abandon:
                try:
                    t.f.write(data)
                    t.f.flush()
                    ok = True
                except Exception as exc:  # nothing may end this thread
                    self._fail(t, exc)
            del item, data  # free before it stops counting as pending
            with self._account_lock:
                if not self._abandon:  # else close() has counted it
                    if ok:
                        t.written_chunks += 1
                        t.written_bytes += n
                    else:
                        t.lost_chunks += 1
                        t.lost_bytes += n
            self._out_bytes += n
            self._out_chunks += 1
            # Logged from here, not from submit(): no I/O on the caller's thread.
            if self._refused_full != reported_full and time.monotonic() >= next_report:
                reported_full = self._refused_full
                next_report = time.monotonic() + 5.0
                log.warning(
                    "records: the disk is not keeping up; %d chunks dropped (queue full)",
                    reported_full,
                )
        for t in list(self._files.values()):
            if t.failed is None:
                try:
                    t.f.close()
                except Exception as exc:
                    self._fail(t, exc)

    def _fail(self, t: _File, exc: Exception) -> None:
        if isinstance(exc, OSError):
            err = exc
        else:  # a bug, not the disk; still, only this file stops
            err = OSError(f"{type(exc).__name__}: {exc}")
            err.__cause__ = exc
        t.failed = err  # first: submit() refuses its chunks from now on
        log.error("%s: cannot write, recording of this file stops: %s", t.path, err)
        with contextlib.suppress(Exception):
            t.f.close()
        self._failures.append((t.key, err))


class _Sink:
    """Where a log's flushed buffers go: a :class:`RecordWriter`, or its own file."""

    def __init__(
        self, path: Path, what: str, writer: RecordWriter | None, header: bytes = b""
    ) -> None:
        self.path = path
        self.what = what
        self.writer = writer
        self.key = path.name
        self.failed: OSError | None = None
        self._f: BinaryIO | None = None
        if writer is not None:
            writer.open(self.key, path, header=header)
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        f = open(path, "wb")  # noqa: SIM115 (closed in close())
        try:
            if header:
                f.write(header)
                f.flush()  # a killed process leaves a file with its header
        except BaseException:
            with contextlib.suppress(Exception):
                f.close()
            raise
        self._f = f

    def failure(self) -> OSError | None:
        if self.failed is None and self.writer is not None:
            return self.writer.failure(self.key)
        return self.failed

    def put(self, data: Chunk) -> bool:
        """Hand ``data`` on; False once this file has stopped recording (``failed``)."""
        w = self.writer
        if w is not None:
            exc = w.failure(self.key)
            if exc is not None:
                self.failed = exc
                return False
            w.submit(self.key, data)  # a full queue drops the chunk; the writer counts it
            return True
        f = self._f
        if f is None:
            return False
        try:
            f.write(data)
            f.flush()
        except OSError as exc:
            log.error("%s: cannot write the %s, recording stops: %s", self.path, self.what, exc)
            self.failed = exc
            self._f = None
            with contextlib.suppress(OSError):
                f.close()
            return False
        return True

    def close(self) -> None:
        """Close the own file (a writer's files are closed by the writer)."""
        f, self._f = self._f, None
        if f is not None:
            try:
                f.close()
            except OSError as exc:
                log.error("%s: closing the %s failed: %s", self.path, self.what, exc)
                self.failed = exc


class TlogWriter:
    """Append MAVLink frames to a ``.tlog`` file.

    The format is the one pymavlink's ``mavutil.mavlogfile`` reads (and QGC,
    MAVProxy and Mission Planner write): for each message, an 8-byte
    big-endian unsigned integer of unix time in microseconds, then the raw
    MAVLink frame, nothing else. ``mavutil.mavlink_connection(path)`` and
    ``mavlogdump.py path`` read it; ``msg._timestamp`` is the time given here.

    Parameters
    ----------
    path
        The file to create (parent directories are created; an existing file
        is replaced).
    flush_interval_s
        The buffer is handed on at the first :meth:`write` at least this long
        after the last flush (monotonic clock).
    writer
        Hand the buffer to this :class:`RecordWriter` (file key: the file's
        name) instead of writing it from the caller; the writer closes the file.
        None: write synchronously, as offline tools do.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        flush_interval_s: float = 0.2,
        writer: RecordWriter | None = None,
    ) -> None:
        if not (math.isfinite(flush_interval_s) and flush_interval_s >= 0.0):
            raise ValueError(f"flush_interval_s must be >= 0, got {flush_interval_s!r}")
        self.path = Path(path)
        self._sink = _Sink(self.path, "MAVLink log", writer)
        self._open = True  # False once closed, or stopped by a write error
        self._buf = bytearray()
        self._interval = flush_interval_s
        self._next_flush = time.monotonic() + flush_interval_s
        self.written_in = 0
        """Frames received from the link (``outgoing=False``)."""
        self.written_out = 0
        """Frames sent by the companion (``outgoing=True``)."""
        self.dropped = 0
        """Frames not recorded because of an earlier write error."""

    @property
    def failed(self) -> OSError | None:
        """The write error that stopped recording (with a writer: its error for this file)."""
        return self._sink.failure()

    def write(self, unix_time_s: float, raw: bytes, outgoing: bool) -> None:
        """Record one MAVLink frame (``raw``, as on the wire) seen at ``unix_time_s``.

        ``outgoing`` only counts (``written_out``/``written_in``): a tlog has no
        direction field; the sender is in each frame's system and component ids.
        """
        if not self._open:
            if self._sink.failed is not None:
                self.dropped += 1
                return
            raise ValueError(f"{self.path}: TlogWriter is closed")
        buf = self._buf
        buf += _pack_usec(int(unix_time_s * 1e6 + 0.5) if unix_time_s > 0.0 else 0)
        buf += raw
        if outgoing:
            self.written_out += 1
        else:
            self.written_in += 1
        if time.monotonic() >= self._next_flush:
            self.flush()

    def flush(self) -> None:
        """Hand the buffer on now: to the writer's queue, or to the OS (no fsync)."""
        self._next_flush = time.monotonic() + self._interval
        if not self._open or not self._buf:
            return
        buf, self._buf = self._buf, bytearray()
        if not self._sink.put(buf):
            self._open = False

    def close(self) -> None:
        """Flush and close; closing twice is harmless."""
        if not self._open:
            return
        self.flush()
        self._open = False
        self._sink.close()

    def __enter__(self) -> TlogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ColumnarLog:
    """A binary columnar flight log: a text header, then one float64 row per sample.

    Layout: ``# key: value`` metadata lines, a line of comma-separated column
    names, the marker line ``# float64 rows follow``, then the rows as raw
    float64 in the writer's byte order (recorded in the ``byteorder``
    metadata). Every value round-trips exactly; :func:`read_columnar` reads it
    back into numpy arrays (``companion log-csv`` style conversion is one
    ``numpy.savetxt`` away).

    Parameters
    ----------
    path
        The file to create (parent directories are created; an existing file
        is replaced).
    columns
        Column names, in order (usually :func:`columns`).
    meta
        Metadata written as ``# key: value`` lines (profile, controller, ...).
        ``format``, ``version``, ``byteorder``, ``start_unix_s`` and
        ``start_utc`` are added unless given. Newlines in values become spaces.
    flush_interval_s
        Buffered rows are handed on at the first :meth:`append` at least this
        long after the last flush.
    writer
        Hand the rows to this :class:`RecordWriter` (file key: the file's name)
        instead of writing them from the caller; the header is still written
        at once, by :meth:`RecordWriter.open`. None: write synchronously.

    Notes
    -----
    :meth:`append` copies the row into an ``array('d')`` (well under a
    microsecond for 32 columns) and a flush swaps that array for an empty one
    and hands over a byte view of it (no copy): nothing is formatted on the
    control path, so there is no per-sample formatting cost and no flush
    burst to delay the next IMU sample.
    """

    def __init__(
        self,
        path: str | Path,
        columns: list[str],
        *,
        meta: dict[str, Any] | None = None,
        flush_interval_s: float = 0.2,
        writer: RecordWriter | None = None,
    ) -> None:
        cols = list(columns)
        if not cols:
            raise ValueError("columns must not be empty")
        if len(set(cols)) != len(cols):
            raise ValueError(f"duplicate column names in {cols}")
        for c in cols:
            if not c or any(ch in c for ch in ",#\n\r ") or c != c.strip():
                raise ValueError(f"invalid column name {c!r}")
        if not (math.isfinite(flush_interval_s) and flush_interval_s >= 0.0):
            raise ValueError(f"flush_interval_s must be >= 0, got {flush_interval_s!r}")
        self.path = Path(path)
        self.columns = cols
        self.n_columns = len(cols)
        self._buf = array("d")
        self._interval = flush_interval_s
        self.rows = 0
        """Rows appended."""
        self.dropped = 0
        """Rows not recorded because of an earlier write error."""

        from companion import __version__

        now = time.time()
        full_meta: dict[str, Any] = {
            "format": FORMAT,
            "version": __version__,
            "byteorder": sys.byteorder,
            "start_unix_s": f"{now:.6f}",
            "start_utc": datetime.fromtimestamp(now, timezone.utc).isoformat(),
        }
        full_meta.update(meta or {})
        head = []
        for k, v in full_meta.items():
            key = " ".join(str(k).replace(":", "_").split())
            val = " ".join(str(v).splitlines())
            head.append(f"# {key}: {val}\n")
        head.append(",".join(cols) + "\n")
        head.append(_MARKER.decode())
        # The header goes out at once: a killed process leaves a readable file.
        self._sink = _Sink(self.path, "flight log", writer, header="".join(head).encode())
        self._open = True  # False once closed, or stopped by a write error
        self._next_flush = time.monotonic() + flush_interval_s

    @property
    def failed(self) -> OSError | None:
        """The write error that stopped recording (with a writer: its error for this file)."""
        return self._sink.failure()

    def append(self, row: Sequence[float]) -> None:
        """Record one row (numbers in column order; bools and ints are fine).

        Raises
        ------
        ValueError
            If ``len(row)`` is not the number of columns, or a value is not a number.
        """
        if len(row) != self.n_columns:
            raise ValueError(f"{self.path}: row has {len(row)} values, expected {self.n_columns}")
        if not self._open:
            if self._sink.failed is not None:
                self.dropped += 1
                return
            raise ValueError(f"{self.path}: ColumnarLog is closed")
        n = len(self._buf)
        try:
            self._buf.extend(row)
        except TypeError as exc:
            del self._buf[n:]  # keep rows whole
            raise ValueError(f"{self.path}: row has a value that is not a number: {exc}") from None
        self.rows += 1
        if time.monotonic() >= self._next_flush:
            self.flush()

    def flush(self) -> None:
        """Hand the buffered rows on now: to the writer's queue, or to the OS (no fsync)."""
        self._next_flush = time.monotonic() + self._interval
        if not self._open or not self._buf:
            return
        buf, self._buf = self._buf, array("d")
        if not self._sink.put(memoryview(buf).cast("B")):
            self._open = False

    def close(self) -> None:
        """Flush and close; closing twice is harmless."""
        if not self._open:
            return
        self.flush()
        self._open = False
        self._sink.close()

    def __enter__(self) -> ColumnarLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class EventLog:
    """The run's events: the last ``ring_size`` in memory, all of them in a JSON-lines file.

    :meth:`append` keeps the event (a dict, by reference) in :attr:`recent`
    and, with a file, serialises it to one line (``json.dumps``, values it
    cannot encode as ``str``) into a buffer. The buffer is handed on, like the
    other logs', at the first append at least ``flush_interval_s`` after the
    last flush: an event after a quiet spell goes at once, a burst (a flood
    of STATUSTEXT) becomes one chunk per interval, and at most
    ``max_buffer_bytes`` wait on the caller's side. Lines still buffered when
    the events stop are handed on by :meth:`flush` (call it on a timer) or
    :meth:`close`. Memory stays bounded however long the run.

    Parameters
    ----------
    path
        The file to create (``events.jsonl``; parent directories are created,
        an existing file is replaced), or None to keep the ring only.
    writer
        Hand the lines to this :class:`RecordWriter` (file key: the file's
        name); None: write them synchronously from the caller.
    ring_size
        Events kept in :attr:`recent` (default 1000: a run's start-up, mode
        changes and failsafes, and several minutes of periodic counters).
    flush_interval_s
        See above (default 0.2 s).
    max_buffer_bytes
        The buffer is handed on as soon as it holds this many bytes (default
        64 KiB).

    Notes
    -----
    Unlike the other logs, :meth:`append` after :meth:`close` does not raise
    (an event at shutdown must not fail the shutdown): the event goes to the
    ring and is counted in :attr:`dropped`.
    """

    def __init__(
        self,
        path: str | Path | None = None,
        *,
        writer: RecordWriter | None = None,
        ring_size: int = 1000,
        flush_interval_s: float = 0.2,
        max_buffer_bytes: int = 64 * 1024,
    ) -> None:
        if not isinstance(ring_size, int) or isinstance(ring_size, bool) or ring_size < 1:
            raise ValueError(f"ring_size must be a positive integer, got {ring_size!r}")
        if not (math.isfinite(flush_interval_s) and flush_interval_s >= 0.0):
            raise ValueError(f"flush_interval_s must be >= 0, got {flush_interval_s!r}")
        if not isinstance(max_buffer_bytes, int) or max_buffer_bytes < 1:
            raise ValueError(
                f"max_buffer_bytes must be a positive integer, got {max_buffer_bytes!r}"
            )
        if path is None and writer is not None:
            raise ValueError("EventLog: a writer needs a path")
        self.path = None if path is None else Path(path)
        self.recent: deque[dict[str, Any]] = deque(maxlen=ring_size)
        """The last ``ring_size`` events, oldest first."""
        self.count = 0
        """Events appended."""
        self.dropped = 0
        """Events not recorded in the file: after a write error, or after :meth:`close`."""
        self._sink = None if self.path is None else _Sink(self.path, "event log", writer)
        self._open = self._sink is not None  # False once closed, or stopped by a write error
        self._buf = bytearray()
        self._interval = flush_interval_s
        self._max_buf = max_buffer_bytes
        self._next_flush = -math.inf  # the first event goes at once

    @property
    def failed(self) -> OSError | None:
        """The write error that stopped recording (with a writer: its error for this file)."""
        return None if self._sink is None else self._sink.failure()

    @property
    def buffered_bytes(self) -> int:
        """Bytes of lines not handed on yet (below ``max_buffer_bytes`` plus one line)."""
        return len(self._buf)

    def append(self, event: dict[str, Any]) -> None:
        """Record one event (a JSON-serialisable dict; it is kept by reference)."""
        self.recent.append(event)
        self.count += 1
        if not self._open:
            if self._sink is not None:
                self.dropped += 1
            return
        buf = self._buf
        buf += json.dumps(event, default=str).encode()
        buf += b"\n"
        if len(buf) >= self._max_buf or time.monotonic() >= self._next_flush:
            self.flush()

    def flush(self) -> None:
        """Hand the buffered lines on now (cheap when there are none)."""
        self._next_flush = time.monotonic() + self._interval
        if not self._open or not self._buf or self._sink is None:
            return
        buf, self._buf = self._buf, bytearray()
        if not self._sink.put(buf):
            self._open = False

    def close(self) -> None:
        """Flush and close the file; closing twice is harmless. The ring stays readable."""
        if not self._open or self._sink is None:
            return
        self.flush()
        self._open = False
        self._sink.close()

    def __enter__(self) -> EventLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def last_row(path: str | Path) -> tuple[float, ...] | None:
    """The last complete row of a :class:`ColumnarLog` being written, or None.

    Reads only the header and the file's tail: cheap enough to poll a live log.
    """
    p = Path(path)
    try:
        with p.open("rb") as f:
            head = f.read(65536)
            i = head.find(_MARKER)
            if i < 0:
                return None
            names_line = head[:i].rstrip(b"\n").rsplit(b"\n", 1)[-1]
            n = names_line.count(b",") + 1
            start = i + len(_MARKER)
            size = p.stat().st_size
            n_rows = (size - start) // (8 * n)
            if n_rows <= 0:
                return None
            f.seek(start + (n_rows - 1) * 8 * n)
            data = f.read(8 * n)
    except OSError:
        return None
    order = "<" if sys.byteorder == "little" else ">"
    return struct.unpack(f"{order}{n}d", data)


def read_columnar(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Read a :class:`ColumnarLog` file: ``({column: float64 array}, {key: value})``.

    A last row cut short (a killed writer can leave one) is ignored; the
    returned metadata then has ``partial_last_row_bytes``.

    Raises
    ------
    ValueError
        Naming the file when it has no header, no row marker, or another format.
    """
    p = Path(path)
    raw = p.read_bytes()
    head, sep, body = raw.partition(_MARKER)
    if not sep:
        raise ValueError(f"{p}: not a columnar log (no '{_MARKER.decode().strip()}' line)")
    lines = head.decode("utf-8", errors="replace").split("\n")
    meta: dict[str, str] = {}
    names: list[str] = []
    for line in lines:
        if line.startswith("#"):
            key, colon, val = line[1:].partition(":")
            if colon:
                meta[key.strip()] = val.strip()
        elif line.strip():
            names = line.strip().split(",")
    if not names:
        raise ValueError(f"{p}: no column-name line before the rows")
    fmt = meta.get("format", "")
    if fmt.split(" (")[0] != FORMAT.split(" (")[0]:
        raise ValueError(f"{p}: format {fmt!r}; this version reads {FORMAT!r}")
    n = len(names)
    width = 8 * n
    n_rows = len(body) // width
    if len(body) % width:
        log.info("%s: ignoring a truncated last row", p)
        meta["partial_last_row_bytes"] = str(len(body) % width)
    dtype = np.dtype("<f8" if meta.get("byteorder", "little") == "little" else ">f8")
    data = np.frombuffer(body[: n_rows * width], dtype=dtype).reshape(n_rows, n)
    cols = {
        name: np.ascontiguousarray(data[:, j], dtype=np.float64) for j, name in enumerate(names)
    }
    return cols, meta
