"""The MAVLink telemetry log (``.tlog``)."""

from __future__ import annotations

import logging
import math
import struct
import time
from pathlib import Path

from companion.records.sink import BufferedLog, Sink
from companion.records.writer import RecordWriter

__all__ = ["TlogWriter"]

log = logging.getLogger("companion.records")

_pack_usec = struct.Struct(">Q").pack


class TlogWriter(BufferedLog):
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

    _sink: Sink  # always a file here

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
        self._sink = Sink(self.path, "MAVLink log", writer)
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
