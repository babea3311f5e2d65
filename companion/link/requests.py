"""Requests to the autopilot and their replies: HEARTBEAT, COMMAND_LONG, parameters.

:class:`Requester` keeps the waits (futures) and sends the requests through the
link's encoder; the receiver (:mod:`companion.link.receive`) hands it the
replies the acceptor (:mod:`companion.link.accept`) took as the autopilot's.
"""

from __future__ import annotations

import asyncio
import logging
import struct
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from companion.errors import LinkError
from companion.link.accept import Acceptor
from companion.link.transport import Transport

__all__ = ["Requester", "param_value"]

logger = logging.getLogger("companion.link.mavlink")

_MAX_IN_PROGRESS = 100
"""At most this many MAV_RESULT_IN_PROGRESS acks extend one command's wait."""

_MAV_AUTOPILOT_PX4 = 12
_INT_FORMATS = {
    mavlink2.MAV_PARAM_TYPE_UINT8: "<B",
    mavlink2.MAV_PARAM_TYPE_INT8: "<b",
    mavlink2.MAV_PARAM_TYPE_UINT16: "<H",
    mavlink2.MAV_PARAM_TYPE_INT16: "<h",
    mavlink2.MAV_PARAM_TYPE_UINT32: "<I",
    mavlink2.MAV_PARAM_TYPE_INT32: "<i",
}


def param_value(msg: Any, *, bytewise: bool) -> float:
    """The value a PARAM_VALUE carries.

    With ``bytewise`` (the MAVLink parameter protocol's bytewise encoding, as
    PX4 sends), an integer parameter's bytes sit in the float field and are
    read back as that integer; otherwise (C-cast, as ArduPilot sends) the float
    is the value."""
    fmt = _INT_FORMATS.get(int(msg.param_type)) if bytewise else None
    if fmt is None:
        return float(msg.param_value)
    raw = struct.pack("<f", msg.param_value)
    return float(struct.unpack_from(fmt, raw)[0])


