"""The companion's MAVLink 2 link to one autopilot, over any :class:`Transport`.

::

    link = MavlinkLink(open_transport("udpin:0.0.0.0:14540"), on_message=handle)
    async with link:                                  # start(): open + our HEARTBEAT task
        hb = await link.wait_heartbeat(5.0)           # learns link.target
        await link.request_message_interval(mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU, 4000)
        link.send(link.mav.set_actuator_control_target_encode(...))

Receive path (the IMU-driven hot path): the link finds the frames in each
chunk from the transport itself and has pymavlink decode each one; each
decoded message is checked (signature when signing is configured, then
source = the autopilot, then, on ``udpin``, the address it came from) and
handed to ``on_message`` synchronously, in the event-loop thread. Nothing is
queued.

Garbage costs little and takes nothing with it. A datagram (UDP) holds whole
frames, so each is parsed on its own: what is left of a frame cut at its end
is dropped, never joined to the next datagram. A byte stream (serial) keeps a
cut frame's start for the next chunk. Either way garbage is skipped to the
next start byte (0xFD, 0xFE) with ``bytes.find``, and a start byte whose frame
does not check out (flags, length, CRC) is passed over by one byte, so a good
frame behind garbage is still found. The work on one chunk is bounded:
datagrams over 4096 bytes are dropped unread, and after 128 start bytes
examined in vain the rest of a chunk is dropped.

Messages registered with :meth:`MavlinkLink.add_fast_handler` (the IMU
sample) take a shorter road when they can: a chunk that starts with whole,
unsigned MAVLink 2 frames of registered ids from the autopilot, with a good
CRC, is decoded with one precompiled ``struct`` per frame, without
pymavlink's decoder and message objects (1 us instead of 8 us for a
HIGHRES_IMU datagram, measured in a tight loop). Anything else (a frame split
across chunks, a bad CRC, another sender or sender address, signing,
MAVLink 1) takes the long road, and a registered message decoded there
reaches the same handler with the same values. Counters and ``on_raw`` see
both roads alike.

Only the autopilot's messages reach ``on_message``: the autopilot is pinned
(``target_system``/``target_component``) or learned from the first HEARTBEAT
whose ``autopilot`` is not ``MAV_AUTOPILOT_INVALID`` and whose ``type`` is not
a GCS or an onboard controller. Everything else is counted and dropped. On
``udpin`` the autopilot's address is confirmed by its HEARTBEATs; frames with
its ids from any other address are ignored (a HEARTBEAT from a new address
is taken once the old one has been silent for ``peer_silence_s``) and
reported through ``on_anomaly``.

Counters (``link.counters``): ``received`` (frames decoded, before any check),
``accepted`` (passed to ``on_message``), ``foreign_ignored`` (not from the
autopilot, including anything before it is known except its first HEARTBEAT),
``spoofed_ignored`` (the autopilot's ids from another address than its
confirmed one, ``udpin``), ``bad_data`` (garbage: a run of bytes that is not a
frame, a frame with bad flags or a bad CRC), ``garbage_bytes`` (bytes skipped
as garbage), ``truncated_dropped`` (a frame cut short by the end of its
datagram), ``oversize_dropped`` (datagrams over 4096 bytes, dropped unread),
``resync_abandoned`` (chunks whose rest was dropped after 128 start bytes
examined in vain),
``unknown_ignored`` (message ids outside the common dialect),
``v1_ignored`` (MAVLink 1 frames under the ids of an autopilot whose
heartbeat came as MAVLink 2), ``unsigned_rejected``,
``bad_signature_rejected``, ``replay_rejected``,
``unsigned_accepted`` (with ``allow_unsigned``), ``sent``,
``callback_errors`` (``on_message``, a fast handler or ``on_anomaly`` raised:
logged once, the link keeps going).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import operator
import os
import re
import struct
import time
from collections.abc import Callable, Sequence
from typing import Any

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink2
from pymavlink.generator import mavcrc

from companion.errors import LinkError
from companion.link.signing import SignatureChecker, SigningConfig, signing_timestamp_now
from companion.link.transport import Transport

__all__ = ["MavlinkLink", "mavlink2"]

logger = logging.getLogger(__name__)

# The two messages sent once per control sample, packed without pymavlink's
# generic path (wire order: fields sorted by type size, as the generator does).
_HEADER = struct.Struct("<BBBBBBBHB")
_U16 = struct.Struct("<H")
_ACTUATOR = struct.Struct("<Q8fBBB")  # time_usec, controls[8], group_mlx, target sys, comp
_ID_ACTUATOR = mavlink2.MAVLINK_MSG_ID_SET_ACTUATOR_CONTROL_TARGET
_CRC_ACTUATOR = mavlink2.MAVLink_set_actuator_control_target_message.crc_extra
# time_boot_ms, q[4], body rates, thrust, target sys, comp, type_mask (thrust_body, an
# extension, is all zeros and so dropped with the trailing zeros)
_ATTITUDE_TARGET = struct.Struct("<I4fffffBBB")
_ID_ATTITUDE_TARGET = mavlink2.MAVLINK_MSG_ID_SET_ATTITUDE_TARGET
_CRC_ATTITUDE_TARGET = mavlink2.MAVLink_set_attitude_target_message.crc_extra
_EXTRA_ACTUATOR = bytes((_CRC_ACTUATOR,))
_EXTRA_ATTITUDE_TARGET = bytes((_CRC_ATTITUDE_TARGET,))


def _crc16_py(data: bytes, crc: int = 0xFFFF) -> int:
    acc = mavcrc.x25crc_slow()
    acc.crc = crc
    acc.accumulate(bytes(data))
    return int(acc.crc)


# CRC-16/MCRF4XX (MAVLink's X.25 checksum) as a function: fastcrc's, which
# pymavlink requires and uses itself, or pymavlink's pure-Python one.
_crc16: Callable[..., int] = mavcrc.mcrf4xx if mavcrc.mcrf4xx is not None else _crc16_py

_MAGIC_V2 = 0xFD
_MAGIC_V1 = 0xFE
_IFLAG_SIGNED = 0x01
_SIGNATURE_LEN = 13
_NUMERIC_FORMATS = frozenset("bBhHiIqQfd")

_MAX_DATAGRAM_BYTES = 4096
"""A longer datagram is dropped unread (``oversize_dropped``). A MAVLink 2 frame
is at most 280 bytes; a sender packing several frames into one datagram keeps it
within a network MTU (1472 bytes of UDP payload on Ethernet without IP
fragmentation). 4096 leaves room for any such packer (14 frames of the largest
size) and bounds the work on what is read: 4 kB of the smallest valid frames
took 1.5 ms to decode and judge, 4 kB of crafted garbage 0.2 ms (development
box), where one 60 kB datagram of random bytes held the loop for 8 ms."""

_MAX_CHECKS = 128
"""Start bytes examined in vain per chunk (false starts, and start bytes looked
at inside a frame of an unknown id) before the rest of the chunk is dropped
(``resync_abandoned``). Each costs a header read and at most one CRC (one C
call), about a microsecond. Random noise holds one start byte in 128 bytes, so
a good frame behind kilobytes of noise is still found, while crafted garbage (a
start byte every few bytes) costs a bounded amount of work."""

OnMessage = Callable[[Any], None]
FastHandler = Callable[[tuple[Any, ...]], None]
OnRaw = Callable[[float, bytes, bool], None]
OnAnomaly = Callable[[str, str], None]

_NOT_AUTOPILOT_TYPES = frozenset({mavlink2.MAV_TYPE_GCS, mavlink2.MAV_TYPE_ONBOARD_CONTROLLER})
_Unknown = mavlink2.MAVLink_unknown
_MAX_IN_PROGRESS = 100
"""At most this many MAV_RESULT_IN_PROGRESS acks extend one command's wait."""
_ANOMALY_PERIOD_S = 1.0
"""``on_anomaly`` is called at most once per this period for each kind."""


