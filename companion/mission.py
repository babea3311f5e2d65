r"""A mission: waypoints flown in position mode (``companion run --mode position --mission FILE``).

The file (YAML)::

    speed_m_s: 2.0                 # default speed along a leg, m/s
    accel_m_s2: 2.5                # speeding up and slowing down on a leg, m/s^2 (optional)
    jerk_m_s3: 1.0                 # how fast that acceleration comes and goes, m/s^3 (optional)
    waypoints:                     # from where the mission starts: north, east, up (m)
      - {north_m: 0, east_m: 0, up_m: 5, hold_s: 2}
      - {north_m: 10, east_m: 0, up_m: 5}
      - {north_m: 10, east_m: 10, up_m: 8, speed_m_s: 3}

Positions are relative to where the vehicle is when the mission starts (its
position estimate as it engages), so a file flies the same anywhere. The first
leg goes from there to the first waypoint.

The path (:class:`MissionPath`) moves the position setpoint along each leg in a
straight line, the velocity and acceleration as feedforward: from rest up to the
leg's speed, on at that speed, and down to rest at the waypoint, as the
autopilots' own missions slow for a corner. The acceleration is limited to
``accel_m_s2`` and comes and goes at ``jerk_m_s3`` (an S-curve, as both
autopilots' missions shape theirs): a mission starts without a jolt. Where the
file does not give them, they are the autopilot's own mission's, read from it
(:class:`~companion.control.stick_limits.MissionLimits`: PX4's ``MPC_ACC_HOR``
and ``MPC_JERK_AUTO``, 3 m/s^2 and 4 m/s^3 by default; ArduCopter's
``WPNAV_ACCEL`` and ``WPNAV_JERK``, 2.5 m/s^2 and 1 m/s^3). A leg too short to
reach its speed peaks lower; ``jerk_m_s3: null`` steps the acceleration (a leg
of length :math:`L` at speed :math:`v` then takes :math:`L/v + v/a`; with the
jerk :math:`j`, :math:`a/j` longer). The setpoint
holds at a waypoint for its ``hold_s``; a climb and a descent are no faster than
the position mode's stick limits (the autopilot's: PX4 3 and 1.5 m/s by default,
ArduCopter 2.5 m/s), the leg slower if need be. After the last waypoint the
setpoint stays there: the vehicle holds until the pilot hands back (the engage
switch, as any run). The clock of the path is the caller's (the app runs it only
while the vehicle is in the air).

No I/O beyond :func:`load_mission`; no clock.
"""

from __future__ import annotations

import bisect
import math
from pathlib import Path
from typing import Annotated, Protocol

from pydantic import Field

from companion.control.horizontal import DEFAULT_HORIZONTAL_GAINS, HorizontalSetpoint
from companion.control.outer import OuterSetpoint
from companion.control.stick_limits import StickLimits
from companion.control.vertical import VerticalSetpoint
from companion.schema import StrictModel, load_yaml_model

__all__ = ["FlightPlan", "Mission", "MissionPath", "PlannedPath", "Waypoint", "load_mission"]

MAX_RANGE_M = 5000.0
"""How far from the start a waypoint may be, per axis."""
MAX_WAYPOINTS = 1000
MAX_SPEED_M_S = DEFAULT_HORIZONTAL_GAINS.speed_max_m_s
"""A leg's speed at most the horizontal loop's bound (12 m/s): a faster leg would
leave the vehicle behind its setpoint."""

MAX_ACCEL_M_S2 = 10.0
"""A leg's acceleration at most about 45 deg of tilt."""
MAX_JERK_M_S3 = 100.0

Vec3 = tuple[float, float, float]


class PlannedPath(Protocol):
    """A plan as flown from where an engagement started: the setpoint against the
    plan's own clock (the caller's: the app runs it while the vehicle is in the air)."""

    duration_s: float
    """When the plan ends; the setpoint stays where it is after."""

    def at(self, t_s: float) -> OuterSetpoint:
        """The setpoint ``t_s`` seconds into the plan."""
        ...

    def target_at(self, t_s: float) -> Vec3:
        """The waypoint the setpoint is flying to (or holding at), NED, m: above the
        vehicle on its legs, it takes off."""
        ...

    def waypoints_reached(self, t_s: float) -> int:
        """How many of the plan's waypoints the setpoint has reached by ``t_s``."""
        ...

    def summary(self) -> str:
        """The path in a line (the ``mission_started`` event)."""
        ...


