"""The companion's MAVLink 2 link to one autopilot, over any :class:`Transport`.

::

    link = MavlinkLink(open_transport("udpin:0.0.0.0:14540"), on_message=handle)
    async with link:                                  # start(): open + our HEARTBEAT task
        hb = await link.wait_heartbeat(5.0)           # learns link.target
        await link.request_message_interval(mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU, 4000)
        link.send(link.mav.set_actuator_control_target_encode(...))

:class:`MavlinkLink` here holds the set-up and the lifecycle, and
owns four parts it calls: a :class:`~companion.link.receive.Receiver` (the
frames in the bytes, the fast road of :meth:`MavlinkLink.add_fast_handler`), an
:class:`~companion.link.accept.Acceptor` (which frames are the autopilot's, and
who the autopilot is), a :class:`~companion.link.requests.Requester` (the
requests and the waits for their replies) and a
:class:`~companion.link.send.Sender` (the per-sample commands, our HEARTBEAT,
SETUP_SIGNING; every frame sent goes through a
:class:`~companion.link.send.FrameSink`). The wire format is in
:mod:`companion.link.frames`.

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
import logging
import math
from collections.abc import Sequence
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from companion.errors import LinkError
from companion.link.accept import Acceptor, FastHandler, OnAnomaly, OnMessage, OnRaw
from companion.link.receive import Receiver
from companion.link.requests import Requester
from companion.link.send import FrameSink, Sender
from companion.link.signing import SigningConfig
from companion.link.transport import Transport

__all__ = ["MavlinkLink", "mavlink2"]

logger = logging.getLogger(__name__)


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
        # Encoder: what callers use (link.mav.xxx_encode / xxx_send); signs when configured.
        self._sink = FrameSink(transport, self.counters, on_raw)  # the receiver has its own on_raw
        self.mav = mavlink2.MAVLink(
            self._sink, srcSystem=source_system, srcComponent=source_component
        )
        self._acceptor = Acceptor(
            transport,
            self.counters,
            target_system=target_system,
            target_component=target_component,
            signing=signing,
            signing_state=self.mav.signing,
            peer_silence_s=peer_silence_s,
            on_anomaly=on_anomaly,
        )
        self._requester = Requester(
            transport,
            self._acceptor,
            self.mav,
            source_system=source_system,
            source_component=source_component,
        )
        self._sender = Sender(self._sink, self.mav, self._acceptor, signing=signing)
        # The receiver finds the frames; pymavlink only decodes them, with a parser
        # of its own, separate and keyless, so it does not judge signatures (the
        # acceptor does).
        self._receiver = Receiver(
            transport,
            self.counters,
            mavlink2.MAVLink(None, srcSystem=source_system, srcComponent=source_component),
            self._acceptor,
            self._requester,
            short_road=signing is None,
            on_message=on_message,
            on_raw=on_raw,
        )
        self._started = False
        self._closed = False

    def add_fast_handler(self, msg_id: int, fields: Sequence[str], handler: FastHandler) -> None:
        """Hand the autopilot's ``msg_id`` messages to ``handler`` instead of ``on_message``.

        ``handler`` receives a tuple of the values of ``fields`` (scalar
        fields, in the message's wire order, e.g. ``("time_usec", "xgyro",
        "ygyro", "zgyro")`` of HIGHRES_IMU), exactly as pymavlink decodes
        them. Whole unsigned frames are decoded straight from the chunk (see
        :mod:`companion.link.receive`); the rest through pymavlink. Checks, counters,
        ``on_raw`` and the handling of exceptions are those of ``on_message``.

        Raises
        ------
        ValueError
            For an unknown message id or field, a non-scalar field, or fields
            out of wire order.
        """
        self._receiver.add_fast_handler(msg_id, fields, handler)

    # ------------------------------------------------------- what the parts keep

    @property
    def target(self) -> tuple[int, int] | None:
        """The autopilot's ``(system, component)``: pinned, learned from its first
        HEARTBEAT, or ``None`` yet. Set, it takes that sender for the autopilot."""
        return self._acceptor.target

    @target.setter
    def target(self, target: tuple[int, int] | None) -> None:
        self._acceptor.target = target

    @property
    def last_heartbeat(self) -> Any | None:
        """The autopilot's last HEARTBEAT, ``None`` before the first."""
        return self._acceptor.last_heartbeat

    @property
    def last_heartbeat_monotonic_s(self) -> float | None:
        """``time.monotonic()`` when :attr:`last_heartbeat` arrived."""
        return self._acceptor.last_heartbeat_monotonic_s

    @property
    def rx_perf_s(self) -> float:
        """``time.perf_counter()`` when the chunk being handled arrived (read it in a handler)."""
        return self._receiver.rx_perf_s

    @property
    def on_message(self) -> OnMessage | None:
        """See the class; may be replaced at any time."""
        return self._receiver.on_message

    @on_message.setter
    def on_message(self, on_message: OnMessage | None) -> None:
        self._receiver.on_message = on_message

    @property
    def on_raw(self) -> OnRaw | None:
        """See the class; may be replaced at any time (for both directions)."""
        return self._sink.on_raw

    @on_raw.setter
    def on_raw(self, on_raw: OnRaw | None) -> None:
        self._sink.on_raw = on_raw
        self._receiver.on_raw = on_raw

    @property
    def on_anomaly(self) -> OnAnomaly | None:
        """See the class; may be replaced at any time."""
        return self._acceptor.on_anomaly

    @on_anomaly.setter
    def on_anomaly(self, on_anomaly: OnAnomaly | None) -> None:
        self._acceptor.on_anomaly = on_anomaly

    @property
    def peer_silence_s(self) -> float:
        """See the class; may be changed at any time."""
        return self._acceptor.peer_silence_s

    @peer_silence_s.setter
    def peer_silence_s(self, peer_silence_s: float) -> None:
        self._acceptor.peer_silence_s = peer_silence_s

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
        self._sender.start_signing()
        await self.transport.open(self._receiver.on_bytes)
        self._started = True
        self._closed = False
        self._requester.opened()
        self._sender.start_heartbeat(self.heartbeat_hz)
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
        return self._sender.heartbeat_task

    async def close(self) -> None:
        """Stop the heartbeat, fail pending waits with :class:`LinkError`, close the transport."""
        if self._closed:
            return
        self._closed = True
        self._requester.closing()
        await self._sender.stop_heartbeat()
        self._requester.fail_waits(LinkError(f"{self.transport.description}: link closed"))
        await self.transport.close()

    async def __aenter__(self) -> MavlinkLink:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    # ------------------------------------------------------------------ requests

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
        return await self._requester.wait_heartbeat(timeout_s, new=new)

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
        return await self._requester.command_long(
            command,
            *params,
            timeout_s=timeout_s,
            retries=retries,
            in_progress_timeout_s=in_progress_timeout_s,
        )

    async def param_read(self, name: str, *, timeout_s: float = 0.5, retries: int = 3) -> float:
        """Read one parameter (PARAM_REQUEST_READ by name, PARAM_VALUE back).

        Raises
        ------
        LinkError
            If the target is unknown or no PARAM_VALUE for ``name`` came after all attempts.
        """
        return await self._requester.param_read(name, timeout_s=timeout_s, retries=retries)

    async def param_set(
        self, name: str, value: float, *, timeout_s: float = 0.5, retries: int = 3
    ) -> float:
        """Set one parameter (PARAM_SET) and return the value the autopilot reports back."""
        return await self._requester.param_set(name, value, timeout_s=timeout_s, retries=retries)

    async def request_message_interval(
        self, message_id: int, interval_us: float, *, timeout_s: float = 0.5, retries: int = 3
    ) -> int:
        """``MAV_CMD_SET_MESSAGE_INTERVAL``: stream ``message_id`` every ``interval_us``.

        ``interval_us`` -1 stops the stream, 0 restores the default. Returns the MAV_RESULT.
        """
        return await self._requester.request_message_interval(
            message_id, interval_us, timeout_s=timeout_s, retries=retries
        )

    # ------------------------------------------------------------------- sending

    def send(self, msg: Any) -> None:
        """Pack ``msg`` (signed when signing is configured) and write it; never blocks."""
        self.mav.send(msg)

    def send_actuator_controls(
        self, time_usec: int, controls: Sequence[float], group: int = 0
    ) -> None:
        """SET_ACTUATOR_CONTROL_TARGET to the autopilot: the per-sample command
        (packed as :meth:`companion.link.send.Sender.send_actuator_controls` says)."""
        self._sender.send_actuator_controls(time_usec, controls, group)

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
        self._sender.send_body_rates(time_boot_ms, rates_frd_rad_s, thrust, type_mask)

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
        self._sender.send_setup_signing(key, initial_timestamp)
