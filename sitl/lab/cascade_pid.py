r"""PX4's default cascaded controller (attitude P, position P, velocity PID), the baseline.

The baseline for the outer loops is PX4's mc_att_control / mc_pos_control with
their default gains, flown behind the same interface as the
MFC outer loops (:class:`companion.control.outer.OuterController`), so that
:mod:`sitl.lab.outer_flight` can fly either. This module is that baseline: pure
(no I/O, no clock; ``dt_s`` and the samples come from the caller), written from
PX4's source, not copied from it.

Sources (PX4-Autopilot, ``main``; read for the algorithm and the defaults)
-------------------------------------------------------------------------
* ``src/modules/mc_att_control/AttitudeControl/AttitudeControl.cpp``
  (``AttitudeControl::update``, ``setProportionalGain``): the attitude law below.
* ``src/modules/mc_att_control/mc_att_control_params.yaml`` (and
  ``mc_att_control_params.c``): ``MC_ROLL_P`` = ``MC_PITCH_P`` = 4.0 1/s (6.5 in
  releases up to v1.13), ``MC_YAW_P`` = 2.8 1/s, ``MC_YAW_WEIGHT`` = 0.4,
  ``MC_ROLLRATE_MAX`` = ``MC_PITCHRATE_MAX`` = 220 deg/s, ``MC_YAWRATE_MAX`` =
  200 deg/s. The reference model of the newest ``AttitudeControl.cpp``
  (``MC_REF_FF``) is off by default (0), which is the law below.
* ``src/modules/mc_pos_control/PositionControl/PositionControl.cpp``
  (``_positionControl``, ``_velocityControl``, ``_accelerationControl``) and
  ``PositionControl/ControlMath.cpp`` (``constrainXY``, ``limitTilt``,
  ``bodyzToAttitude``): the position, velocity and thrust laws below.
* ``src/modules/mc_pos_control/multicopter_position_control_gain_params.c``:
  ``MPC_XY_P`` = 0.95, ``MPC_Z_P`` = 1.0 (1/s); ``MPC_XY_VEL_P_ACC`` = 1.8,
  ``MPC_Z_VEL_P_ACC`` = 4.0 ((m/s^2)/(m/s)); ``MPC_XY_VEL_I_ACC`` = 0.4,
  ``MPC_Z_VEL_I_ACC`` = 2.0 ((m/s^2)/m); ``MPC_XY_VEL_D_ACC`` = 0.2,
  ``MPC_Z_VEL_D_ACC`` = 0.0 ((m/s^2)/(m/s^2)).
* ``multicopter_position_control_limits_params.c``: ``MPC_XY_VEL_MAX`` = 12 m/s,
  ``MPC_Z_VEL_MAX_UP`` = 3 m/s, ``MPC_Z_VEL_MAX_DN`` = 1.5 m/s,
  ``MPC_TILTMAX_AIR`` = 45 deg, ``MPC_THR_MIN`` = 0.12, ``MPC_THR_MAX`` = 1.0.
* ``multicopter_position_control_params.c``: ``MPC_THR_HOVER`` = 0.5,
  ``MPC_THR_XY_MARG`` = 0.3, ``MPC_VELD_LP`` = 5 Hz (the velocity derivative's
  low-pass, ``MulticopterPositionControl.cpp``).

Attitude (``mc_att_control``)
-----------------------------
With ``q`` the estimate and ``q_d`` the setpoint (body FRD to NED): the reduced
setpoint :math:`q_{red} = q_{arc}(e_z, e_{z,d}) \otimes q` tilts the thrust axis
the shortest way; the heading still missing, :math:`q_{red}^{-1} \otimes q_d =
(\cos\frac{\psi}{2}, 0, 0, \sin\frac{\psi}{2})`, is scaled by ``MC_YAW_WEIGHT``
(its half-angle multiplied by :math:`w`); with :math:`q_e = q^{-1} \otimes q_w`
canonical, the error is :math:`e = 2\,\mathrm{Im}(q_e)` (twice the sine of the
half angle times the axis, not the angle) and the rate reference

.. math::  \omega_r = K \circ e + r_{ff}\, R^T e_z, \qquad
           K = (K_\phi, K_\theta, K_\psi / w)

each axis clamped to its maximum rate (the yaw gain over the weight, so a pure
heading error still gets :math:`K_\psi`). No state: a P law.

Position and velocity (``mc_pos_control``), NED
-----------------------------------------------
* position P: :math:`v_r = v_{ff} + K_x (p_{sp} - p)`; horizontally the P part
  keeps priority over the feedforward within ``MPC_XY_VEL_MAX``
  (``constrainXY``); vertically clamped to [-``MPC_Z_VEL_MAX_UP``,
  ``MPC_Z_VEL_MAX_DN``];
* velocity PID to an acceleration: :math:`a = a_{ff} + K_P (v_r - v) + I - K_D
  \dot v`, :math:`\dot v` the finite difference of the velocity through a
  first-order low-pass at ``MPC_VELD_LP`` (derivative on the measurement);
* acceleration to thrust: the thrust direction :math:`\propto (-a_x, -a_y, g)`
  with its tilt limited to ``MPC_TILTMAX_AIR``; the collective
  :math:`T_z = a_z T_h / g - T_h` (negative up, :math:`T_h` = ``MPC_THR_HOVER``)
  divided by the cosine of that direction, at least ``MPC_THR_MIN``;
* altitude first: the vertical thrust may use :math:`\sqrt{T_{max}^2 -
  \min(|T_{xy}|, m)^2}` (``MPC_THR_XY_MARG`` = m kept for the horizontal), the
  horizontal what is left, :math:`\sqrt{T_{max}^2 - T_z^2}`;
* anti-windup: vertically, the integrator stops when the thrust is at a bound and
  the error would push further; horizontally, tracking anti-windup (the error is
  reduced by :math:`2/K_P` times the acceleration the saturation removed); the
  vertical integrator is bounded by :math:`g`;
* the attitude setpoint: body z along minus the thrust, the heading the
  setpoint's (the current one without), the collective the thrust's norm.

Units: the collective is PX4's normalised thrust, 0..1, the same units as the
rate loop's thrust input in the lab (and as
:class:`~companion.control.vertical.VerticalLoop`'s); ``MPC_THR_HOVER`` = 0.5
whatever the vehicle (its hover command is 0.57-0.74 on the paper's four).

What differs from PX4 (on purpose or not modelled)
--------------------------------------------------
* No hover-thrust estimator (``mc_hover_thrust_estimator``, ``MPC_USE_HTE`` = 1
  by default): the hover thrust stays ``MPC_THR_HOVER`` and the vertical
  integrator takes up the difference, as PX4 does with ``MPC_USE_HTE`` = 0.
  :attr:`PxVertical.hover_thrust` reports the hover collective the integrator
  implies, :math:`T_h (1 - I_z / g)`.
* No trajectory generator (jerk-limited setpoints, ``MPC_ACC_HOR`` ...): the
  setpoints are flown as given, as the MFC loops fly them.
* Take-off: PX4 resets the integrators while landed and not asked to take off,
  and lets them run during the take-off ramp. Here, while :attr:`on_ground`, the
  horizontal integrators are held, and the vertical one too unless a climb is
  asked (the take-off: without it a vehicle hovering above ``MPC_THR_HOVER`` plus
  the P term's 1 m/s share, 0.70, would never lift off).
* The applied collective (``applied_thrust``) is accepted and ignored: PX4's
  position controller does not use it.

Failure behaviour (``fault`` set, ``nonfinite_events`` counted)
---------------------------------------------------------------
Attitude estimate non-finite or of zero norm: zero rates. Position, velocity or
``dt_s`` non-finite (or ``dt_s <= 0``): level, the hover collective the
integrator implies, nothing integrated (PX4's failsafe holds still). Setpoint
non-finite: zero velocity reference (brake and hold). No output is ever
non-finite; an absurd finite input whose sums overflow resets the integrators.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from companion.control.attitude import AttitudeSetpoint
from companion.control.outer import OuterOutput, OuterSetpoint
from companion.control.quaternion import (
    Quat,
    Vec3,
    body_z_ned,
    canonical,
    euler_to_quat,
    ned_down_frd,
    normalise_or_none,
    quat_conj,
    quat_mul,
    shortest_arc,
    yaw_rad,
)
from companion.control.ultralocal import DT_MAX_S, DT_MIN_S, GRAVITY_M_S2, check_positive
from companion.control.vertical import VerticalSetpoint

__all__ = [
    "PX4_DEFAULT_CASCADE",
    "CascadeGains",
    "CascadePid",
    "PxAttitude",
    "PxHorizontal",
    "PxVertical",
    "attitude_rate_setpoint",
    "bodyz_to_quat",
    "constrain_xy",
    "limit_tilt",
]

Vec2 = tuple[float, float]
_ZERO3: Vec3 = (0.0, 0.0, 0.0)
_ZERO2: Vec2 = (0.0, 0.0)


@dataclass(frozen=True)
class CascadeGains:
    """PX4's cascade parameters, in SI units (:data:`PX4_DEFAULT_CASCADE`: the defaults).

    Attributes (PX4 parameter in brackets)
    --------------------------------------
    roll_p_1_s, pitch_p_1_s, yaw_p_1_s
        Attitude P gains, (rad/s)/rad [``MC_ROLL_P``, ``MC_PITCH_P``, ``MC_YAW_P``].
    yaw_weight
        Share of the heading error asked at once, in (0, 1] [``MC_YAW_WEIGHT``].
    roll_rate_max_rad_s, pitch_rate_max_rad_s, yaw_rate_max_rad_s
        Rate-reference limits [``MC_ROLLRATE_MAX``, ``MC_PITCHRATE_MAX``,
        ``MC_YAWRATE_MAX``].
    xy_p_1_s, z_p_1_s
        Position P gains [``MPC_XY_P``, ``MPC_Z_P``].
    xy_vel_p_1_s, z_vel_p_1_s
        Velocity P gains, (m/s^2)/(m/s) [``MPC_XY_VEL_P_ACC``, ``MPC_Z_VEL_P_ACC``].
    xy_vel_i_1_s2, z_vel_i_1_s2
        Velocity I gains, (m/s^2)/m [``MPC_XY_VEL_I_ACC``, ``MPC_Z_VEL_I_ACC``].
    xy_vel_d, z_vel_d
        Velocity D gains, (m/s^2)/(m/s^2) [``MPC_XY_VEL_D_ACC``, ``MPC_Z_VEL_D_ACC``].
    vel_deriv_lp_hz
        Cut-off of the velocity derivative's low-pass, Hz [``MPC_VELD_LP``].
    xy_vel_max_m_s, z_vel_max_up_m_s, z_vel_max_dn_m_s
        Velocity-reference limits [``MPC_XY_VEL_MAX``, ``MPC_Z_VEL_MAX_UP``,
        ``MPC_Z_VEL_MAX_DN``].
    hover_thrust
        Collective that hovers, normalised [``MPC_THR_HOVER``].
    tilt_max_rad
        Tilt limit [``MPC_TILTMAX_AIR``].
    thrust_min, thrust_max
        Collective bounds, normalised [``MPC_THR_MIN``, ``MPC_THR_MAX``].
    thrust_xy_margin
        Horizontal thrust kept under altitude priority [``MPC_THR_XY_MARG``].
    """

    roll_p_1_s: float = 4.0
    pitch_p_1_s: float = 4.0
    yaw_p_1_s: float = 2.8
    yaw_weight: float = 0.4
    roll_rate_max_rad_s: float = math.radians(220.0)
    pitch_rate_max_rad_s: float = math.radians(220.0)
    yaw_rate_max_rad_s: float = math.radians(200.0)
    xy_p_1_s: float = 0.95
    z_p_1_s: float = 1.0
    xy_vel_p_1_s: float = 1.8
    z_vel_p_1_s: float = 4.0
    xy_vel_i_1_s2: float = 0.4
    z_vel_i_1_s2: float = 2.0
    xy_vel_d: float = 0.2
    z_vel_d: float = 0.0
    vel_deriv_lp_hz: float = 5.0
    xy_vel_max_m_s: float = 12.0
    z_vel_max_up_m_s: float = 3.0
    z_vel_max_dn_m_s: float = 1.5
    hover_thrust: float = 0.5
    tilt_max_rad: float = math.radians(45.0)
    thrust_min: float = 0.12
    thrust_max: float = 1.0
    thrust_xy_margin: float = 0.3

    def __post_init__(self) -> None:
        check_positive(
            self,
            (
                "roll_p_1_s", "pitch_p_1_s", "yaw_p_1_s", "yaw_weight", "roll_rate_max_rad_s",
                "pitch_rate_max_rad_s", "yaw_rate_max_rad_s", "xy_p_1_s", "z_p_1_s",
                "xy_vel_p_1_s", "z_vel_p_1_s", "vel_deriv_lp_hz", "xy_vel_max_m_s",
                "z_vel_max_up_m_s", "z_vel_max_dn_m_s", "hover_thrust", "tilt_max_rad",
                "thrust_min", "thrust_max",
            ),
        )  # fmt: skip
        check_positive(
            self,
            ("xy_vel_i_1_s2", "z_vel_i_1_s2", "xy_vel_d", "z_vel_d", "thrust_xy_margin"),
            zero_ok=True,
        )
        name = type(self).__name__
        if self.yaw_weight > 1.0:
            raise ValueError(f"{name}.yaw_weight must be in (0, 1], got {self.yaw_weight!r}")
        if not self.thrust_min < self.hover_thrust < self.thrust_max <= 1.0:
            raise ValueError(
                f"{name}: expected thrust_min < hover_thrust < thrust_max <= 1, got "
                f"{self.thrust_min!r}, {self.hover_thrust!r}, {self.thrust_max!r}"
            )
        if self.tilt_max_rad >= 0.5 * math.pi:
            raise ValueError(f"{name}.tilt_max_rad must be in (0, pi/2), got {self.tilt_max_rad!r}")


PX4_DEFAULT_CASCADE = CascadeGains()
"""PX4's default parameters (module docstring, with the files they come from)."""


