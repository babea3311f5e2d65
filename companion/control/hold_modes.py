"""The altitude and position modes: sticks as climb rate and velocity, held when centred.

``companion run --mode altitude|position``, as PX4's Altitude and Position modes
behave for a pilot, flown by the model-free outer loops
(:class:`companion.control.outer.OuterController`, one set of gains for every
vehicle) on the autopilot's attitude and position estimates.

Sticks (PX4's defaults, 1.14)
-----------------------------
* Throttle: a climb rate. The stick's deflection from centre,
  :math:`x_t = 2 s - 1`, past a deadband of ``MPC_HOLD_DZ`` (0.1) and rescaled,
  times ``MPC_Z_VEL_MAX_UP`` (3 m/s) up or ``MPC_Z_VEL_MAX_DN`` (1.5 m/s) down.
  Inside the deadband the altitude where the stick came back is held.
* Roll and pitch, ``altitude``: angles, as in angle mode
  (:func:`companion.control.angle_mode.stick_tilt_rad`).
* Roll and pitch, ``position``: a horizontal velocity in the heading's frame, the
  two deflections one vector, past the deadband on its length and rescaled,
  times ``MPC_VEL_MANUAL`` (10 m/s): roll right flies right; the pitch stick
  above centre (nose up, as in rates mode) flies backwards. Inside the deadband
  the position where the sticks came back is held.
* Yaw: a yaw rate (the stick's rate curve); no heading is held.

Smoothing, and where the hold locks
-----------------------------------
The loops never fly a stick's step. The climb-rate setpoint follows the stick's
climb at most ``MPC_ACC_UP_MAX`` (4 m/s^2) faster upwards and
``MPC_ACC_DOWN_MAX`` (3 m/s^2) downwards; the horizontal velocity setpoint follows
the sticks' velocity, as one vector, at most ``MPC_ACC_HOR_MAX`` (5 m/s^2, PX4's
limit for its smoothed-velocity Position mode, accelerating and braking). The
slope is flown as the acceleration feedforward. Slammed, full stick reaches 10 m/s
in 2 s, and the tilt asked is the ramp's 5 m/s^2 with the drag and the loops'
corrections (36 deg at most on the tests' plant), not the 45 deg limit at once.

A hold locks where the vehicle is when the smoothed setpoint has come back to
zero with the stick centred, not where the stick came back: released at speed,
the vehicle brakes along the ramp and stops, rather than being pulled back to
the point of release. Leaving a hold, the ramp starts from the reference the
hold was flying, so the stick moves the setpoint without a jump. After
:meth:`HoldMode.reset` (an engagement) the ramps start from the estimated
velocity, bounded to what the sticks can ask: a vehicle handed over while moving
brakes along them.

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

from companion.control.angle_mode import MAX_TILT_DEG, stick_tilt_rad
from companion.control.attitude import AttitudeSetpoint
from companion.control.horizontal import HorizontalSetpoint
from companion.control.outer import DEFAULT_OUTER_GAINS, OuterController, OuterGains, OuterSetpoint
from companion.control.quaternion import Quat, Vec3, normalise_or_none, yaw_rad
from companion.control.vertical import VerticalSetpoint

__all__ = [
    "ACCEL_DOWN_MAX_M_S2",
    "ACCEL_HORIZONTAL_MAX_M_S2",
    "ACCEL_UP_MAX_M_S2",
    "CLIMB_MAX_DOWN_M_S",
    "CLIMB_MAX_UP_M_S",
    "HOLD_DEADBAND",
    "TAKEOFF_CLIMB_M_S",
    "VELOCITY_MAX_M_S",
    "HoldCommand",
    "HoldMode",
    "stick_climb_m_s",
    "stick_velocity_ne_m_s",
]

HOLD_DEADBAND = 0.1
"""Share of the stick's travel around centre that holds (PX4 ``MPC_HOLD_DZ``)."""
CLIMB_MAX_UP_M_S = 3.0
"""Full throttle's climb rate, m/s (PX4 ``MPC_Z_VEL_MAX_UP``)."""
CLIMB_MAX_DOWN_M_S = 1.5
"""Zero throttle's descent rate, m/s (PX4 ``MPC_Z_VEL_MAX_DN``)."""
VELOCITY_MAX_M_S = 10.0
"""Full stick's horizontal speed, m/s (PX4 ``MPC_VEL_MANUAL``)."""
ACCEL_UP_MAX_M_S2 = 4.0
"""The climb setpoint's largest rise, m/s^2 (PX4 ``MPC_ACC_UP_MAX``)."""
ACCEL_DOWN_MAX_M_S2 = 3.0
"""The climb setpoint's largest fall, m/s^2 (PX4 ``MPC_ACC_DOWN_MAX``)."""
ACCEL_HORIZONTAL_MAX_M_S2 = 5.0
"""The horizontal velocity setpoint's largest change, m/s^2 (PX4 ``MPC_ACC_HOR_MAX``)."""

