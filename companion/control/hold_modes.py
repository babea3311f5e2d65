"""The altitude and position modes: sticks as climb rate and velocity, held when centred.

``companion run --mode altitude|position``, as the autopilot's own Altitude and
Position modes (PX4 ALTCTL and POSCTL, ArduCopter ALT_HOLD and LOITER) behave for
a pilot, flown by the model-free outer loops
(:class:`companion.control.outer.OuterController`, one set of gains for every
vehicle) on the autopilot's attitude and position estimates. What the sticks may
ask is the autopilot's own (:class:`~companion.control.stick_limits.StickLimits`,
read from its parameters):

* Throttle: a climb rate, held at mid-stick (:class:`~.stick_limits.ClimbLimits`).
* Roll and pitch, ``altitude``: angles, as in angle mode, up to the limits'
  ``tilt_max_deg`` (:func:`companion.control.angle_mode.stick_tilt_rad`).
* Roll and pitch, ``position``: one vector in the heading's frame (roll right
  flies right; the pitch stick above centre, nose up as in rates mode, flies
  backwards), shaped into a velocity setpoint and its slope as the stack shapes
  it (:class:`~.stick_limits.HorizontalShaper`).
* Yaw: a yaw rate (the stick's rate curve); no heading is held.

Smoothing, and where the hold locks
-----------------------------------
The loops never fly a stick's step: the climb setpoint follows the stick's at
the limits' rise and fall, the velocity setpoint follows the stack's shaper, and
the slopes are flown as feedforward. A hold locks where the vehicle is when the
setpoint has come back to zero with the stick centred, not where the stick came
back: released at speed, the vehicle brakes as the stack would and stops, rather
than being pulled back to the point of release. Leaving a hold, the setpoint
starts from the reference the hold was flying, so the stick moves it without a
jump.

Taking over
-----------
:meth:`HoldMode.reset` (an engagement) starts from the vehicle's state, as PX4's
switch into Position mode does: the collective the caller gives (what the
autopilot flew), the climb and velocity setpoints at the estimated velocity
(bounded to what the sticks can ask; below :data:`TAKE_OVER_STILL_M_S`, zero), the
tilt it flies (the horizontal loop's
estimate starts from the disturbance that tilt was holding), the altitude and
position held where the vehicle is once they are back at zero. A vehicle
handed over while moving brakes along them; one handed over in a hover holds
where it is.

On the ground (the autopilot's landed state) only the vertical loop runs, on the
throttle's climb rate and never an altitude to hold: the vehicle lifts off when
the climb asked raises the collective enough, and sits at the lowest collective
with the throttle down. The attitude and horizontal loops are held reset and ask
for no rates (a vehicle on its legs cannot turn).

Pure: no I/O, no clock. Stale or invalid estimates are the caller's (the app's
failsafes).
"""

from __future__ import annotations

import math
from typing import NamedTuple

from companion.control.angle_mode import stick_tilt_rad
from companion.control.attitude import AttitudeSetpoint
from companion.control.horizontal import HorizontalSetpoint, tilt_of_attitude
from companion.control.outer import (
    DEFAULT_OUTER_GAINS,
    OuterController,
    OuterGains,
    OuterLaw,
    OuterSetpoint,
)
from companion.control.quaternion import Quat, Vec3, normalise_or_none, yaw_rad
from companion.control.stick_limits import StickLimits, expo_past_deadband
from companion.control.vertical import VerticalSetpoint

__all__ = [
    "TAKEOFF_CLIMB_M_S",
    "TAKE_OVER_STILL_M_S",
    "HoldCommand",
    "HoldMode",
    "stick_ne",
]

_ZERO3: Vec3 = (0.0, 0.0, 0.0)


def stick_ne(
    x_roll: float, x_pitch: float, heading_rad: float, deadband: float, expo: float
) -> tuple[float, float] | None:
    """The roll and pitch sticks as one deflection in north and east (length at
    most 1, past ``deadband`` on its length and through ``expo``) at
    ``heading_rad``; None when centred, and for non-finite input."""
    if not math.isfinite(x_roll + x_pitch + heading_rad):
        return None
    n = math.hypot(x_roll, x_pitch)
    a = expo_past_deadband(min(n, 1.0), deadband, expo)
    if a == 0.0:
        return None
    forward, right = -x_pitch * a / n, x_roll * a / n
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    return (forward * c - right * s, forward * s + right * c)