# --- pure functions ------------------------------------------------------------------


def attitude_rate_setpoint(
    q: Quat, q_sp: Quat, gains: CascadeGains, yaw_rate_rad_s: float = 0.0
) -> tuple[Vec3, Vec3]:
    r"""PX4's attitude P law: the body-rate reference (FRD, rad/s, clamped) and the
    error :math:`2\,\mathrm{Im}(q_e)` it came from (module docstring).

    ``q`` and ``q_sp`` are unit quaternions (w, x, y, z), body FRD to NED.
    """
    e_z = body_z_ned(q)
    e_z_d = body_z_ned(q_sp)
    q_red = shortest_arc(e_z, e_z_d)
    if abs(q_red[1]) > 1.0 - 1e-5 or abs(q_red[2]) > 1.0 - 1e-5:
        # Thrust axes opposite: no unique tilt; the full setpoint (as PX4).
        q_red = q_sp
    else:
        q_red = quat_mul(q_red, q)
    dyaw = canonical(quat_mul(quat_conj(q_red), q_sp))
    w = gains.yaw_weight
    c = min(max(dyaw[0], -1.0), 1.0)
    s = min(max(dyaw[3], -1.0), 1.0)
    q_w = quat_mul(q_red, (math.cos(w * math.acos(c)), 0.0, 0.0, math.sin(w * math.asin(s))))
    qe = canonical(quat_mul(quat_conj(q), q_w))
    err: Vec3 = (2.0 * qe[1], 2.0 * qe[2], 2.0 * qe[3])
    k = (gains.roll_p_1_s, gains.pitch_p_1_s, gains.yaw_p_1_s / w)
    lim = (gains.roll_rate_max_rad_s, gains.pitch_rate_max_rad_s, gains.yaw_rate_max_rad_s)
    d = ned_down_frd(q)
    out = [0.0, 0.0, 0.0]
    for i in range(3):
        r = k[i] * err[i] + yaw_rate_rad_s * d[i]
        out[i] = min(max(r, -lim[i]), lim[i])
    return (out[0], out[1], out[2]), err