_ZERO3: Vec3 = (0.0, 0.0, 0.0)


def _past_deadband(x: float) -> float:
    """``x`` in [0, 1] less the deadband, rescaled to [0, 1]."""
    return 0.0 if x <= HOLD_DEADBAND else min(1.0, (x - HOLD_DEADBAND) / (1.0 - HOLD_DEADBAND))


def stick_climb_m_s(throttle: float) -> float | None:
    """The climb rate (m/s, up) for a throttle stick in [0, 1]; None inside the
    deadband around centre (hold), and for a non-finite stick."""
    if not math.isfinite(throttle):
        return None
    x = 2.0 * min(1.0, max(0.0, throttle)) - 1.0
    a = _past_deadband(abs(x))
    if a == 0.0:
        return None
    return a * CLIMB_MAX_UP_M_S if x > 0.0 else -a * CLIMB_MAX_DOWN_M_S


def stick_velocity_ne_m_s(
    x_roll: float, x_pitch: float, heading_rad: float
) -> tuple[float, float] | None:
    """The horizontal velocity (north, east; m/s) for the roll and pitch sticks at
    ``heading_rad``; None inside the deadband (hold), and for non-finite input."""
    if not math.isfinite(x_roll + x_pitch + heading_rad):
        return None
    n = math.hypot(x_roll, x_pitch)
    a = _past_deadband(n)
    if a == 0.0:
        return None
    speed = a * VELOCITY_MAX_M_S / n
    forward, right = -x_pitch * speed, x_roll * speed
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    return (forward * c - right * s, forward * s + right * c)


def slew_climb(current: float, target: float, dt_s: float) -> float:
    """``current`` moved toward ``target`` by at most :data:`ACCEL_UP_MAX_M_S2`
    (upwards) or :data:`ACCEL_DOWN_MAX_M_S2` (downwards) times ``dt_s``."""
    if target > current:
        return min(target, current + ACCEL_UP_MAX_M_S2 * dt_s)
    return max(target, current - ACCEL_DOWN_MAX_M_S2 * dt_s)


