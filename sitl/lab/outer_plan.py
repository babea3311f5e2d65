"""The lab's outer-loop scenarios as the product flies them: a plan, or sticks.

An outer scenario (:class:`sitl.lab.outer_flight.OuterScenario`) asks setpoints
against time. The product flies them through its own flight modes
(:func:`sitl.lab.simulate.simulate_flight`), so an outer figure is the product's:

* the altitude and position scenarios are a position-mode plan
  (:class:`ScenarioPlan`, flown as ``--mission`` flies a mission's waypoints):
  on its legs, a climb at :data:`~companion.control.hold_modes.TAKEOFF_CLIMB_M_S`
  to the scenario's altitude, a hold, then the scenario's own setpoints. Unlike a
  mission's, they are in the estimate's local frame, whose origin is where the
  vehicle stands at the start (as the scenarios are written), not relative to
  where the estimate put it as it engaged: the true state against them is then
  the loops' error and the estimate's now, not also the estimate's then. The
  plan's clock is the mission's (it runs while the vehicle is in the air), so
  the scenario starts :data:`PLAN_LIFT_OFF_S` earlier on it than on the
  flight's; the flight records when it really started.
* the angle scenario is a pilot (:class:`AnglePilot`) flying the altitude mode:
  the throttle up to climb, centred to hold; the roll and pitch sticks at the
  angles asked (the stack's tilt at full stick); the yaw stick turning the
  heading asked, as a pilot closes it by eye.

No I/O, no clock.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from companion.control.hold_modes import TAKEOFF_CLIMB_M_S
from companion.control.horizontal import HorizontalSetpoint
from companion.control.outer import OuterSetpoint
from companion.control.stick_limits import StickLimits
from companion.control.vertical import VerticalSetpoint
from sitl.pilot import PilotView, Sticks

__all__ = [
    "PLAN_LIFT_OFF_S",
    "AnglePilot",
    "CentredSticks",
    "ScenarioPath",
    "ScenarioPlan",
    "Setpoints",
]

Vec3 = tuple[float, float, float]

PLAN_LIFT_OFF_S = 1.0
"""About when the autopilot reports the vehicle in the air (flight time, s;
lift-off at about 0.8 s, the landed state a few tenths later): the plan's clock,
which starts then, begins the scenario this much earlier."""

_YAW_STICK_PER_RAD = 0.5
"""The angle pilot's yaw stick per radian of heading error (a turn by eye)..."""
_YAW_STICK_MAX = 0.25
"""... at most this deflection."""


@dataclass(frozen=True)
class Setpoints:
    """What a scenario asks at one time: a position-mode plan's setpoint, or the
    angles and heading the angle scenario's pilot flies."""

    up_m: float
    climb_m_s: float = 0.0
    position_ne_m: tuple[float, float] = (0.0, 0.0)
    velocity_ne_m_s: tuple[float, float] = (0.0, 0.0)
    accel_ne_m_s2: tuple[float, float] = (0.0, 0.0)
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float = 0.0


class _Scenario(Protocol):
    @property
    def name(self) -> str: ...
    @property
    def hold_up_m(self) -> float: ...
    @property
    def start_s(self) -> float: ...
    @property
    def duration_s(self) -> float: ...
    @property
    def setpoints(self) -> Callable[[float], Setpoints]: ...