class Requester:
    """Requests to the autopilot, and the waits for their replies.

    Parameters
    ----------
    transport
        Named in the errors (its ``description``).
    autopilot
        Who the requests go to (``require_target``) and its last HEARTBEAT.
    mav
        The link's pymavlink encoder: requests are encoded and sent with it
        (signed when the link signs).
    source_system, source_component
        Our ids: a COMMAND_ACK addressed to anyone else is not ours.
    """

    def __init__(
        self,
        transport: Transport,
        autopilot: Acceptor,
        mav: Any,
        *,
        source_system: int,
        source_component: int,
    ) -> None:
        self._transport = transport
        self._autopilot = autopilot
        self._mav = mav
        self._source_system = source_system
        self._source_component = source_component
        self._started = False
        self._closed = False
        self._heartbeat_waiters: list[asyncio.Future[Any]] = []
        self._ack_waiters: dict[int, asyncio.Future[Any]] = {}
        self._param_waiters: dict[str, list[asyncio.Future[Any]]] = {}
        self._command_locks: dict[int, asyncio.Lock] = {}

    def opened(self) -> None:
        """The link is up: waits may begin."""
        self._started = True
        self._closed = False

    def closing(self) -> None:
        """The link is closing: a command whose ack is late fails as closed."""
        self._closed = True

    def fail_waits(self, err: LinkError) -> None:
        """Fail the pending waits for a HEARTBEAT or a COMMAND_ACK with ``err``."""
        for fut in [*self._heartbeat_waiters, *self._ack_waiters.values()]:
            if not fut.done():
                fut.set_exception(err)
        self._heartbeat_waiters.clear()
        self._ack_waiters.clear()

    def on_heartbeat(self, hb: Any) -> None:
        """The autopilot's HEARTBEAT (accepted): it ends the waits for one."""
        waiters = self._heartbeat_waiters
        if waiters:
            self._heartbeat_waiters = []
            for fut in waiters:
                if not fut.done():
                    fut.set_result(hb)

    async def wait_heartbeat(self, timeout_s: float, *, new: bool = False) -> Any:
        """See :meth:`companion.link.mavlink.MavlinkLink.wait_heartbeat`."""
        last = self._autopilot.last_heartbeat
        if not new and last is not None:
            return last
        if self._closed or not self._started:
            raise LinkError(f"{self._transport.description}: link not started")
        fut: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._heartbeat_waiters.append(fut)
        try:
            return await asyncio.wait_for(fut, timeout_s)
        except asyncio.TimeoutError:
            target = self._autopilot.target
            who = f"autopilot {target}" if target else "any autopilot"
            raise LinkError(
                f"{self._transport.description}: no HEARTBEAT from {who} within {timeout_s:g} s"
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
        """See :meth:`companion.link.mavlink.MavlinkLink.command_long`."""
        if len(params) > 7:
            raise ValueError(f"COMMAND_LONG takes at most 7 parameters, got {len(params)}")
        if retries < 0 or not timeout_s > 0:
            raise ValueError("retries must be >= 0 and timeout_s > 0")
        sysid, compid = self._autopilot.require_target()
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        loop = asyncio.get_running_loop()
        lock = self._command_locks.setdefault(command, asyncio.Lock())
        async with lock:
            attempt = 0
            in_progress = 0
            fut: asyncio.Future[Any] = loop.create_future()
            self._ack_waiters[command] = fut
            try:
                self._mav.send(self._mav.command_long_encode(sysid, compid, command, 0, *p))
                while True:
                    wait_s = in_progress_timeout_s if in_progress else timeout_s
                    try:
                        ack = await asyncio.wait_for(asyncio.shield(fut), wait_s)
                    except asyncio.TimeoutError:
                        if self._closed:
                            raise LinkError(f"{self._transport.description}: link closed") from None
                        if in_progress:
                            raise LinkError(
                                f"{self._transport.description}: command {command} in progress "
                                f"but no final COMMAND_ACK within {in_progress_timeout_s:g} s"
                            ) from None
                        attempt += 1
                        if attempt > retries:
                            raise LinkError(
                                f"{self._transport.description}: no COMMAND_ACK for command "
                                f"{command} from {sysid}/{compid} after {attempt} attempts "
                                f"({timeout_s:g} s each)"
                            ) from None
                        logger.debug("command %d: no ack, retry %d", command, attempt)
                        self._mav.send(
                            self._mav.command_long_encode(
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

    def on_command_ack(self, ack: Any) -> None:
        """A COMMAND_ACK from the autopilot: it ends the wait for its command's ack."""
        fut = self._ack_waiters.get(ack.command)
        if fut is None or fut.done():
            return
        # Extension fields (0 when the autopilot leaves them out): skip acks for others.
        if ack.target_system not in (0, self._source_system):
            return
        if ack.target_component not in (0, self._source_component):
            return
        fut.set_result(ack)

    async def param_read(self, name: str, *, timeout_s: float = 0.5, retries: int = 3) -> float:
        """See :meth:`companion.link.mavlink.MavlinkLink.param_read`."""
        return await self._param(name, None, timeout_s=timeout_s, retries=retries)

    async def param_set(
        self, name: str, value: float, *, timeout_s: float = 0.5, retries: int = 3
    ) -> float:
        """See :meth:`companion.link.mavlink.MavlinkLink.param_set`."""
        return await self._param(name, float(value), timeout_s=timeout_s, retries=retries)

    async def _param(
        self, name: str, value: float | None, *, timeout_s: float, retries: int
    ) -> float:
        if not 0 < len(name) <= 16:
            raise ValueError(f"parameter names are 1..16 characters, got {name!r}")
        sysid, compid = self._autopilot.require_target()
        loop = asyncio.get_running_loop()
        for attempt in range(retries + 1):
            fut: asyncio.Future[Any] = loop.create_future()
            self._param_waiters.setdefault(name, []).append(fut)
            try:
                if value is None:
                    self._mav.send(
                        self._mav.param_request_read_encode(sysid, compid, name.encode(), -1)
                    )
                else:
                    self._mav.send(
                        self._mav.param_set_encode(
                            sysid, compid, name.encode(), value, mavlink2.MAV_PARAM_TYPE_REAL32
                        )
                    )
                msg = await asyncio.wait_for(fut, timeout_s)
                return param_value(msg, bytewise=self._params_bytewise())
            except asyncio.TimeoutError:
                logger.debug("parameter %s: no PARAM_VALUE, attempt %d", name, attempt + 1)
            finally:
                waiters = self._param_waiters.get(name, [])
                if fut in waiters:
                    waiters.remove(fut)
        raise LinkError(
            f"{self._transport.description}: no PARAM_VALUE for {name} from {sysid}/{compid} "
            f"after {retries + 1} attempts ({timeout_s:g} s each)"
        )

    def _params_bytewise(self) -> bool:
        """Whether the autopilot sends integer parameters bytewise: PX4 does (its
        int32's bits in the float field); ArduPilot casts them to float."""
        hb = self._autopilot.last_heartbeat
        return hb is not None and int(hb.autopilot) == _MAV_AUTOPILOT_PX4

    def on_param_value(self, msg: Any) -> None:
        """A PARAM_VALUE from the autopilot: it ends the waits for that parameter."""
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
        """See :meth:`companion.link.mavlink.MavlinkLink.request_message_interval`."""
        return await self.command_long(
            mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL,
            float(message_id),
            float(interval_us),
            timeout_s=timeout_s,
            retries=retries,
        )
