"""The ArduPilot personality's control primitives: filter, attitude and rate control, motors.

Pure objects and functions after ArduCopter 4.5's own, written from its source
and independent of the companion's laws: ``LowPassFilter2p`` (:class:`GyroLowPass`),
``AC_AttitudeControl`` for body-rate input (:class:`AttitudeControl`: input
shaping, the attitude target, the square-root angle controller), ``AC_PID``
(:class:`ApRatePid`), ``AP_MotorsMatrix`` (:class:`MotorsMatrix`),
``AP_Motors_Thrust_Linearization`` and ``GCS_MAVLINK_Copter``'s
thrust-as-climb-rate; :class:`sitl.ardupilot.ArduCopter` runs them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from sitl.frames import (
    Quat,
    Vec3,
    axis_angle_to_quat,
    quat_conj,
    quat_mul,
    quat_rotate,
    quat_to_axis_angle,
)

if TYPE_CHECKING:
    from companion.profile import VehicleProfile

__all__ = [
    "ApAxisGains",
    "ApRatePid",
    "AttitudeControl",
    "AttitudeGains",
    "GyroLowPass",
    "MotorsMatrix",
    "MotorsOutput",
    "actuator_to_thrust",
    "climb_rate_from_thrust",
    "shape_rate",
    "sqrt_controller",
    "thrust_heading_error",
    "thrust_to_actuator",
]


def _lowpass_alpha(dt_s: float, cutoff_hz: float) -> float:
    """ArduPilot ``calc_lowpass_alpha_dt``: 1 (no filtering) when the cutoff is 0."""
    if cutoff_hz <= 0.0 or dt_s <= 0.0:
        return 1.0
    rc = 1.0 / (2.0 * math.pi * cutoff_hz)
    return dt_s / (dt_s + rc)


class GyroLowPass:
    r"""Three-axis 2nd-order Butterworth low-pass (ArduPilot ``LowPassFilter2p``).

    Coefficients for sample rate :math:`f_s` and cutoff :math:`f_c`, with
    :math:`\Omega = \tan(\pi f_c / f_s)` and :math:`c = 1 + \sqrt2\,\Omega + \Omega^2`:
    :math:`b_0 = b_2 = \Omega^2/c`, :math:`b_1 = 2 b_0`,
    :math:`a_1 = 2(\Omega^2 - 1)/c`, :math:`a_2 = (1 - \sqrt2\,\Omega + \Omega^2)/c`.
    A cutoff of 0 passes the signal through.
    """

    def __init__(self, cutoff_hz: float) -> None:
        self.cutoff_hz = float(cutoff_hz)
        self._fs_hz = 0.0
        self._coef = (1.0, 0.0, 0.0, 0.0, 0.0)
        self._d1 = [0.0, 0.0, 0.0]
        self._d2 = [0.0, 0.0, 0.0]
        self._primed = False

    def _design(self, fs_hz: float) -> None:
        self._fs_hz = fs_hz
        fc = self.cutoff_hz
        if fc <= 0.0 or fc >= 0.5 * fs_hz:
            self._coef = (1.0, 0.0, 0.0, 0.0, 0.0)
            return
        ohm = math.tan(math.pi * fc / fs_hz)
        c = 1.0 + 2.0 * math.cos(math.pi / 4.0) * ohm + ohm * ohm
        b0 = ohm * ohm / c
        a1 = 2.0 * (ohm * ohm - 1.0) / c
        a2 = (1.0 - 2.0 * math.cos(math.pi / 4.0) * ohm + ohm * ohm) / c
        self._coef = (b0, 2.0 * b0, b0, a1, a2)

    def apply(self, x: Sequence[float], dt_s: float) -> tuple[float, float, float]:
        """Filter one sample taken ``dt_s`` after the previous one."""
        fs = 1.0 / dt_s if dt_s > 0.0 else self._fs_hz
        if fs > 0.0 and (self._fs_hz <= 0.0 or abs(fs - self._fs_hz) > 0.1 * self._fs_hz):
            self._design(fs)
        b0, b1, b2, a1, a2 = self._coef
        if not self._primed:
            # Start at steady state on the first sample (no start-up transient).
            for i in range(3):
                d = x[i] / (1.0 + a1 + a2) if b1 else 0.0
                self._d1[i] = self._d2[i] = d
            self._primed = True
        out = [0.0, 0.0, 0.0]
        for i in range(3):
            d0 = x[i] - self._d1[i] * a1 - self._d2[i] * a2
            out[i] = d0 * b0 + self._d1[i] * b1 + self._d2[i] * b2 if b1 else x[i]
            self._d2[i] = self._d1[i]
            self._d1[i] = d0
        return (out[0], out[1], out[2])

    def reset(self) -> None:
        self._primed = False


@dataclass(frozen=True)
class ApAxisGains:
    """``AC_PID`` gains of one axis (ATC_RAT_{RLL,PIT,YAW}_*)."""

    kp: float
    ki: float
    kd: float
    kff: float = 0.0
    imax: float = 0.5
    filt_t_hz: float = 20.0
    filt_e_hz: float = 0.0
    filt_d_hz: float = 20.0


class ApRatePid:
    r"""Three-axis ArduPilot rate controller (``AC_PID::update_all``), a pure object.

    Per axis, at the loop period ``dt_s``:

    .. math::  T_f \leftarrow T_f + \alpha_T (T - T_f), \qquad
               e \leftarrow e + \alpha_E ((T_f - \omega) - e), \\
               \dot e_f \leftarrow \dot e_f + \alpha_D (\tfrac{e - e_{prev}}{dt} - \dot e_f), \\
               I \leftarrow \operatorname{clip}(I + K_I e\,dt, \pm I_{max}), \qquad
               u = K_P e + I + K_D \dot e_f + K_{FF} T_f

    (D on the error, as ArduPilot does: a target step kicks D through the FLTT
    filter). The integrator does not grow while ``limit`` says the output
    saturated in the direction of the error. Outputs are normalised torques.
    """

    def __init__(self, gains: Sequence[ApAxisGains]) -> None:
        self.gains = tuple(gains)
        self._target = [0.0, 0.0, 0.0]
        self._error = [0.0, 0.0, 0.0]
        self._deriv = [0.0, 0.0, 0.0]
        self._integ = [0.0, 0.0, 0.0]
        self._reset = True

    @property
    def integrator(self) -> tuple[float, float, float]:
        i = self._integ
        return (i[0], i[1], i[2])

    def reset(self) -> None:
        """Forget the filters and the integrator."""
        self._integ = [0.0, 0.0, 0.0]
        self._reset = True

    def reset_integrator(self) -> None:
        self._integ = [0.0, 0.0, 0.0]

    def update(
        self,
        dt_s: float,
        target_rad_s: Sequence[float],
        measured_rad_s: Sequence[float],
        limit: Sequence[bool] = (False, False, False),
    ) -> tuple[float, float, float]:
        out = [0.0, 0.0, 0.0]
        for i in range(3):
            g = self.gains[i]
            tgt = target_rad_s[i]
            meas = measured_rad_s[i]
            if self._reset:
                self._target[i] = tgt
                self._error[i] = tgt - meas
                self._deriv[i] = 0.0
            else:
                prev_err = self._error[i]
                self._target[i] += _lowpass_alpha(dt_s, g.filt_t_hz) * (tgt - self._target[i])
                err = self._target[i] - meas
                self._error[i] += _lowpass_alpha(dt_s, g.filt_e_hz) * (err - self._error[i])
                raw_d = (self._error[i] - prev_err) / dt_s
                self._deriv[i] += _lowpass_alpha(dt_s, g.filt_d_hz) * (raw_d - self._deriv[i])
            e = self._error[i]
            integ = self._integ[i]
            if g.ki > 0.0 and (not limit[i] or integ * e < 0.0):
                integ = min(g.imax, max(-g.imax, integ + e * g.ki * dt_s))
            self._integ[i] = integ
            out[i] = g.kp * e + integ + g.kd * self._deriv[i] + g.kff * self._target[i]
        self._reset = False
        return (out[0], out[1], out[2])


def climb_rate_from_thrust(thrust: float, speed_up_m_s: float, speed_dn_m_s: float) -> float:
    """SET_ATTITUDE_TARGET thrust as a climb-rate request (``GCS_MAVLINK_Copter``).

    Clipped to [0, 1]; 0.5 holds altitude; 1 climbs at ``speed_up_m_s``; 0
    descends at ``speed_dn_m_s``. Returns m/s, positive up.
    """
    t = min(1.0, max(0.0, thrust))
    if t == 0.5:
        return 0.0
    if t > 0.5:
        return (t - 0.5) * 2.0 * speed_up_m_s
    return -(0.5 - t) * 2.0 * speed_dn_m_s


def thrust_to_actuator(thrust: float, expo: float) -> float:
    """``AP_Motors_Thrust_Linearization::apply_thrust_curve_and_volt_scaling`` (no battery)."""
    t = min(1.0, max(0.0, thrust))
    if abs(expo) < 1e-6:
        return t
    return ((expo - 1.0) + math.sqrt((1.0 - expo) ** 2 + 4.0 * expo * t)) / (2.0 * expo)


def actuator_to_thrust(actuator: float, expo: float) -> float:
    """Inverse of :func:`thrust_to_actuator`: ``(1 - expo) a + expo a^2``."""
    a = min(1.0, max(0.0, actuator))
    return (1.0 - expo) * a + expo * a * a


# ---------------------------------------------------------------- attitude control

ACCEL_RP_CONTROLLER_MIN_RAD_S2 = math.radians(40.0)
ACCEL_RP_CONTROLLER_MAX_RAD_S2 = math.radians(720.0)
ACCEL_Y_CONTROLLER_MIN_RAD_S2 = math.radians(10.0)
ACCEL_Y_CONTROLLER_MAX_RAD_S2 = math.radians(120.0)
"""``AC_AttitudeControl.h``: bounds of the angle controller's acceleration limit
(half the axis's ``ATC_ACCEL_*_MAX``)."""
THRUST_ERROR_ANGLE_RAD = math.radians(30.0)
"""``AC_ATTITUDE_THRUST_ERROR_ANGLE``: past it the heading is corrected less, past
twice it not at all."""


def sqrt_controller(error: float, p: float, second_ord_lim: float, dt_s: float) -> float:
    """ArduPilot's square-root controller (``AP_Math/control.cpp``).

    Linear (``p * error``) within ``second_ord_lim / p**2`` of zero, beyond it the
    rate that stops at zero error with deceleration ``second_ord_lim``,
    ``sqrt(2 a (|e| - d/2))``; no overshoot within one step (``|e| / dt``).
    """
    if second_ord_lim <= 0.0:
        rate = error * p
    elif p == 0.0:
        rate = math.copysign(math.sqrt(2.0 * second_ord_lim * abs(error)), error)
    else:
        linear = second_ord_lim / (p * p)
        if error > linear:
            rate = math.sqrt(max(0.0, 2.0 * second_ord_lim * (error - 0.5 * linear)))
        elif error < -linear:
            rate = -math.sqrt(max(0.0, 2.0 * second_ord_lim * (-error - 0.5 * linear)))
        else:
            rate = error * p
    if dt_s > 0.0:
        bound = abs(error) / dt_s
        return min(max(rate, -bound), bound)
    return rate


def shape_rate(target: float, desired: float, accel_max: float, dt_s: float) -> float:
    """``AC_AttitudeControl::input_shaping_ang_vel`` without a time constant: slew
    ``target`` towards ``desired`` at ``accel_max`` (rad/s^2; 0: no limit)."""
    if accel_max > 0.0:
        step = accel_max * dt_s
        return min(max(desired, target - step), target + step)
    return desired


def thrust_heading_error(target: Quat, body: Quat, yaw_p: float) -> tuple[Vec3, float, Quat]:
    """``AC_AttitudeControl::thrust_heading_rotation_angles``: the attitude error.

    Returns the body-frame error vector (x, y: the tilt that brings the thrust
    vector onto the target's; z: the heading left after it), the angle between the
    two thrust vectors, and the target (moved towards the body when the heading
    error exceeds what the yaw angle controller's acceleration limit allows,
    ``ACCEL_Y_CONTROLLER_MAX / ATC_ANG_YAW_P``).
    """
    up = (0.0, 0.0, -1.0)
    t_thrust = quat_rotate(target, up)
    b_thrust = quat_rotate(body, up)
    cx = b_thrust[1] * t_thrust[2] - b_thrust[2] * t_thrust[1]
    cy = b_thrust[2] * t_thrust[0] - b_thrust[0] * t_thrust[2]
    cz = b_thrust[0] * t_thrust[1] - b_thrust[1] * t_thrust[0]
    dot = b_thrust[0] * t_thrust[0] + b_thrust[1] * t_thrust[1] + b_thrust[2] * t_thrust[2]
    angle = math.acos(min(1.0, max(-1.0, dot)))
    n = math.sqrt(cx * cx + cy * cy + cz * cz)
    axis_ned = up if n == 0.0 or angle == 0.0 else (cx / n, cy / n, cz / n)
    axis_body = quat_rotate(quat_conj(body), axis_ned)
    tilt_corr = axis_angle_to_quat(
        (axis_body[0] * angle, axis_body[1] * angle, axis_body[2] * angle)
    )
    rot = quat_to_axis_angle(tilt_corr)
    heading = quat_mul(quat_mul(quat_conj(tilt_corr), quat_conj(body)), target)
    err_z = quat_to_axis_angle(heading)[2]
    if yaw_p > 0.0:
        lim = ACCEL_Y_CONTROLLER_MAX_RAD_S2 / yaw_p
        if abs(err_z) > lim:
            err_z = min(max(_wrap_pi(err_z), -lim), lim)
            target = quat_mul(quat_mul(body, tilt_corr), axis_angle_to_quat((0.0, 0.0, err_z)))
    return (rot[0], rot[1], err_z), angle, target


def _wrap_pi(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@dataclass(frozen=True)
class AttitudeGains:
    """The ``ATC_*`` settings of the attitude controller.

    ``accel_max_rad_s2`` is ``ATC_ACCEL_R_MAX`` / ``_P_MAX`` / ``_Y_MAX``
    (110000, 110000, 27000 centideg/s^2 by default); ``angle_p`` ``ATC_ANG_RLL_P`` /
    ``PIT_P`` / ``YAW_P`` (4.5); ``rate_ff`` ``ATC_RATE_FF_ENAB`` (1: the input
    is shaped and integrated into the attitude target).
    """

    accel_max_rad_s2: Vec3 = (
        math.radians(1100.0),
        math.radians(1100.0),
        math.radians(270.0),
    )
    angle_p: Vec3 = (4.5, 4.5, 4.5)
    rate_ff: bool = True


class AttitudeControl:
    """ArduCopter's attitude controller for body-rate input (``AC_AttitudeControl``).

    ``input_rate_bf_roll_pitch_yaw`` (ArduCopter 4.5: GUIDED / GUIDED_NOGPS
    body rates through ``ModeGuided::angle_control_run``, and ACRO) does, each
    main-loop run of ``dt``:

    1. the target attitude turns by the last shaped rate times ``dt``
       (``attitude_controller_run_quat``, which integrates after use);
    2. the requested body rate is slewed at ``ATC_ACCEL_*_MAX`` into the shaped
       rate target (``input_shaping_ang_vel``; with ``ATC_RATE_FF_ENAB`` = 0 the
       target turns by the request and no rate is fed forward);
    3. the attitude error (``thrust_heading_rotation_angles``) goes through the
       square-root controller with ``ATC_ANG_*_P`` and half the axis's
       acceleration limit (clamped to 40..720 deg/s^2 roll/pitch, 10..120 yaw)
       (``update_ang_vel_target_from_att_error``);
    4. the rate target of the rate PIDs is that correction plus the shaped rate,
       rotated from the target frame into the body frame; past a 30 deg thrust
       error the heading is blended to the gyro, past 60 deg held at it.

    Sources: ArduPilot ``libraries/AC_AttitudeControl/AC_AttitudeControl.cpp``
    (``input_rate_bf_roll_pitch_yaw``, ``input_shaping_ang_vel``,
    ``attitude_controller_run_quat``, ``thrust_heading_rotation_angles``,
    ``update_ang_vel_target_from_att_error``), ``AC_AttitudeControl_Multi.h``
    (defaults), ``ArduCopter/mode_guided.cpp`` (``angle_control_run``), tag
    Copter-4.5.x. The rate time constant ``_rate_rp_tc`` / ``_rate_y_tc`` is 0 here:
    only ACRO sets one.
    """

    def __init__(self, gains: AttitudeGains | None = None) -> None:
        self.gains = gains or AttitudeGains()
        self.target_q: Quat = (1.0, 0.0, 0.0, 0.0)
        self.target_rate: Vec3 = (0.0, 0.0, 0.0)
        """Shaped body-rate target (``_ang_vel_target``), rad/s."""
        self.rate_target: Vec3 = (0.0, 0.0, 0.0)
        """What the rate PIDs get (``_ang_vel_body``), rad/s."""
        self.thrust_error_rad = 0.0

    def relax(self, body_q: Quat, gyro: Sequence[float]) -> None:
        """``relax_attitude_controllers``: target = current attitude and rate."""
        self.target_q = body_q
        g = (float(gyro[0]), float(gyro[1]), float(gyro[2]))
        self.target_rate = g
        self.rate_target = g
        self.thrust_error_rad = 0.0

    def input_rate_bf(
        self, rates_rad_s: Sequence[float], body_q: Quat, gyro: Sequence[float], dt_s: float
    ) -> Vec3:
        """One run of ``input_rate_bf_roll_pitch_yaw``; returns the rate PIDs' target."""
        g = self.gains
        if g.rate_ff:
            self.target_rate = (
                shape_rate(self.target_rate[0], rates_rad_s[0], g.accel_max_rad_s2[0], dt_s),
                shape_rate(self.target_rate[1], rates_rad_s[1], g.accel_max_rad_s2[1], dt_s),
                shape_rate(self.target_rate[2], rates_rad_s[2], g.accel_max_rad_s2[2], dt_s),
            )
        else:
            step = axis_angle_to_quat(tuple(r * dt_s for r in rates_rad_s[:3]))  # type: ignore[arg-type]
            self.target_q = _normalised(quat_mul(self.target_q, step))
            self.target_rate = (0.0, 0.0, 0.0)
        return self._run_quat(body_q, gyro, dt_s)

    def _run_quat(self, body_q: Quat, gyro: Sequence[float], dt_s: float) -> Vec3:
        g = self.gains
        err, thrust_err, self.target_q = thrust_heading_error(self.target_q, body_q, g.angle_p[2])
        self.thrust_error_rad = thrust_err
        a_rp = [
            min(max(a / 2.0, ACCEL_RP_CONTROLLER_MIN_RAD_S2), ACCEL_RP_CONTROLLER_MAX_RAD_S2)
            for a in g.accel_max_rad_s2[:2]
        ]
        a_y = min(
            max(g.accel_max_rad_s2[2] / 2.0, ACCEL_Y_CONTROLLER_MIN_RAD_S2),
            ACCEL_Y_CONTROLLER_MAX_RAD_S2,
        )
        lims = (a_rp[0], a_rp[1], a_y)
        corr = [
            sqrt_controller(
                err[i], g.angle_p[i], lims[i] if g.accel_max_rad_s2[i] > 0 else 0.0, dt_s
            )
            for i in range(3)
        ]
        # The shaped rate, from the target frame into the body frame.
        to_body = quat_mul(quat_conj(body_q), self.target_q)
        ff = quat_rotate(to_body, self.target_rate)
        if thrust_err > 2.0 * THRUST_ERROR_ANGLE_RAD:
            out = (corr[0], corr[1], float(gyro[2]))
        elif thrust_err > THRUST_ERROR_ANGLE_RAD:
            k = 1.0 - (thrust_err - THRUST_ERROR_ANGLE_RAD) / THRUST_ERROR_ANGLE_RAD
            z = corr[2] + ff[2]
            out = (corr[0] + ff[0], corr[1] + ff[1], float(gyro[2]) * (1.0 - k) + z * k)
        else:
            out = (corr[0] + ff[0], corr[1] + ff[1], corr[2] + ff[2])
        if g.rate_ff:
            step = axis_angle_to_quat(
                (self.target_rate[0] * dt_s, self.target_rate[1] * dt_s, self.target_rate[2] * dt_s)
            )
            self.target_q = quat_mul(self.target_q, step)
        self.target_q = _normalised(self.target_q)
        self.rate_target = out
        return out


def _normalised(q: Quat) -> Quat:
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n) if n > 0.0 else (1.0, 0.0, 0.0, 0.0)


# ---------------------------------------------------------------- motors


@dataclass(frozen=True)
class MotorsOutput:
    """What :meth:`MotorsMatrix.output_armed_stabilizing` produced.

    ``thrust`` per motor in [0, 1] (thrust space, before the thrust curve);
    ``limit`` roll, pitch, yaw saturated (``AP_Motors::limit``, the rate PIDs'
    integrator stop); ``throttle_upper`` the collective was cut.
    """

    thrust: tuple[float, ...]
    limit: tuple[bool, bool, bool]
    throttle_upper: bool


class MotorsMatrix:
    """ArduCopter's ``AP_MotorsMatrix::output_armed_stabilizing`` for a flat frame.

    Factors from the motor positions and spins, normalised to +/-0.5 per axis
    (``normalise_rpy_factors``): roll ``-y``, pitch ``x``, yaw +1 counter-clockwise
    (``AP_MOTORS_MATRIX_YAW_FACTOR_CCW``), -1 clockwise. Per output:

    1. roll and pitch per motor; the yaw each motor can still take around the
       throttle best for attitude (``min(0.5, throttle_avg_max)``), but at least
       ``MOT_YAW_HEADROOM`` / 1000 (0.2); yaw clipped to it (``limit.yaw``);
    2. if roll + pitch + yaw span more than the range, or would go below 0 at
       ``throttle_avg_max``, all three are scaled down together (``limit`` on all);
    3. the collective is placed as close to the request as the span allows
       (never below what roll, pitch and yaw need; the top cut sets ``throttle_upper``).

    Source: ArduPilot ``libraries/AP_Motors/AP_MotorsMatrix.cpp`` (tag Copter-4.5.x),
    without battery compensation, thrust boost or a lost motor.
    """

    def __init__(
        self,
        positions_frd_m: Sequence[Sequence[float]],
        spins: Sequence[str],
        *,
        yaw_headroom: float = 200.0,
    ) -> None:
        xs = [float(p[0]) for p in positions_frd_m]
        ys = [float(p[1]) for p in positions_frd_m]
        if len(spins) != len(xs) or len(xs) < 4:
            raise ValueError("expected at least 4 motors and one spin per motor")
        rmax = max(abs(y) for y in ys)
        pmax = max(abs(x) for x in xs)
        if rmax <= 0.0 or pmax <= 0.0:
            raise ValueError("motors must be spread in both x and y")
        self.roll = tuple(0.5 * -y / rmax for y in ys)
        self.pitch = tuple(0.5 * x / pmax for x in xs)
        self.yaw = tuple(0.5 if s == "ccw" else -0.5 for s in spins)
        self.n_motors = len(xs)
        self.yaw_headroom = float(yaw_headroom)

    @classmethod
    def from_profile(cls, profile: VehicleProfile) -> MotorsMatrix:
        """The frame of a vehicle profile (``physics.mixer: paper`` is the paper's '+')."""
        if profile.physics.mixer == "paper":
            pos = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (-1.0, 0.0, 0.0), (0.0, -1.0, 0.0))
            return cls(pos, ("cw", "ccw", "cw", "ccw"))
        motors = profile.frame.motors
        return cls([m.position_frd_m for m in motors], [m.spin for m in motors])

    def output_armed_stabilizing(
        self, roll: float, pitch: float, yaw: float, throttle: float, throttle_avg_max: float
    ) -> MotorsOutput:
        """Mix normalised roll, pitch, yaw and a collective in [0, 1] to thrusts."""
        thr_upper = False
        thr = throttle
        if thr <= 0.0:
            thr = 0.0
        if thr >= 1.0:
            thr = 1.0
            thr_upper = True
        avg_max = min(max(throttle_avg_max, thr), 1.0)
        best_rpy = min(0.5, avg_max)
        n = self.n_motors
        rp = [roll * self.roll[i] + pitch * self.pitch[i] for i in range(n)]
        yaw_allowed = 1.0
        for i in range(n):
            f = self.yaw[i]
            if f == 0.0:
                continue
            if yaw * f > 0.0:
                room = max(1.0 - (best_rpy + rp[i]), 0.0) / abs(f)
            else:
                room = max(best_rpy + rp[i], 0.0) / abs(f)
            yaw_allowed = min(yaw_allowed, room)
        yaw_allowed = max(yaw_allowed, self.yaw_headroom * 0.001)
        limit_y = False
        if abs(yaw) > yaw_allowed:
            yaw = min(max(yaw, -yaw_allowed), yaw_allowed)
            limit_y = True
        rpy = [rp[i] + yaw * self.yaw[i] for i in range(n)]
        lo, hi = min(rpy), max(rpy)
        scale = 1.0
        if hi - lo > 1.0:
            scale = 1.0 / (hi - lo)
        if avg_max + lo < 0.0:
            scale = min(scale, -avg_max / lo)
        hi *= scale
        lo *= scale
        best_rpy = -lo
        adj = thr - best_rpy
        limit_rp = False
        if scale < 1.0:
            limit_rp = limit_y = True
            if adj > 0.0:
                thr_upper = True
            adj = 0.0
        elif adj < 0.0:
            adj = 0.0
        elif adj > 1.0 - (best_rpy + hi):
            adj = 1.0 - (best_rpy + hi)
            thr_upper = True
        base = best_rpy + adj
        out = tuple(base + scale * v for v in rpy)
        return MotorsOutput(out, (limit_rp, limit_rp, limit_y), thr_upper)