def constrain_xy(v0: Vec2, v1: Vec2, max_norm: float) -> Vec2:
    """``v0 + v1`` within ``max_norm``, ``v0`` first (PX4 ``ControlMath::constrainXY``):
    all of ``v0`` (scaled down if it alone is too long), then as much of ``v1``'s
    direction as fits."""
    sx, sy = v0[0] + v1[0], v0[1] + v1[1]
    if math.hypot(sx, sy) <= max_norm:
        return (sx, sy)
    n0 = math.hypot(v0[0], v0[1])
    if n0 >= max_norm:
        return (v0[0] / n0 * max_norm, v0[1] / n0 * max_norm)
    n1 = math.hypot(v1[0], v1[1])
    if n0 < 1e-3:
        return (v1[0] / n1 * max_norm, v1[1] / n1 * max_norm)
    ux, uy = v1[0] / n1, v1[1] / n1
    m = ux * v0[0] + uy * v0[1]
    c = n0 * n0 - max_norm * max_norm  # < 0 here
    s = -m + math.sqrt(m * m - c)
    return (v0[0] + s * ux, v0[1] + s * uy)


def limit_tilt(body: Vec3, max_angle_rad: float) -> tuple[Vec3, bool]:
    """A unit vector tilted from NED z by at most ``max_angle_rad`` (its azimuth
    kept; PX4 ``ControlMath::limitTilt`` against (0, 0, 1)), and whether it was limited."""
    dot = min(max(body[2], -1.0), 1.0)
    angle = math.acos(dot)
    if angle <= max_angle_rad:
        return body, False
    rx, ry = body[0], body[1]
    n = math.hypot(rx, ry)
    if n < 1e-12:
        rx, ry, n = 1.0, 0.0, 1.0
    s = math.sin(max_angle_rad)
    return (s * rx / n, s * ry / n, math.cos(max_angle_rad)), True