class ScenarioPath:
    """An outer scenario's setpoints in the local frame (module docstring);
    ``origin_ned_m``: where the estimate put the vehicle as it engaged (its
    take-off climbs from there)."""

    def __init__(self, scenario: _Scenario, origin_ned_m: Vec3) -> None:
        self._scenario = scenario
        self._origin = origin_ned_m
        self._climb_s = scenario.hold_up_m / TAKEOFF_CLIMB_M_S
        self.start_s = max(self._climb_s, scenario.start_s - PLAN_LIFT_OFF_S)
        """The plan's time at which the scenario's own setpoints start."""
        self.duration_s = self.start_s + scenario.duration_s

    def _setpoints(self, t_s: float) -> Setpoints:
        sc = self._scenario
        if t_s >= self.start_s:
            return sc.setpoints(t_s - self.start_s)
        up = -self._origin[2] + TAKEOFF_CLIMB_M_S * max(t_s, 0.0)
        if up < sc.hold_up_m:
            return Setpoints(up, climb_m_s=TAKEOFF_CLIMB_M_S)
        return Setpoints(sc.hold_up_m)

    def at(self, t_s: float) -> OuterSetpoint:
        sp = self._setpoints(t_s)
        return OuterSetpoint(
            HorizontalSetpoint(sp.velocity_ne_m_s, sp.position_ne_m, sp.accel_ne_m_s2),
            VerticalSetpoint(sp.climb_m_s, sp.up_m),
            sp.yaw_rad,
        )

    def target_at(self, t_s: float) -> Vec3:
        if t_s < self.start_s:  # climbing to, or holding at, the first altitude
            return (0.0, 0.0, -self._scenario.hold_up_m)
        sp = self.at(t_s)
        pos = sp.horizontal.position_ne_m
        assert pos is not None and sp.vertical.up_m is not None
        return (pos[0], pos[1], -sp.vertical.up_m)

    def waypoints_reached(self, t_s: float) -> int:
        return 0

    def summary(self) -> str:
        sc = self._scenario
        return (
            f"the lab's {sc.name}: a climb to {sc.hold_up_m:g} m at {TAKEOFF_CLIMB_M_S:g} m/s, "
            f"its setpoints from {self.start_s:.1f} s, {self.duration_s:.1f} s"
        )


@dataclass
class ScenarioPlan:
    """An outer scenario as a position-mode plan (module docstring); keeps the path
    it made, for the flight's record."""

    scenario: _Scenario
    made: ScenarioPath | None = None

    @property
    def n_waypoints(self) -> int:
        return 0

    def path(self, origin_ned_m: Vec3, limits: StickLimits) -> ScenarioPath:
        self.made = ScenarioPath(self.scenario, origin_ned_m)
        return self.made


def _us(x: float) -> int:
    return math.floor(1500.0 + 500.0 * min(1.0, max(-1.0, x)) + 0.5)


class AnglePilot:
    """The angle scenario's pilot in the altitude mode (module docstring)."""

    def __init__(self, scenario: _Scenario, limits: StickLimits) -> None:
        self._scenario = scenario
        self.duration_s = scenario.duration_s
        self._tilt_max = math.radians(limits.tilt_max_deg)
        climb = limits.climb
        # The throttle whose climb is the take-off's (the stick's curve, searched).
        lo, hi = 0.5, 1.0
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            c = climb.climb_m_s(mid)
            lo, hi = (mid, hi) if c is None or c < TAKEOFF_CLIMB_M_S else (lo, mid)
        self._climb_throttle = hi

    def sticks(self, view: PilotView) -> Sticks:
        sc = self._scenario
        t = view.t_s - sc.start_s
        if t < 0.0:
            up = view.altitude_m < sc.hold_up_m - 0.2
            throttle = self._climb_throttle if up else 0.5
            return Sticks(1500, 1500, math.floor(1000.0 + 1000.0 * throttle + 0.5), 1500)
        sp = sc.setpoints(t)
        err = (sp.yaw_rad - view.yaw_rad + math.pi) % (2.0 * math.pi) - math.pi
        yaw = max(-_YAW_STICK_MAX, min(_YAW_STICK_MAX, _YAW_STICK_PER_RAD * err))
        return Sticks(
            _us(sp.roll_rad / self._tilt_max), _us(sp.pitch_rad / self._tilt_max), 1500, _us(yaw)
        )


class CentredSticks:
    """A pilot who leaves the sticks centred (a plan flies the vehicle)."""

    def __init__(self, duration_s: float) -> None:
        self.duration_s = duration_s

    def sticks(self, view: PilotView) -> Sticks:
        return Sticks(1500, 1500, 1500, 1500)
