"""Start-up over MAVLink: recognise the stack, read its parameters, ask for the streams.

What the run needs before anything is flown, each request ACK-checked: the
stack's dialect (and a refusal of what it cannot do: actuator output on
ArduPilot, SET_ATTITUDE_TARGET thrust read as a climb rate), how it shapes a
body-rate setpoint and what its own modes let the sticks ask (its parameters,
its documented defaults where it does not answer), then the IMU stream at the
highest rate it accepts up to the loop rate, the pilot's input, and the
estimates the flight mode flies on. What it learns goes into the run's flight
core (:class:`companion.core.FlightCore`).
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable
from typing import Any

from companion.control import AXES
from companion.core import FlightCore
from companion.errors import EngageError, LinkError
from companion.handback import candidates
from companion.rate_loop import ALL_AXES, RateLoopGains
from companion.run_options import RunOptions
from companion.stacks import RateShapingParams, SafeMode, StickParams, stack_for
from companion.step import LANDED_STATE_RATE_HZ, law_axes_names

__all__ = ["HOLD_POSITION_RATE_HZ", "StartUp"]

# MAVLink numbers used here (common.xml).
_MSG_SYS_STATUS = 1
_MSG_ATTITUDE = 30
_MSG_ATTITUDE_QUATERNION = 31
_MSG_LOCAL_POSITION_NED = 32
_MSG_RC_CHANNELS = 65
_MSG_MANUAL_CONTROL = 69
_MSG_ATTITUDE_TARGET = 83
_MSG_HIGHRES_IMU = 105
_MSG_EXTENDED_SYS_STATE = 245
_CMD_SET_MESSAGE_INTERVAL = 511
_RESULT_ACCEPTED = 0
_RESULT_DENIED = 2
_POSITION_RATE_HZ = 4.0
HOLD_POSITION_RATE_HZ = 50.0
"""The position estimate's rate the altitude and position modes fly on."""
_ATTITUDE_TARGET_RATE_HZ = 20.0
"""The autopilot's own collective, which the hold modes take over at."""
_SYS_STATUS_RATE_HZ = 5.0
_QUICK_PARAM_TIMEOUT_S = 0.25
"""Each parameter read for a choice with a default (the stick limits, the rate gains) is
asked twice at most, all at once: an autopilot that does not answer one costs the
start-up 0.5 s, not a second per parameter."""


