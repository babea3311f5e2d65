"""Byte transports under the MAVLink link: UDP in/out, serial, and an in-memory pair.

A transport moves opaque chunks of bytes. It knows nothing about MAVLink: the
:class:`~companion.link.mavlink.MavlinkLink` above it parses what arrives and
packs what leaves. Every transport has the same shape::

    t = open_transport("udpin:0.0.0.0:14540")   # nothing is opened yet
    await t.open(on_bytes)                       # on_bytes(chunk) runs in the loop thread
    t.write(data)                                # never blocks; may drop (counted)
    await t.close()                              # idempotent

Receiving uses ``loop.add_reader`` on a non-blocking file descriptor: one
datagram (UDP) or what is waiting (serial) per wake-up, no thread, no task per
message. Sending is a
direct non-blocking ``sendto`` / ``os.write``; what the kernel will not take right
now is dropped (UDP: a stale setpoint is worth less than the next one) or, for
serial, queued in a bounded buffer flushed by a loop writer.

Counters (``transport.counters``): ``bytes_in``, ``bytes_out``, ``chunks_in``,
``chunks_out``, ``dropped_no_peer`` (UDP in before the autopilot talked to
us), ``dropped_not_open``, ``dropped_would_block`` (socket/serial buffer full),
``send_errors``, ``recv_errors``; udpin only: ``peer_changes``,
``other_sender_chunks`` (datagrams from an address that was not the peer
when they arrived).

Who ``udpin`` answers is the link's decision, not the network's: the
transport replies to the address the link last confirmed
(:meth:`Transport.confirm_peer`, called by the link for each HEARTBEAT it
accepts from the autopilot, i.e. from the right system and, with signing,
correctly signed). A datagram from anyone else is delivered to the link
(which ignores and counts what is not from the autopilot) but does not move
our replies: before, any sender, even of junk, became the peer until the
autopilot spoke again, and our setpoints and hand-back went to it. While it
delivers a chunk, the transport says whether it came from that confirmed
address (:attr:`Transport.rx_from_peer`): the link ignores frames that claim
the autopilot's identity from anywhere else (see
:class:`~companion.link.mavlink.MavlinkLink`).

What the parser may assume about chunk boundaries is
:attr:`Transport.datagrams`: a UDP datagram holds whole frames, so what is
left of a frame at its end is garbage; a serial read is a cut through a byte
stream, and a frame may continue in the next read.
"""

from __future__ import annotations

import abc
import asyncio
import errno
import logging
import os
import socket
from collections.abc import Callable
from typing import Any

from companion.errors import LinkError

__all__ = [
    "MemoryTransport",
    "SerialTransport",
    "Transport",
    "UdpInTransport",
    "UdpOutTransport",
    "open_transport",
]

logger = logging.getLogger(__name__)

OnBytes = Callable[[bytes], None]

_RECV_BYTES = 65535
_SERIAL_READ_BYTES = 4096
_SERIAL_MAX_PENDING = 64 * 1024
"""Serial output waiting for the port beyond this is dropped (57600 baud moves ~5.7 kB/s)."""

_URL_FORMS = "udpin:HOST:PORT, udpout:HOST:PORT or serial:DEVICE:BAUD"


def _new_counters(*extra: str) -> dict[str, int]:
    names = (
        "bytes_in",
        "bytes_out",
        "chunks_in",
        "chunks_out",
        "dropped_not_open",
        "dropped_would_block",
        "send_errors",
        "recv_errors",
        *extra,
    )
    return dict.fromkeys(names, 0)


