"""The in-memory transport: two connected ends, for tests."""

from __future__ import annotations

import asyncio

from companion.errors import LinkError
from companion.link.transport_base import OnBytes, Transport, new_counters

__all__ = ["MemoryTransport"]


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
        self.counters = new_counters("dropped_no_peer")
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
