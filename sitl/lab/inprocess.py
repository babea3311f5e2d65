"""The product's flight core, flown in process: the lab's shell around it.

``companion run`` drives :class:`companion.core.FlightCore` from MAVLink; the
lab's flights drive the same core from the simulated plant, so a lab figure is
the product's figure: the same timestamp checks, pilot input, engagement, law,
command gate and per-sample failsafes. :func:`engaged_core` builds a core that
is engaged as the product engages on PX4 (the stack recognised, the setpoints
streaming and flown, then the heartbeat that shows OFFBOARD and armed), and
:class:`LabShell` keeps what the core asks: the last command, the events, the
failsafes. A failsafe stops the commands, as it does in the product; the lab's
autopilot then holds the last one it had (the plant has no failsafe of its own).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.control import RateController
from companion.control.outer import OuterLaw
from companion.control.stick_limits import StickLimits
from companion.core import FlightCore
from companion.run_options import RunOptions
from companion.stacks import PX4
from sitl.px4_params import px4_param_specs

__all__ = [
    "LabShell",
    "LocalPosition",
    "attitude_quaternion",
    "engaged_core",
    "px4_stick_limits",
    "rc_frame",
    "start_mode",
]

_ARMED = 128  # MAV_MODE_FLAG_SAFETY_ARMED
_STANDBY = 4  # MAV_STATE_ACTIVE
_ON_GROUND, _IN_AIR = 1, 2  # MAV_LANDED_STATE
_MSG_LOCAL_POSITION_NED = 32


@dataclass(frozen=True)
class _Heartbeat:
    custom_mode: int
    base_mode: int
    system_status: int


class LabShell:
    """What the core asks of an in-process flight: kept, not carried out over a link."""

    stopping = False

    def __init__(self) -> None:
        self.controls: tuple[float, ...] | None = None
        """The last actuator controls sent (roll, pitch, yaw, collective, ...)."""
        self.rates: tuple[Sequence[float], float] | None = None
        """The last body rates and collective sent."""
        self.events: list[tuple[str, str]] = []
        self.failsafes: list[tuple[str, str]] = []
        self.on_event: Callable[[str, str], None] | None = None
        """Also called with each event (a control log's ``/events``)."""

    def event(self, kind: str, detail: str) -> None:
        self.events.append((kind, detail))
        if self.on_event is not None:
            self.on_event(kind, detail)

    def send_actuator_controls(self, time_usec: int, controls: tuple[float, ...]) -> None:
        self.controls = controls

    def send_body_rates(self, time_boot_ms: int, rates: Sequence[float], thrust: float) -> None:
        self.rates = (rates, thrust)

    def engage(self) -> None:
        """The lab's flights are engaged from the start (:func:`engaged_core`)."""

    def cancel_engaging(self) -> bool:
        return False

    def hand_back(self, reason: str, *, was_commanding: bool) -> None:
        self.events.append(("hand_back", reason))

    def after_failsafe(self, kind: str, detail: str, *, was_commanding: bool) -> None:
        self.failsafes.append((kind, detail))

    def rerequest_streams(self, why: str) -> None:
        """Nothing to ask again: the plant streams what it streams."""

    def stop(self, *, hand_back_owed: bool) -> None:
        self.stopping = True


def engaged_core(
    opts: RunOptions,
    shell: LabShell,
    clock: Callable[[], float],
    *,
    controller: RateController | None = None,
    outer_law: Callable[[], OuterLaw] | None = None,
    before: Callable[[FlightCore], None] | None = None,
) -> FlightCore:
    """A flight core for ``opts``, engaged as ``companion run`` engages a PX4:
    it streams setpoints, then the heartbeat shows OFFBOARD and armed (over
    MAVLink that heartbeat reaches the core before the arming's ACK reaches the
    engagement, so the laws start at the engaged edge in every mode).
    ``before``: what the autopilot told the core before that (start-up's);
    ``controller``, ``outer_law``: as :class:`~companion.core.FlightCore`'s."""
    core = FlightCore(opts, shell, clock, controller=controller, outer_law=outer_law)
    core.stack = PX4
    core.started_up = True
    if before is not None:
        before(core)
    core.begin_commanding()
    offboard = PX4.modes.custom_mode(*PX4.engage_mode)
    core.on_heartbeat(_Heartbeat(offboard, _ARMED, _STANDBY))
    assert core.engaged
    return core


def start_mode(core: FlightCore, imu_rate_hz: float, *, on_ground: bool) -> None:
    """What ``companion run``'s start-up gives a flight mode on the bundled SITL's PX4:
    the IMU rate granted, the landed state, and the law built with the stick limits
    and hover thrust the SITL's parameters answer."""
    core.modes.imu_rate_hz = imu_rate_hz
    core.messages.on_landed_state(_ON_GROUND if on_ground else _IN_AIR)
    limits, hover = px4_stick_limits()
    core.modes.build(limits, hover, on_ground=bool(core.controller.on_ground))


def px4_stick_limits() -> tuple[StickLimits, float]:
    """What the sticks may ask on the bundled SITL's PX4, and its hover thrust, from
    its parameters as ``companion run``'s start-up reads them (PARAM_VALUE: float32)."""
    params = PX4.stick_params
    answered = {
        s.name: float(np.float32(s.default)) for s in px4_param_specs() if s.name in params.defaults
    }
    hover = answered.get(params.hover_thrust, params.defaults[params.hover_thrust])
    return params.limits(answered), hover


@dataclass(frozen=True)
class LocalPosition:
    """LOCAL_POSITION_NED's fields the core reads, as they come off the wire (float32)."""

    x: float
    y: float
    z: float
    vx: float
    vy: float
    vz: float

    @classmethod
    def of(cls, pos: Sequence[float], vel: Sequence[float]) -> LocalPosition:
        return cls(*(float(np.float32(v)) for v in (*pos, *vel)))

    def get_msgId(self) -> int:  # pymavlink's name
        return _MSG_LOCAL_POSITION_NED


def attitude_quaternion(t_s: float, q_wxyz: Sequence[float]) -> tuple[float, ...]:
    """ATTITUDE_QUATERNION's ``(time_boot_ms, q1, q2, q3, q4)`` as they come off the
    wire (the quaternion float32)."""
    return (round(t_s * 1e3), *(float(np.float32(v)) for v in q_wxyz))


def rc_frame(channels: Sequence[int]) -> tuple[Any, ...]:
    """RC_CHANNELS' fields ``(chan1_raw, ..., chan18_raw, chancount)`` for ``channels``."""
    n = len(channels)
    return (*channels, *(0,) * (18 - n), n)