class Transport(abc.ABC):
    """A bidirectional byte pipe driven by the asyncio event loop.

    Attributes
    ----------
    description
        Human-readable address, e.g. ``"udpin:0.0.0.0:14540"``.
    counters
        Monotonic counters; see the module docstring for the names.
    datagrams
        Each chunk holds whole frames (UDP datagrams): a frame cut at the end of
        a chunk is garbage, not the start of a frame continued in the next one.
        False for a byte stream (serial), where a frame may go on in the next
        chunk.
    rx_from_peer
        While ``on_bytes`` runs: False if the chunk came from an address other
        than the peer the link confirmed (``udpin`` only, once a peer is
        confirmed); True otherwise, and always on transports without addresses.
    rx_address
        While ``on_bytes`` runs: the address the chunk came from, on transports
        that have addresses (UDP); None elsewhere.
    """

    description: str
    counters: dict[str, int]
    datagrams: bool = False
    rx_from_peer: bool = True
    rx_address: tuple[Any, ...] | None = None

    @abc.abstractmethod
    async def open(self, on_bytes: OnBytes) -> None:
        """Start delivering received chunks to ``on_bytes`` (called in the loop thread).

        Raises
        ------
        LinkError
            If the transport cannot be opened (port in use, no such device, ...).
        """

    @abc.abstractmethod
    def write(self, data: bytes) -> None:
        """Send ``data`` without blocking; drop (and count) what cannot go now."""

    @abc.abstractmethod
    async def close(self) -> None:
        """Stop receiving and release the resource. Safe to call more than once."""

    @property
    def is_open(self) -> bool:
        return False

    def confirm_peer(self) -> None:  # noqa: B027 (a no-op by default, not abstract)
        """Called while the chunk being delivered is from the autopilot: answer its sender.

        Only ``udpin`` has anything to learn; other transports have one peer.
        """

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.description}>"


# --------------------------------------------------------------------------- UDP


class _UdpTransport(Transport):
    """Shared machinery of the two UDP transports: a raw non-blocking socket + add_reader."""

    datagrams = True

    def __init__(self, kind: str, host: str, port: int) -> None:
        if not host:
            raise ValueError(f"{kind}: empty host")
        if not 0 <= port <= 65535:
            raise ValueError(f"{kind}: port {port} outside 0..65535")
        self.host = host
        self.port = port
        self.description = f"{kind}:{host}:{port}"
        self.counters = _new_counters("dropped_no_peer")
        self.peer: tuple[Any, ...] | None = None
        self.local_address: tuple[Any, ...] | None = None
        self._sock: socket.socket | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._on_bytes: OnBytes | None = None
        self.rx_address: tuple[Any, ...] | None = None

    @property
    def is_open(self) -> bool:
        return self._sock is not None

    async def _resolve(self, loop: asyncio.AbstractEventLoop) -> tuple[int, tuple[Any, ...]]:
        try:
            infos = await loop.getaddrinfo(self.host, self.port, type=socket.SOCK_DGRAM)
        except OSError as exc:
            raise LinkError(f"{self.description}: cannot resolve {self.host!r}: {exc}") from exc
        family, _type, _proto, _canon, addr = infos[0]
        return int(family), tuple(addr)

    def _start(
        self, sock: socket.socket, loop: asyncio.AbstractEventLoop, on_bytes: OnBytes
    ) -> None:
        sock.setblocking(False)
        self._sock = sock
        self._loop = loop
        self._on_bytes = on_bytes
        self.local_address = tuple(sock.getsockname())
        loop.add_reader(sock.fileno(), self._read_ready)

    def _read_ready(self) -> None:
        sock = self._sock
        on_bytes = self._on_bytes
        if sock is None or on_bytes is None:
            return
        # One datagram per wake-up, as asyncio's own datagram transport does: the
        # selector is level-triggered and calls again while more is waiting, so a
        # flood cannot starve the loop, and the common single datagram costs one
        # recvfrom instead of a second one ending in BlockingIOError.
        counters = self.counters
        try:
            data, addr = sock.recvfrom(_RECV_BYTES)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:  # e.g. ECONNREFUSED from an ICMP error on Linux
            counters["recv_errors"] += 1
            if exc.errno not in (errno.ECONNREFUSED, errno.EHOSTUNREACH):
                logger.warning("%s: receive failed: %s", self.description, exc)
            return
        counters["chunks_in"] += 1
        counters["bytes_in"] += len(data)
        self.rx_from_peer = addr == self.peer or self._on_new_sender(addr)
        self.rx_address = addr
        on_bytes(data)

    def _on_new_sender(self, addr: tuple[Any, ...]) -> bool:
        """A datagram came from an address other than ``self.peer``: whether to
        deliver it as from the peer (:attr:`rx_from_peer`)."""
        return True

    def write(self, data: bytes) -> None:
        sock = self._sock
        if sock is None:
            self.counters["dropped_not_open"] += 1
            return
        peer = self.peer
        if peer is None:
            self.counters["dropped_no_peer"] += 1
            return
        try:
            sock.sendto(data, peer)
        except (BlockingIOError, InterruptedError):
            self.counters["dropped_would_block"] += 1
            return
        except OSError as exc:
            # ECONNREFUSED: the peer's port is closed (ICMP); keep going, it may come back.
            self.counters["send_errors"] += 1
            if self.counters["send_errors"] == 1:
                logger.warning("%s: send to %s failed: %s", self.description, peer, exc)
            return
        self.counters["chunks_out"] += 1
        self.counters["bytes_out"] += len(data)

    async def close(self) -> None:
        sock = self._sock
        if sock is None:
            return
        self._sock = None
        self._on_bytes = None
        if self._loop is not None and not self._loop.is_closed():
            self._loop.remove_reader(sock.fileno())
        sock.close()


