"""A fake autopilot for app-level tests, built from pymavlink on the far end of a MemoryTransport.

It speaks for system 1 / component 1 as PX4 (``autopilot`` 12) or ArduPilot (3):

* sends HEARTBEAT with its current ``custom_mode`` and armed bit, on demand and
  every ``heartbeat_period_s`` in the background (so the link never times out);
* answers COMMAND_LONG with COMMAND_ACK, the result chosen per command id
  (``results``: a MAV_RESULT, or a callable of the message returning one or None
  for "stay silent"); ACCEPTED by default;
* answers PARAM_REQUEST_READ with PARAM_VALUE from ``params``;
* with ``position`` (the default), sends LOCAL_POSITION_NED with each
  background HEARTBEAT, as a vehicle with a position estimate does;
* with ``follow_modes`` (the default), shows an accepted DO_SET_MODE in a
  HEARTBEAT at once, as the real stacks do;
* with ``timesync_clock`` set (None by default: no answer), answers the
  companion's TIMESYNC requests (``tc1 = 0``) with ``tc1`` that clock in ns and
  ``ts1`` copied, each way ``timesync_delay_s`` late (as PX4 and ArduPilot do,
  through a link of that delay);
* sends HIGHRES_IMU / ATTITUDE / RC_CHANNELS (and TIMESYNC) when the test asks;
* records every message it receives (``received``), decoded by its own parser.

Armed state (and the mode, with ``follow_modes=False``) change only when the
test says so (``set_state``): the tests decide when the autopilot "really"
switched, so they can check that the companion waits for the heartbeat rather
than trusting the ACK.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import Callable, Iterator
from typing import Any

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink2

from companion.link.transport import MemoryTransport

__all__ = [
    "APM_ALT_HOLD",
    "APM_GUIDED_NOGPS",
    "APM_STABILIZE",
    "CMD_ARM",
    "CMD_DO_SET_MODE",
    "CMD_SET_MESSAGE_INTERVAL",
    "HANG_SLACK",
    "PX4_MANUAL",
    "PX4_OFFBOARD",
    "PX4_POSCTL",
    "FakeAutopilot",
    "mavlink2",
    "settle",
]

HANG_SLACK = 5.0
"""A wait's ``timeout_s`` (here and in tests/app/flight.py) only guards against a
hang: it gives up after this many times as long, for a loaded machine stretches
every wait. What a test says about time it says on a clock it drives, or in
samples, never in a wait's bound."""

CMD_DO_SET_MODE = mavlink2.MAV_CMD_DO_SET_MODE  # 176
CMD_ARM = mavlink2.MAV_CMD_COMPONENT_ARM_DISARM  # 400
CMD_SET_MESSAGE_INTERVAL = mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL  # 511

# PX4 custom_mode: main mode in bits 16..23.
PX4_MANUAL = 1 << 16
PX4_POSCTL = 3 << 16
PX4_OFFBOARD = 6 << 16
# ArduCopter custom_mode is the mode number.
APM_STABILIZE = 0
APM_ALT_HOLD = 2
APM_GUIDED_NOGPS = 20

Result = int | Callable[[Any], int | None]

ARDUPILOT_DEFAULTS: dict[str, float | None] = {
    "ATC_RATE_FF_ENAB": 1.0,
    "ATC_ACCEL_R_MAX": 110000.0,
    "ATC_ACCEL_P_MAX": 110000.0,
    "ATC_ACCEL_Y_MAX": 27000.0,
}
"""What an ArduCopter 4.5 answers for its input shaping unless a test says otherwise."""
PX4_DEFAULTS: dict[str, float | None] = {
    "MC_ROLLRATE_K": 1.0,
    "MC_ROLLRATE_P": 0.15,
    "MC_PITCHRATE_K": 1.0,
    "MC_PITCHRATE_P": 0.15,
}
"""What a PX4 v1.16 answers for its rate loop's gains unless a test says otherwise."""


async def settle(n: int = 10) -> None:
    """Let call_soon deliveries run both ways (one loop iteration per hop)."""
    for _ in range(n):
        await asyncio.sleep(0)


