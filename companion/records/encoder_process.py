"""A record's encoder run in a child process (:mod:`companion.child_process`).

A record's encoder (:class:`companion.records.writer.Encoder`) runs on the
writer's thread, but formatting in this process would hold the interpreter's
lock the control loop needs. :class:`ProcessEncoder` hands each batch to the
same encoder in a child process and waits for the bytes with the lock
released. The writer's thread still writes the file, so a full disk, a killed
companion or a stalled write behave as with an encoder in the thread.

The child is started at the first batch, off the control path; if it cannot
start, the encoder in this process takes over (nothing was encoded yet, so the
file is the same). Once it has encoded, a child that ends or fails stops the
record, as a write error does: the flight goes on.
"""

from __future__ import annotations

import contextlib
import logging
from typing import Any

from companion.child_process import ChildObject
from companion.records.writer import Encoder

__all__ = ["ProcessEncoder"]

log = logging.getLogger("companion.records")


class ProcessEncoder:
    """``local``'s twin, ``factory(*args)``, encoding in a child process (module
    docstring). ``local`` has written the header; it encodes in this process if
    the child cannot start. The twin's own header is discarded."""

    def __init__(self, factory: str, args: tuple[Any, ...], local: Encoder) -> None:
        self._factory = factory
        self._args = args
        self._local = local
        self._child: ChildObject | None = None
        self._in_process = False
        """The child could not start: ``local`` encodes."""

    def __del__(self) -> None:
        # A file that failed is never finished: its child ends with its encoder.
        with contextlib.suppress(Exception):
            self._end()

    @property
    def pid(self) -> int | None:
        """The child's process id, while it runs."""
        return None if self._child is None else self._child.pid

    def encode(self, data: Any) -> bytes:
        if self._child is None and not self._in_process:
            self._start()
        if self._child is None:
            return self._local.encode(data)
        return bytes(self._child.call("encode", data))

    def finish(self) -> bytes:
        if self._child is None:
            return self._local.finish()
        try:
            return bytes(self._child.call("finish"))
        finally:
            self._end()

    def _start(self) -> None:
        try:
            child = ChildObject(self._factory, self._args)
            child.call("header")  # its twin here wrote it
        except OSError as exc:
            log.warning("records: the encoder's process did not start (%s); encoding here", exc)
            self._in_process = True
            return
        self._child = child

    def _end(self) -> None:
        if self._child is not None:
            self._child.close()