class UdpInTransport(_UdpTransport):
    """Bind ``host:port`` and reply to the address the autopilot's frames come from.

    The link says which sender that is (:meth:`confirm_peer`); until it has,
    there is nobody to reply to: writes are dropped and counted in
    ``dropped_no_peer``. Port 0 binds an ephemeral port (see
    :attr:`local_address` after :meth:`open`).
    """

    def __init__(self, host: str, port: int) -> None:
        super().__init__("udpin", host, port)
        self.counters["peer_changes"] = 0
        self.counters["other_sender_chunks"] = 0

    async def open(self, on_bytes: OnBytes) -> None:
        if self._sock is not None:
            raise LinkError(f"{self.description}: already open")
        loop = asyncio.get_running_loop()
        family, addr = await self._resolve(loop)
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.bind(addr)
        except OSError as exc:
            sock.close()
            what = "address already in use" if exc.errno == errno.EADDRINUSE else str(exc)
            raise LinkError(f"{self.description}: cannot bind: {what}") from exc
        self._start(sock, loop, on_bytes)
        logger.info("%s: listening on %s", self.description, self.local_address)

    def _on_new_sender(self, addr: tuple[Any, ...]) -> bool:
        self.counters["other_sender_chunks"] += 1
        return self.peer is None  # before the autopilot is known nobody is singled out

    def confirm_peer(self) -> None:
        addr = self.rx_address
        if addr is None or addr == self.peer:
            return
        if self.peer is not None:
            self.counters["peer_changes"] += 1
        logger.info("%s: peer is now %s", self.description, addr)
        self.peer = addr
        self.rx_from_peer = True  # the rest of this chunk is from the peer now


class UdpOutTransport(_UdpTransport):
    """Send to ``host:port`` from an ephemeral local port; receive what comes back on it.

    Replies are accepted from any address (an autopilot may answer from another
    interface), so :attr:`rx_from_peer` is always True; the destination stays
    ``host:port``.
    """

    def __init__(self, host: str, port: int) -> None:
        if port == 0:
            raise ValueError("udpout: port 0 is not a destination")
        super().__init__("udpout", host, port)

    async def open(self, on_bytes: OnBytes) -> None:
        if self._sock is not None:
            raise LinkError(f"{self.description}: already open")
        loop = asyncio.get_running_loop()
        family, addr = await self._resolve(loop)
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.bind(("::", 0) if family == socket.AF_INET6 else ("0.0.0.0", 0))
        except OSError as exc:
            sock.close()
            raise LinkError(f"{self.description}: cannot open a local UDP socket: {exc}") from exc
        self.peer = addr
        self._start(sock, loop, on_bytes)
        logger.info("%s: sending from %s", self.description, self.local_address)


# ------------------------------------------------------------------------ serial


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
        self.counters = _new_counters()
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


# ------------------------------------------------------------------------ memory