TAKE_OVER_STILL_M_S = 0.3
"""Taking over, a horizontal speed or a climb rate below this is a vehicle holding
still (an autopilot's hover wanders about 0.1 m/s): it is held where it is at once,
as PX4 locks its Position mode on a zero setpoint from its own hold."""

TAKEOFF_CLIMB_M_S = 1.0
"""The climb asked on the ground when a given setpoint is above (:meth:`HoldMode.fly`)."""


class HoldCommand(NamedTuple):
    """One sample's output: what the rate loop flies."""

    rate_ref_frd_rad_s: Vec3
    """Body-rate reference, rad/s."""
    thrust: float
    """Collective, normalised (the vertical loop's, tilt-compensated)."""


class HoldMode:
    """Sticks and the estimates to the rate loop's reference and collective
    (module docstring).

    Parameters
    ----------
    position
        True: position mode (the sticks are a velocity); False: altitude mode (angles).
    limits
        What the sticks may ask: the stack's (:mod:`companion.stacks`).
    gains
        The outer loops' (:data:`DEFAULT_OUTER_GAINS`: one set for every vehicle).
    outer
        Other outer loops to fly instead of :class:`OuterController` with
        ``gains`` (the lab's baseline, PX4's default cascade).
    """

    def __init__(
        self,
        *,
        position: bool,
        limits: StickLimits,
        gains: OuterGains = DEFAULT_OUTER_GAINS,
        outer: OuterLaw | None = None,
    ) -> None:
        self.position = position
        self.limits = limits
        self.outer: OuterLaw = OuterController(gains) if outer is None else outer
        self.max_tilt_rad = math.radians(limits.tilt_max_deg)
        self.setpoint = OuterSetpoint()
        """The last setpoint flown."""
        self.attitude_setpoint: AttitudeSetpoint | None = None
        """What the attitude loop was last asked (None: on the ground, not flown)."""
        self.tilt_limited = False
        """Whether the last sample's tilt was clamped (position mode: its max, or
        altitude first)."""
        self._up_hold: float | None = None
        self._ne_hold: tuple[float, float] | None = None
        self._climb_sp = 0.0
        self._shaper = limits.horizontal.shaper()
        self._ramps_from_estimate = True

    @property
    def on_ground(self) -> bool:
        return self.outer.vertical.on_ground

    @on_ground.setter
    def on_ground(self, value: bool) -> None:
        self.outer.vertical.on_ground = value

    def reset(
        self,
        thrust: float | None = None,
        hover_thrust: float | None = None,
        q_wxyz: Quat | None = None,
    ) -> None:
        """Forget the loops' state and the holds (an engagement: module docstring).

        Parameters
        ----------
        thrust
            The collective flying as the loops take over (``None``: the hover estimate).
        hover_thrust
            A prior for the hover-thrust estimate (the autopilot's own; ``None``:
            the vertical loop's initial value).
        q_wxyz
            The attitude flying as they take over (``None``: level): in position
            mode the horizontal loop starts holding its tilt, as what holds the
            vehicle there (a wind, a trim) is still there.
        """
        tilt = (0.0, 0.0) if q_wxyz is None or not self.position else tilt_of_attitude(q_wxyz)
        self.outer.reset(thrust=thrust, hover_thrust=hover_thrust, tilt_ne=tilt, at_rest=True)
        self.attitude_setpoint = None
        self._up_hold = None
        self._ne_hold = None
        self._climb_sp = 0.0
        self._shaper.reset((0.0, 0.0))
        self._ramps_from_estimate = True

    def _start_ramps(self, velocity_ned_m_s: Vec3) -> None:
        """The setpoints from the estimated velocity (the first sample after a reset
        or a mission), bounded to what the sticks can ask; below
        :data:`TAKE_OVER_STILL_M_S`, zero (held at once); non-finite: left as they are."""
        vn, ve, vd = velocity_ned_m_s
        climb = self.limits.climb
        if math.isfinite(vd):
            c = min(max(-vd, -climb.down_max_m_s), climb.up_max_m_s)
            self._climb_sp = c if abs(c) >= TAKE_OVER_STILL_M_S else 0.0
        if math.isfinite(vn + ve):
            speed = math.hypot(vn, ve)
            v_max = self.limits.horizontal.full_stick_speed_m_s
            k = 0.0 if speed < TAKE_OVER_STILL_M_S else min(1.0, v_max / speed)
            self._shaper.reset((vn * k, ve * k))

    def _climb_setpoint(self, dt: float, throttle: float, up_now: float) -> VerticalSetpoint:
        """The throttle's climb, smoothed, and the altitude hold (module docstring);
        ``dt`` 0 for no step."""
        climb = self.limits.climb
        stick = climb.climb_m_s(throttle)
        if stick is not None and self._up_hold is not None:
            ref = self.outer.vertical.climb_ref_m_s  # leave the hold smoothly
            self._climb_sp = ref if math.isfinite(ref) else 0.0
        prev = self._climb_sp
        c = self._climb_sp = climb.slew(prev, 0.0 if stick is None else stick, dt)
        if stick is not None or self.on_ground or not math.isfinite(up_now):
            self._up_hold = None
        elif self._up_hold is None and c == 0.0:
            self._up_hold = up_now  # centred, and the ramp has come back: hold here
        if self._up_hold is not None:
            return VerticalSetpoint(0.0, self._up_hold)
        return VerticalSetpoint(c, None, (c - prev) / dt if dt > 0.0 else 0.0)

    def _velocity_setpoint(
        self,
        dt: float,
        deflection: tuple[float, float, float],
        heading: float,
        ne_now: tuple[float, float],
    ) -> HorizontalSetpoint:
        """The sticks' velocity, shaped as the stack shapes it, and the position
        hold (module docstring); ``dt`` 0 for no step."""
        h = self.limits.horizontal
        stick = stick_ne(deflection[0], deflection[1], heading, h.deadband, h.expo)
        shaper = self._shaper
        if stick is not None and self._ne_hold is not None:
            ref = self.outer.horizontal.velocity_ref_ne_m_s  # leave the hold smoothly
            shaper.reset(ref if math.isfinite(ref[0] + ref[1]) else (0.0, 0.0))
        v = shaper.update(dt, (0.0, 0.0) if stick is None else stick)
        if stick is not None or not math.isfinite(ne_now[0] + ne_now[1]):
            self._ne_hold = None
        elif self._ne_hold is None and v == (0.0, 0.0):
            self._ne_hold = ne_now  # centred, and the setpoint has come back: hold here
        if self._ne_hold is not None:
            return HorizontalSetpoint((0.0, 0.0), self._ne_hold)
        return HorizontalSetpoint(v, None, shaper.accel_ne_m_s2 if dt > 0.0 else (0.0, 0.0))

    def update(
        self,
        dt_s: float,
        q_wxyz: Quat,
        gyro_frd_rad_s: Vec3,
        position_ned_m: Vec3,
        velocity_ned_m_s: Vec3,
        deflection: tuple[float, float, float],
        throttle: float,
        yaw_rate_rad_s: float,
        *,
        applied_thrust: float | None = None,
        rate_saturated: tuple[bool, bool, bool] | None = None,
    ) -> HoldCommand:
        """One sample (parameters as :meth:`OuterController.update`; ``deflection``,
        ``throttle`` and ``yaw_rate_rad_s``: the pilot's sticks)."""
        outer = self.outer
        yaw_rate = yaw_rate_rad_s if math.isfinite(yaw_rate_rad_s) else 0.0
        if self._ramps_from_estimate:
            self._start_ramps(velocity_ned_m_s)
            self._ramps_from_estimate = False
        dt = dt_s if math.isfinite(dt_s) and dt_s > 0.0 else 0.0
        vsp = self._climb_setpoint(dt, throttle, -position_ned_m[2])
        q = normalise_or_none(q_wxyz)
        cos_tilt = 1.0 if q is None else 1.0 - 2.0 * (q[1] * q[1] + q[2] * q[2])

        if self.on_ground or not self.position:
            self.tilt_limited = False
            self._ne_hold = None
            self._shaper.reset((0.0, 0.0))
            thrust = outer.vertical.update(
                dt_s, position_ned_m[2], velocity_ned_m_s[2], vsp, cos_tilt=cos_tilt,
                applied=applied_thrust,
            )  # fmt: skip
            if self.on_ground:
                outer.attitude.reset()
                outer.horizontal.reset()
                self.setpoint = OuterSetpoint(vertical=vsp)
                self.attitude_setpoint = None
                return HoldCommand(_ZERO3, thrust)
            roll, pitch = stick_tilt_rad(deflection[0], deflection[1], self.max_tilt_rad)
            att_sp = self.attitude_setpoint = AttitudeSetpoint(roll, pitch, None, yaw_rate)
            self.setpoint = OuterSetpoint(vertical=vsp, yaw_rate_rad_s=yaw_rate)
            outer.note_rate_saturation(dt_s, rate_saturated)
            rate_ref = outer.attitude.update(dt_s, q_wxyz, gyro_frd_rad_s, att_sp)
            return HoldCommand(rate_ref, thrust)

        heading = yaw_rad(q) if q is not None else math.nan
        hsp = self._velocity_setpoint(
            dt, deflection, heading, (position_ned_m[0], position_ned_m[1])
        )
        self.setpoint = OuterSetpoint(hsp, vsp, None, yaw_rate)
        o = outer.update(
            dt_s, q_wxyz, gyro_frd_rad_s, position_ned_m, velocity_ned_m_s, self.setpoint,
            applied_thrust=applied_thrust, rate_saturated=rate_saturated,
        )  # fmt: skip
        self.attitude_setpoint = o.attitude_setpoint
        self.tilt_limited = o.tilt_limited
        return HoldCommand(o.rate_ref_frd_rad_s, o.thrust)

    def fly(
        self,
        dt_s: float,
        q_wxyz: Quat,
        gyro_frd_rad_s: Vec3,
        position_ned_m: Vec3,
        velocity_ned_m_s: Vec3,
        setpoint: OuterSetpoint,
        *,
        take_off: bool,
        applied_thrust: float | None = None,
        rate_saturated: tuple[bool, bool, bool] | None = None,
    ) -> HoldCommand:
        """Fly a given setpoint (a mission's) instead of the sticks.

        On the ground only the vertical loop runs: a climb of
        :data:`TAKEOFF_CLIMB_M_S` when ``take_off`` (the caller's: the waypoint
        flown to is above), else the lowest collective (a descent asked)."""
        outer = self.outer
        self._up_hold = self._ne_hold = None
        self._ramps_from_estimate = True  # sticks after a mission start from the estimate
        if self.on_ground:
            down = -self.limits.climb.down_max_m_s
            vsp = VerticalSetpoint(TAKEOFF_CLIMB_M_S if take_off else down)
            q = normalise_or_none(q_wxyz)
            cos_tilt = 1.0 if q is None else 1.0 - 2.0 * (q[1] * q[1] + q[2] * q[2])
            thrust = outer.vertical.update(
                dt_s, position_ned_m[2], velocity_ned_m_s[2], vsp, cos_tilt=cos_tilt,
                applied=applied_thrust,
            )  # fmt: skip
            outer.attitude.reset()
            outer.horizontal.reset()
            self.setpoint = OuterSetpoint(vertical=vsp)
            self.attitude_setpoint = None
            self.tilt_limited = False
            return HoldCommand(_ZERO3, thrust)
        self.setpoint = setpoint
        o = outer.update(
            dt_s, q_wxyz, gyro_frd_rad_s, position_ned_m, velocity_ned_m_s, setpoint,
            applied_thrust=applied_thrust, rate_saturated=rate_saturated,
        )  # fmt: skip
        self.attitude_setpoint = o.attitude_setpoint
        self.tilt_limited = o.tilt_limited
        return HoldCommand(o.rate_ref_frd_rad_s, o.thrust)
