"""What preflight reads from the autopilot and the run it judges it for: the
observation, the plan, the law's measured cost, and one checklist line."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

from companion.link.timesync import LinkStats
from companion.rate_loop import LawAxes
from companion.stacks import FlightStack, stack_for

if TYPE_CHECKING:
    from companion.fly_check import FlyCheck

__all__ = ["Check", "CoreCost", "Observed", "Plan", "Status"]

Status = Literal["pass", "warn", "fail"]


LATE_PERIODS = 4
"""An IMU interval longer than this many of the asked periods is late."""

STALL_S = 0.05
"""A single IMU gap longer than this (or ten periods, if shorter) is a stall: a fifth
of the stale-IMU failsafe's 0.25 s."""

SLOW_CLOCK_RATIO = 0.97
"""An autopilot whose clock runs below this share of real time (a simulator falling
behind it) is named as the cause of a slow IMU stream."""

STALL_SHARE = 0.01
"""Late intervals beyond this share of the stream are a stream that keeps stalling."""


@dataclass(frozen=True)
class Check:
    """One line of the checklist."""

    name: str
    status: Status
    detail: str
    fix: str = ""


@dataclass(frozen=True)
class Plan:
    """The run the checks judge the autopilot for (``companion run``'s options)."""

    output: Literal["actuator", "rates"] = "actuator"
    rates_law_axes: LawAxes | None = None
    """With rates output: whether the law corrects roll, pitch and yaw (None:
    ``--rates-law-axes auto``, chosen from the autopilot's rate gains)."""
    engage: Literal["auto", "rc-switch", "none"] = "rc-switch"
    engage_channel: int = 5
    rate_hz: float = 250.0
    sticks_channels: tuple[int, int, int, int] = (1, 2, 3, 4)
    """Roll, pitch, throttle, yaw (the controller config's ``sticks.channels``)."""
    signing: bool = False
    serial: bool = False
    """The link is a serial port (no one else on it), not a network."""
    source_system: int = 1
    source_component: int = 191
    fly_check: FlyCheck | None = None
    """What this computer knows of the controller file's fly check (None: not judged)."""
    skip_fly_check: bool = False
    """``--skip-fly-check``: the run flies a file without a passed check anyway."""


@dataclass(frozen=True)
class CoreCost:
    """The control law's cost per update on this computer."""

    compiled: bool
    median_us: float
    p99_us: float
    updates: int


@dataclass
class Observed:
    """What the autopilot showed during preflight (None: not seen)."""

    heartbeat: bool = False
    autopilot_id: int | None = None
    target: tuple[int, int] | None = None
    armed: bool = False
    version: tuple[int, int, int] | None = None
    capabilities: int | None = None
    params: dict[str, float | None] = field(default_factory=dict)
    imu_message: str = ""
    imu_asked_hz: float = 0.0
    imu_result: int | None = None
    imu_count: int = 0
    imu_window_s: float = 0.0
    imu_max_gap_s: float = math.nan
    imu_late: int = 0
    """Intervals between IMU messages longer than four of the asked periods."""
    imu_clock_ratio: float = math.nan
    """The IMU stream's span on the autopilot's clock over its span on ours: 1 for
    a real autopilot, below 1 for a simulator running behind real time."""
    link: LinkStats | None = None
    timesync_requests: int = 0
    rc_messages: int = 0
    rc_chancount: int = 0
    rc_min_us: list[int] = field(default_factory=list)
    rc_max_us: list[int] = field(default_factory=list)
    rc_last_us: list[int] = field(default_factory=list)
    joystick_messages: int = 0
    """MANUAL_CONTROL frames from the autopilot (a ground station's joystick, PX4)."""
    joystick_min_us: list[int] = field(default_factory=list)
    joystick_max_us: list[int] = field(default_factory=list)
    joystick_last_us: list[int] = field(default_factory=list)
    """The joystick as the channels ``companion run`` reads it (aux1..6 as 5..10)."""
    landed_states: list[int] = field(default_factory=list)
    position_messages: int = 0
    frames_signed: int = 0
    frames_unsigned: int = 0
    frames_rejected_unsigned: int = 0
    error: str = ""
    """Why the observation stopped early (no heartbeat, unsupported stack)."""

    @property
    def stack(self) -> FlightStack | None:
        return stack_for(self.autopilot_id) if self.autopilot_id is not None else None
