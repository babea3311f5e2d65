"""What the link sends: every frame through one sink, the per-sample commands, our HEARTBEAT.

:class:`FrameSink` is pymavlink's output "file": every frame the link sends
goes through it to the transport, counted in ``sent`` and passed to
``on_raw``. :class:`Sender` makes the sends that are the link's own: the
per-sample commands, each packed with one precompiled ``struct`` (with signing,
through pymavlink, which signs), SETUP_SIGNING (never passed to ``on_raw``) and
our HEARTBEAT; with signing, it turns the encoder's signing on when the link
starts. The requests and their replies are
:class:`~companion.link.requests.Requester`'s.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Sequence
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from companion.link import frames
from companion.link.accept import Acceptor, OnRaw
from companion.link.frames import (
    EXTRA_ACTUATOR,
    EXTRA_ATTITUDE_TARGET,
    ID_ACTUATOR,
    ID_ATTITUDE_TARGET,
    crc16,
)
from companion.link.signing import SigningConfig, signing_timestamp_now
from companion.link.transport import Transport

__all__ = ["FrameSink", "Sender"]

logger = logging.getLogger("companion.link.mavlink")

# Assigned, not imported by name: CPython (3.11) compiles ``NAME.pack(...)`` for an
# imported NAME as an attribute load and a call, a bound method made each time.
_HEADER = frames.HEADER
_U16 = frames.U16
_ACTUATOR = frames.ACTUATOR
_ATTITUDE_TARGET = frames.ATTITUDE_TARGET


class FrameSink:
    """pymavlink's output "file": every frame the link sends goes through it.

    Parameters
    ----------
    transport
        Where the frames go.
    counters
        The link's counters: each frame is counted in ``sent``.
    on_raw
        As :class:`~companion.link.mavlink.MavlinkLink`'s, for what we send; may
        be replaced at any time.
    """

    __slots__ = ("_counters", "_transport", "on_raw")

    def __init__(
        self, transport: Transport, counters: dict[str, int], on_raw: OnRaw | None
    ) -> None:
        self._transport = transport
        self._counters = counters
        self.on_raw = on_raw

    def write(self, buf: bytes) -> None:
        self._transport.write(buf)
        self._counters["sent"] += 1
        on_raw = self.on_raw
        if on_raw is not None:
            on_raw(time.time(), bytes(buf), True)

    def write_unlogged(self, buf: bytes) -> None:
        """Write a frame that carries a key (SETUP_SIGNING): counted, never passed to ``on_raw``."""
        self._transport.write(buf)
        self._counters["sent"] += 1


class Sender:
    """The link's own sends: the per-sample commands, SETUP_SIGNING, our HEARTBEAT.

    Parameters
    ----------
    sink
        Where the frames packed here go.
    mav
        The link's pymavlink encoder (its file is ``sink``): its sequence
        number and ids go in every frame; with signing, the frames are encoded
        and signed by it.
    autopilot
        Who the frames go to (``require_target``).
    signing
        The link's signing (``None``: frames go unsigned, packed here).
    """

    def __init__(
        self, sink: FrameSink, mav: Any, autopilot: Acceptor, *, signing: SigningConfig | None
    ) -> None:
        self._sink = sink
        self._mav = mav
        self._autopilot = autopilot
        self._signing = signing
        self.heartbeat_task: asyncio.Task[None] | None = None
        """Our HEARTBEAT task while the link runs."""

    def start_signing(self) -> None:
        """With signing, sign every frame the encoder packs from now on."""
        if self._signing is not None:
            s = self._mav.signing
            s.secret_key = self._signing.key
            s.link_id = self._signing.link_id
            s.sign_outgoing = True
            s.timestamp = max(s.timestamp, signing_timestamp_now())

    def send_actuator_controls(
        self, time_usec: int, controls: Sequence[float], group: int = 0
    ) -> None:
        """SET_ACTUATOR_CONTROL_TARGET to the autopilot: the per-sample command.

        Packs the frame with one precompiled ``struct`` instead of pymavlink's
        message object and generic packer (bytes identical, tested); with
        signing it takes pymavlink's path, which signs.
        """
        sysid, compid = self._autopilot.require_target()
        if self._signing is not None:
            self._mav.send(
                self._mav.set_actuator_control_target_encode(
                    time_usec, group, sysid, compid, list(controls)
                )
            )
            return
        payload = _ACTUATOR.pack(time_usec, *controls, group, sysid, compid)
        self._write_fast(ID_ACTUATOR, EXTRA_ACTUATOR, payload)

    def send_body_rates(
        self, time_boot_ms: int, rates_frd_rad_s: Sequence[float], thrust: float, type_mask: int
    ) -> None:
        """SET_ATTITUDE_TARGET with body rates and thrust (``type_mask`` 128:
        ignore the attitude quaternion). Same fast path as
        :meth:`send_actuator_controls`."""
        sysid, compid = self._autopilot.require_target()
        r0, r1, r2 = rates_frd_rad_s
        if self._signing is not None:
            self._mav.send(
                self._mav.set_attitude_target_encode(
                    time_boot_ms, sysid, compid, type_mask, [1.0, 0.0, 0.0, 0.0], r0, r1, r2,
                    thrust,
                )
            )  # fmt: skip
            return
        payload = _ATTITUDE_TARGET.pack(
            time_boot_ms, 1.0, 0.0, 0.0, 0.0, r0, r1, r2, thrust, sysid, compid, type_mask
        )
        self._write_fast(ID_ATTITUDE_TARGET, EXTRA_ATTITUDE_TARGET, payload)

    def _write_fast(self, msg_id: int, crc_extra: bytes, payload: bytes) -> None:
        # MAVLink 2 drops trailing zero bytes of a payload (at least one byte stays).
        body = payload.rstrip(b"\x00") or payload[:1]
        mav = self._mav
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
        frame += _U16.pack(crc16(crc_extra, crc16(frame[1:])))
        self._sink.write(frame)

    def send_setup_signing(self, key: bytes, initial_timestamp: int | None = None) -> None:
        """See :meth:`companion.link.mavlink.MavlinkLink.send_setup_signing`."""
        if len(key) != 32:
            raise ValueError("signing key must be exactly 32 bytes")
        sysid, compid = self._autopilot.require_target()
        ts = signing_timestamp_now() if initial_timestamp is None else initial_timestamp
        mav = self._mav
        msg = mav.setup_signing_encode(sysid, compid, list(key), ts)
        buf = msg.pack(mav)
        mav.seq = (mav.seq + 1) % 256
        self._sink.write_unlogged(buf)

    def start_heartbeat(self, heartbeat_hz: float) -> None:
        """Start our HEARTBEAT task (``mavlink-heartbeat``) at ``heartbeat_hz``, Hz; 0: none."""
        if heartbeat_hz > 0:
            task = asyncio.get_running_loop().create_task(
                self._heartbeat_loop(1.0 / heartbeat_hz), name="mavlink-heartbeat"
            )
            task.add_done_callback(self._heartbeat_done)
            self.heartbeat_task = task

    async def stop_heartbeat(self) -> None:
        """Cancel our HEARTBEAT task, if it runs, and wait for its end."""
        task, self.heartbeat_task = self.heartbeat_task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    async def _heartbeat_loop(self, period_s: float) -> None:
        loop = asyncio.get_running_loop()
        mav = self._mav
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
