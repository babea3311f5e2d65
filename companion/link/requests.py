"""Requests to the autopilot and their replies: HEARTBEAT, COMMAND_LONG, parameters."""

from __future__ import annotations

import asyncio
import logging
import struct
from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import common as mavlink2

from companion.errors import LinkError
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
    """The request side of :class:`~companion.link.mavlink.MavlinkLink` (a base of it)."""

    transport: Transport
    target: tuple[int, int] | None
    mav: Any
    source_system: int
    source_component: int
    last_heartbeat: Any | None
    _started: bool
    _closed: bool
    _heartbeat_waiters: list[asyncio.Future[Any]]
    _ack_waiters: dict[int, asyncio.Future[Any]]
    _param_waiters: dict[str, list[asyncio.Future[Any]]]
    _command_locks: dict[int, asyncio.Lock]

    if TYPE_CHECKING:  # defined in MavlinkLink

        def send(self, msg: Any) -> None: ...

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
                return param_value(msg, bytewise=self._params_bytewise())
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

    def _params_bytewise(self) -> bool:
        """Whether the autopilot sends integer parameters bytewise: PX4 does (its
        int32's bits in the float field); ArduPilot casts them to float."""
        hb = self.last_heartbeat
        return hb is not None and int(hb.autopilot) == _MAV_AUTOPILOT_PX4

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
