"""Receiving: the frames in each chunk from the transport (the IMU-driven hot path).

The link finds the frames in each chunk from the transport itself and has
pymavlink decode each one; each decoded message is checked (signature when
signing is configured, then source = the autopilot, then, on ``udpin``, the
address it came from: :mod:`companion.link.accept`) and handed to
``on_message`` synchronously, in the event-loop thread. Nothing is queued.

Garbage costs little and takes nothing with it. A datagram (UDP) holds whole
frames, so each is parsed on its own: what is left of a frame cut at its end
is dropped, never joined to the next datagram. A byte stream (serial) keeps a
cut frame's start for the next chunk. Either way garbage is skipped to the
next start byte (0xFD, 0xFE) with ``bytes.find``, and a start byte whose frame
does not check out (flags, length, CRC) is passed over by one byte, so a good
frame behind garbage is still found. The work on one chunk is bounded:
datagrams over 4096 bytes are dropped unread, and after 128 start bytes
examined in vain the rest of a chunk is dropped.

Messages registered with :meth:`MavlinkLink.add_fast_handler
<companion.link.mavlink.MavlinkLink.add_fast_handler>` (the IMU sample) take a
shorter road when they can: a chunk that starts with whole, unsigned MAVLink 2
frames of registered ids from the autopilot, with a good CRC, is decoded with
one precompiled ``struct`` per frame, without pymavlink's decoder and message
objects (1 us instead of 8 us for a HIGHRES_IMU datagram, measured in a tight
loop). Anything else (a frame split across chunks, a bad CRC, another sender
or sender address, signing, MAVLink 1) takes the long road, and a registered
message decoded there reaches the same handler with the same values. Counters
and ``on_raw`` see both roads alike.
"""

from __future__ import annotations

import logging
import operator
import struct
import time
from collections.abc import Callable, Sequence
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from companion.link import frames
from companion.link.accept import Acceptor, FastHandler, OnMessage, OnRaw, callback_failed
from companion.link.frames import (
    MAGIC_V1,
    MAGIC_V2,
    crc16,
    crc_ok,
    fast_layout,
    next_start,
    read_header,
)
from companion.link.requests import Requester
from companion.link.transport import Transport

__all__ = ["MAX_CHECKS", "Receiver"]

logger = logging.getLogger("companion.link.mavlink")

# Assigned, not imported by name: CPython (3.11) compiles ``NAME.unpack_from(...)``
# for an imported NAME as an attribute load and a call, a bound method made each time.
_HEADER = frames.HEADER

_MAX_DATAGRAM_BYTES = 4096
"""A longer datagram is dropped unread (``oversize_dropped``). A MAVLink 2 frame
is at most 280 bytes; a sender packing several frames into one datagram keeps it
within a network MTU (1472 bytes of UDP payload on Ethernet without IP
fragmentation). 4096 leaves room for any such packer (14 frames of the largest
size) and bounds the work on what is read: 4 kB of the smallest valid frames
took 1.5 ms to decode and judge, 4 kB of crafted garbage 0.2 ms (development
box), where one 60 kB datagram of random bytes held the loop for 8 ms."""

MAX_CHECKS = 128
"""Start bytes examined in vain per chunk (false starts, and start bytes looked
at inside a frame of an unknown id) before the rest of the chunk is dropped
(``resync_abandoned``). Each costs a header read and at most one CRC (one C
call), about a microsecond. Random noise holds one start byte in 128 bytes, so
a good frame behind kilobytes of noise is still found, while crafted garbage (a
start byte every few bytes) costs a bounded amount of work."""


