r"""The horizontal loop: position and velocity to roll and pitch setpoints.

Inputs are NED (north, east; ``LOCAL_POSITION_NED``) and the heading the attitude
setpoint will carry; the outputs are that setpoint's roll and pitch (ZYX Euler,
rad), for :class:`~companion.control.attitude.AttitudeLoop`.

Position (hold)
---------------
A proportional law: :math:`v_r = v_{ff} + K_x (p_{sp} - p)` per axis, the vector
clamped to ``speed_max_m_s`` (its direction kept).

Velocity (iP, order 1, per NED axis)
------------------------------------
The command of each axis is the *tilt vector* ``u``: the horizontal component of
the thrust direction over its vertical one, in NED. With the collective
compensated for tilt (the vertical loop holds the vertical thrust at the
weight), the horizontal acceleration it gives is exactly :math:`g\,u`, so

.. math::  \dot v_i = F_i + \alpha u_i, \qquad \alpha = g, \qquad
           u_i = -\frac{\hat F_i - \dot v_{r,i} + K_v (v_i - v_{r,i})}{\alpha}

:math:`\alpha = g` is known (gravity; no vehicle parameter) and exact, not only
for small angles: :math:`|u| = \tan\vartheta` (tilt :math:`\vartheta`), which for
small angles is the tilt itself. ``F`` holds drag, wind, the attitude loop's lag
(:class:`~companion.control.ultralocal.LagAwareEstimate` models it) and the rest.
:math:`\dot v` is the finite difference of the measured velocity. The models are
per *NED* axis, not per heading axis: a yaw turn does not rotate the window's
history, and drag and wind are no more heading-bound than north-bound. The tilt
vector is clamped to :math:`\tan` (``tilt_max_rad``, or the caller's lower limit:
altitude first, :class:`~companion.control.outer.OuterController`), its direction
kept; the estimate learns from the clamped one.

To roll and pitch, through the heading
--------------------------------------
In the heading frame (x forward along the heading :math:`\psi`, y right, level):
:math:`u_f = u_N \cos\psi + u_E \sin\psi`, :math:`u_r = -u_N \sin\psi + u_E
\cos\psi`. The thrust (along body :math:`-z`) of the ZYX attitude
:math:`(\phi, \theta, \psi)` points along :math:`(-\sin\theta\cos\phi,\; \sin\phi,\;
-\cos\theta\cos\phi)` in the heading frame, so

.. math::  \theta = -\arctan u_f, \qquad \phi = \arctan(u_r \cos\theta)

Pitch down (negative) accelerates forward; roll right (positive) accelerates
right. Facing east (:math:`\psi = 90°`), a northward demand is a roll to the left.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

from companion.control.quaternion import Quat, body_z_ned, normalise_or_none
from companion.control.ultralocal import (
    DT_MAX_S,
    DT_MIN_S,
    GRAVITY_M_S2,
    LagAwareEstimate,
    check_positive,
)

__all__ = [
    "DEFAULT_HORIZONTAL_GAINS",
    "HORIZONTAL_ALPHA",
    "HorizontalGains",
    "HorizontalLoop",
    "HorizontalSetpoint",
    "tilt_of_attitude",
    "tilt_to_roll_pitch",
]

HORIZONTAL_ALPHA = GRAVITY_M_S2
"""alpha of the horizontal model, (m/s^2) per unit tilt vector: gravity, not a gain."""

Vec2 = tuple[float, float]
_ZERO2: Vec2 = (0.0, 0.0)


@dataclass(frozen=True)
class HorizontalGains:
    """The horizontal loop's gains and bounds (one set: :data:`DEFAULT_HORIZONTAL_GAINS`).

    Attributes
    ----------
    kp_velocity_1_s
        :math:`K_v`, 1/s: velocity error decay rate.
    kp_position_1_s
        :math:`K_x`, 1/s: position error to velocity reference (1.0 with
        :math:`K_v` 2.0: damping sqrt(K_v / K_x) / 2 = 1 / sqrt(2) on an ideal
        velocity loop).
    speed_max_m_s
        Bound on the velocity reference's magnitude, m/s (12: PX4's
        ``MPC_XY_VEL_MAX``; above the sticks' 10 m/s, ``MPC_VEL_MANUAL``, so a
        full stick, and a fast leg with its position error, are not cut short).
    tilt_max_rad
        Bound on the tilt, rad, in (0, pi/2) (45 deg: PX4's ``MPC_TILTMAX_AIR``,
        as its position controller; 35 deg before the gains were raised).
    window_s, inner_lag_s
        Window and lag (the attitude loop) of the estimate of ``F``, s.
    """

    kp_velocity_1_s: float = 2.0
    kp_position_1_s: float = 1.0
    speed_max_m_s: float = 12.0
    tilt_max_rad: float = math.radians(45.0)
    window_s: float = 1.0
    inner_lag_s: float = 0.26

    def __post_init__(self) -> None:
        check_positive(
            self,
            (
                "kp_velocity_1_s", "kp_position_1_s", "speed_max_m_s", "tilt_max_rad", "window_s",
            ),
        )  # fmt: skip
        check_positive(self, ("inner_lag_s",), zero_ok=True)
        if self.tilt_max_rad >= 0.5 * math.pi:
            raise ValueError(
                f"HorizontalGains.tilt_max_rad must be in (0, pi/2), got {self.tilt_max_rad!r}"
            )


DEFAULT_HORIZONTAL_GAINS = HorizontalGains()
"""The shipped horizontal gains (``docs/research/outer.md``)."""


class HorizontalSetpoint(NamedTuple):
    """What the horizontal loop is asked to fly (NED)."""

    velocity_ne_m_s: Vec2 = _ZERO2
    """Velocity reference (feedforward with a position setpoint), north and east, m/s."""
    position_ne_m: Vec2 | None = None
    """Position to hold, north and east, m; ``None``: velocity mode."""
    accel_ne_m_s2: Vec2 = _ZERO2
    """The velocity reference's derivative (feedforward), m/s^2."""