def _next_start(data: bytes, i: int) -> int:
    """Index of the first MAVLink start byte (0xFD or 0xFE) at or after ``i``, or -1.

    ``bytes.find`` skips garbage at C speed, where pymavlink walks it byte by byte.
    """
    v2 = data.find(b"\xfd", i)
    v1 = data.find(b"\xfe", i, v2 if v2 >= 0 else len(data))
    return v1 if v1 >= 0 else v2


def _read_header(data: bytes, j: int) -> tuple[Any, int, int] | None:
    """``(message class or None, crc_at, end)`` of the frame whose start byte is
    ``data[j]``, from its header; ``None`` if the header is cut off; ``crc_at``
    -1 for MAVLink 2 incompatibility flags other than "signed" (not a frame we
    can read)."""
    v2 = data[j] == _MAGIC_V2
    header_len = 10 if v2 else 6
    if j + header_len > len(data):
        return None
    if v2:
        flags = data[j + 2]
        if flags & ~_IFLAG_SIGNED:
            return None, -1, 0
        msg_id = data[j + 7] | data[j + 8] << 8 | data[j + 9] << 16
        signature_len = _SIGNATURE_LEN if flags else 0
    else:
        msg_id = data[j + 5]
        signature_len = 0
    crc_at = j + header_len + data[j + 1]
    return mavlink2.mavlink_map.get(msg_id), crc_at, crc_at + 2 + signature_len


def _crc_ok(data: bytes, j: int, crc_at: int, msgtype: Any) -> bool:
    crc = _crc16(bytes((msgtype.crc_extra,)), _crc16(data[j + 1 : crc_at]))
    return bool(crc == data[crc_at] | data[crc_at + 1] << 8)


class _Sink:
    """pymavlink's output "file": every packed frame goes through the link."""

    __slots__ = ("_link",)

    def __init__(self, link: MavlinkLink) -> None:
        self._link = link

    def write(self, buf: bytes) -> None:
        self._link._write_frame(buf)