class FlightPlan(Protocol):
    """What the position mode flies instead of the sticks: a :class:`Mission`, or
    the lab's scripted setpoints (:mod:`sitl.lab.outer_flight`)."""

    @property
    def n_waypoints(self) -> int: ...

    def path(self, origin_ned_m: Vec3, limits: StickLimits) -> PlannedPath:
        """The plan flown from ``origin_ned_m`` within the stack's ``limits``."""
        ...


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
    accel_m_s2: Annotated[float, Field(gt=0.0, le=MAX_ACCEL_M_S2)] | None = Field(
        None,
        description="speeding up from and slowing down to rest at each waypoint, m/s^2; "
        "absent: the autopilot's own missions'",
    )
    jerk_m_s3: Annotated[float, Field(ge=0.1, le=MAX_JERK_M_S3)] | None = Field(
        None,
        description="how fast the acceleration comes and goes, m/s^3; absent: the "
        "autopilot's own missions'; null: at once",
    )
    waypoints: Annotated[list[Waypoint], Field(min_length=1, max_length=MAX_WAYPOINTS)]

    @property
    def n_waypoints(self) -> int:
        return len(self.waypoints)

    def path(self, origin_ned_m: Vec3, limits: StickLimits) -> MissionPath:
        return MissionPath(self, origin_ned_m, limits)


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
    limits
        The stack's: no leg climbs or descends faster than its sticks may
        (``climb``); its own missions' acceleration and jerk (``mission``) where
        the file gives none.
    """

    def __init__(self, mission: Mission, origin_ned_m: Vec3, limits: StickLimits) -> None:
        o = origin_ned_m
        points = [o] + [
            (o[0] + w.north_m, o[1] + w.east_m, o[2] - w.up_m) for w in mission.waypoints
        ]
        climb = limits.climb
        accel = limits.mission.accel_m_s2 if mission.accel_m_s2 is None else mission.accel_m_s2
        given = "jerk_m_s3" in mission.model_fields_set  # null, given: stepped
        jerk = mission.jerk_m_s3 if given else limits.mission.jerk_m_s3
        self.accel_m_s2 = accel
        """The acceleration flown (the file's, or the stack's), m/s^2."""
        self.jerk_m_s3 = jerk
        """The jerk flown (the file's, the stack's, or None: stepped), m/s^3."""
        self._legs: list[_Leg] = []
        """In time order; a hold at a waypoint is a leg of length 0."""
        self.arrivals_s: list[float] = []
        """When the setpoint reaches each waypoint, s from the start."""
        t = 0.0
        for a, b, w in zip(points, points[1:], mission.waypoints, strict=False):
            d = (b[0] - a[0], b[1] - a[1], b[2] - a[2])
            length = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
            if length > 0.0:
                speed = w.speed_m_s if w.speed_m_s is not None else mission.speed_m_s
                up = -d[2]
                # The climb and descent limits slow the whole leg.
                vertical = up / climb.up_max_m_s if up > 0.0 else -up / climb.down_max_m_s
                speed = min(speed, length / vertical) if vertical > 0.0 else speed
                unit = (d[0] / length, d[1] / length, d[2] / length)
                leg = _Leg(t, a, unit, length, speed, accel, jerk)
                self._legs.append(leg)
                t += leg.duration_s
            self.arrivals_s.append(t)
            if w.hold_s > 0.0:
                self._legs.append(_Leg(t, b, (0.0, 0.0, 0.0), 0.0, 1.0, accel, None, w.hold_s))
                t += w.hold_s
        self._starts = [leg.t_start_s for leg in self._legs]
        self._end = points[-1]
        self._targets = points[1:]
        self.duration_s = t
        """When the last waypoint's hold ends; the setpoint stays there after."""

    def at(self, t_s: float) -> OuterSetpoint:
        """The setpoint ``t_s`` seconds into the mission (held at the last waypoint
        after its end, at the start before 0)."""
        if not t_s < self.duration_s or not self._legs:
            p, v, acc = self._end, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
        else:
            i = max(0, bisect.bisect_right(self._starts, t_s) - 1)
            p, v, acc = self._legs[i].at(t_s)
        return OuterSetpoint(
            HorizontalSetpoint((v[0], v[1]), (p[0], p[1]), (acc[0], acc[1])),
            VerticalSetpoint(-v[2], -p[2], -acc[2]),
        )

    def summary(self) -> str:
        jerk = "none (stepped)" if self.jerk_m_s3 is None else f"{self.jerk_m_s3:g} m/s^3"
        return f"{self.duration_s:.1f} s, accelerating at {self.accel_m_s2:g} m/s^2, jerk {jerk}"

    def target_at(self, t_s: float) -> Vec3:
        """The waypoint the setpoint is flying to (or holding at) at ``t_s``, NED, m."""
        i = self.waypoints_reached(t_s)
        return self._targets[min(i, len(self._targets) - 1)]

    def waypoints_reached(self, t_s: float) -> int:
        """How many waypoints the setpoint has reached by ``t_s``."""
        return bisect.bisect_right(self.arrivals_s, t_s)