def bodyz_to_quat(body_z: Vec3, yaw_sp_rad: float) -> Quat:
    """The attitude whose body z axis (NED) is ``body_z`` at heading ``yaw_sp_rad``
    (PX4 ``ControlMath::bodyzToAttitude``), as a unit quaternion (w, x, y, z)."""
    zx, zy, zz = body_z
    n = math.sqrt(zx * zx + zy * zy + zz * zz)
    if n * n < 1.2e-7:
        zx, zy, zz, n = 0.0, 0.0, 1.0, 1.0
    zx, zy, zz = zx / n, zy / n, zz / n
    yc = (-math.sin(yaw_sp_rad), math.cos(yaw_sp_rad), 0.0)
    # body x = y_C x body z
    xx = yc[1] * zz - yc[2] * zy
    xy = yc[2] * zx - yc[0] * zz
    xz = yc[0] * zy - yc[1] * zx
    if zz < 0.0:  # keep the nose forward upside down
        xx, xy, xz = -xx, -xy, -xz
    if abs(zz) < 1e-6:
        xx, xy, xz = 0.0, 0.0, 1.0
    nx = math.sqrt(xx * xx + xy * xy + xz * xz)
    xx, xy, xz = xx / nx, xy / nx, xz / nx
    # body y = body z x body x
    yx = zy * xz - zz * xy
    yy = zz * xx - zx * xz
    yz = zx * xy - zy * xx
    return _dcm_to_quat(((xx, yx, zx), (xy, yy, zy), (xz, yz, zz)))


