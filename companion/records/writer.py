"""The records' writer thread: every write, flush and close of a run's record files.

A log hands its buffer over in one piece (:mod:`companion.records.sink`); with a
:class:`RecordWriter` the buffer is queued to one thread, bounded, so a slow or
stalled disk never blocks the control path (see :mod:`companion.records`).
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Protocol

__all__ = ["Chunk", "Encoder", "RecordFileStats", "RecordWriter"]

log = logging.getLogger("companion.records")

Chunk = bytes | bytearray | memoryview
"""Bytes for :meth:`RecordWriter.submit`; ``len()`` must be the size in bytes."""


class Encoder(Protocol):
    """Turns what a log hands on into the bytes of its file, on the writer's thread.

    A file opened with an encoder (:meth:`RecordWriter.open`) may be handed any
    object whose ``len()`` is its size in bytes; the writer's thread calls
    :meth:`encode` on each, in submit order, and writes what it returns, then
    :meth:`finish`'s bytes before it closes the file (unless the file failed).
    So the formatting a file format needs costs the control path nothing.
    """

    def encode(self, data: Any) -> bytes: ...

    def finish(self) -> bytes: ...


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
        "encoder",
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

    def __init__(self, key: str, path: Path, f: BinaryIO, encoder: Encoder | None) -> None:
        self.key = key
        self.path = path
        self.f = f
        self.encoder = encoder
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
        about a minute of a 1 kHz flight's records (the control log's rows and the
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
    def open(
        self,
        file_key: str,
        path: str | Path,
        *,
        header: bytes = b"",
        encoder: Encoder | None = None,
    ) -> None:
        """Create ``path`` (replacing a file there), write ``header``, and accept chunks for it.

        Synchronous, on the caller's thread (at start-up, before the flight);
        parent folders are created. With an ``encoder``, what is submitted for
        this file is encoded on the writer's thread (:class:`Encoder`), and the
        encoder's last bytes are written when the writer closes the file.

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
                self._files[file_key] = _File(file_key, p, f, encoder)
        except BaseException:
            with contextlib.suppress(Exception):
                f.close()
            raise

    def submit(self, file_key: str, data: Any) -> bool:
        """Queue ``data`` to be appended to ``file_key``'s file. O(1); never blocks.

        ``data`` is a :data:`Chunk`, or, for a file opened with an encoder, what
        that encoder takes (its ``len()`` counts against the bounds).

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
                    t.f.write(data if t.encoder is None else t.encoder.encode(data))
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
                    if t.encoder is not None:
                        t.f.write(t.encoder.finish())
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