def _fast_layout(msg_id: int, fields: Sequence[str]) -> tuple[struct.Struct, int]:
    """The ``struct`` reading ``fields`` (in wire order) from a payload of ``msg_id``,
    and the message's full payload length.

    Raises
    ------
    ValueError
        For an unknown id, an unknown or non-scalar field, or fields out of wire order.
    """
    msgtype = mavlink2.mavlink_map.get(msg_id)
    if msgtype is None:
        raise ValueError(f"message id {msg_id} is not in the common dialect")
    if not fields:
        raise ValueError("at least one field is needed")
    wire = list(msgtype.ordered_fieldnames)
    # The unpacker's format is in wire order: one code (with a count for arrays) per field.
    codes = re.findall(r"(\d*)([a-zA-Z])", msgtype.unpacker.format.lstrip("<"))
    if len(codes) != len(wire):
        raise ValueError(f"{msgtype.msgname}: cannot map its fields to its wire format")
    want = list(fields)
    fmt = ["<"]
    pos = 0
    for name in want:
        if name not in wire:
            raise ValueError(f"{msgtype.msgname} has no field {name!r}")
        j = wire.index(name)
        if j < pos:
            raise ValueError(f"{msgtype.msgname}: fields must be in wire order {wire}")
        for count, code in codes[pos:j]:
            fmt.append(f"{struct.calcsize(count + code)}x")
        count, code = codes[j]
        if count not in ("", "1") or code not in _NUMERIC_FORMATS:
            raise ValueError(f"{msgtype.msgname}.{name}: only scalar numeric fields")
        fmt.append(code)
        pos = j + 1
    return struct.Struct("".join(fmt)), int(msgtype.unpacker.size)


