"""The UDP transports: ``udpin`` (bind, answer the autopilot) and ``udpout`` (send to it).

Who ``udpin`` answers is the link's decision, not the network's: the
transport replies to the address the link last confirmed
(:meth:`~companion.link.transport_base.Transport.confirm_peer`, called by the
link for each HEARTBEAT it accepts from the autopilot, i.e. from the right
system and, with signing, correctly signed). A datagram from anyone else is
delivered to the link (which ignores and counts what is not from the
autopilot) but does not move our replies. While it delivers a chunk, the
transport says whether it came from that confirmed address
(:attr:`~companion.link.transport_base.Transport.rx_from_peer`): the link
ignores frames that claim the autopilot's identity from anywhere else (see
:class:`~companion.link.mavlink.MavlinkLink`).
"""

from __future__ import annotations

import asyncio
import errno
import logging
import socket
from typing import Any

from companion.errors import LinkError
from companion.link.transport_base import OnBytes, Transport, new_counters

__all__ = ["UdpInTransport", "UdpOutTransport"]

logger = logging.getLogger("companion.link.transport")

_RECV_BYTES = 65535


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
        self.counters = new_counters("dropped_no_peer")
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
