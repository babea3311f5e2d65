"""What a log writes through: its :class:`Sink` and the buffer every record shares.

A :class:`BufferedLog` hands its buffer to its :class:`Sink` in one piece; the
sink queues it to a :class:`~companion.records.writer.RecordWriter` or writes it
to its own file (see :mod:`companion.records`).
"""

from __future__ import annotations

import contextlib
import logging
import time
from pathlib import Path
from typing import Any, BinaryIO, TypeVar

from companion.records.writer import Chunk, Encoder, RecordWriter

__all__ = ["BufferedLog", "Sink"]

log = logging.getLogger("companion.records")


class Sink:
    """Where a log's flushed buffers go: a :class:`RecordWriter`, or its own file."""

    def __init__(
        self,
        path: Path,
        what: str,
        writer: RecordWriter | None,
        header: bytes = b"",
        encoder: Encoder | None = None,
    ) -> None:
        self.path = path
        self.what = what
        self.writer = writer
        self.key = path.name
        self.failed: OSError | None = None
        self._f: BinaryIO | None = None
        self._encoder = encoder
        if writer is not None:
            writer.open(self.key, path, header=header, encoder=encoder)
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

    def put(self, data: Any) -> bool:
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
            f.write(data if self._encoder is None else self._encoder.encode(data))
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
                try:
                    if self._encoder is not None:
                        f.write(self._encoder.finish())
                finally:
                    f.close()
            except OSError as exc:
                log.error("%s: closing the %s failed: %s", self.path, self.what, exc)
                self.failed = exc


_L = TypeVar("_L", bound="BufferedLog")


class BufferedLog:
    """What every record shares: a buffer handed on to its :class:`Sink` in one
    piece, at most every ``_interval`` seconds, and closing.

    A record sets ``_sink`` (None: nowhere to write), ``_open``, ``_buf``,
    ``_interval`` and ``_next_flush``; it appends to ``_buf`` itself.
    """

    _sink: Sink | None
    _open: bool  # False once closed, or stopped by a write error
    _buf: Any
    _interval: float
    _next_flush: float

    @property
    def failed(self) -> OSError | None:
        """The write error that stopped recording (with a writer: its error for this file)."""
        return None if self._sink is None else self._sink.failure()

    def _take(self) -> Chunk:
        """The buffered bytes, with an empty buffer left in their place."""
        buf, self._buf = self._buf, bytearray()
        return buf  # type: ignore[no-any-return]

    def flush(self) -> None:
        """Hand the buffer on now: to the writer's queue, or to the OS (no fsync)."""
        self._next_flush = time.monotonic() + self._interval
        if not self._open or not self._buf or self._sink is None:
            return
        if not self._sink.put(self._take()):
            self._open = False

    def close(self) -> None:
        """Flush and close; closing twice is harmless."""
        if not self._open or self._sink is None:
            return
        self.flush()
        self._open = False
        self._sink.close()

    def __enter__(self: _L) -> _L:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