def _dcm_to_quat(r: tuple[Vec3, Vec3, Vec3]) -> Quat:
    """Rotation matrix (rows) to a unit quaternion, w >= 0 (Shepperd's method)."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = r
    tr = r00 + r11 + r22
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = (0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s)
    elif r00 > r11 and r00 > r22:
        s = 2.0 * math.sqrt(1.0 + r00 - r11 - r22)
        q = ((r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s)
    elif r11 > r22:
        s = 2.0 * math.sqrt(1.0 + r11 - r00 - r22)
        q = ((r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + r22 - r00 - r11)
        q = ((r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s)
    return canonical(q)


def _euler_zyx(q: Quat) -> Vec3:
    w, x, y, z = q
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(min(max(2.0 * (w * y - z * x), -1.0), 1.0))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return (roll, pitch, yaw)


def _dt_ok(dt_s: float) -> float | None:
    """``dt_s`` clamped to [DT_MIN_S, DT_MAX_S], or None when not finite and > 0."""
    if not (math.isfinite(dt_s) and dt_s > 0.0):
        return None
    return min(max(dt_s, DT_MIN_S), DT_MAX_S)


class _Derivative:
    """Finite difference through a first-order low-pass (PX4's ``BlockDerivative``)."""

    __slots__ = ("_prev", "_tau", "value")

    def __init__(self, cutoff_hz: float) -> None:
        self._tau = 1.0 / (2.0 * math.pi * cutoff_hz)
        self.reset()

    def reset(self) -> None:
        self._prev: float | None = None
        self.value = 0.0

    def update(self, dt_s: float, x: float) -> float:
        prev = self._prev
        self._prev = x
        if prev is None:
            return self.value
        raw = (x - prev) / dt_s
        self.value += (raw - self.value) * (dt_s / (dt_s + self._tau))
        return self.value


# --- the three loops -----------------------------------------------------------------


class PxAttitude:
    """PX4's attitude P controller (``mc_att_control``): no state, the same
    ``update``/``reset`` as :class:`companion.control.attitude.AttitudeLoop`.

    Attributes (after each update): ``error_frd_rad`` (:math:`2\\,\\mathrm{Im}(q_e)`),
    ``saturated`` per axis, ``fault``, ``nonfinite_events``.
    """

    __slots__ = ("_gains", "error_frd_rad", "fault", "nonfinite_events", "saturated")

    def __init__(self, gains: CascadeGains = PX4_DEFAULT_CASCADE) -> None:
        self._gains = gains
        self.nonfinite_events = 0
        self.reset()

    @property
    def gains(self) -> CascadeGains:
        return self._gains

    def reset(self) -> None:
        """Nothing to forget but the diagnostics (a P law)."""
        self.error_frd_rad: Vec3 = _ZERO3
        self.saturated = (False, False, False)
        self.fault = False

    def update(
        self, dt_s: float, q_wxyz: Quat, rate_frd_rad_s: Vec3, setpoint: AttitudeSetpoint
    ) -> Vec3:
        """The body-rate reference (FRD, rad/s) for a roll/pitch/heading setpoint
        (``dt_s`` and the rates unused: a P law; kept for the interface)."""
        q = normalise_or_none(q_wxyz)
        if q is None:
            return self._fail()
        sp = setpoint
        yaw_sp = sp.yaw_rad
        fault = False
        if not math.isfinite(
            sp.roll_rad + sp.pitch_rad + sp.yaw_rate_rad_s + (0.0 if yaw_sp is None else yaw_sp)
        ):
            fault = True
            sp = AttitudeSetpoint(0.0, 0.0, None, 0.0)
            yaw_sp = None
        heading = yaw_rad(q) if yaw_sp is None else yaw_sp
        q_sp = euler_to_quat(sp.roll_rad, sp.pitch_rad, heading)
        return self.update_q(q, q_sp, sp.yaw_rate_rad_s, _fault=fault)

    def update_q(
        self, q_wxyz: Quat, q_sp_wxyz: Quat, yaw_rate_rad_s: float = 0.0, *, _fault: bool = False
    ) -> Vec3:
        """The body-rate reference for a quaternion setpoint (body FRD to NED)."""
        q = normalise_or_none(q_wxyz)
        if q is None:
            return self._fail()
        q_sp = normalise_or_none(q_sp_wxyz)
        fault = _fault
        if q_sp is None:
            fault = True
            q_sp = euler_to_quat(0.0, 0.0, yaw_rad(q))
        if not math.isfinite(yaw_rate_rad_s):
            fault = True
            yaw_rate_rad_s = 0.0
        rates, err = attitude_rate_setpoint(q, q_sp, self._gains, yaw_rate_rad_s)
        if not math.isfinite(rates[0] + rates[1] + rates[2]):
            return self._fail()
        g = self._gains
        lim = (g.roll_rate_max_rad_s, g.pitch_rate_max_rad_s, g.yaw_rate_max_rad_s)
        self.error_frd_rad = err
        self.saturated = (
            abs(rates[0]) >= lim[0],
            abs(rates[1]) >= lim[1],
            abs(rates[2]) >= lim[2],
        )
        if fault:
            self.nonfinite_events += 1
        self.fault = fault
        return rates

    def _fail(self) -> Vec3:
        self.nonfinite_events += 1
        self.fault = True
        self.saturated = (False, False, False)
        return _ZERO3


class PxVertical:
    """The vertical channel of PX4's position controller: altitude P, climb-rate
    PID, collective (and its integrator). Alone (:meth:`update`, PX4's altitude
    mode under an attitude setpoint) or inside :class:`CascadePid`.

    Attributes (after each update)
    ------------------------------
    integral_m_s2
        The velocity integrator, NED down, m/s^2 (bounded by g).
    level_thrust
        The vertical collective (up), normalised.
    saturated
        Whether the vertical thrust was at a bound (the anti-windup's condition).
    climb_ref_m_s
        The climb rate asked last (up, m/s): :meth:`velocity_setpoint`'s.
    on_ground
        Set by the caller while landed (module docstring, take-off).
    fault, nonfinite_events
        As the MFC loops'.
    """

    __slots__ = (
        "_deriv",
        "_gains",
        "climb_ref_m_s",
        "fault",
        "integral_m_s2",
        "level_thrust",
        "nonfinite_events",
        "on_ground",
        "saturated",
    )

    def __init__(self, gains: CascadeGains = PX4_DEFAULT_CASCADE) -> None:
        self._gains = gains
        self._deriv = _Derivative(gains.vel_deriv_lp_hz)
        self.on_ground = False
        self.nonfinite_events = 0
        self.reset()

    @property
    def gains(self) -> CascadeGains:
        return self._gains

    @property
    def hover_thrust(self) -> float:
        """The hover collective the integrator implies, :math:`T_h (1 - I_z / g)`."""
        return self._gains.hover_thrust * (1.0 - self.integral_m_s2 / GRAVITY_M_S2)

    def reset(self, thrust: float | None = None, hover_thrust: float | None = None) -> None:
        """Zero the integrator and the derivative. ``thrust`` and ``hover_thrust``
        are accepted for the MFC interface and ignored: PX4 starts from
        ``MPC_THR_HOVER`` and an empty integrator."""
        self.integral_m_s2 = 0.0
        self._deriv.reset()
        self.climb_ref_m_s = 0.0
        self.level_thrust = self._gains.hover_thrust
        self.saturated = False
        self.fault = False

    def restart_derivative(self) -> None:
        """The next sample starts a new finite difference (after a bad sample)."""
        self._deriv.reset()

    def velocity_setpoint(self, z_ned_m: float, setpoint: VerticalSetpoint) -> float:
        """The down-velocity reference, m/s: feedforward plus altitude P, clamped."""
        g = self._gains
        v = -setpoint.climb_m_s
        if setpoint.up_m is not None:
            v += g.z_p_1_s * (-setpoint.up_m - z_ned_m)
        v = min(max(v, -g.z_vel_max_up_m_s), g.z_vel_max_dn_m_s)
        self.climb_ref_m_s = -v
        return v

    def acceleration(self, dt_s: float, vz_ned_m_s: float, vz_sp: float, accel_ff: float) -> float:
        """The down-acceleration the PID asks, m/s^2 (the derivative updated)."""
        g = self._gains
        vdot = self._deriv.update(dt_s, vz_ned_m_s)
        p_term = g.z_vel_p_1_s * (vz_sp - vz_ned_m_s)
        return accel_ff + p_term + self.integral_m_s2 - g.z_vel_d * vdot

    def integrate(self, dt_s: float, vel_err: float, thrust_z: float, climb_asked: bool) -> None:
        """The integrator step with PX4's vertical anti-windup (``thrust_z`` NED,
        negative up); held on the ground unless a climb is asked (take-off)."""
        g = self._gains
        sat = (thrust_z >= -g.thrust_min - 1e-9 and vel_err >= 0.0) or (
            thrust_z <= -g.thrust_max + 1e-9 and vel_err <= 0.0
        )
        self.saturated = thrust_z >= -g.thrust_min - 1e-9 or thrust_z <= -g.thrust_max + 1e-9
        if sat or (self.on_ground and not climb_asked):
            return
        i = self.integral_m_s2 + vel_err * g.z_vel_i_1_s2 * dt_s
        self.integral_m_s2 = min(max(i, -GRAVITY_M_S2), GRAVITY_M_S2)

    def update(
        self,
        dt_s: float,
        z_ned_m: float,
        vz_ned_m_s: float,
        setpoint: VerticalSetpoint,
        *,
        cos_tilt: float = 1.0,
        applied: float | None = None,
    ) -> float:
        """The collective, normalised [thrust_min, thrust_max]: the vertical thrust
        over ``cos_tilt`` (the measured tilt, bounded at ``MPC_TILTMAX_AIR``).
        ``applied`` is ignored (PX4 does not use it)."""
        g = self._gains
        fault = False
        if not math.isfinite(cos_tilt):
            fault = True
            cos_tilt = 1.0
        c = max(cos_tilt, math.cos(g.tilt_max_rad))
        dt = _dt_ok(dt_s)
        if dt is None or not math.isfinite(z_ned_m + vz_ned_m_s):
            self.nonfinite_events += 1
            self.fault = True
            self._deriv.reset()
            t = min(max(self.hover_thrust / c, g.thrust_min), g.thrust_max)
            self.level_thrust = self.hover_thrust
            self.saturated = False
            return t
        sp = setpoint
        if not math.isfinite(
            sp.climb_m_s + sp.climb_accel_m_s2 + (0.0 if sp.up_m is None else sp.up_m)
        ):
            fault = True
            sp = VerticalSetpoint(0.0, None, 0.0)
        vz_sp = self.velocity_setpoint(z_ned_m, sp)
        acc = self.acceleration(dt, vz_ned_m_s, vz_sp, -sp.climb_accel_m_s2)
        h = g.hover_thrust
        thr_z = acc * h / GRAVITY_M_S2 - h
        thr_z = min(max(thr_z, -g.thrust_max), -g.thrust_min)
        self.integrate(dt, vz_sp - vz_ned_m_s, thr_z, sp.climb_m_s > 0.0 or vz_sp < 0.0)
        out = min(max(-thr_z / c, g.thrust_min), g.thrust_max)
        if not math.isfinite(out):
            fault = True
            self.reset()
            out = min(max(g.hover_thrust / c, g.thrust_min), g.thrust_max)
            thr_z = -g.hover_thrust
        self.level_thrust = -thr_z
        if fault:
            self.nonfinite_events += 1
        self.fault = fault
        return out


class PxHorizontal:
    """The horizontal channel's state: the velocity integrator and derivative
    (north, east). The law runs in :meth:`CascadePid.update` (PX4 couples the
    axes through the thrust vector).

    Attributes: ``integral_m_s2`` (north, east), ``velocity_ref_ne_m_s``,
    ``limited`` (the tilt or the horizontal thrust was clamped), ``fault``,
    ``nonfinite_events``.
    """

    __slots__ = (
        "_de",
        "_dn",
        "_gains",
        "fault",
        "integral_m_s2",
        "limited",
        "nonfinite_events",
        "velocity_ref_ne_m_s",
    )

    def __init__(self, gains: CascadeGains = PX4_DEFAULT_CASCADE) -> None:
        self._gains = gains
        self._dn = _Derivative(gains.vel_deriv_lp_hz)
        self._de = _Derivative(gains.vel_deriv_lp_hz)
        self.nonfinite_events = 0
        self.reset()

    @property
    def gains(self) -> CascadeGains:
        return self._gains

    def reset(self) -> None:
        """Zero the integrators and the derivatives."""
        self.integral_m_s2: Vec2 = _ZERO2
        self._dn.reset()
        self._de.reset()
        self.velocity_ref_ne_m_s: Vec2 = _ZERO2
        self.limited = False
        self.fault = False

    def restart_derivative(self) -> None:
        """The next sample starts a new finite difference (after a bad sample)."""
        self._dn.reset()
        self._de.reset()

    def derivative(self, dt_s: float, vn: float, ve: float) -> Vec2:
        """The filtered velocity derivative, north and east, m/s^2."""
        return (self._dn.update(dt_s, vn), self._de.update(dt_s, ve))


class CascadePid:
    """PX4's default cascade behind :class:`~companion.control.outer.OuterController`'s
    interface: ``update`` (one sample to an :class:`~companion.control.outer.OuterOutput`),
    ``reset``, and ``attitude``, ``vertical``, ``horizontal`` for their diagnostics,
    ``on_ground`` (on ``vertical``) and the attitude-only and altitude-only modes.
    """

    __slots__ = ("_gains", "attitude", "horizontal", "vertical")

    def __init__(self, gains: CascadeGains = PX4_DEFAULT_CASCADE) -> None:
        self._gains = gains
        self.attitude = PxAttitude(gains)
        self.vertical = PxVertical(gains)
        self.horizontal = PxHorizontal(gains)

    @property
    def gains(self) -> CascadeGains:
        return self._gains

    def reset(
        self,
        thrust: float | None = None,
        hover_thrust: float | None = None,
        tilt_ne: tuple[float, float] = (0.0, 0.0),
        *,
        at_rest: bool = False,
    ) -> None:
        """Forget all state. ``thrust``, ``hover_thrust``: see :meth:`PxVertical.reset`;
        ``tilt_ne`` and ``at_rest`` are accepted for the MFC interface and ignored:
        PX4's position controller starts its integrators empty."""
        self.attitude.reset()
        self.vertical.reset(thrust, hover_thrust)
        self.horizontal.reset()

    def _safe(self, q: Quat | None, yaw_sp: float | None, yaw_rate: float) -> OuterOutput:
        """Level at the setpoint's (or current) heading, the hover collective."""
        g = self._gains
        vert, hor = self.vertical, self.horizontal
        vert.nonfinite_events += 1
        vert.fault = True
        hor.fault = True
        vert.saturated = False
        hor.limited = False
        t = min(max(vert.hover_thrust, g.thrust_min), g.thrust_max)
        vert.level_thrust = t
        att_sp = AttitudeSetpoint(0.0, 0.0, yaw_sp, yaw_rate)
        if q is None:
            rates = self.attitude.update_q((math.nan, 0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0))
        else:
            heading = yaw_rad(q) if yaw_sp is None else yaw_sp
            rates = self.attitude.update_q(q, euler_to_quat(0.0, 0.0, heading), yaw_rate)
        return OuterOutput(rates, t, att_sp, t, g.tilt_max_rad, False, True)

    @property
    def gain_scale(self) -> float:
        """PX4's gains do not back off: 1 (as :attr:`OuterController.gain_scale`)."""
        return 1.0

    def note_rate_saturation(
        self, dt_s: float, rate_saturated: tuple[bool, bool, bool] | None
    ) -> float:
        """PX4's gains do not back off (as :meth:`OuterController.note_rate_saturation`'s
        interface): 1."""
        return 1.0

    def update(
        self,
        dt_s: float,
        q_wxyz: Quat,
        rate_frd_rad_s: Vec3,
        position_ned_m: Vec3,
        velocity_ned_m_s: Vec3,
        setpoint: OuterSetpoint,
        *,
        applied_thrust: float | None = None,
        rate_saturated: tuple[bool, bool, bool] | None = None,
    ) -> OuterOutput:
        """One update of PX4's position controller and attitude controller (module
        docstring); the arguments as :meth:`OuterController.update`'s
        (``rate_frd_rad_s``, ``applied_thrust`` and ``rate_saturated`` unused: PX4's
        gains do not back off)."""
        g = self._gains
        vert, hor = self.vertical, self.horizontal
        q = normalise_or_none(q_wxyz)
        yaw_sp = setpoint.yaw_rad
        yaw_rate = setpoint.yaw_rate_rad_s
        fault = False
        if yaw_sp is not None and not math.isfinite(yaw_sp):
            fault = True
            yaw_sp = None
        if not math.isfinite(yaw_rate):
            fault = True
            yaw_rate = 0.0
        dt = _dt_ok(dt_s)
        pn, pe, pd = position_ned_m
        vn, ve, vd = velocity_ned_m_s
        if dt is None or not math.isfinite(pn + pe + pd + vn + ve + vd):
            vert.restart_derivative()
            hor.restart_derivative()
            return self._safe(q, yaw_sp, yaw_rate)

        # Setpoints (a non-finite one: brake and hold the altitude there is).
        hsp, vsp = setpoint.horizontal, setpoint.vertical
        (fn, fe), (an, ae) = hsp.velocity_ne_m_s, hsp.accel_ne_m_s2
        pos_sp = hsp.position_ne_m
        if not math.isfinite(
            fn + fe + an + ae + (0.0 if pos_sp is None else pos_sp[0] + pos_sp[1])
        ):
            fault = True
            fn = fe = an = ae = 0.0
            pos_sp = None
        if not math.isfinite(
            vsp.climb_m_s + vsp.climb_accel_m_s2 + (0.0 if vsp.up_m is None else vsp.up_m)
        ):
            fault = True
            vsp = VerticalSetpoint(0.0, None, 0.0)

        # Position P to the velocity reference (P part first horizontally).
        p_part = _ZERO2
        if pos_sp is not None:
            p_part = (g.xy_p_1_s * (pos_sp[0] - pn), g.xy_p_1_s * (pos_sp[1] - pe))
        vsp_n, vsp_e = constrain_xy(p_part, (fn, fe), g.xy_vel_max_m_s)
        vsp_d = vert.velocity_setpoint(pd, vsp)
        hor.velocity_ref_ne_m_s = (vsp_n, vsp_e)

        # Velocity PID to the acceleration.
        en, ee, ed = vsp_n - vn, vsp_e - ve, vsp_d - vd
        dn, de = hor.derivative(dt, vn, ve)
        i_n, i_e = hor.integral_m_s2
        acc_n = an + g.xy_vel_p_1_s * en + i_n - g.xy_vel_d * dn
        acc_e = ae + g.xy_vel_p_1_s * ee + i_e - g.xy_vel_d * de
        acc_d = vert.acceleration(dt, vd, vsp_d, -vsp.climb_accel_m_s2)

        # Acceleration to a thrust vector (tilt-limited direction, at least thrust_min).
        bx, by, bz = -acc_n, -acc_e, GRAVITY_M_S2
        nb = math.sqrt(bx * bx + by * by + bz * bz)
        body, tilt_clamped = limit_tilt((bx / nb, by / nb, bz / nb), g.tilt_max_rad)
        h = g.hover_thrust
        coll = (acc_d * h / GRAVITY_M_S2 - h) / body[2]
        coll = min(coll, -g.thrust_min)
        tn, te, td = body[0] * coll, body[1] * coll, body[2] * coll

        # Altitude first, keeping a horizontal margin.
        txy = math.hypot(tn, te)
        t_max2 = g.thrust_max * g.thrust_max
        alloc = min(txy, g.thrust_xy_margin)
        td = max(td, -math.sqrt(t_max2 - alloc * alloc))
        # The vertical integrator's anti-windup looks at the thrust before this clamp
        # (as PX4 orders it); the "saturated" flag at the bounds after it.
        vert.integrate(dt, ed, body[2] * coll, vsp.climb_m_s > 0.0 or vsp_d < 0.0)
        rem2 = t_max2 - td * td
        txy_max = math.sqrt(rem2) if rem2 > 0.0 else 0.0
        xy_clamped = txy > txy_max
        if xy_clamped:
            k = txy_max / txy
            tn *= k
            te *= k

        # Horizontal tracking anti-windup, then the integrators.
        pn_acc, pe_acc = tn * GRAVITY_M_S2 / h, te * GRAVITY_M_S2 / h
        if acc_n * acc_n + acc_e * acc_e > pn_acc * pn_acc + pe_acc * pe_acc:
            lim_n, lim_e = pn_acc, pe_acc
        else:
            lim_n, lim_e = acc_n, acc_e
        arw = 2.0 / g.xy_vel_p_1_s
        en -= arw * (acc_n - lim_n)
        ee -= arw * (acc_e - lim_e)
        if not vert.on_ground:
            hor.integral_m_s2 = (i_n + en * g.xy_vel_i_1_s2 * dt, i_e + ee * g.xy_vel_i_1_s2 * dt)
        hor.limited = tilt_clamped or xy_clamped

        # Thrust vector to the attitude setpoint and the collective.
        heading = yaw_sp
        if heading is None:
            heading = yaw_rad(q) if q is not None else 0.0
        thrust = math.sqrt(tn * tn + te * te + td * td)
        q_d = bodyz_to_quat((-tn, -te, -td), heading)
        rates = self.attitude.update_q(q_wxyz, q_d, yaw_rate)
        roll, pitch, _ = _euler_zyx(q_d)
        out_t = min(max(thrust, g.thrust_min), g.thrust_max)
        if not math.isfinite(out_t + roll + pitch + hor.integral_m_s2[0] + hor.integral_m_s2[1]):
            # Only an absurd finite input gets here (its sums overflowed).
            self.reset()
            return self._safe(q, yaw_sp, yaw_rate)
        vert.level_thrust = -td
        vert.saturated = vert.saturated or out_t >= g.thrust_max - 1e-9
        if fault:
            vert.nonfinite_events += 1
        vert.fault = fault
        hor.fault = fault
        att_sp = AttitudeSetpoint(roll, pitch, yaw_sp, yaw_rate)
        tilt_lim = min(g.tilt_max_rad, math.atan2(txy_max, -td))
        return OuterOutput(
            rates,
            out_t,
            att_sp,
            -td,
            tilt_lim,
            hor.limited,
            fault or self.attitude.fault,
        )
