"""A mission: waypoints flown in position mode (``companion run --mode position --mission FILE``).

The file (YAML)::

    speed_m_s: 2.0                 # default speed along a leg, m/s
    waypoints:                     # from where the mission starts: north, east, up (m)
      - {north_m: 0, east_m: 0, up_m: 5, hold_s: 2}
      - {north_m: 10, east_m: 0, up_m: 5}
      - {north_m: 10, east_m: 10, up_m: 8, speed_m_s: 3}

Positions are relative to where the vehicle is when the mission starts (its
position estimate as it engages), so a file flies the same anywhere. The first
leg goes from there to the first waypoint.

The path (:class:`MissionPath`) moves the position setpoint along each leg in a
straight line at the leg's speed, the velocity as feedforward, and holds it at a
waypoint for its ``hold_s``; a climb and a descent are no faster than the
position mode's stick limits (the autopilot's: PX4 3 and 1.5 m/s by default,
ArduCopter 2.5 m/s), the leg taking longer if need be. After the last
waypoint the setpoint stays there: the vehicle holds until the pilot hands back
(the engage switch, as any run). The clock of the path is the caller's (the app
runs it only while the vehicle is in the air).

No I/O beyond :func:`load_mission`; no clock.
"""

from __future__ import annotations

import bisect
import math
from pathlib import Path
from typing import Annotated

from pydantic import Field

from companion.control.horizontal import DEFAULT_HORIZONTAL_GAINS, HorizontalSetpoint
from companion.control.outer import OuterSetpoint
from companion.control.stick_limits import ClimbLimits
from companion.control.vertical import VerticalSetpoint
from companion.schema import StrictModel, load_yaml_model

__all__ = ["Mission", "MissionPath", "Waypoint", "load_mission"]

MAX_RANGE_M = 5000.0
"""How far from the start a waypoint may be, per axis."""
MAX_WAYPOINTS = 1000
MAX_SPEED_M_S = DEFAULT_HORIZONTAL_GAINS.speed_max_m_s
"""A leg's speed at most the horizontal loop's bound (12 m/s): a faster leg would
leave the vehicle behind its setpoint."""

Vec3 = tuple[float, float, float]


class Waypoint(StrictModel):
    """One waypoint, from where the mission starts."""

    north_m: Annotated[float, Field(ge=-MAX_RANGE_M, le=MAX_RANGE_M)]
    east_m: Annotated[float, Field(ge=-MAX_RANGE_M, le=MAX_RANGE_M)]
    up_m: Annotated[float, Field(ge=-100.0, le=500.0, description="height above the start, m")]
    speed_m_s: Annotated[float, Field(gt=0.0, le=MAX_SPEED_M_S)] | None = Field(
        None, description="speed of the leg to it, m/s; null: the mission's"
    )
    hold_s: Annotated[float, Field(ge=0.0, le=3600.0)] = Field(
        0.0, description="time held at it, s"
    )


class Mission(StrictModel):
    """A mission file (module docstring)."""

    speed_m_s: Annotated[float, Field(gt=0.0, le=MAX_SPEED_M_S)] = Field(
        2.0, description="speed along a leg, m/s"
    )
    waypoints: Annotated[list[Waypoint], Field(min_length=1, max_length=MAX_WAYPOINTS)]


def load_mission(path: str | Path) -> Mission:
    """Read and validate a mission file.

    Raises
    ------
    companion.errors.ConfigError
        Naming the file and each offending key (``waypoints.2.speed_m_s``, ...).
    """
    return load_yaml_model(path, Mission)


class MissionPath:
    """The setpoints of a mission started at ``origin_ned_m`` (module docstring).

    Parameters
    ----------
    mission
        The waypoints.
    origin_ned_m
        Where the mission starts (the position estimate as it engages), NED, m.
    climb
        The stack's climb and descent limits (its sticks'): no leg climbs or
        descends faster.
    """

    def __init__(self, mission: Mission, origin_ned_m: Vec3, climb: ClimbLimits) -> None:
        o = origin_ned_m
        points = [o] + [
            (o[0] + w.north_m, o[1] + w.east_m, o[2] - w.up_m) for w in mission.waypoints
        ]
        # Per segment: start time, start point, velocity (moving) or zero (holding).
        self._t: list[float] = []
        self._p: list[Vec3] = []
        self._v: list[Vec3] = []
        self.arrivals_s: list[float] = []
        """When the setpoint reaches each waypoint, s from the start."""
        t = 0.0
        for a, b, w in zip(points, points[1:], mission.waypoints, strict=False):
            d = (b[0] - a[0], b[1] - a[1], b[2] - a[2])
            length = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
            speed = w.speed_m_s if w.speed_m_s is not None else mission.speed_m_s
            up = -d[2]
            duration = max(
                length / speed,
                up / climb.up_max_m_s if up > 0.0 else -up / climb.down_max_m_s,
            )
            if duration > 0.0:
                self._t.append(t)
                self._p.append(a)
                self._v.append((d[0] / duration, d[1] / duration, d[2] / duration))
                t += duration
            self.arrivals_s.append(t)
            if w.hold_s > 0.0:
                self._t.append(t)
                self._p.append(b)
                self._v.append((0.0, 0.0, 0.0))
                t += w.hold_s
        self._end = points[-1]
        self._targets = points[1:]
        self.duration_s = t
        """When the last waypoint's hold ends; the setpoint stays there after."""

    def at(self, t_s: float) -> OuterSetpoint:
        """The setpoint ``t_s`` seconds into the mission (held at the last waypoint
        after its end, at the start before 0)."""
        if not t_s < self.duration_s or not self._t:
            p, v = self._end, (0.0, 0.0, 0.0)
        else:
            i = max(0, bisect.bisect_right(self._t, t_s) - 1)
            dt = max(0.0, t_s - self._t[i])
            a, v = self._p[i], self._v[i]
            p = (a[0] + v[0] * dt, a[1] + v[1] * dt, a[2] + v[2] * dt)
        return OuterSetpoint(
            HorizontalSetpoint((v[0], v[1]), (p[0], p[1])),
            VerticalSetpoint(-v[2], -p[2]),
        )

    def target_at(self, t_s: float) -> Vec3:
        """The waypoint the setpoint is flying to (or holding at) at ``t_s``, NED, m."""
        i = self.waypoints_reached(t_s)
        return self._targets[min(i, len(self._targets) - 1)]

    def waypoints_reached(self, t_s: float) -> int:
        """How many waypoints the setpoint has reached by ``t_s``."""
        return bisect.bisect_right(self.arrivals_s, t_s)