def slew_velocity(
    current: tuple[float, float], target: tuple[float, float], dt_s: float
) -> tuple[float, float]:
    """``current`` moved toward ``target`` along the difference, by at most
    :data:`ACCEL_HORIZONTAL_MAX_M_S2` times ``dt_s`` in length."""
    dn, de = target[0] - current[0], target[1] - current[1]
    step = ACCEL_HORIZONTAL_MAX_M_S2 * dt_s
    d = math.hypot(dn, de)
    if d <= step:
        return target
    k = step / d
    return (current[0] + dn * k, current[1] + de * k)


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
    gains
        The outer loops' (:data:`DEFAULT_OUTER_GAINS`: one set for every vehicle).
    """

    def __init__(self, *, position: bool, gains: OuterGains = DEFAULT_OUTER_GAINS) -> None:
        self.position = position
        self.outer = OuterController(gains)
        self.max_tilt_rad = math.radians(MAX_TILT_DEG)
        self.setpoint = OuterSetpoint()
        """The last setpoint flown."""
        self.attitude_setpoint: AttitudeSetpoint | None = None
        """What the attitude loop was last asked (None: on the ground, not flown)."""
        self._up_hold: float | None = None
        self._ne_hold: tuple[float, float] | None = None
        self._climb_sp = 0.0
        self._vel_sp: tuple[float, float] = (0.0, 0.0)
        self._ramps_from_estimate = True

    @property
    def on_ground(self) -> bool:
        return self.outer.vertical.on_ground

    @on_ground.setter
    def on_ground(self, value: bool) -> None:
        self.outer.vertical.on_ground = value

    def reset(self, thrust: float | None = None) -> None:
        """Forget the loops' state and the holds; ``thrust``: the collective flying
        as the loops take over (``None``: the hover estimate)."""
        self.outer.reset(thrust=thrust)
        self.attitude_setpoint = None
        self._up_hold = None
        self._ne_hold = None
        self._climb_sp = 0.0
        self._vel_sp = (0.0, 0.0)
        self._ramps_from_estimate = True

    def _start_ramps(self, velocity_ned_m_s: Vec3) -> None:
        """The ramps from the estimated velocity (the first sample after a reset or
        a mission), bounded to what the sticks can ask; non-finite: left as they are."""
        vn, ve, vd = velocity_ned_m_s
        if math.isfinite(vd):
            self._climb_sp = min(max(-vd, -CLIMB_MAX_DOWN_M_S), CLIMB_MAX_UP_M_S)
        if math.isfinite(vn + ve):
            k = min(1.0, VELOCITY_MAX_M_S / max(math.hypot(vn, ve), 1e-9))
            self._vel_sp = (vn * k, ve * k)

    def _climb_setpoint(self, dt: float, throttle: float, up_now: float) -> VerticalSetpoint:
        """The throttle's climb, smoothed, and the altitude hold (module docstring);
        ``dt`` 0 for no step."""
        stick = stick_climb_m_s(throttle)
        if stick is not None and self._up_hold is not None:
            ref = self.outer.vertical.climb_ref_m_s  # leave the hold smoothly
            self._climb_sp = ref if math.isfinite(ref) else 0.0
        prev = self._climb_sp
        c = self._climb_sp = slew_climb(prev, 0.0 if stick is None else stick, dt)
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
        """The sticks' velocity, smoothed, and the position hold (module docstring);
        ``dt`` 0 for no step."""
        stick = stick_velocity_ne_m_s(deflection[0], deflection[1], heading)
        if stick is not None and self._ne_hold is not None:
            ref = self.outer.horizontal.velocity_ref_ne_m_s  # leave the hold smoothly
            self._vel_sp = ref if math.isfinite(ref[0] + ref[1]) else (0.0, 0.0)
        prev = self._vel_sp
        v = self._vel_sp = slew_velocity(prev, (0.0, 0.0) if stick is None else stick, dt)
        if stick is not None or not math.isfinite(ne_now[0] + ne_now[1]):
            self._ne_hold = None
        elif self._ne_hold is None and v == (0.0, 0.0):
            self._ne_hold = ne_now  # centred, and the ramp has come back: hold here
        if self._ne_hold is not None:
            return HorizontalSetpoint((0.0, 0.0), self._ne_hold)
        acc = ((v[0] - prev[0]) / dt, (v[1] - prev[1]) / dt) if dt > 0.0 else (0.0, 0.0)
        return HorizontalSetpoint(v, None, acc)

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
            self._ne_hold = None
            self._vel_sp = (0.0, 0.0)
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
            vsp = VerticalSetpoint(TAKEOFF_CLIMB_M_S if take_off else -CLIMB_MAX_DOWN_M_S)
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
            return HoldCommand(_ZERO3, thrust)
        self.setpoint = setpoint
        o = outer.update(
            dt_s, q_wxyz, gyro_frd_rad_s, position_ned_m, velocity_ned_m_s, setpoint,
            applied_thrust=applied_thrust, rate_saturated=rate_saturated,
        )  # fmt: skip
        self.attitude_setpoint = o.attitude_setpoint
        return HoldCommand(o.rate_ref_frd_rad_s, o.thrust)