class FakeAutopilot:
    """The autopilot end of a :meth:`MemoryTransport.pair`."""

    def __init__(
        self,
        transport: MemoryTransport,
        *,
        autopilot: int = mavlink2.MAV_AUTOPILOT_PX4,
        custom_mode: int = PX4_MANUAL,
        armed: bool = False,
        results: dict[int, Result] | None = None,
        params: dict[str, float | None] | None = None,
        heartbeat_period_s: float = 0.2,
        follow_modes: bool = True,
        position: bool = True,
    ) -> None:
        self.transport = transport
        self.autopilot = autopilot
        self.custom_mode = custom_mode
        self.armed = armed
        self.results: dict[int, Result] = dict(results or {})
        given = dict(params or {})
        if autopilot == mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA:
            given = {**ARDUPILOT_DEFAULTS, **given}
        elif autopilot == mavlink2.MAV_AUTOPILOT_PX4:
            given = {**PX4_DEFAULTS, **given}
        # A name given as None is one the autopilot does not answer.
        self.params: dict[str, float] = {k: v for k, v in given.items() if v is not None}
        self.heartbeat_period_s = heartbeat_period_s
        self.follow_modes = follow_modes
        self.position = position
        self.mav = mavlink2.MAVLink(self, srcSystem=1, srcComponent=1)
        self.parser = mavlink2.MAVLink(None)
        self.parser.robust_parsing = True
        self.received: list[Any] = []
        self.imu_sent: list[int] = []  # time_usec / time_boot_ms of every IMU sample sent
        self._changed = asyncio.Event()
        self._hb_task: asyncio.Task[None] | None = None
        self._bundle: list[bytes] | None = None
        self.timesync_clock: Callable[[], float] | None = None
        """The autopilot's clock (s) for TIMESYNC answers; None: requests go unanswered."""
        self.timesync_delay_s = 0.0
        """Each way: a request is stamped this late, and its answer arrives this late after."""
        self._timers: set[asyncio.TimerHandle] = set()
        self.system_status: int | None = None
        """HEARTBEAT ``system_status`` to show; None: STANDBY, ACTIVE when armed.
        CRITICAL is how PX4 and ArduPilot say they are failing safe."""

    # ----------------------------------------------------------------- plumbing
    def write(self, buf: bytes) -> None:  # pymavlink's output "file"
        if self._bundle is not None:
            self._bundle.append(bytes(buf))
        else:
            self.transport.write(buf)

    @contextlib.contextmanager
    def bundle(self) -> Iterator[None]:
        """Send everything written inside as one chunk (PX4 packs several messages
        into one UDP datagram; a serial read returns what is waiting)."""
        self._bundle = []
        try:
            yield
        finally:
            chunk, self._bundle = b"".join(self._bundle), None
            if chunk:
                self.transport.write(chunk)

    async def open(self) -> FakeAutopilot:
        await self.transport.open(self._on_bytes)
        if self.heartbeat_period_s > 0:
            self._hb_task = asyncio.get_running_loop().create_task(
                self._heartbeat_loop(), name="fake-autopilot-heartbeat"
            )
        return self

    async def close(self) -> None:
        for timer in self._timers:
            timer.cancel()
        self._timers.clear()
        task, self._hb_task = self._hb_task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        await self.transport.close()

    async def _heartbeat_loop(self) -> None:
        while True:
            await asyncio.sleep(self.heartbeat_period_s)
            self.heartbeat()
            if self.position:
                self.local_position()

    def _on_bytes(self, chunk: bytes) -> None:
        for msg in self.parser.parse_buffer(chunk) or []:
            if msg.get_type() == "BAD_DATA":
                continue
            self.received.append(msg)
            self._changed.set()
            mtype = msg.get_type()
            if mtype == "COMMAND_LONG":
                self._answer_command(msg)
            elif mtype == "PARAM_REQUEST_READ":
                self._answer_param(msg)
            elif mtype == "TIMESYNC" and msg.tc1 == 0 and self.timesync_clock is not None:
                self._later(self._answer_timesync, msg.ts1)

    def _answer_command(self, msg: Any) -> None:
        policy = self.results.get(msg.command, mavlink2.MAV_RESULT_ACCEPTED)
        result = policy(msg) if callable(policy) else policy
        if result is None:
            return  # a lost ack
        self.mav.command_ack_send(
            msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
        )
        if (
            self.follow_modes
            and msg.command == CMD_DO_SET_MODE
            and result == mavlink2.MAV_RESULT_ACCEPTED
        ):
            # As the real stacks do: the accepted mode shows in the next HEARTBEAT.
            if self.autopilot == mavlink2.MAV_AUTOPILOT_PX4:
                self.custom_mode = (int(msg.param2) << 16) | (int(msg.param3) << 24)
            else:
                self.custom_mode = int(msg.param2)
            self.heartbeat()

    def _later(self, fn: Callable[..., None], *args: Any) -> None:
        """``fn(*args)`` after ``timesync_delay_s`` (at once without a delay)."""
        delay = self.timesync_delay_s
        if delay <= 0.0:
            fn(*args)
            return
        timer: asyncio.TimerHandle

        def fire() -> None:
            self._timers.discard(timer)
            fn(*args)

        timer = asyncio.get_running_loop().call_later(delay, fire)
        self._timers.add(timer)

    def _answer_timesync(self, ts1_ns: int) -> None:
        """Stamped now, on our clock; on its way back ``timesync_delay_s`` more."""
        assert self.timesync_clock is not None
        answer = self.mav.timesync_encode(round(self.timesync_clock() * 1e9), ts1_ns)
        self._later(self.mav.send, answer)

    def _answer_param(self, msg: Any) -> None:
        name = msg.param_id
        if isinstance(name, bytes):
            name = name.decode()
        name = name.rstrip("\x00")
        if name not in self.params:
            return
        index = sorted(self.params).index(name)
        self.mav.param_value_send(
            name.encode(),
            float(self.params[name]),
            mavlink2.MAV_PARAM_TYPE_REAL32,
            len(self.params),
            index,
        )

    # ------------------------------------------------------------------ sending
    def set_state(self, custom_mode: int | None = None, armed: bool | None = None) -> None:
        """Change mode / armed and announce it with a HEARTBEAT at once."""
        if custom_mode is not None:
            self.custom_mode = custom_mode
        if armed is not None:
            self.armed = armed
        self.heartbeat()

    def heartbeat(self) -> None:
        base_mode = mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.armed:
            base_mode |= mavlink2.MAV_MODE_FLAG_SAFETY_ARMED
        state = mavlink2.MAV_STATE_ACTIVE if self.armed else mavlink2.MAV_STATE_STANDBY
        self.mav.heartbeat_send(
            mavlink2.MAV_TYPE_QUADROTOR,
            self.autopilot,
            base_mode,
            self.custom_mode,
            state if self.system_status is None else self.system_status,
        )

    def local_position(
        self,
        pos_ned: tuple[float, float, float] = (0.0, 0.0, -5.0),
        vel_ned: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> None:
        """LOCAL_POSITION_NED: both stacks send it only while their estimate is valid."""
        self.mav.local_position_ned_send(0, *pos_ned, *vel_ned)

    def extended_sys_state(self, landed_state: int) -> None:
        self.mav.extended_sys_state_send(mavlink2.MAV_VTOL_STATE_UNDEFINED, landed_state)

    def timesync(self, tc1_ns: int, ts1_ns: int) -> None:
        """TIMESYNC: a request of ours (``tc1 = 0``) or an answer, as the test says."""
        self.mav.timesync_send(tc1_ns, ts1_ns)

    def statustext(self, text: bytes, severity: int = mavlink2.MAV_SEVERITY_INFO) -> None:
        self.mav.statustext_send(severity, text)

    def highres_imu(self, time_usec: int, gyro: tuple[float, float, float]) -> None:
        self.imu_sent.append(time_usec)
        self.mav.highres_imu_send(
            time_usec, 0.0, 0.0, -9.81, *gyro, 0.2, 0.0, 0.4, 1013.0, 0.0, 0.0, 20.0, 0x3F
        )

    def attitude(self, time_boot_ms: int, rates: tuple[float, float, float]) -> None:
        self.imu_sent.append(time_boot_ms)
        self.mav.attitude_send(time_boot_ms, 0.0, 0.0, 0.0, *rates)

    def attitude_quaternion(self, time_boot_ms: int, q_wxyz: tuple[float, ...]) -> None:
        """ATTITUDE_QUATERNION: the estimator's attitude (body rates zero)."""
        self.mav.attitude_quaternion_send(time_boot_ms, *q_wxyz, 0.0, 0.0, 0.0)

    def rc(
        self, ch5_us: int = 1000, *, sticks: tuple[int, int, int, int] = (1500, 1500, 1500, 1500)
    ) -> None:
        """RC_CHANNELS with AETR sticks and ch5 (the engage switch); 8 channels."""
        chans = [*sticks, ch5_us, 1500, 1500, 1500] + [0] * 10
        self.mav.rc_channels_send(0, 8, *chans, 255)

    def manual_control(
        self,
        aux1: int = -1000,
        *,
        sticks: tuple[int, int, int, int] = (0, 0, 500, 0),
        aux_present: bool = True,
    ) -> None:
        """MANUAL_CONTROL as PX4 streams a ground station's joystick: ``sticks`` are
        (x pitch, y roll, z thrust, r yaw), ``aux1`` the engage switch (-1000 low,
        1000 high), aux2..6 centred."""
        x, y, z, r = sticks
        ext = 0b11111100 if aux_present else 0
        self.mav.manual_control_send(1, x, y, z, r, 0, 0, ext, 0, 0, aux1, 0, 0, 0, 0, 0)

    def sys_status(
        self, *, rc_present: bool = True, rc_healthy: bool = True, prearm: bool | None = None
    ) -> None:
        """SYS_STATUS with the RC receiver's bits (present, enabled, healthy) and,
        unless ``prearm`` is None (not reported, the default), the pre-arm check's
        (present and enabled; healthy while the checks pass, as PX4 and ArduPilot
        report them)."""
        rc = mavlink2.MAV_SYS_STATUS_SENSOR_RC_RECEIVER
        present = rc if rc_present else 0
        health = rc if rc_present and rc_healthy else 0
        if prearm is not None:
            present |= mavlink2.MAV_SYS_STATUS_PREARM_CHECK
            health |= mavlink2.MAV_SYS_STATUS_PREARM_CHECK if prearm else 0
        self.mav.sys_status_send(present, present, health, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)

    # --------------------------------------------------------------- inspecting
    def of_type(self, *mtypes: str) -> list[Any]:
        return [m for m in self.received if m.get_type() in mtypes]

    def commands(self, command: int) -> list[Any]:
        return [m for m in self.of_type("COMMAND_LONG") if m.command == command]

    def setpoints(self) -> list[Any]:
        return self.of_type("SET_ACTUATOR_CONTROL_TARGET", "SET_ATTITUDE_TARGET")

    async def wait_until(self, cond: Callable[[], bool], timeout_s: float = 2.0) -> None:
        """Wait until ``cond()`` holds, re-checking on every message received
        (and every 10 ms, for conditions on the companion's state); TimeoutError
        after ``timeout_s`` times ``HANG_SLACK``.

        A deadline rather than an outer ``wait_for``: before Python 3.12, a
        ``wait_for`` cancelled just as what it awaits completes returns the result
        and drops the cancellation (CPython gh-86296), so the inner wait below
        could swallow the outer one's cancel; the loop went on, and the outer
        ``wait_for`` waited for it for ever (a failing test hung instead of failing)."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + HANG_SLACK * timeout_s
        while not cond():
            left = deadline - loop.time()
            if left <= 0.0:
                raise asyncio.TimeoutError(f"condition not met within {HANG_SLACK * timeout_s} s")
            self._changed.clear()
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(self._changed.wait(), min(0.01, left))
