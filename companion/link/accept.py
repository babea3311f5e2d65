"""Judging each decoded message: is it the autopilot's? Who the autopilot is.

Only the autopilot's messages reach ``on_message``: the autopilot is pinned
(``target_system``/``target_component``) or learned from the first HEARTBEAT
whose ``autopilot`` is not ``MAV_AUTOPILOT_INVALID`` and whose ``type`` is not
a GCS or an onboard controller. Everything else is counted and dropped. On
``udpin`` the autopilot's address is confirmed by its HEARTBEATs; frames with
its ids from any other address are ignored (a HEARTBEAT from a new address
is taken once the old one has been silent for ``peer_silence_s``) and
reported through ``on_anomaly``.

:class:`Acceptor` keeps the answer (the target, its last HEARTBEAT, its
address confirmed or not); the receiver (:mod:`companion.link.receive`) asks it
about each decoded frame and hands on what it accepts.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from companion.errors import LinkError
from companion.link.frames import MAGIC_V1, MAGIC_V2
from companion.link.signing import SignatureChecker, SigningConfig
from companion.link.transport import Transport

__all__ = ["Acceptor", "FastHandler", "OnAnomaly", "OnMessage", "OnRaw", "callback_failed"]

logger = logging.getLogger("companion.link.mavlink")

OnMessage = Callable[[Any], None]
FastHandler = Callable[[tuple[Any, ...]], None]
OnRaw = Callable[[float, bytes, bool], None]
OnAnomaly = Callable[[str, str], None]

_NOT_AUTOPILOT_TYPES = frozenset({mavlink2.MAV_TYPE_GCS, mavlink2.MAV_TYPE_ONBOARD_CONTROLLER})
_Unknown = mavlink2.MAVLink_unknown
_ANOMALY_PERIOD_S = 1.0
"""``on_anomaly`` is called at most once per this period for each kind."""


def callback_failed(counters: dict[str, int], what: str) -> None:
    """Count a callback that raised (``callback_errors``); log the first one."""
    counters["callback_errors"] += 1
    if counters["callback_errors"] == 1:
        logger.exception("%s raised (logged once, counted after)", what)


class Acceptor:
    """Judges each decoded frame (is it the autopilot's?) and keeps who the autopilot is.

    Parameters
    ----------
    transport
        The frames' transport: ``rx_from_peer`` / ``rx_address`` say where the
        frame being judged came from, ``confirm_peer`` is told of the
        autopilot's HEARTBEATs.
    counters
        The link's counters; the rejections are counted in them.
    target_system, target_component
        The pins (checked by the link); ``None`` learns from the first HEARTBEAT.
    signing
        Check the signature of each frame (``None``: no checks).
    signing_state
        pymavlink's signing state of the link's encoder (``mav.signing``): its
        ``timestamp`` is the replay floor, and follows the newest valid one.
    peer_silence_s, on_anomaly
        As :class:`~companion.link.mavlink.MavlinkLink`'s.
    """

    def __init__(
        self,
        transport: Transport,
        counters: dict[str, int],
        *,
        target_system: int | None,
        target_component: int | None,
        signing: SigningConfig | None,
        signing_state: Any,
        peer_silence_s: float,
        on_anomaly: OnAnomaly | None,
    ) -> None:
        self._transport = transport
        self._counters = counters
        self._want_system = target_system
        self._want_component = target_component
        self.target: tuple[int, int] | None = (
            (target_system, target_component)
            if target_system is not None and target_component is not None
            else None
        )
        """The autopilot's ``(system, component)``: pinned, learned, or ``None`` yet."""
        self.last_heartbeat: Any | None = None
        self.last_heartbeat_monotonic_s: float | None = None
        self.peer_silence_s = peer_silence_s
        self.on_anomaly = on_anomaly
        self._target_v2 = False
        """The autopilot's heartbeat came as MAVLink 2: it does not fall back to 1."""
        self._checker = SignatureChecker(signing.key) if signing is not None else None
        self._allow_unsigned = signing is not None and signing.allow_unsigned
        self._signing_state = signing_state
        self._anomaly_next_s: dict[str, float] = {}

    def require_target(self) -> tuple[int, int]:
        """The target, for a message to it.

        Raises
        ------
        LinkError
            If it is not known yet.
        """
        if self.target is None:
            raise LinkError(
                f"{self._transport.description}: autopilot not known yet (no HEARTBEAT from one)"
            )
        return self.target

    def accept(self, msg: Any, mtype: str) -> bool:
        """Signature, dialect, sender and sender-address checks; counts what it rejects."""
        counters = self._counters
        checker = self._checker
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
        if not self._transport.rx_from_peer and not self._autopilot_moved(mtype):
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

    def on_heartbeat(self, hb: Any) -> None:
        """The autopilot's own HEARTBEAT, accepted (right sender, right signature):
        replies go where it came from."""
        self._transport.confirm_peer()
        if hb._msgbuf[0] == MAGIC_V2:
            self._target_v2 = True
        self.last_heartbeat = hb
        self.last_heartbeat_monotonic_s = time.monotonic()

    def _autopilot_moved(self, mtype: str) -> bool:
        """A frame with the autopilot's ids came from a new address: is it the
        autopilot, moved (restarted on a new source port)? Yes for a HEARTBEAT once
        its confirmed address has sent none for ``peer_silence_s``; the HEARTBEAT,
        accepted, then moves the transport's peer (:meth:`on_heartbeat`)."""
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
        addr = self._transport.rx_address
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
            callback_failed(self._counters, "on_anomaly")

    def _signature_ok(self, checker: SignatureChecker, msg: Any) -> bool:
        signing = self._signing_state
        verdict, timestamp = checker.check(msg._msgbuf, signing.timestamp)
        if verdict == SignatureChecker.OK:
            if timestamp > signing.timestamp:  # spec: follow the newest valid timestamp
                signing.timestamp = timestamp
            return True
        if verdict == SignatureChecker.UNSIGNED:
            if self._allow_unsigned:
                self._counters["unsigned_accepted"] += 1
                return True
            self._counters["unsigned_rejected"] += 1
        elif verdict == SignatureChecker.BAD_SIGNATURE:
            self._counters["bad_signature_rejected"] += 1
        else:
            self._counters["replay_rejected"] += 1
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
