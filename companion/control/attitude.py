r"""The attitude loop: attitude estimate and setpoint to a body-rate reference.

The outermost-but-one loop of the cascade (``docs/research/outer.md``): its
output is the reference of the rate loop (:class:`companion.control.MfcController`,
or an autopilot's own rate loop over ``SET_ATTITUDE_TARGET``), which stays as it is.

Attitude error (tilt first, as PX4's ``AttitudeControl::update``)
-----------------------------------------------------------------
With ``q`` the estimate and ``q_d`` the setpoint (body FRD to NED):

1. the *reduced* setpoint :math:`q_{red} = q_{arc} \otimes q`, :math:`q_{arc}` the
   shortest rotation taking the body z axis (in NED) onto the setpoint's: it tilts
   the thrust where it should point and leaves the heading alone;
2. the heading still missing, :math:`q_{red}^{-1} \otimes q_d`, is a rotation by
   :math:`\psi_m \in [-\pi, \pi]` about z; only a share ``yaw_weight`` of it is
   asked for at once: :math:`q_w = q_{red} \otimes q_z(w_\psi \psi_m)`;
3. the error is the rotation vector (axis times angle, the short way) of
   :math:`q^{-1} \otimes q_w`, in body axes, rad: :math:`\varepsilon`.

So a large tilt error is fixed by roll and pitch before yaw spends the motors'
differential thrust (yaw is the weakest axis), a heading error of 170 deg
against -170 deg is 20 deg the short way, and a 180 deg error stays finite. The
yaw gain is divided by ``yaw_weight`` (as PX4 does), so a pure heading error
:math:`\psi_e` still gets :math:`K_\psi \psi_e`. Without a heading
(``yaw_rad = None``), step 2 is skipped (weight 0): the yaw axis follows the yaw-rate
feedforward alone.

The ultra-local model, per body axis (iP, order 1)
--------------------------------------------------
``y`` is the body-axis angle, the integral of the gyro rate, as in the rate loop
(:mod:`companion.control.estimator`): :math:`\dot y = \omega`, measured by the
gyro, and the command is the body-rate reference :math:`u = \omega_r`:

.. math::  \dot y = F + \alpha\, \omega_r, \qquad \alpha = 1

:math:`\alpha` is known: the derivative of a body-axis angle is the body rate,
exactly (kinematics, no vehicle parameter), so a rate reference the rate loop
delivers moves the angle by itself. ``F`` is what the rate loop does not deliver
(its lag, its saturation, its errors), estimated with
:class:`~companion.control.ultralocal.LagAwareEstimate`. With
:math:`e = y - y_r = -\varepsilon` the iP law reads

.. math::  \omega_r = -\frac{\hat F - \dot y_r + K_P e}{\alpha}
           = \dot y_r + K_P \varepsilon - \hat F

with :math:`\dot y_r` the setpoint's own rate in body axes: the yaw-rate
feedforward about the NED vertical, :math:`r_{ff} R^T e_z`. Each axis is saturated
at its maximum rate; the estimate learns from the saturated reference.

With a perfect ``F`` (a rate loop that delivers its reference), a rotation about
one axis obeys :math:`\dot\varepsilon = -K_P \varepsilon`:
:math:`\varepsilon(t) = \varepsilon_0 e^{-K_P t}`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

from companion.control.quaternion import (
    Quat,
    Vec3,
    body_z_ned,
    canonical,
    euler_to_quat,
    ned_down_frd,
    normalise_or_none,
    quat_conj,
    quat_log,
    quat_mul,
    shortest_arc,
    yaw_rad,
)
from companion.control.ultralocal import DT_MAX_S, DT_MIN_S, LagAwareEstimate, check_positive

__all__ = [
    "ATTITUDE_ALPHA",
    "DEFAULT_ATTITUDE_GAINS",
    "AttitudeGains",
    "AttitudeLoop",
    "AttitudeSetpoint",
    "attitude_error_frd_rad",
]

ATTITUDE_ALPHA = 1.0
"""alpha of the attitude model, (rad/s) per (rad/s): kinematics, not a gain."""

_ZERO3: Vec3 = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class AttitudeGains:
    """The attitude loop's gains (one set for every vehicle: :data:`DEFAULT_ATTITUDE_GAINS`).

    Attributes
    ----------
    kp_roll_pitch_1_s, kp_yaw_1_s
        :math:`K_P`, 1/s: the error's decay rate with a perfect ``F``.
    yaw_weight
        Share of a heading error asked for at once, in (0, 1] (tilt first).
    rate_max_roll_pitch_rad_s, rate_max_yaw_rad_s
        Saturation of the rate reference, rad/s.
    window_s
        Window of the estimate of ``F``, s.
    inner_lag_s
        The rate loop's expected lag in the estimate of ``F``, s (0: the paper's).
    """

    kp_roll_pitch_1_s: float = 5.5
    kp_yaw_1_s: float = 2.5
    yaw_weight: float = 0.4
    rate_max_roll_pitch_rad_s: float = math.radians(220.0)
    rate_max_yaw_rad_s: float = math.radians(150.0)
    window_s: float = 0.1
    inner_lag_s: float = 0.08

    def __post_init__(self) -> None:
        check_positive(
            self,
            (
                "kp_roll_pitch_1_s", "kp_yaw_1_s", "yaw_weight", "rate_max_roll_pitch_rad_s",
                "rate_max_yaw_rad_s", "window_s",
            ),
        )  # fmt: skip
        check_positive(self, ("inner_lag_s",), zero_ok=True)
        if self.yaw_weight > 1.0:
            raise ValueError(f"AttitudeGains.yaw_weight must be in (0, 1], got {self.yaw_weight!r}")


DEFAULT_ATTITUDE_GAINS = AttitudeGains()
"""The shipped attitude gains (``docs/research/outer.md``: the bandwidth separation)."""


class AttitudeSetpoint(NamedTuple):
    """What the attitude loop is asked to fly (ZYX Euler, NED)."""

    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float | None = None
    """Heading to hold, rad; ``None``: no heading, the yaw follows ``yaw_rate_rad_s``."""
    yaw_rate_rad_s: float = 0.0
    """Feedforward rate about the NED vertical, rad/s (positive: nose right)."""


def attitude_error_frd_rad(q: Quat, q_sp: Quat, yaw_weight: float) -> Vec3:
    r"""Tilt-first attitude error: the rotation vector from ``q`` to the weighted
    setpoint, body FRD, rad (module docstring, steps 1-3).

    Parameters
    ----------
    q, q_sp
        Unit quaternions (w, x, y, z), body FRD to NED: the estimate and the setpoint.
    yaw_weight
        Share of the heading error kept, in [0, 1] (0: tilt only).
    """
    qd_red = shortest_arc(body_z_ned(q), body_z_ned(q_sp))
    if abs(qd_red[1]) > 1.0 - 1e-5 or abs(qd_red[2]) > 1.0 - 1e-5:
        # Thrust axes opposite: the shortest arc has no unique axis; the full
        # setpoint then carries roll and pitch to the right heading (as PX4).
        qd_red = q_sp
    else:
        qd_red = quat_mul(qd_red, q)
    if yaw_weight > 0.0:
        q_mix = canonical(quat_mul(quat_conj(qd_red), q_sp))
        half = 0.5 * yaw_weight * 2.0 * math.atan2(q_mix[3], q_mix[0])
        q_w = quat_mul(qd_red, (math.cos(half), 0.0, 0.0, math.sin(half)))
    else:
        q_w = qd_red
    return quat_log(quat_mul(quat_conj(q), q_w))


class AttitudeLoop:
    r"""Attitude to body-rate reference: an iP per body axis (module docstring).

    Parameters
    ----------
    gains
        :data:`DEFAULT_ATTITUDE_GAINS` unless testing.

    Attributes (after each :meth:`update`)
    ---------------------------------------
    error_frd_rad
        The attitude error :math:`\varepsilon` (setpoint minus estimate), rad.
    f_hat
        :math:`\hat F` per axis, rad/s.
    saturated
        Per axis, whether the rate reference was at its limit.
    gain_scale
        The roll and pitch gain's scale (:meth:`set_gain_scale`).
    fault
        True when a non-finite or invalid input was replaced (see :meth:`update`).
    """

    __slots__ = (
        "_est",
        "_gains",
        "_k",
        "_lim",
        "_primed",
        "_u",
        "dt_clamped_events",
        "error_frd_rad",
        "f_hat",
        "fault",
        "gain_scale",
        "nonfinite_events",
        "saturated",
    )

    def __init__(self, gains: AttitudeGains = DEFAULT_ATTITUDE_GAINS) -> None:
        self._gains = gains
        w = gains.yaw_weight
        self._k = (gains.kp_roll_pitch_1_s, gains.kp_roll_pitch_1_s, gains.kp_yaw_1_s / w)
        self.gain_scale = 1.0
        rp, yw = gains.rate_max_roll_pitch_rad_s, gains.rate_max_yaw_rad_s
        self._lim = (rp, rp, yw)
        self._est = (
            LagAwareEstimate(gains.window_s, gains.inner_lag_s),
            LagAwareEstimate(gains.window_s, gains.inner_lag_s),
            LagAwareEstimate(gains.window_s, gains.inner_lag_s),
        )
        self.nonfinite_events = 0
        self.dt_clamped_events = 0
        self.reset()

    @property
    def gains(self) -> AttitudeGains:
        return self._gains

    def set_gain_scale(self, scale: float) -> None:
        """Scale the roll and pitch gain by ``scale`` from the next update (the
        heading's stays: :class:`~companion.control.outer.SaturationBackoff`)."""
        g = self._gains
        k = g.kp_roll_pitch_1_s * scale
        self._k = (k, k, self._k[2])
        self.gain_scale = scale

    def reset(self) -> None:
        """Forget the windows and the last reference (on disarm, on hand-back)."""
        for est in self._est:
            est.reset()
        self._primed = False
        self._u: Vec3 = _ZERO3
        self.error_frd_rad: Vec3 = _ZERO3
        self.f_hat: Vec3 = _ZERO3
        self.saturated = (False, False, False)
        self.fault = False

    def update(
        self, dt_s: float, q_wxyz: Quat, rate_frd_rad_s: Vec3, setpoint: AttitudeSetpoint
    ) -> Vec3:
        """One update; returns the body-rate reference (FRD, rad/s) for the rate loop.

        Parameters
        ----------
        dt_s
            Time since the previous update (sample timestamps), s; clamped to
            [DT_MIN_S, DT_MAX_S].
        q_wxyz
            Attitude estimate, body FRD to NED (normalised here).
        rate_frd_rad_s
            Measured body rates (gyro), rad/s: :math:`\\dot y`.
        setpoint
            Roll, pitch, heading (or none) and yaw-rate feedforward.

        Failure behaviour (:attr:`fault` set, :attr:`nonfinite_events` counted)
        -----------------------------------------------------------------------
        * estimate non-finite or of zero norm: zero rates (the rate loop holds the
          attitude it has), the estimate of ``F`` not updated;
        * setpoint non-finite: level at the current heading, no feedforward;
        * rates non-finite, or ``dt_s`` not finite and > 0: the estimate of ``F``
          is not updated this sample (the law runs on the last one).
        """
        fault = False
        q = normalise_or_none(q_wxyz)
        if q is None:
            self.nonfinite_events += 1
            self.fault = True
            self._u = _ZERO3
            self.saturated = (False, False, False)
            return _ZERO3
        sp = setpoint
        yaw_sp = sp.yaw_rad
        if not math.isfinite(
            sp.roll_rad + sp.pitch_rad + sp.yaw_rate_rad_s + (0.0 if yaw_sp is None else yaw_sp)
        ):
            fault = True
            sp = AttitudeSetpoint(0.0, 0.0, None, 0.0)
            yaw_sp = None
        w0, w1, w2 = rate_frd_rad_s
        learn = math.isfinite(dt_s + w0 + w1 + w2) and dt_s > 0.0
        if not learn:
            fault = True
        elif dt_s < DT_MIN_S or dt_s > DT_MAX_S:
            self.dt_clamped_events += 1
            dt_s = DT_MIN_S if dt_s < DT_MIN_S else DT_MAX_S

        # The error: tilt first, then a share of the heading (none without a heading).
        if yaw_sp is None:
            q_sp = euler_to_quat(sp.roll_rad, sp.pitch_rad, yaw_rad(q))
            eps = attitude_error_frd_rad(q, q_sp, 0.0)
        else:
            q_sp = euler_to_quat(sp.roll_rad, sp.pitch_rad, yaw_sp)
            eps = attitude_error_frd_rad(q, q_sp, self._gains.yaw_weight)
        self.error_frd_rad = eps

        # F per axis, from the gyro and the reference sent last time.
        e0, e1, e2 = self._est
        if not learn:
            pass
        elif self._primed:
            u = self._u
            e0.update(dt_s, w0, u[0], ATTITUDE_ALPHA)
            e1.update(dt_s, w1, u[1], ATTITUDE_ALPHA)
            e2.update(dt_s, w2, u[2], ATTITUDE_ALPHA)
        else:
            # First sample: nothing of ours was applied yet. The rate loop is taken
            # to be following what the vehicle does now.
            e0.reset(w0)
            e1.reset(w1)
            e2.reset(w2)
            self._primed = True
        f = (e0.f_hat, e1.f_hat, e2.f_hat)
        self.f_hat = f

        # iP: omega_r = (y_r' + K eps - F) / alpha, y_r' the feedforward in body axes.
        r_ff = sp.yaw_rate_rad_s
        d = ned_down_frd(q)
        k = self._k
        lim = self._lim
        out = [0.0, 0.0, 0.0]
        sat = [False, False, False]
        for i in range(3):
            u_i = (r_ff * d[i] + k[i] * eps[i] - f[i]) / ATTITUDE_ALPHA
            li = lim[i]
            if u_i > li:
                u_i = li
                sat[i] = True
            elif u_i < -li:
                u_i = -li
                sat[i] = True
            out[i] = u_i
        res: Vec3 = (out[0], out[1], out[2])
        if not math.isfinite(res[0] + res[1] + res[2]):
            # Only an absurd (finite) input can get here (its sums overflowed): start
            # the estimate again rather than carry it.
            fault = True
            res = _ZERO3
            self._primed = False
        self._u = res
        self.saturated = (sat[0], sat[1], sat[2])
        if fault:
            self.nonfinite_events += 1
        self.fault = fault
        return res
