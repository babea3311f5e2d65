"""The :class:`Transport` every byte transport under the MAVLink link implements.

A transport moves opaque chunks of bytes. It knows nothing about MAVLink: the
:class:`~companion.link.mavlink.MavlinkLink` above it parses what arrives and
packs what leaves.

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

What the parser may assume about chunk boundaries is
:attr:`Transport.datagrams`: a UDP datagram holds whole frames, so what is
left of a frame at its end is garbage; a serial read is a cut through a byte
stream, and a frame may continue in the next read.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import Any

__all__ = ["OnBytes", "Transport", "new_counters"]

OnBytes = Callable[[bytes], None]


def new_counters(*extra: str) -> dict[str, int]:
    """Zeroed counters: those every transport keeps, then ``extra``."""
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