class StartUp:
    """The requests of a run's start-up, over ``link``, into ``core``."""

    def __init__(
        self,
        link: Any,
        core: FlightCore,
        opts: RunOptions,
        event: Callable[[str, str], None],
        learnt: Callable[[dict[str, str]], None] | None = None,
    ) -> None:
        self.link = link
        self.core = core
        self.opts = opts
        self.event = event
        self.learnt = learnt
        """Where what the start-up chose goes into the log's metadata."""

    async def recognise(self, autopilot: int) -> tuple[SafeMode, ...]:
        """Pick the stack's dialect and refuse what it cannot do, before sending
        anything; returns the safe modes a hand-back tries, in order."""
        stack = stack_for(autopilot)
        if stack is None:
            raise EngageError(
                f"autopilot type {autopilot} is not supported (PX4 = 12, ArduPilot = 3)"
            )
        core = self.core
        core.stack = stack
        self.event("connected", f"{stack.name} (autopilot {autopilot}) at {self.link.target}")
        opts = self.opts
        if opts.output == "actuator" and not stack.supports_actuator_output:
            raise EngageError(
                f"{stack.name} accepts no actuator setpoints over MAVLink: use --output rates"
            )
        try:
            safe_modes = candidates(stack, opts.failsafe.safe_mode)
        except ValueError as exc:
            raise EngageError(str(exc)) from None
        if core.imu_source == "auto":
            core.imu_source = stack.imu_message  # type: ignore[assignment]
        if stack.thrust_param_bit is not None and opts.output == "rates" and opts.engage != "none":
            # Our thrust is a normalised collective; a stack that reads it otherwise
            # (ArduPilot: as a climb-rate request) unless a bit is set would fly the
            # wrong meaning, which would be dangerous: refuse instead.
            name, bit = stack.thrust_param_bit
            value = int(await self.link.param_read(name))
            if not value & (1 << bit):
                raise EngageError(
                    f"{stack.display_name} {name} = {value}: SET_ATTITUDE_TARGET thrust would "
                    f"be read as a climb rate; set bit {bit} (add {1 << bit}, e.g. {name} = "
                    f"{value | (1 << bit)}) so it is a normalised thrust"
                )
        if opts.output == "rates" and stack.rate_shaping is not None:
            await self._learn_rate_shaping(stack.rate_shaping)
        if opts.output == "rates" and opts.rates_law_axes is None and not opts.rates_passthrough:
            await self._choose_law_axes(stack.rate_gains)
        if core.needs_attitude:
            await self._learn_stick_limits(stack.stick_params)
        return safe_modes

    async def _learn_stick_limits(self, params: StickParams) -> None:
        """Read the autopilot's stick limits (companion.stacks: what its own modes
        let the sticks ask) and its hover thrust, and build the flight mode's law
        with them. A parameter it does not answer takes the stack's documented
        default, and an event says so; so do values the limits cannot take."""

        names = params.names
        got = await asyncio.gather(*(self._read_quickly(n) for n in names))
        values = {n: v for n, v in zip(names, got, strict=True) if v is not None}
        missing = [n for n in names if n not in values]
        if missing:
            shown = ", ".join(f"{n} {params.defaults[n]:g}" for n in missing)
            self.event(
                "stick_limits_assumed",
                f"the autopilot did not answer {len(missing)} of {len(names)} parameters: "
                f"their defaults assumed ({shown})",
            )
        try:
            limits = params.limits(values)
        except ValueError as exc:
            self.event(
                "stick_limits_assumed",
                f"the autopilot's parameters give no usable limits ({exc}): its defaults assumed",
            )
            limits = params.limits()
            values = {}
        hover = values.get(params.hover_thrust, params.defaults[params.hover_thrust])
        self.event(
            "stick_limits",
            f"{limits.summary()}; hover thrust {hover:.3g} ({params.hover_thrust})",
        )
        self.core.modes.build(limits, hover, on_ground=bool(self.core.controller.on_ground))

    async def _read_quickly(self, name: str) -> float | None:
        """A parameter's value, or None where it is not answered (asked twice, briefly)
        or not finite."""
        try:
            value = await self.link.param_read(name, timeout_s=_QUICK_PARAM_TIMEOUT_S, retries=1)
        except LinkError:
            return None
        return value if math.isfinite(value) else None

    async def _choose_law_axes(self, gains: RateLoopGains | None) -> None:
        """``--rates-law-axes auto``: the axes the law corrects, from the autopilot's
        rate-loop gains (:mod:`companion.rate_loop`), into the step and the log's
        metadata. A stack with no rule here, or gains not answered (or not
        positive), leaves all three, and an event says which."""
        axes = ALL_AXES
        if gains is None:
            said = "no rule for this stack's rate gains"
        else:
            names = gains.names
            got = await asyncio.gather(*(self._read_quickly(n) for n in names))
            values, missing = gains.usable(dict(zip(names, got, strict=True)))
            if missing:
                said = f"{', '.join(missing)} not read (or not positive)"
                self.event("rates_law_axes_assumed", f"{said}: the law corrects all three axes")
            else:
                said = gains.said(values)
                axes = gains.law_axes(values)
        self.core.step.set_law_axes(axes)
        left = [a for a, on in zip(AXES, axes, strict=True) if not on]
        self.event(
            "rates_law_axes",
            f"{said}: the law corrects {law_axes_names(axes).replace(',', ', ')}"
            + (f"; {' and '.join(left)}: the pilot's rate and the lead" if left else ""),
        )
        if self.learnt is not None:
            self.learnt({"rates_law_axes": law_axes_names(axes)})

    async def _learn_rate_shaping(self, shaping: RateShapingParams) -> None:
        """Read how the autopilot shapes body-rate setpoints (ArduCopter's input
        shaping: companion.control.shaping) and give it to the step. Unreadable, its
        documented defaults are assumed, and an event says so."""
        values: list[float] = []
        try:
            enabled = await self.link.param_read(shaping.enable_param)
            for name in shaping.accel_params:
                values.append(await self.link.param_read(name))
        except LinkError as exc:
            values = list(shaping.default_accel_cdeg_s2)
            enabled = 1.0
            self.event(
                "rate_shaping_assumed",
                f"the autopilot's {shaping.enable_param} and {', '.join(shaping.accel_params)} "
                f"could not be read ({exc}): its defaults assumed",
            )
        if not int(enabled):
            self.event("rate_shaping", f"{shaping.enable_param} = 0: rate setpoints not shaped")
            return
        deg = tuple(v * 0.01 for v in values)
        self.core.step.set_rate_shaping(tuple(math.radians(d) for d in deg))  # type: ignore[arg-type]
        if self.core.step.shaper is not None:
            shown = "/".join(f"{d:g}" if d > 0 else "none" for d in deg)
            self.event(
                "rate_shaping",
                f"the autopilot limits a rate setpoint's acceleration to {shown} deg/s^2 "
                f"(roll/pitch/yaw, {', '.join(shaping.accel_params)}): the law flies the "
                "pilot's rates so shaped, its setpoints within them, no lead",
            )

    async def request_streams(self) -> None:
        """The IMU stream at the highest rate the stack accepts up to the loop rate,
        falling back when a rate is DENIED; then RC_CHANNELS. ACK-checked. Then
        EXTENDED_SYS_STATE, best effort (a refusal is logged, not fatal)."""
        core = self.core
        assert core.stack is not None
        imu_id = _MSG_HIGHRES_IMU if core.imu_source == "highres_imu" else _MSG_ATTITUDE
        want = min(self.opts.loop_rate_hz, core.stack.max_imu_rate_hz)
        rates = [want] + [r for r in (400.0, 333.0, 250.0, 200.0, 100.0, 50.0) if r < want]
        res = _RESULT_ACCEPTED
        for hz in rates:
            res = await self.link.command_long(_CMD_SET_MESSAGE_INTERVAL, imu_id, 1e6 / hz)
            if res == _RESULT_ACCEPTED:
                core.modes.imu_rate_hz = hz
                self.event("imu_stream", f"message {imu_id} at {hz:g} Hz")
                break
            if res != _RESULT_DENIED:
                break
            self.event("imu_rate_denied", f"message {imu_id} at {hz:g} Hz denied")
        if core.modes.imu_rate_hz is None:
            raise EngageError(
                f"the autopilot refused the IMU stream (message {imu_id}, last MAV_RESULT {res})"
            )
        res = await self.link.command_long(
            _CMD_SET_MESSAGE_INTERVAL, _MSG_RC_CHANNELS, 1e6 / self.opts.rc_rate_hz
        )
        if res != _RESULT_ACCEPTED:
            raise EngageError(
                f"the autopilot refused RC_CHANNELS at {self.opts.rc_rate_hz} Hz (MAV_RESULT {res})"
            )
        # The pilot's joystick where there is no radio (PX4 streams its MANUAL_CONTROL),
        # and the RC receiver's health (ArduPilot's RC_CHANNELS freeze when it is lost).
        await self._request_best_effort(
            "joystick_refused", "MANUAL_CONTROL", _MSG_MANUAL_CONTROL, self.opts.rc_rate_hz,
            "the pilot's input is RC_CHANNELS alone",
        )  # fmt: skip
        await self._request_best_effort(
            "sys_status_refused", "SYS_STATUS", _MSG_SYS_STATUS, _SYS_STATUS_RATE_HZ,
            "an RC receiver the autopilot calls lost is seen only when its frames stop",
        )  # fmt: skip
        if core.needs_attitude:
            # The outer loops fly on the autopilot's attitude estimate, as often as the IMU.
            assert core.modes.imu_rate_hz is not None
            await self._request_for_mode(
                "ATTITUDE_QUATERNION", _MSG_ATTITUDE_QUATERNION, core.modes.imu_rate_hz, event=True
            )
        if core.needs_position:
            await self._request_for_mode(
                "LOCAL_POSITION_NED", _MSG_LOCAL_POSITION_NED, HOLD_POSITION_RATE_HZ, event=True
            )
            await self._request_best_effort(
                "attitude_target_refused", "ATTITUDE_TARGET", _MSG_ATTITUDE_TARGET,
                _ATTITUDE_TARGET_RATE_HZ,
                "the hold modes take over at the autopilot's hover thrust, not its collective",
            )  # fmt: skip
        # The landed state stops identification on the ground (MfcController.on_ground);
        # the flight modes hold their loops on the ground by it: for them it is needed.
        if core.needs_attitude:
            await self._request_for_mode(
                "EXTENDED_SYS_STATE", _MSG_EXTENDED_SYS_STATE, LANDED_STATE_RATE_HZ
            )
        else:
            await self._request_best_effort(
                "landed_state_refused", "EXTENDED_SYS_STATE", _MSG_EXTENDED_SYS_STATE,
                LANDED_STATE_RATE_HZ,
                "identification is gated by the collective alone unless the autopilot sends it",
            )  # fmt: skip
        # Whether a position estimate exists decides the hand-back's hold.
        if not core.needs_position:
            await self._request_best_effort(
                "position_refused", "LOCAL_POSITION_NED", _MSG_LOCAL_POSITION_NED,
                _POSITION_RATE_HZ, "a hand-back without RC lands unless the autopilot sends it",
            )  # fmt: skip

    async def _request_for_mode(
        self, name: str, msg_id: int, hz: float, *, event: bool = False
    ) -> None:
        """Ask for a stream the flight mode cannot fly without: a refusal stops the
        start-up (EngageError); ``event``: an ``estimate_stream`` event once granted."""
        res = await self.link.command_long(_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)
        if res != _RESULT_ACCEPTED:
            raise EngageError(
                f"the autopilot refused {name} at {hz:g} Hz (MAV_RESULT {res}): "
                f"--mode {self.opts.mode} flies on it"
            )
        if event:
            self.event("estimate_stream", f"{name} at {hz:g} Hz")

    async def _request_best_effort(
        self, kind: str, name: str, msg_id: int, hz: float, without: str
    ) -> None:
        """Ask for a stream the run can do without: a refusal is an event saying so."""
        res = await self.link.command_long(_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)
        if res != _RESULT_ACCEPTED:
            self.event(kind, f"{name} at {hz:g} Hz refused (MAV_RESULT {res}): {without}")