class Receiver:
    """Finds the frames in each chunk from the transport, has each decoded and
    judged, and hands the autopilot's on: to a fast handler or ``on_message``,
    and its replies to the requester.

    Parameters
    ----------
    transport
        Whose chunks these are: ``datagrams`` (each chunk whole frames) or a byte
        stream; ``rx_from_peer`` (the chunk came from the autopilot's confirmed
        address); ``description`` (for the log).
    counters
        The link's counters.
    parser
        A pymavlink ``MAVLink`` without a key, used only to decode the frames
        found (signatures are judged by the acceptor).
    acceptor
        Judges each decoded frame; its ``target`` is the only sender the short
        road takes.
    requester
        Is handed the autopilot's HEARTBEAT, COMMAND_ACK and PARAM_VALUE.
    short_road
        Whether registered messages may be decoded straight from the chunk: not
        with signing (signed frames are judged by the acceptor's checker).
    on_message, on_raw
        As :class:`~companion.link.mavlink.MavlinkLink`'s; either may be replaced
        at any time.
    """

    def __init__(
        self,
        transport: Transport,
        counters: dict[str, int],
        parser: Any,
        acceptor: Acceptor,
        requester: Requester,
        *,
        short_road: bool,
        on_message: OnMessage | None,
        on_raw: OnRaw | None,
    ) -> None:
        self._transport = transport
        self._counters = counters
        self._parser = parser
        self._acceptor = acceptor
        self._requester = requester
        self._short_road = short_road
        self.on_message = on_message
        self.on_raw = on_raw
        self.rx_perf_s = 0.0
        """``time.perf_counter()`` when the chunk being handled arrived."""
        self._datagrams = transport.datagrams
        self._pending = b""  # a byte stream: the start of a frame, waiting for the rest
        self._checks_left = MAX_CHECKS  # per chunk
        # msg id -> (getter of the values from a pymavlink message, handler)
        self._fast: dict[int, tuple[Callable[[Any], tuple[Any, ...]], FastHandler]] = {}
        # msg id -> (layout, crc extra byte, full payload length, handler); the short road
        self._fast_wire: dict[int, tuple[struct.Struct, bytes, int, FastHandler]] = {}

    def add_fast_handler(self, msg_id: int, fields: Sequence[str], handler: FastHandler) -> None:
        """See :meth:`companion.link.mavlink.MavlinkLink.add_fast_handler`."""
        layout, full_len = fast_layout(msg_id, fields)
        names = tuple(fields)
        getter: Callable[[Any], tuple[Any, ...]]
        if len(names) == 1:
            name = names[0]

            def getter(msg: Any) -> tuple[Any, ...]:
                return (getattr(msg, name),)

        else:
            getter = operator.attrgetter(*names)
        self._fast[msg_id] = (getter, handler)
        if self._short_road:
            crc_extra = mavlink2.mavlink_map[msg_id].crc_extra
            self._fast_wire[msg_id] = (layout, bytes((crc_extra,)), full_len, handler)

    def on_bytes(self, chunk: bytes) -> None:
        """One chunk from the transport (its ``on_bytes``)."""
        self.rx_perf_s = time.perf_counter()
        on_raw = self.on_raw
        # Stamped on arrival, recorded after the callback: the tlog entry of an IMU
        # sample is written after the command it caused has left.
        t_rx = time.time() if on_raw is not None else 0.0
        counters = self._counters
        n = len(chunk)
        if n > _MAX_DATAGRAM_BYTES and self._datagrams:  # see _MAX_DATAGRAM_BYTES
            counters["oversize_dropped"] += 1
            if counters["oversize_dropped"] == 1:
                logger.warning(
                    "%s: dropped a %d-byte datagram unread (over %d bytes; logged once, "
                    "counted in oversize_dropped)",
                    self._transport.description,
                    n,
                    _MAX_DATAGRAM_BYTES,
                )
            return
        wire = self._fast_wire
        if wire and not self._pending:
            # The short road: whole unsigned MAVLink 2 frames of registered ids from
            # the autopilot, CRC checked; the first frame that is anything else
            # sends the rest of the chunk to the long road. A chunk from another
            # address than the autopilot's confirmed one (udpin) matches no target
            # here: the long road judges it.
            i = 0
            target = self._acceptor.target if self._transport.rx_from_peer else None
            while i + 12 <= n:
                magic, plen, incompat, _c, _s, sysid, compid, id_lo, id_hi = _HEADER.unpack_from(
                    chunk, i
                )
                end = i + 12 + plen
                spec = wire.get(id_lo | id_hi << 16)
                if (
                    spec is None
                    or magic != MAGIC_V2
                    or incompat
                    or end > n
                    or (sysid, compid) != target
                ):
                    break
                layout, crc_extra, full_len, handler = spec
                if plen > full_len or crc16(crc_extra, crc16(chunk[i + 1 : end - 2])) != (
                    chunk[end - 2] | chunk[end - 1] << 8
                ):
                    break
                if plen >= layout.size:
                    values = layout.unpack_from(chunk, i + 10)
                else:  # MAVLink 2 dropped the payload's trailing zeros
                    values = layout.unpack(chunk[i + 10 : end - 2] + bytes(layout.size - plen))
                counters["received"] += 1
                counters["accepted"] += 1
                try:
                    handler(values)
                except Exception:
                    callback_failed(counters, "a fast handler")
                if on_raw is not None:
                    on_raw(t_rx, chunk if end == n and i == 0 else chunk[i:end], False)
                i = end
            if i == n:
                return
            if i:
                chunk = chunk[i:]
        self._scan(chunk, t_rx, on_raw)

    def _scan(self, data: bytes, t_rx: float, on_raw: OnRaw | None) -> None:
        """The long road: find the frames in ``data``, decode and judge each.

        ``data`` is the rest of a datagram, or of a byte stream's chunk behind what
        was pending from the previous chunk. A start byte (0xFD, 0xFE) begins a
        frame only if the frame checks out (:meth:`_frame_at`); if not, the scan
        goes on from the next start byte after it. pymavlink's own parser, fed
        chunk after chunk, took the length a garbage start byte claims and dropped
        that many bytes, the good frame behind with them, and carried a frame cut
        at the end of one datagram into the next.
        """
        counters = self._counters
        if self._pending:
            data = self._pending + data
            self._pending = b""
        n = len(data)
        i = 0
        self._checks_left = MAX_CHECKS
        after_reject = False  # bytes skipped right after a false start are part of it
        while i < n:
            j = next_start(data, i)
            if j != i:
                skipped_to = n if j < 0 else j
                counters["garbage_bytes"] += skipped_to - i
                if not after_reject:
                    counters["bad_data"] += 1
                if j < 0:
                    return
            end, why = self._frame_at(data, j)
            if why == "wait":  # a byte stream: the rest of the frame is still to come
                self._pending = data[j:]
                return
            msg = None
            if not why:
                try:
                    msg = self._parser.decode(bytearray(data[j:end]))
                except mavlink2.MAVError:  # not expected after _frame_at's checks: a guard
                    why, end = "bad_data", j + 1
            if msg is None:
                counters[why] += 1
                counters["garbage_bytes"] += end - j
                i = end
                after_reject = True
                self._checks_left -= 1
                if self._checks_left <= 0:
                    counters["garbage_bytes"] += n - i
                    counters["resync_abandoned"] += 1
                    return
                continue
            self._deliver(msg, t_rx, on_raw)
            i = end
            after_reject = False

    def _deliver(self, msg: Any, t_rx: float, on_raw: OnRaw | None) -> None:
        """Have one decoded frame judged and hand it on if it is the autopilot's."""
        counters = self._counters
        mtype = msg._type
        counters["received"] += 1
        if self._acceptor.accept(msg, mtype):
            counters["accepted"] += 1
            if mtype == "HEARTBEAT":
                self._acceptor.on_heartbeat(msg)
                self._requester.on_heartbeat(msg)
            elif mtype == "COMMAND_ACK":
                self._requester.on_command_ack(msg)
            elif mtype == "PARAM_VALUE":
                self._requester.on_param_value(msg)
            fast = self._fast
            registered = fast.get(msg.get_msgId()) if fast else None
            try:
                if registered is not None:
                    getter, handler = registered
                    handler(getter(msg))
                elif self.on_message is not None:
                    self.on_message(msg)
            except Exception:
                callback_failed(counters, "on_message")
        if on_raw is not None:
            on_raw(t_rx, bytes(msg._msgbuf), False)

    def _frame_at(self, data: bytes, j: int) -> tuple[int, str]:
        """Whether a frame starts at the start byte ``data[j]``.

        Returns ``(end, why)``. ``why`` empty: the frame is ``data[j:end]``.
        ``"wait"``: a byte stream, and it may be one once more bytes arrive.
        Else ``why`` is the counter of the false start, ``"bad_data"`` (bad
        flags, bad CRC) or ``"truncated_dropped"`` (its datagram ends inside it),
        and the scan resumes at ``end``: the next byte, or a frame found inside
        (the start bytes before that one were looked at already).

        The CRC is checked here, with one C call, before pymavlink sees the frame.
        pymavlink cannot check the CRC of an id outside the dialect (it lacks the
        id's CRC extra byte), and a start byte in noise is followed by such an id
        almost always. So a frame of an unknown id is taken only if the next
        frame starts right behind it (or its datagram ends there) and no frame
        that checks out, or on a stream may yet, starts inside it (as far as the
        chunk's budget of checks goes): else noise would take, and drop, the up
        to 280 bytes its random header claims. (A real frame of an unknown id
        rejected by mistake costs nothing: it would have been ignored.)
        """
        n = len(data)
        header = read_header(data, j)
        if header is None:
            return self._cut_short(data, j)
        msgtype, crc_at, end = header
        if crc_at < 0:
            return j + 1, "bad_data"
        if end > n:
            return self._cut_short(data, j)
        if msgtype is not None:
            return (end, "") if crc_ok(data, j, crc_at, msgtype) else (j + 1, "bad_data")
        if end == n:  # a stream: see what follows; a datagram ends here
            if not self._datagrams:
                return self._cut_short(data, j)
        elif data[end] not in (MAGIC_V2, MAGIC_V1):
            return j + 1, "bad_data"
        inside = self._frame_inside(data, j + 1, end, stream=not self._datagrams)
        if inside == -1:
            return end, ""
        return (j + 1 if inside is None else inside), "bad_data"

    def _cut_short(self, data: bytes, j: int) -> tuple[int, str]:
        """The frame at ``data[j]`` runs past the end of ``data``: see :meth:`_frame_at`."""
        if self._datagrams:
            return j + 1, "truncated_dropped"
        # A byte stream: wait for the rest, unless a good frame starts inside what
        # is there. That says the start byte was noise (a real frame holds one by
        # chance only), and waiting would hold the good frames up until the length
        # noise claimed had arrived.
        inside = self._frame_inside(data, j + 1, len(data), stream=False)
        if inside is None or inside == -1:
            return j, "wait"
        return inside, "bad_data"

    def _frame_inside(self, data: bytes, lo: int, hi: int, *, stream: bool) -> int | None:
        """Where the first frame that checks out starts in ``data[lo:hi]``: a whole
        frame of a dialect id with a good CRC or, with ``stream``, one that may
        become one (cut off by the end of ``data``). -1: none; ``None``: the
        chunk's budget of checks ran out before the answer."""
        k = next_start(data, lo)
        while 0 <= k < hi:
            if self._checks_left <= 0:
                return None
            self._checks_left -= 1
            header = read_header(data, k)
            if header is None:
                if stream:
                    return k
            else:
                msgtype, crc_at, end = header
                if msgtype is not None:
                    if end > len(data):
                        if stream:
                            return k
                    elif crc_ok(data, k, crc_at, msgtype):
                        return k
            k = next_start(data, k + 1)
        return -1
