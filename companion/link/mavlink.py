"""The companion's MAVLink 2 link to one autopilot, over any :class:`Transport`.

::

    link = MavlinkLink(open_transport("udpin:0.0.0.0:14540"), on_message=handle)
    async with link:                                  # start(): open + our HEARTBEAT task
        hb = await link.wait_heartbeat(5.0)           # learns link.target
        await link.request_message_interval(mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU, 4000)
        link.send(link.mav.set_actuator_control_target_encode(...))

Receive path (the IMU-driven hot path): each chunk from the transport goes
through one ``parse_buffer``; each parsed message is checked (signature when
signing is configured, then source = the autopilot) and handed to
``on_message`` synchronously, in the event-loop thread. Nothing is queued.

Messages registered with :meth:`MavlinkLink.add_fast_handler` (the IMU
sample) take a shorter road when they can: a chunk that starts with whole,
unsigned MAVLink 2 frames of registered ids from the autopilot, with a good
CRC, is decoded with one precompiled ``struct`` per frame, without
pymavlink's generic parser and message objects (1 us instead of 8 us for a
HIGHRES_IMU datagram, measured in a tight loop). Anything else (a frame split
across chunks, a bad CRC, another sender, signing, MAVLink 1) goes through
pymavlink as before, and a registered message decoded there reaches the same
handler with the same values. Counters and ``on_raw`` see both roads alike;
pymavlink's own parser statistics count only the frames it parsed.

Only the autopilot's messages reach ``on_message``: the autopilot is pinned
(``target_system``/``target_component``) or learned from the first HEARTBEAT
whose ``autopilot`` is not ``MAV_AUTOPILOT_INVALID`` and whose ``type`` is not
a GCS or an onboard controller. Everything else is counted and dropped.

Counters (``link.counters``): ``received`` (frames decoded, before any check),
``accepted`` (passed to ``on_message``), ``foreign_ignored`` (not from the
autopilot, including anything before it is known except its first HEARTBEAT),
``bad_data`` (garbage, CRC errors), ``unknown_ignored`` (message ids outside
the common dialect), ``unsigned_rejected``, ``bad_signature_rejected``,
``replay_rejected``, ``unsigned_accepted`` (with ``allow_unsigned``), ``sent``,
``callback_errors`` (``on_message`` raised: logged, the link keeps going).
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
_NUMERIC_FORMATS = frozenset("bBhHiIqQfd")

OnMessage = Callable[[Any], None]
FastHandler = Callable[[tuple[Any, ...]], None]
OnRaw = Callable[[float, bytes, bool], None]

_NOT_AUTOPILOT_TYPES = frozenset({mavlink2.MAV_TYPE_GCS, mavlink2.MAV_TYPE_ONBOARD_CONTROLLER})
_Unknown = mavlink2.MAVLink_unknown
_MAX_IN_PROGRESS = 100
"""At most this many MAV_RESULT_IN_PROGRESS acks extend one command's wait."""


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
        self.transport = transport
        self.source_system = source_system
        self.source_component = source_component
        self.signing = signing
        self.heartbeat_hz = heartbeat_hz
        self.on_message = on_message
        self.on_raw = on_raw
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
            ),
            0,
        )
        # Encoder: what callers use (link.mav.xxx_encode / xxx_send); signs when configured.
        self.mav = mavlink2.MAVLink(
            _Sink(self), srcSystem=source_system, srcComponent=source_component
        )
        # Parser: separate and keyless, so pymavlink does not judge signatures (we do).
        self._parser = mavlink2.MAVLink(
            None, srcSystem=source_system, srcComponent=source_component
        )
        self._parser.robust_parsing = True
        self._parser_idle = True  # no partial frame waiting in the parser
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
        wire = self._fast_wire
        if wire and self._parser_idle:
            # The short road: whole unsigned MAVLink 2 frames of registered ids from
            # the autopilot, CRC checked; the first frame that is anything else
            # sends the rest of the chunk to pymavlink.
            n = len(chunk)
            i = 0
            target = self.target
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
                    self._callback_failed()
                if on_raw is not None:
                    on_raw(t_rx, chunk if end == n and i == 0 else chunk[i:end], False)
                i = end
            if i == n:
                return
            if i:
                chunk = chunk[i:]
        try:
            msgs = self._parser.parse_buffer(chunk)
        except mavlink2.MAVError:  # only without robust_parsing; kept as a guard
            counters["bad_data"] += 1
            return
        finally:
            self._parser_idle = self._parser.buf_len() == 0
        if msgs is None:
            return
        checker = self._checker
        fast = self._fast
        for msg in msgs:
            mtype = msg._type
            if mtype == "BAD_DATA":
                counters["bad_data"] += 1
                continue
            counters["received"] += 1
            if self._accept(msg, mtype, checker, counters):
                counters["accepted"] += 1
                if mtype == "HEARTBEAT":
                    self._on_heartbeat(msg)
                elif mtype == "COMMAND_ACK":
                    self._on_command_ack(msg)
                elif mtype == "PARAM_VALUE":
                    self._on_param_value(msg)
                registered = fast.get(msg.get_msgId()) if fast else None
                try:
                    if registered is not None:
                        getter, handler = registered
                        handler(getter(msg))
                    elif self.on_message is not None:
                        self.on_message(msg)
                except Exception:
                    self._callback_failed()
            if on_raw is not None:
                on_raw(t_rx, bytes(msg._msgbuf), False)

    def _callback_failed(self) -> None:
        counters = self.counters
        counters["callback_errors"] += 1
        if counters["callback_errors"] == 1:
            logger.exception("on_message raised (logged once, counted after)")

    def _accept(self, msg: Any, mtype: str, checker: Any, counters: dict[str, int]) -> bool:
        """Signature, dialect and sender checks; counts what it rejects."""
        if checker is not None and not self._signature_ok(checker, msg):
            return False
        if msg.__class__ is _Unknown:  # an id outside the dialect (pymavlink skips its CRC)
            counters["unknown_ignored"] += 1
            return False
        hdr = msg._header
        if (hdr.srcSystem, hdr.srcComponent) != self.target and not (
            mtype == "HEARTBEAT" and self.target is None and self._learn_target(msg)
        ):
            counters["foreign_ignored"] += 1
            return False
        return True

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