class _Leg:
    r"""A straight leg from rest to rest: from ``start`` along ``unit`` for
    ``length_m``, speeding up to ``speed_m_s`` with the acceleration at most
    ``accel_m_s2``, reached and left at ``jerk_m_s3`` (None: at once), and
    slowing down the same way (module docstring). The speed-up is symmetric about
    half the speed, so it covers :math:`v T / 2` in its time :math:`T`; a leg too
    short for both at ``speed_m_s`` peaks at the speed whose two ramps fill it. A
    hold is a leg of length 0 lasting ``hold_s``."""

    def __init__(
        self, t_start_s: float, start: Vec3, unit: Vec3, length_m: float, speed_m_s: float,
        accel_m_s2: float, jerk_m_s3: float | None, hold_s: float = 0.0,
    ) -> None:  # fmt: skip
        self.t_start_s = t_start_s
        self.start, self.unit, self.length_m = start, unit, length_m
        a, j = accel_m_s2, (math.inf if jerk_m_s3 is None else jerk_m_s3)
        v = speed_m_s
        if v * _ramp_s(v, a, j) > length_m:  # both ramps at this speed do not fit
            v = _peak_for(length_m, a, j)
        self.peak_m_s = v
        self.ramp = _Ramp(v, a, j)
        self.ramp_s = self.ramp.duration_s
        cruise_s = (length_m - v * self.ramp_s) / v if length_m > 0.0 else 0.0
        self.duration_s = hold_s if length_m == 0.0 else 2.0 * self.ramp_s + max(0.0, cruise_s)

    def at(self, t_s: float) -> tuple[Vec3, Vec3, Vec3]:
        """Position, velocity and acceleration (NED) ``t_s`` into the mission."""
        if self.length_m == 0.0:
            return self.start, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
        tau = min(max(0.0, t_s - self.t_start_s), self.duration_s)
        v = self.peak_m_s
        left = self.duration_s - tau
        if tau < self.ramp_s:
            s, sd, sdd = self.ramp.at(tau)
        elif left < self.ramp_s:
            s, sd, sdd = self.ramp.at(left)
            s, sdd = self.length_m - s, -sdd
        else:
            s, sd, sdd = 0.5 * v * self.ramp_s + v * (tau - self.ramp_s), v, 0.0
        u, o = self.unit, self.start
        return (
            (o[0] + s * u[0], o[1] + s * u[1], o[2] + s * u[2]),
            (sd * u[0], sd * u[1], sd * u[2]),
            (sdd * u[0], sdd * u[1], sdd * u[2]),
        )


def _ramp_s(v: float, a: float, j: float) -> float:
    r"""How long speeding up from rest to ``v`` takes, acceleration at most ``a``,
    jerk at most ``j``: :math:`v/a + a/j`, or :math:`2\sqrt{v/j}` when ``a`` is
    not reached."""
    if v >= a * a / j:
        return v / a + a / j
    return 2.0 * math.sqrt(v / j)


def _peak_for(length_m: float, a: float, j: float) -> float:
    r"""The speed whose speed-up and slow-down together cover ``length_m``
    (:math:`v\,T(v) = L`)."""
    if math.isinf(j):
        return math.sqrt(a * length_m)
    v = 0.5 * a * (math.sqrt(a * a / (j * j) + 4.0 * length_m / a) - a / j)
    if v >= a * a / j:
        return v
    return float((0.5 * length_m * math.sqrt(j)) ** (2.0 / 3.0))  # a never reached


class _Ramp:
    """Speeding up from rest to ``v``: jerk ``j`` until the acceleration reaches its
    peak (``a``, or less when ``v`` is small), that acceleration, then jerk ``-j``
    down to none at ``v``; :meth:`at` gives distance, speed and acceleration."""

    def __init__(self, v: float, a: float, j: float) -> None:
        if math.isinf(j):
            peak, t_j = a, 0.0
        elif v >= a * a / j:
            peak, t_j = a, a / j
        else:
            peak = math.sqrt(v * j)
            t_j = peak / j
        self.peak, self.t_j = peak, t_j
        self.jerk = 0.0 if t_j == 0.0 else peak / t_j
        self.t_a = v / peak - t_j
        self.duration_s = 2.0 * t_j + self.t_a
        j_ = self.jerk
        self.v1 = 0.5 * j_ * t_j * t_j
        self.s1 = j_ * t_j**3 / 6.0
        self.v2 = self.v1 + peak * self.t_a
        self.s2 = self.s1 + self.v1 * self.t_a + 0.5 * peak * self.t_a * self.t_a

    def at(self, t: float) -> tuple[float, float, float]:
        j, peak, t_j = self.jerk, self.peak, self.t_j
        if t < t_j:
            return j * t**3 / 6.0, 0.5 * j * t * t, j * t
        u = t - t_j
        if u < self.t_a:
            return self.s1 + self.v1 * u + 0.5 * peak * u * u, self.v1 + peak * u, peak
        u -= self.t_a
        return (
            self.s2 + self.v2 * u + 0.5 * peak * u * u - j * u**3 / 6.0,
            self.v2 + peak * u - 0.5 * j * u * u,
            peak - j * u,
        )