class MemoryTransport(Transport):
    """One end of an in-memory pipe, for tests: see :meth:`pair`.

    ``write`` on one end schedules ``on_bytes`` of the other end with
    ``loop.call_soon`` (so delivery is asynchronous, as on a real link). Writes
    while the other end is not open are dropped and counted in ``dropped_no_peer``.

    Each write arrives as one chunk. ``datagrams`` says what the link may assume
    of that (see :attr:`Transport.datagrams`): False by default, a byte stream,
    where tests may also hand the link frames cut across chunks; True to play a
    UDP link, where a chunk holds whole frames.
    """

    def __init__(self, name: str = "memory", *, datagrams: bool = False) -> None:
        self.description = name
        self.datagrams = datagrams
        self.counters = _new_counters("dropped_no_peer")
        self.peer: MemoryTransport | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._on_bytes: OnBytes | None = None

    @staticmethod
    def pair(*, datagrams: bool = False) -> tuple[MemoryTransport, MemoryTransport]:
        """Two connected ends: what one writes, the other receives."""
        a = MemoryTransport("memory:a", datagrams=datagrams)
        b = MemoryTransport("memory:b", datagrams=datagrams)
        a.peer, b.peer = b, a
        return a, b

    @property
    def is_open(self) -> bool:
        return self._on_bytes is not None

    async def open(self, on_bytes: OnBytes) -> None:
        if self._on_bytes is not None:
            raise LinkError(f"{self.description}: already open")
        self._loop = asyncio.get_running_loop()
        self._on_bytes = on_bytes

    def write(self, data: bytes) -> None:
        if self._on_bytes is None:
            self.counters["dropped_not_open"] += 1
            return
        peer = self.peer
        if peer is None or peer._on_bytes is None or peer._loop is None:
            self.counters["dropped_no_peer"] += 1
            return
        chunk = bytes(data)
        self.counters["chunks_out"] += 1
        self.counters["bytes_out"] += len(chunk)
        peer._loop.call_soon(peer._deliver, chunk)

    def _deliver(self, chunk: bytes) -> None:
        on_bytes = self._on_bytes
        if on_bytes is None:  # closed while the chunk was in flight
            self.counters["dropped_not_open"] += 1
            return
        self.counters["chunks_in"] += 1
        self.counters["bytes_in"] += len(chunk)
        on_bytes(chunk)

    async def close(self) -> None:
        self._on_bytes = None


# --------------------------------------------------------------------------- URL


def _bad_url(url: str, why: str) -> ValueError:
    return ValueError(f"bad link URL {url!r}: {why}; expected {_URL_FORMS}")


def _parse_port(url: str, text: str, *, allow_zero: bool) -> int:
    try:
        port = int(text)
    except ValueError:
        raise _bad_url(url, f"port {text!r} is not an integer") from None
    if not (0 if allow_zero else 1) <= port <= 65535:
        raise _bad_url(url, f"port {port} outside {0 if allow_zero else 1}..65535")
    return port


def open_transport(url: str) -> Transport:
    """Build (but do not open) the transport a link URL names.

    Parameters
    ----------
    url
        ``udpin:HOST:PORT`` (bind; port 0 = ephemeral), ``udpout:HOST:PORT``, or
        ``serial:DEVICE:BAUD`` (DEVICE may contain ``/`` and ``:``; the baud rate
        is after the last ``:``). An IPv6 HOST goes in brackets: ``udpin:[::]:14540``.

    Raises
    ------
    ValueError
        Naming the URL and the expected forms.
    """
    if not isinstance(url, str):
        raise TypeError(f"link URL must be a str, got {type(url).__name__}")
    kind, sep, rest = url.strip().partition(":")
    if not sep:
        raise _bad_url(url, "no scheme")
    if kind in ("udpin", "udpout"):
        host, sep, port_s = rest.rpartition(":")
        if not sep or not host:
            raise _bad_url(url, "missing HOST or PORT")
        if host.startswith("[") and host.endswith("]"):
            host = host[1:-1]
        elif ":" in host:
            raise _bad_url(url, f"host {host!r} has ':' (put an IPv6 address in brackets)")
        if not host:
            raise _bad_url(url, "empty host")
        port = _parse_port(url, port_s, allow_zero=kind == "udpin")
        return UdpInTransport(host, port) if kind == "udpin" else UdpOutTransport(host, port)
    if kind == "serial":
        device, sep, baud_s = rest.rpartition(":")
        if not sep or not device:
            raise _bad_url(url, "missing DEVICE or BAUD")
        try:
            baud = int(baud_s)
        except ValueError:
            raise _bad_url(url, f"baud rate {baud_s!r} is not an integer") from None
        if baud <= 0:
            raise _bad_url(url, f"baud rate {baud} must be > 0")
        return SerialTransport(device, baud)
    raise _bad_url(url, f"unknown scheme {kind!r}")
