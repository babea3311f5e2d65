"""Judging each decoded message (is it the autopilot's?) and handing it on.

Only the autopilot's messages reach ``on_message``: the autopilot is pinned
(``target_system``/``target_component``) or learned from the first HEARTBEAT
whose ``autopilot`` is not ``MAV_AUTOPILOT_INVALID`` and whose ``type`` is not
a GCS or an onboard controller. Everything else is counted and dropped. On
``udpin`` the autopilot's address is confirmed by its HEARTBEATs; frames with
its ids from any other address are ignored (a HEARTBEAT from a new address
is taken once the old one has been silent for ``peer_silence_s``) and
reported through ``on_anomaly``.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import common as mavlink2

from companion.link.frames import MAGIC_V1, MAGIC_V2
from companion.link.signing import SignatureChecker, SigningConfig
from companion.link.transport import Transport

__all__ = ["Acceptor", "FastHandler", "OnAnomaly", "OnMessage", "OnRaw"]

logger = logging.getLogger("companion.link.mavlink")

OnMessage = Callable[[Any], None]
FastHandler = Callable[[tuple[Any, ...]], None]
OnRaw = Callable[[float, bytes, bool], None]
OnAnomaly = Callable[[str, str], None]

_NOT_AUTOPILOT_TYPES = frozenset({mavlink2.MAV_TYPE_GCS, mavlink2.MAV_TYPE_ONBOARD_CONTROLLER})
_Unknown = mavlink2.MAVLink_unknown
_ANOMALY_PERIOD_S = 1.0
"""``on_anomaly`` is called at most once per this period for each kind."""


class Acceptor:
    """The accepting side of :class:`~companion.link.mavlink.MavlinkLink` (a base of it)."""

    transport: Transport
    target: tuple[int, int] | None
    counters: dict[str, int]
    signing: SigningConfig | None
    mav: Any
    on_message: OnMessage | None
    on_anomaly: OnAnomaly | None
    peer_silence_s: float
    last_heartbeat: Any | None
    last_heartbeat_monotonic_s: float | None
    _want_system: int | None
    _want_component: int | None
    _target_v2: bool
    _checker: SignatureChecker | None
    _fast: dict[int, tuple[Callable[[Any], tuple[Any, ...]], FastHandler]]
    _anomaly_next_s: dict[str, float]
    _heartbeat_waiters: list[asyncio.Future[Any]]

    if TYPE_CHECKING:  # defined in Requester

        def _on_command_ack(self, ack: Any) -> None: ...
        def _on_param_value(self, msg: Any) -> None: ...

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
        if self._target_v2 and msg._msgbuf[0] == MAGIC_V1:
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
        if hb._msgbuf[0] == MAGIC_V2:
            self._target_v2 = True
        self.last_heartbeat = hb
        self.last_heartbeat_monotonic_s = time.monotonic()
        waiters = self._heartbeat_waiters
        if waiters:
            self._heartbeat_waiters = []
            for fut in waiters:
                if not fut.done():
                    fut.set_result(hb)
