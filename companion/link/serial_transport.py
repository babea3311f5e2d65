"""The serial transport: a serial port driven through the event loop."""

from __future__ import annotations

import asyncio
import logging
import os
from typing import Any

from companion.errors import LinkError
from companion.link.transport_base import OnBytes, Transport, new_counters

__all__ = ["SerialTransport"]

logger = logging.getLogger("companion.link.transport")

_SERIAL_READ_BYTES = 4096
_SERIAL_MAX_PENDING = 64 * 1024
"""Serial output waiting for the port beyond this is dropped (57600 baud moves ~5.7 kB/s)."""


class SerialTransport(Transport):
    """A serial port (pyserial for setup, raw non-blocking fd I/O through the loop).

    Reads: ``loop.add_reader`` on the port's fd, ``os.read`` of what is there.
    Writes: ``os.write`` straight away; the remainder waits in a bounded buffer
    flushed by ``loop.add_writer``; beyond ``_SERIAL_MAX_PENDING`` bytes new data
    is dropped and counted in ``dropped_would_block``. If the device goes away
    (EOF/EIO), reading stops, ``failure`` holds a :class:`LinkError` and the error
    is logged; the link above notices the missing heartbeats.
    """

    def __init__(self, device: str, baud: int) -> None:
        if not device:
            raise ValueError("serial: empty device")
        if baud <= 0:
            raise ValueError(f"serial: baud rate must be > 0, got {baud}")
        self.device = device
        self.baud = baud
        self.description = f"serial:{device}:{baud}"
        self.counters = new_counters()
        self.failure: LinkError | None = None
        self._serial: Any = None
        self._fd: int | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._on_bytes: OnBytes | None = None
        self._pending = bytearray()
        self._writer_armed = False

    @property
    def is_open(self) -> bool:
        return self._fd is not None

    async def open(self, on_bytes: OnBytes) -> None:
        if self._fd is not None:
            raise LinkError(f"{self.description}: already open")
        import serial  # pyserial; imported here so UDP-only users do not pay for it

        loop = asyncio.get_running_loop()
        try:
            ser = serial.Serial(self.device, self.baud, timeout=0, write_timeout=0, exclusive=True)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise LinkError(f"{self.description}: cannot open: {exc}") from exc
        fd = ser.fileno()
        os.set_blocking(fd, False)
        self._serial = ser
        self._fd = fd
        self._loop = loop
        self._on_bytes = on_bytes
        self.failure = None
        loop.add_reader(fd, self._read_ready)
        logger.info("%s: open", self.description)

    def _read_ready(self) -> None:
        fd = self._fd
        on_bytes = self._on_bytes
        if fd is None or on_bytes is None:
            return
        try:
            data = os.read(fd, _SERIAL_READ_BYTES)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._fail(f"read failed: {exc}", exc)
            return
        if not data:
            self._fail("device closed (EOF)", None)
            return
        self.counters["chunks_in"] += 1
        self.counters["bytes_in"] += len(data)
        on_bytes(data)

    def _fail(self, what: str, exc: BaseException | None) -> None:
        self.counters["recv_errors"] += 1
        self.failure = LinkError(f"{self.description}: {what}")
        if exc is not None:
            self.failure.__cause__ = exc
        logger.error("%s", self.failure)
        if self._loop is not None and self._fd is not None:
            self._loop.remove_reader(self._fd)
            self._disarm_writer()

    def write(self, data: bytes) -> None:
        fd = self._fd
        if fd is None or self.failure is not None:
            self.counters["dropped_not_open"] += 1
            return
        if self._pending:
            self._queue(data)
            return
        try:
            n = os.write(fd, data)
        except (BlockingIOError, InterruptedError):
            n = 0
        except OSError as exc:
            self.counters["send_errors"] += 1
            if self.counters["send_errors"] == 1:
                logger.warning("%s: write failed: %s", self.description, exc)
            return
        self.counters["bytes_out"] += n
        if n == len(data):
            self.counters["chunks_out"] += 1
            return
        self._queue(data[n:])

    def _queue(self, data: bytes) -> None:
        if len(self._pending) + len(data) > _SERIAL_MAX_PENDING:
            self.counters["dropped_would_block"] += 1
            return
        self._pending += data
        self.counters["chunks_out"] += 1
        if not self._writer_armed and self._loop is not None and self._fd is not None:
            self._loop.add_writer(self._fd, self._write_ready)
            self._writer_armed = True

    def _write_ready(self) -> None:
        fd = self._fd
        if fd is None:
            return
        try:
            n = os.write(fd, self._pending)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self.counters["send_errors"] += 1
            logger.warning("%s: write failed: %s", self.description, exc)
            self._pending.clear()
            self._disarm_writer()
            return
        self.counters["bytes_out"] += n
        del self._pending[:n]
        if not self._pending:
            self._disarm_writer()

    def _disarm_writer(self) -> None:
        if self._writer_armed and self._loop is not None and self._fd is not None:
            self._loop.remove_writer(self._fd)
        self._writer_armed = False

    async def close(self) -> None:
        fd = self._fd
        if fd is None:
            return
        if self._loop is not None and not self._loop.is_closed():
            self._loop.remove_reader(fd)
            self._disarm_writer()
        self._fd = None
        self._on_bytes = None
        self._pending.clear()
        ser, self._serial = self._serial, None
        try:
            ser.close()
        except OSError as exc:  # the device may already be gone
            logger.debug("%s: close: %s", self.description, exc)