class MavlinkLink:
    """A MAVLink 2 (common dialect) link from the companion to one autopilot.

    Parameters
    ----------
    transport
        Where bytes go; not opened until :meth:`start`.
    source_system, source_component
        Our ids (default 1 / 191 = ``MAV_COMP_ID_ONBOARD_COMPUTER``).
    target_system, target_component
        Pin the autopilot; ``None`` learns it from its first HEARTBEAT (a pinned
        system id with ``target_component=None`` learns the component).
    signing
        Sign outgoing frames and check incoming ones (see :mod:`.signing`).
    heartbeat_hz
        Rate of our HEARTBEAT (``MAV_TYPE_ONBOARD_CONTROLLER``,
        ``MAV_AUTOPILOT_INVALID``); 0 sends none.
    on_message
        Called synchronously with every accepted message from the autopilot.
        Keep it short: it runs in the receive path.
    on_raw
        Telemetry-log hook ``(unix_time_s, frame, outgoing)``, called for every
        frame sent and every frame decoded (accepted *or not*: rejected, foreign
        and unknown frames are included; garbage that does not decode is not).
        Frames are as on the wire, signatures included; the one exception is
        SETUP_SIGNING, which carries the key and is never passed to ``on_raw``.
    on_anomaly
        Called ``(kind, detail)`` when the link sees something an operator should
        know of: ``"spoofed"`` (a frame claiming the autopilot's identity from
        another address, ignored) and ``"peer_changed"`` (the autopilot now
        speaks from a new address). At most once per second per kind, so a flood
        costs nothing; the counters say how many there were. It runs in the
        receive path: keep it short.
    peer_silence_s
        On ``udpin``, frames with the autopilot's identity from an address other
        than the one it was confirmed at are ignored (``spoofed_ignored``), except
        a HEARTBEAT once no HEARTBEAT came from the autopilot for this long, s:
        an autopilot restarting on a new source port takes over after that. 3 s,
        the default, is beyond the app's link-loss failsafe (2 s), so a vehicle
        under our control has already failed safe when the address can move. This
        is no authentication: against a determined sender use signing.
    """

    def __init__(
        self,
        transport: Transport,
        *,
        source_system: int = 1,
        source_component: int = mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER,
        target_system: int | None = None,
        target_component: int | None = None,
        signing: SigningConfig | None = None,
        heartbeat_hz: float = 1.0,
        on_message: OnMessage | None = None,
        on_raw: OnRaw | None = None,
        on_anomaly: OnAnomaly | None = None,
        peer_silence_s: float = 3.0,
    ) -> None:
        for name, value in (
            ("source_system", source_system),
            ("source_component", source_component),
        ):
            if not 1 <= value <= 255:
                raise ValueError(f"{name} must be in 1..255, got {value}")
        for name, opt in (("target_system", target_system), ("target_component", target_component)):
            if opt is not None and not 1 <= opt <= 255:
                raise ValueError(f"{name} must be in 1..255 or None, got {opt}")
        if target_component is not None and target_system is None:
            raise ValueError("target_component needs target_system")
        if not (math.isfinite(heartbeat_hz) and heartbeat_hz >= 0.0):
            raise ValueError(f"heartbeat_hz must be >= 0, got {heartbeat_hz}")
        if not (math.isfinite(peer_silence_s) and peer_silence_s >= 0.0):
            raise ValueError(f"peer_silence_s must be >= 0, got {peer_silence_s}")
        self.transport = transport
        self.source_system = source_system
        self.source_component = source_component
        self.signing = signing
        self.heartbeat_hz = heartbeat_hz
        self.on_message = on_message
        self.on_raw = on_raw
        self.on_anomaly = on_anomaly
        self.peer_silence_s = peer_silence_s
        self._want_system = target_system
        self._want_component = target_component
        self.target: tuple[int, int] | None = (
            (target_system, target_component)
            if target_system is not None and target_component is not None
            else None
        )
        self.last_heartbeat: Any | None = None
        self.rx_perf_s = 0.0
        """``time.perf_counter()`` when the chunk being handled arrived (read it in a handler)."""
        self.last_heartbeat_monotonic_s: float | None = None
        self.counters: dict[str, int] = dict.fromkeys(
            (
                "received",
                "accepted",
                "foreign_ignored",
                "bad_data",
                "unknown_ignored",
                "unsigned_rejected",
                "bad_signature_rejected",
                "replay_rejected",
                "unsigned_accepted",
                "sent",
                "callback_errors",
                "garbage_bytes",
                "truncated_dropped",
                "oversize_dropped",
                "resync_abandoned",
                "spoofed_ignored",
                "v1_ignored",
            ),
            0,
        )
        self._target_v2 = False
        """The autopilot's heartbeat came as MAVLink 2: it does not fall back to 1."""
        # Encoder: what callers use (link.mav.xxx_encode / xxx_send); signs when configured.
        self.mav = mavlink2.MAVLink(
            _Sink(self), srcSystem=source_system, srcComponent=source_component
        )
        # Parser: separate and keyless, so pymavlink does not judge signatures (we do).
        self._parser = mavlink2.MAVLink(
            None, srcSystem=source_system, srcComponent=source_component
        )
        # The link finds the frames (see _scan); pymavlink only decodes them.
        self._datagrams = transport.datagrams
        self._pending = b""  # a byte stream: the start of a frame, waiting for the rest
        self._checks_left = _MAX_CHECKS  # per chunk, see _MAX_CHECKS
        self._anomaly_next_s: dict[str, float] = {}
        self._checker = SignatureChecker(signing.key) if signing is not None else None
        # msg id -> (getter of the values from a pymavlink message, handler)
        self._fast: dict[int, tuple[Callable[[Any], tuple[Any, ...]], FastHandler]] = {}
        # msg id -> (layout, crc extra byte, full payload length, handler); only
        # without signing (signed frames are judged by the checker, on pymavlink's road)
        self._fast_wire: dict[int, tuple[struct.Struct, bytes, int, FastHandler]] = {}
        self._heartbeat_task: asyncio.Task[None] | None = None
        self._heartbeat_waiters: list[asyncio.Future[Any]] = []
        self._ack_waiters: dict[int, asyncio.Future[Any]] = {}
        self._param_waiters: dict[str, list[asyncio.Future[Any]]] = {}
        self._command_locks: dict[int, asyncio.Lock] = {}
        self._started = False
        self._closed = False

    def add_fast_handler(self, msg_id: int, fields: Sequence[str], handler: FastHandler) -> None:
        """Hand the autopilot's ``msg_id`` messages to ``handler`` instead of ``on_message``.

        ``handler`` receives a tuple of the values of ``fields`` (scalar
        fields, in the message's wire order, e.g. ``("time_usec", "xgyro",
        "ygyro", "zgyro")`` of HIGHRES_IMU), exactly as pymavlink decodes
        them. Whole unsigned frames are decoded straight from the chunk (see
        the module docstring); the rest through pymavlink. Checks, counters,
        ``on_raw`` and the handling of exceptions are those of ``on_message``.

        Raises
        ------
        ValueError
            For an unknown message id or field, a non-scalar field, or fields
            out of wire order.
        """
        layout, full_len = _fast_layout(msg_id, fields)
        names = tuple(fields)
        getter: Callable[[Any], tuple[Any, ...]]
        if len(names) == 1:
            name = names[0]

            def getter(msg: Any) -> tuple[Any, ...]:
                return (getattr(msg, name),)

        else:
            getter = operator.attrgetter(*names)
        self._fast[msg_id] = (getter, handler)
        if self.signing is None:
            crc_extra = mavlink2.mavlink_map[msg_id].crc_extra
            self._fast_wire[msg_id] = (layout, bytes((crc_extra,)), full_len, handler)

    # ------------------------------------------------------------------ lifecycle

    async def start(self) -> None:
        """Open the transport and start our HEARTBEAT task (``mavlink-heartbeat``).

        Raises
        ------
        LinkError
            If the transport cannot be opened, or the link was already started.
        """
        if self._started:
            raise LinkError(f"{self.transport.description}: link already started")
        if self.signing is not None:
            s = self.mav.signing
            s.secret_key = self.signing.key
            s.link_id = self.signing.link_id
            s.sign_outgoing = True
            s.timestamp = max(s.timestamp, signing_timestamp_now())
        await self.transport.open(self._on_bytes)
        self._started = True
        self._closed = False
        if self.heartbeat_hz > 0:
            task = asyncio.get_running_loop().create_task(
                self._heartbeat_loop(1.0 / self.heartbeat_hz), name="mavlink-heartbeat"
            )
            task.add_done_callback(self._heartbeat_done)
            self._heartbeat_task = task
        logger.info(
            "MAVLink link on %s as %d/%d%s",
            self.transport.description,
            self.source_system,
            self.source_component,
            f", signing key {self.signing.fingerprint}" if self.signing else "",
        )

    @property
    def heartbeat_task(self) -> asyncio.Task[None] | None:
        """Our HEARTBEAT task while the link runs (the app watches it)."""
        return self._heartbeat_task

    async def close(self) -> None:
        """Stop the heartbeat, fail pending waits with :class:`LinkError`, close the transport."""
        if self._closed:
            return
        self._closed = True
        task, self._heartbeat_task = self._heartbeat_task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        err = LinkError(f"{self.transport.description}: link closed")
        for fut in [*self._heartbeat_waiters, *self._ack_waiters.values()]:
            if not fut.done():
                fut.set_exception(err)
        self._heartbeat_waiters.clear()
        self._ack_waiters.clear()
        await self.transport.close()

    async def __aenter__(self) -> MavlinkLink:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def _heartbeat_loop(self, period_s: float) -> None:
        loop = asyncio.get_running_loop()
        mav = self.mav
        next_t = loop.time()
        while True:
            mav.heartbeat_send(
                mavlink2.MAV_TYPE_ONBOARD_CONTROLLER,
                mavlink2.MAV_AUTOPILOT_INVALID,
                0,
                0,
                mavlink2.MAV_STATE_ACTIVE,
            )
            next_t += period_s
            delay = next_t - loop.time()
            if delay < 0.0:  # fell behind (loop was busy): do not send a burst to catch up
                next_t = loop.time()
                delay = 0.0
            await asyncio.sleep(delay)

    def _heartbeat_done(self, task: asyncio.Task[None]) -> None:
        if not task.cancelled() and task.exception() is not None:
            logger.error("heartbeat task died", exc_info=task.exception())

    # ------------------------------------------------------------------- sending

    def send(self, msg: Any) -> None:
        """Pack ``msg`` (signed when signing is configured) and write it; never blocks."""
        self.mav.send(msg)

    # --------------------------------------------------------- the per-sample sends

    def send_actuator_controls(
        self, time_usec: int, controls: Sequence[float], group: int = 0
    ) -> None:
        """SET_ACTUATOR_CONTROL_TARGET to the autopilot: the per-sample command.

        Packs the frame with one precompiled ``struct`` instead of pymavlink's
        message object and generic packer (bytes identical, tested); with
        signing it takes pymavlink's path, which signs.
        """
        sysid, compid = self._require_target()
        if self.signing is not None:
            self.send(
                self.mav.set_actuator_control_target_encode(
                    time_usec, group, sysid, compid, list(controls)
                )
            )
            return
        payload = _ACTUATOR.pack(time_usec, *controls, group, sysid, compid)
        self._write_fast(_ID_ACTUATOR, _EXTRA_ACTUATOR, payload)

    def send_body_rates(
        self,
        time_boot_ms: int,
        rates_frd_rad_s: Sequence[float],
        thrust: float,
        type_mask: int = 128,
    ) -> None:
        """SET_ATTITUDE_TARGET with body rates and thrust (``type_mask`` 128:
        ignore the attitude quaternion). Same fast path as
        :meth:`send_actuator_controls`."""
        sysid, compid = self._require_target()
        r0, r1, r2 = rates_frd_rad_s
        if self.signing is not None:
            self.send(
                self.mav.set_attitude_target_encode(
                    time_boot_ms, sysid, compid, type_mask, [1.0, 0.0, 0.0, 0.0], r0, r1, r2,
                    thrust,
                )
            )  # fmt: skip
            return
        payload = _ATTITUDE_TARGET.pack(
            time_boot_ms, 1.0, 0.0, 0.0, 0.0, r0, r1, r2, thrust, sysid, compid, type_mask
        )
        self._write_fast(_ID_ATTITUDE_TARGET, _EXTRA_ATTITUDE_TARGET, payload)

    def _write_fast(self, msg_id: int, crc_extra: bytes, payload: bytes) -> None:
        # MAVLink 2 drops trailing zero bytes of a payload (at least one byte stays).
        body = payload.rstrip(b"\x00") or payload[:1]
        mav = self.mav
        seq = mav.seq
        frame = (
            _HEADER.pack(
                0xFD,
                len(body),
                0,
                0,
                seq,
                mav.srcSystem,
                mav.srcComponent,
                msg_id & 0xFFFF,
                msg_id >> 16,
            )
            + body
        )
        mav.seq = (seq + 1) & 0xFF
        frame += _U16.pack(_crc16(crc_extra, _crc16(frame[1:])))
        self._write_frame(frame)

    def _write_frame(self, buf: bytes) -> None:
        self.transport.write(buf)
        self.counters["sent"] += 1
        on_raw = self.on_raw
        if on_raw is not None:
            on_raw(time.time(), bytes(buf), True)

    def send_setup_signing(self, key: bytes, initial_timestamp: int | None = None) -> None:
        """Send SETUP_SIGNING with ``key`` to the target (provision the autopilot).

        Only over a trusted link (USB, a wire): the key travels in the clear. An
        all-zero key with timestamp 0 turns signing off on the autopilot. The frame
        is not passed to ``on_raw``.

        Raises
        ------
        LinkError
            If the target is not known yet.
        """
        if len(key) != 32:
            raise ValueError("signing key must be exactly 32 bytes")
        sysid, compid = self._require_target()
        ts = signing_timestamp_now() if initial_timestamp is None else initial_timestamp
        msg = self.mav.setup_signing_encode(sysid, compid, list(key), ts)
        buf = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        self.transport.write(buf)
        self.counters["sent"] += 1

    # ----------------------------------------------------------------- receiving

    def _on_bytes(self, chunk: bytes) -> None:
        self.rx_perf_s = time.perf_counter()
        on_raw = self.on_raw
        # Stamped on arrival, recorded after the callback: the tlog entry of an IMU
        # sample is written after the command it caused has left.
        t_rx = time.time() if on_raw is not None else 0.0
        counters = self.counters
        n = len(chunk)
        if n > _MAX_DATAGRAM_BYTES and self._datagrams:  # see _MAX_DATAGRAM_BYTES
            counters["oversize_dropped"] += 1
            if counters["oversize_dropped"] == 1:
                logger.warning(
                    "%s: dropped a %d-byte datagram unread (over %d bytes; logged once, "
                    "counted in oversize_dropped)",
                    self.transport.description,
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
            target = self.target if self.transport.rx_from_peer else None
            while i + 12 <= n:
                magic, plen, incompat, _c, _s, sysid, compid, id_lo, id_hi = _HEADER.unpack_from(
                    chunk, i
                )
                end = i + 12 + plen
                spec = wire.get(id_lo | id_hi << 16)
                if (
                    spec is None
                    or magic != _MAGIC_V2
                    or incompat
                    or end > n
                    or (sysid, compid) != target
                ):
                    break
                layout, crc_extra, full_len, handler = spec
                if plen > full_len or _crc16(crc_extra, _crc16(chunk[i + 1 : end - 2])) != (
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
                    self._callback_failed("a fast handler")
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
        counters = self.counters
        if self._pending:
            data = self._pending + data
            self._pending = b""
        n = len(data)
        i = 0
        self._checks_left = _MAX_CHECKS
        after_reject = False  # bytes skipped right after a false start are part of it
        while i < n:
            j = _next_start(data, i)
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
        header = _read_header(data, j)
        if header is None:
            return self._cut_short(data, j)
        msgtype, crc_at, end = header
        if crc_at < 0:
            return j + 1, "bad_data"
        if end > n:
            return self._cut_short(data, j)
        if msgtype is not None:
            return (end, "") if _crc_ok(data, j, crc_at, msgtype) else (j + 1, "bad_data")
        if end == n:  # a datagram ends here; a stream: see what follows
            return (end, "") if self._datagrams else self._cut_short(data, j)
        if data[end] not in (_MAGIC_V2, _MAGIC_V1):
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
        k = _next_start(data, lo)
        while 0 <= k < hi:
            if self._checks_left <= 0:
                return None
            self._checks_left -= 1
            header = _read_header(data, k)
            if header is None:
                if stream:
                    return k
            else:
                msgtype, crc_at, end = header
                if msgtype is not None:
                    if end > len(data):
                        if stream:
                            return k
                    elif _crc_ok(data, k, crc_at, msgtype):
                        return k
            k = _next_start(data, k + 1)
        return -1

    def _deliver(self, msg: Any, t_rx: float, on_raw: OnRaw | None) -> None:
        """Judge one decoded frame and hand it on if it is the autopilot's."""
        counters = self.counters
        mtype = msg._type
        counters["received"] += 1
        if self._accept(msg, mtype, self._checker, counters):
            counters["accepted"] += 1
            if mtype == "HEARTBEAT":
                self._on_heartbeat(msg)
            elif mtype == "COMMAND_ACK":
                self._on_command_ack(msg)
            elif mtype == "PARAM_VALUE":
                self._on_param_value(msg)
            fast = self._fast
            registered = fast.get(msg.get_msgId()) if fast else None
            try:
                if registered is not None:
                    getter, handler = registered
                    handler(getter(msg))
                elif self.on_message is not None:
                    self.on_message(msg)
            except Exception:
                self._callback_failed("on_message")
        if on_raw is not None:
            on_raw(t_rx, bytes(msg._msgbuf), False)

    def _callback_failed(self, what: str) -> None:
        counters = self.counters
        counters["callback_errors"] += 1
        if counters["callback_errors"] == 1:
            logger.exception("%s raised (logged once, counted after)", what)

    def _accept(self, msg: Any, mtype: str, checker: Any, counters: dict[str, int]) -> bool:
        """Signature, dialect, sender and sender-address checks; counts what it rejects."""
        if checker is not None and not self._signature_ok(checker, msg):
            return False
        if msg.__class__ is _Unknown:  # an id outside the dialect (pymavlink skips its CRC)
            counters["unknown_ignored"] += 1
            return False
        hdr = msg._header
        if (hdr.srcSystem, hdr.srcComponent) != self.target:
            if mtype == "HEARTBEAT" and self.target is None and self._learn_target(msg):
                return True
            counters["foreign_ignored"] += 1
            return False
        if not self.transport.rx_from_peer and not self._autopilot_moved(mtype):
            counters["spoofed_ignored"] += 1
            self._anomaly(
                "spoofed",
                "%s with the autopilot's ids %d/%d from %s, not its address: ignored "
                "(spoofed_ignored=%d)",
                mtype,
                hdr.srcSystem,
                hdr.srcComponent,
                self._rx_from(),
                counters["spoofed_ignored"],
            )
            return False
        if self._target_v2 and msg._msgbuf[0] == _MAGIC_V1:
            # An autopilot speaking MAVLink 2 does not send MAVLink 1 frames in
            # between: such frames under its ids are someone else's.
            counters["v1_ignored"] += 1
            return False
        return True

    def _autopilot_moved(self, mtype: str) -> bool:
        """A frame with the autopilot's ids came from a new address: is it the
        autopilot, moved (restarted on a new source port)? Yes for a HEARTBEAT once
        its confirmed address has sent none for ``peer_silence_s``; the HEARTBEAT,
        accepted, then moves the transport's peer (:meth:`_on_heartbeat`)."""
        last = self.last_heartbeat_monotonic_s
        if mtype != "HEARTBEAT" or last is None:
            return False
        silent_s = time.monotonic() - last
        if silent_s < self.peer_silence_s:
            return False
        assert self.target is not None  # the frame had the target's ids
        self._anomaly(
            "peer_changed",
            "autopilot %d/%d now speaks from %s (no HEARTBEAT from its old address for %.1f s)",
            *self.target,
            self._rx_from(),
            silent_s,
        )
        return True

    def _rx_from(self) -> str:
        addr = self.transport.rx_address
        return f"{addr[0]}:{addr[1]}" if addr else "an unknown address"

    def _anomaly(self, kind: str, fmt: str, *args: object) -> None:
        """Tell ``on_anomaly`` (or, without one, the log) of ``kind``, at most once
        per ``_ANOMALY_PERIOD_S`` per kind: a flood costs a clock read per frame."""
        now = time.monotonic()
        if now < self._anomaly_next_s.get(kind, -math.inf):
            return
        self._anomaly_next_s[kind] = now + _ANOMALY_PERIOD_S
        detail = fmt % args
        callback = self.on_anomaly
        if callback is None:
            logger.warning("%s: %s", kind, detail)
            return
        try:
            callback(kind, detail)
        except Exception:
            self._callback_failed("on_anomaly")

    def _signature_ok(self, checker: SignatureChecker, msg: Any) -> bool:
        signing = self.mav.signing
        verdict, timestamp = checker.check(msg._msgbuf, signing.timestamp)
        if verdict == SignatureChecker.OK:
            if timestamp > signing.timestamp:  # spec: follow the newest valid timestamp
                signing.timestamp = timestamp
            return True
        if verdict == SignatureChecker.UNSIGNED:
            assert self.signing is not None
            if self.signing.allow_unsigned:
                self.counters["unsigned_accepted"] += 1
                return True
            self.counters["unsigned_rejected"] += 1
        elif verdict == SignatureChecker.BAD_SIGNATURE:
            self.counters["bad_signature_rejected"] += 1
        else:
            self.counters["replay_rejected"] += 1
        return False

    def _learn_target(self, hb: Any) -> bool:
        """Take ``hb``'s sender as the autopilot if it looks like one and fits the pins."""
        if hb.autopilot == mavlink2.MAV_AUTOPILOT_INVALID or hb.type in _NOT_AUTOPILOT_TYPES:
            return False
        sysid, compid = hb.get_srcSystem(), hb.get_srcComponent()
        if self._want_system is not None and sysid != self._want_system:
            return False
        if self._want_component is not None and compid != self._want_component:
            return False
        self.target = (sysid, compid)
        logger.info(
            "autopilot is %d/%d (autopilot=%d type=%d)", sysid, compid, hb.autopilot, hb.type
        )
        return True

    def _on_heartbeat(self, hb: Any) -> None:
        # The autopilot's own heartbeat (accepted: right sender, right signature):
        # replies go where it came from.
        self.transport.confirm_peer()
        if hb._msgbuf[0] == _MAGIC_V2:
            self._target_v2 = True
        self.last_heartbeat = hb
        self.last_heartbeat_monotonic_s = time.monotonic()
        waiters = self._heartbeat_waiters
        if waiters:
            self._heartbeat_waiters = []
            for fut in waiters:
                if not fut.done():
                    fut.set_result(hb)

    def _on_command_ack(self, ack: Any) -> None:
        fut = self._ack_waiters.get(ack.command)
        if fut is None or fut.done():
            return
        # Extension fields (0 when the autopilot leaves them out): skip acks for others.
        if ack.target_system not in (0, self.source_system):
            return
        if ack.target_component not in (0, self.source_component):
            return
        fut.set_result(ack)

    # ------------------------------------------------------------------ requests

    def _require_target(self) -> tuple[int, int]:
        if self.target is None:
            raise LinkError(
                f"{self.transport.description}: autopilot not known yet (no HEARTBEAT from one)"
            )
        return self.target

    async def wait_heartbeat(self, timeout_s: float, *, new: bool = False) -> Any:
        """The autopilot's HEARTBEAT (the target is learned from it).

        Parameters
        ----------
        timeout_s
            How long to wait, s.
        new
            Wait for the next one even if one was already received.

        Raises
        ------
        LinkError
            If none arrives within ``timeout_s``.
        """
        if not new and self.last_heartbeat is not None:
            return self.last_heartbeat
        if self._closed or not self._started:
            raise LinkError(f"{self.transport.description}: link not started")
        fut: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._heartbeat_waiters.append(fut)
        try:
            return await asyncio.wait_for(fut, timeout_s)
        except asyncio.TimeoutError:
            who = f"autopilot {self.target}" if self.target else "any autopilot"
            raise LinkError(
                f"{self.transport.description}: no HEARTBEAT from {who} within {timeout_s:g} s"
            ) from None
        finally:
            if fut in self._heartbeat_waiters:
                self._heartbeat_waiters.remove(fut)

    async def command_long(
        self,
        command: int,
        *params: float,
        timeout_s: float = 0.5,
        retries: int = 3,
        in_progress_timeout_s: float = 5.0,
    ) -> int:
        """Send COMMAND_LONG to the autopilot and return the MAV_RESULT of its COMMAND_ACK.

        Sends up to ``1 + retries`` times, ``timeout_s`` apart, with the
        ``confirmation`` field counting the retransmissions (0, 1, ...). After an
        ack ``MAV_RESULT_IN_PROGRESS`` the command is not resent (that would restart
        it): the final ack is awaited for up to ``in_progress_timeout_s``, renewed by
        each further progress ack. Concurrent calls with the same command id are
        serialised (acks carry only the id).

        Raises
        ------
        LinkError
            If the target is unknown, or no ack came after all attempts.
        ValueError
            For more than 7 parameters.
        """
        if len(params) > 7:
            raise ValueError(f"COMMAND_LONG takes at most 7 parameters, got {len(params)}")
        if retries < 0 or not timeout_s > 0:
            raise ValueError("retries must be >= 0 and timeout_s > 0")
        sysid, compid = self._require_target()
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        loop = asyncio.get_running_loop()
        lock = self._command_locks.setdefault(command, asyncio.Lock())
        async with lock:
            attempt = 0
            in_progress = 0
            fut: asyncio.Future[Any] = loop.create_future()
            self._ack_waiters[command] = fut
            try:
                self.send(self.mav.command_long_encode(sysid, compid, command, 0, *p))
                while True:
                    wait_s = in_progress_timeout_s if in_progress else timeout_s
                    try:
                        ack = await asyncio.wait_for(asyncio.shield(fut), wait_s)
                    except asyncio.TimeoutError:
                        if self._closed:
                            raise LinkError(f"{self.transport.description}: link closed") from None
                        if in_progress:
                            raise LinkError(
                                f"{self.transport.description}: command {command} in progress "
                                f"but no final COMMAND_ACK within {in_progress_timeout_s:g} s"
                            ) from None
                        attempt += 1
                        if attempt > retries:
                            raise LinkError(
                                f"{self.transport.description}: no COMMAND_ACK for command "
                                f"{command} from {sysid}/{compid} after {attempt} attempts "
                                f"({timeout_s:g} s each)"
                            ) from None
                        logger.debug("command %d: no ack, retry %d", command, attempt)
                        self.send(
                            self.mav.command_long_encode(
                                sysid, compid, command, min(attempt, 255), *p
                            )
                        )
                        continue
                    result = int(ack.result)
                    if result == mavlink2.MAV_RESULT_IN_PROGRESS and in_progress < _MAX_IN_PROGRESS:
                        in_progress += 1
                        fut = loop.create_future()
                        self._ack_waiters[command] = fut
                        continue
                    return result
            finally:
                if self._ack_waiters.get(command) is fut:
                    del self._ack_waiters[command]

    async def param_read(self, name: str, *, timeout_s: float = 0.5, retries: int = 3) -> float:
        """Read one parameter (PARAM_REQUEST_READ by name, PARAM_VALUE back).

        Raises
        ------
        LinkError
            If the target is unknown or no PARAM_VALUE for ``name`` came after all attempts.
        """
        return await self._param(name, None, timeout_s=timeout_s, retries=retries)

    async def param_set(
        self, name: str, value: float, *, timeout_s: float = 0.5, retries: int = 3
    ) -> float:
        """Set one parameter (PARAM_SET) and return the value the autopilot reports back."""
        return await self._param(name, float(value), timeout_s=timeout_s, retries=retries)

    async def _param(
        self, name: str, value: float | None, *, timeout_s: float, retries: int
    ) -> float:
        if not 0 < len(name) <= 16:
            raise ValueError(f"parameter names are 1..16 characters, got {name!r}")
        sysid, compid = self._require_target()
        loop = asyncio.get_running_loop()
        for attempt in range(retries + 1):
            fut: asyncio.Future[Any] = loop.create_future()
            self._param_waiters.setdefault(name, []).append(fut)
            try:
                if value is None:
                    self.send(self.mav.param_request_read_encode(sysid, compid, name.encode(), -1))
                else:
                    self.send(
                        self.mav.param_set_encode(
                            sysid, compid, name.encode(), value, mavlink2.MAV_PARAM_TYPE_REAL32
                        )
                    )
                msg = await asyncio.wait_for(fut, timeout_s)
                return float(msg.param_value)
            except asyncio.TimeoutError:
                logger.debug("parameter %s: no PARAM_VALUE, attempt %d", name, attempt + 1)
            finally:
                waiters = self._param_waiters.get(name, [])
                if fut in waiters:
                    waiters.remove(fut)
        raise LinkError(
            f"{self.transport.description}: no PARAM_VALUE for {name} from {sysid}/{compid} "
            f"after {retries + 1} attempts ({timeout_s:g} s each)"
        )

    def _on_param_value(self, msg: Any) -> None:
        name = msg.param_id
        if isinstance(name, bytes):
            name = name.decode(errors="replace")
        name = name.rstrip("\x00")
        for fut in self._param_waiters.pop(name, []):
            if not fut.done():
                fut.set_result(msg)

    async def request_message_interval(
        self, message_id: int, interval_us: float, *, timeout_s: float = 0.5, retries: int = 3
    ) -> int:
        """``MAV_CMD_SET_MESSAGE_INTERVAL``: stream ``message_id`` every ``interval_us``.

        ``interval_us`` -1 stops the stream, 0 restores the default. Returns the MAV_RESULT.
        """
        return await self.command_long(
            mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL,
            float(message_id),
            float(interval_us),
            timeout_s=timeout_s,
            retries=retries,
        )
