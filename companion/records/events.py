"""The event log (``events.jsonl``): one JSON object per event, and the last ones in memory."""

from __future__ import annotations

import json
import logging
import math
import time
from collections import deque
from pathlib import Path
from typing import Any

from companion.records.sink import BufferedLog, Sink
from companion.records.writer import RecordWriter

__all__ = ["EventLog"]

log = logging.getLogger("companion.records")


class EventLog(BufferedLog):
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
        self._sink = None if self.path is None else Sink(self.path, "event log", writer)
        self._open = self._sink is not None  # False once closed, or stopped by a write error
        self._buf = bytearray()
        self._interval = flush_interval_s
        self._max_buf = max_buffer_bytes
        self._next_flush = -math.inf  # the first event goes at once

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