def tilt_to_roll_pitch(u_north: float, u_east: float, heading_rad: float) -> Vec2:
    """Tilt vector (NED) to the (roll, pitch) of a ZYX attitude at ``heading_rad``, rad
    (module docstring: exact, not small-angle)."""
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    u_f = u_north * c + u_east * s
    u_r = -u_north * s + u_east * c
    pitch = -math.atan(u_f)
    roll = math.atan(u_r * math.cos(pitch))
    return (roll, pitch)


def tilt_of_attitude(q_wxyz: Quat) -> Vec2:
    """The tilt vector (NED) an attitude flies: the thrust's north and east
    components over its upward one; zero for a quaternion that is no rotation,
    and for a thrust that does not point up."""
    q = normalise_or_none(q_wxyz)
    if q is None:
        return _ZERO2
    bn, be, bd = body_z_ned(q)  # the thrust points along -body z
    if not bd > 1e-3:
        return _ZERO2
    return (-bn / bd, -be / bd)


class HorizontalLoop:
    """Velocity (and position) to roll and pitch setpoints (module docstring).

    Attributes (after each :meth:`update`)
    ---------------------------------------
    tilt_ne
        The tilt vector sent, north and east (``tan`` of the tilt in magnitude).
    velocity_ref_ne_m_s
        The velocity reference flown, m/s.
    f_hat
        :math:`\\hat F` per axis, m/s^2.
    limited
        Whether the tilt was clamped.
    gain_scale
        The velocity and position gains' scale (:meth:`set_gain_scale`).
    fault
        True when a non-finite input was replaced (see :meth:`update`).
    """

    __slots__ = (
        "_est",
        "_gains",
        "_kv",
        "_kx",
        "_tan_max",
        "_v_prev",
        "dt_clamped_events",
        "f_hat",
        "fault",
        "gain_scale",
        "limited",
        "nonfinite_events",
        "tilt_ne",
        "velocity_ref_ne_m_s",
    )

    def __init__(self, gains: HorizontalGains = DEFAULT_HORIZONTAL_GAINS) -> None:
        self._gains = gains
        self._tan_max = math.tan(gains.tilt_max_rad)
        self._kv = gains.kp_velocity_1_s
        self._kx = gains.kp_position_1_s
        self.gain_scale = 1.0
        self._est = (
            LagAwareEstimate(gains.window_s, gains.inner_lag_s),
            LagAwareEstimate(gains.window_s, gains.inner_lag_s),
        )
        self.nonfinite_events = 0
        self.dt_clamped_events = 0
        self.reset()

    @property
    def gains(self) -> HorizontalGains:
        return self._gains

    def set_gain_scale(self, scale: float) -> None:
        """Scale the velocity and position gains by ``scale`` from the next update
        (:class:`~companion.control.outer.SaturationBackoff`)."""
        self._kv = self._gains.kp_velocity_1_s * scale
        self._kx = self._gains.kp_position_1_s * scale
        self.gain_scale = scale

    def reset(self, tilt_ne: Vec2 = _ZERO2) -> None:
        """Forget the windows and the references. The vehicle is taken to be at rest
        holding the tilt vector ``tilt_ne`` (level by default; bounded to
        ``tilt_max_rad``): the windows start full of that rest, and :math:`\\hat F
        = -\\alpha u` holds it, so the first output is that tilt (an engagement
        from the autopilot's own hold starts from the attitude it flew)."""
        tn, te = tilt_ne
        mag = math.hypot(tn, te)
        if not math.isfinite(mag):
            tn = te = 0.0
        elif mag > self._tan_max:
            tn, te = tn * self._tan_max / mag, te * self._tan_max / mag
        for est, u in zip(self._est, (tn, te), strict=True):
            est.reset(u, -HORIZONTAL_ALPHA * u, at_rest=True)
        self._v_prev: Vec2 | None = None
        self.tilt_ne: Vec2 = (tn, te)
        self.velocity_ref_ne_m_s: Vec2 = _ZERO2
        self.f_hat: Vec2 = _ZERO2
        self.limited = False
        self.fault = False

    def update(
        self,
        dt_s: float,
        position_ne_m: Vec2,
        velocity_ne_m_s: Vec2,
        heading_rad: float,
        setpoint: HorizontalSetpoint,
        *,
        tilt_limit_rad: float = math.inf,
    ) -> Vec2:
        """One update; returns (roll, pitch) setpoints, rad, at ``heading_rad``.

        Parameters
        ----------
        dt_s
            Time since the previous update, s; clamped to [DT_MIN_S, DT_MAX_S].
        position_ne_m, velocity_ne_m_s
            Measured north/east position (m) and velocity (m/s).
        heading_rad
            The heading of the attitude setpoint the output goes into, rad.
        setpoint
            Velocity, position (or none), acceleration feedforward.
        tilt_limit_rad
            A tilt limit below ``tilt_max_rad`` for this update (altitude first);
            the lower of the two applies.

        Failure behaviour (:attr:`fault` set, :attr:`nonfinite_events` counted)
        -----------------------------------------------------------------------
        * position, velocity, heading or ``dt_s`` non-finite (or ``dt_s <= 0``):
          level (roll = pitch = 0), nothing learnt, and the next valid sample
          starts a new finite difference;
        * setpoint non-finite: a velocity reference of zero (brake and hold);
        * ``tilt_limit_rad`` NaN: ``tilt_max_rad``.
        """
        g = self._gains
        fault = False
        pn, pe = position_ne_m
        vn, ve = velocity_ne_m_s
        if not (math.isfinite(dt_s + pn + pe + vn + ve + heading_rad) and dt_s > 0.0):
            self.nonfinite_events += 1
            self.fault = True
            self._v_prev = None
            self.tilt_ne = _ZERO2
            self.limited = False
            return _ZERO2
        if dt_s < DT_MIN_S or dt_s > DT_MAX_S:
            self.dt_clamped_events += 1
            dt_s = DT_MIN_S if dt_s < DT_MIN_S else DT_MAX_S

        # F per NED axis, from the acceleration and the tilt vector sent last time.
        en, ee = self._est
        prev = self._v_prev
        if prev is not None:
            un, ue = self.tilt_ne
            en.update(dt_s, (vn - prev[0]) / dt_s, un, HORIZONTAL_ALPHA)
            ee.update(dt_s, (ve - prev[1]) / dt_s, ue, HORIZONTAL_ALPHA)
        self._v_prev = (vn, ve)
        fn, fe = en.f_hat, ee.f_hat
        self.f_hat = (fn, fe)

        # The reference: position P on top of the velocity feedforward, bounded.
        sp = setpoint
        (rn, re), (an, ae) = sp.velocity_ne_m_s, sp.accel_ne_m_s2
        pos_sp = sp.position_ne_m
        if not math.isfinite(
            rn + re + an + ae + (0.0 if pos_sp is None else pos_sp[0] + pos_sp[1])
        ):
            fault = True
            rn = re = an = ae = 0.0
            pos_sp = None
        if pos_sp is not None:
            kx = self._kx
            rn += kx * (pos_sp[0] - pn)
            re += kx * (pos_sp[1] - pe)
        speed = math.hypot(rn, re)
        if speed > g.speed_max_m_s:
            k = g.speed_max_m_s / speed
            rn *= k
            re *= k
        self.velocity_ref_ne_m_s = (rn, re)

        # iP per axis, then the tilt bound on the vector.
        kv = self._kv
        un = -(fn - an + kv * (vn - rn)) / HORIZONTAL_ALPHA
        ue = -(fe - ae + kv * (ve - re)) / HORIZONTAL_ALPHA
        tan_lim = self._tan_max
        if tilt_limit_rad < g.tilt_max_rad:  # (NaN compares False: tilt_max_rad)
            tan_lim = math.tan(tilt_limit_rad) if tilt_limit_rad > 0.0 else 0.0
        mag = math.hypot(un, ue)
        limited = mag > tan_lim
        if limited:
            k = tan_lim / mag
            un *= k
            ue *= k
        if not math.isfinite(un + ue):  # an absurd finite input overflowed: start again
            fault = True
            self.reset()
            un = ue = 0.0
        self.tilt_ne = (un, ue)
        self.limited = limited
        if fault:
            self.nonfinite_events += 1
        self.fault = fault
        return tilt_to_roll_pitch(un, ue, heading_rad)
