r"""Motor mixing: normalised torques and thrust to per-motor commands.

Conventions
-----------
Torques are normalised in [-1, 1] about the FRD body axes: +roll = roll right,
+pitch = nose up, +yaw = nose right. Thrust and motor commands are in [0, 1].

For a motor at body position (x, y) (metres, FRD) producing thrust ``T`` along
-z, the torque is ``r x F = (-y*T, x*T, 0)``: a motor on the right (y > 0) rolls
the vehicle left, a motor in front (x > 0) pitches the nose up. A propeller
spinning counter-clockwise seen from above pushes the body clockwise, which is
+yaw in FRD. So the mixing factors are

.. math::  R_i = -y_i / \max_j |y_j|, \quad P_i = x_i / \max_j |x_j|, \quad
           Y_i = +1 \text{ (ccw) or } -1 \text{ (cw)}

and ``motor_i = thrust + 0.5 * (R_i*roll + P_i*pitch + Y_i*yaw)``: a full-scale
command on one axis at mid throttle drives the extreme motors to 0 and 1. In
the paper's units a full-scale command is 500 us of differential PWM.

Saturation priority (air mode): roll and pitch first, scaled together when
their spread alone exceeds the motor range; then the collective is shifted so
they fit (authority is kept at zero throttle and at full throttle); yaw gets
the headroom left, and, when the caller offers it a share, as much of roll
and pitch as that share allows. The result reports what was achieved and what
saturated, so a caller can keep an estimator from learning a command that was
never applied.

Yaw never moves the collective. Borrowing some downwards (PX4's
``MC_REDUCE_THRUST``) bought yaw on the cut-prop F450 but sank and crashed
vehicles with a weak motor, gated or not; upwards it cost a light, strong quad
its yaw on the held-out flight. The measurements: docs/research/mixer.md.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

__all__ = ["MixResult", "Mixer"]


class MixResult(NamedTuple):
    """What one call to :meth:`Mixer.mix` produced."""

    motors: tuple[float, ...]
    """Per-motor commands in [idle, 1], in the frame's output order."""
    achieved: tuple[float, float, float]
    """Roll, pitch, yaw torques actually realised (normalised)."""
    saturated_axes: tuple[bool, bool, bool]
    """True where the realised torque is smaller than the requested one."""
    saturated_motors: tuple[bool, ...]
    """True for motors at idle or at full command."""
    thrust: float
    """The collective actually realised (air mode may shift it)."""
    yaw_share: float
    """The fraction of roll and pitch given up for yaw (0 unless a share was
    offered and yaw did not fit without it)."""


_INF = math.inf
_TINY = 1e-9  # |yaw| below this is no request: avoids dividing by an underflowed product
_SHARE_STEPS = 8  # bisection steps for the yaw share: within 1/256 of the share


def _clamp_or_zero(x: float, lo: float, hi: float) -> float:
    """Clamp a finite value to [lo, hi]; NaN and infinities become 0 (no request)."""
    if x != x or x == _INF or x == -_INF:
        return 0.0
    return lo if x < lo else (hi if x > hi else x)


# NamedTuple's generated __new__ is a Python function; building through
# tuple.__new__ directly halves the cost on the per-sample path.
_new_tuple = tuple.__new__


class Mixer:
    """A quadrotor (or any flat multirotor) mixer with air-mode saturation.

    Parameters
    ----------
    roll_factors, pitch_factors, yaw_factors
        Per-motor factors, dimensionless; ``0.5 * factor`` is a motor's
        command change per unit of normalised torque.
    idle
        Lowest command a running motor receives, in [0, 1).
    """

    __slots__ = ("_no_sat", "_pf", "_quad", "_rf", "_rp", "_yf", "idle", "mix_fn", "n_motors")

    def __init__(
        self,
        roll_factors: Sequence[float],
        pitch_factors: Sequence[float],
        yaw_factors: Sequence[float],
        *,
        idle: float = 0.0,
    ) -> None:
        n = len(roll_factors)
        if not (len(pitch_factors) == n == len(yaw_factors)) or n < 3:
            raise ValueError("expected equally long factor lists for at least 3 motors")
        if not 0.0 <= idle < 0.5:
            raise ValueError(f"idle must be in [0, 0.5), got {idle!r}")
        factors = [*roll_factors, *pitch_factors, *yaw_factors]
        if not all(math.isfinite(f) for f in factors):
            raise ValueError("mixer factors must be finite")
        self._rf = tuple(0.5 * float(f) for f in roll_factors)
        self._pf = tuple(0.5 * float(f) for f in pitch_factors)
        self._yf = tuple(0.5 * float(f) for f in yaw_factors)
        self._rp = tuple(zip(self._rf, self._pf))
        self._no_sat = (False,) * n
        # The unrolled path assumes four motors that all take part in yaw.
        self._quad = n == 4 and all(abs(k) >= 1e-6 for k in self._yf)
        #: :meth:`mix` for this geometry, bound once: same contract, one call
        #: less on the per-sample path.
        self.mix_fn = self._mix_quad if self._quad else self._mix_generic
        self.idle = float(idle)
        self.n_motors = n

    @classmethod
    def from_geometry(
        cls,
        positions_frd_m: Sequence[Sequence[float]],
        spins: Sequence[str],
        *,
        idle: float = 0.0,
    ) -> Mixer:
        """Derive the factors from motor positions and spin directions.

        Parameters
        ----------
        positions_frd_m
            Motor positions (x forward, y right[, z down]) in metres.
        spins
            ``"cw"`` or ``"ccw"`` seen from above, per motor.
        """
        if len(positions_frd_m) != len(spins):
            raise ValueError("expected one spin direction per motor position")
        xs = [float(p[0]) for p in positions_frd_m]
        ys = [float(p[1]) for p in positions_frd_m]
        x_max = max(abs(x) for x in xs)
        y_max = max(abs(y) for y in ys)
        if x_max <= 0.0 or y_max <= 0.0:
            raise ValueError("motors must be spread in both x and y to control roll and pitch")
        yaw = []
        for s in spins:
            if s not in ("cw", "ccw"):
                raise ValueError(f"spin must be 'cw' or 'ccw', got {s!r}")
            yaw.append(1.0 if s == "ccw" else -1.0)
        return cls([-y / y_max for y in ys], [x / x_max for x in xs], yaw, idle=idle)

    @classmethod
    def paper(cls, *, idle: float = 0.0) -> Mixer:
        """The paper's equation (motors), in FRD torque terms.

        The paper writes ``u1 = ut - u_theta - u_psi``, ``u2 = ut - u_phi + u_psi``,
        ``u3 = ut + u_theta - u_psi``, ``u4 = ut + u_phi + u_psi`` for a '+'
        frame: motor 1 front, 2 right, 3 back, 4 left; 1 and 3 spin clockwise,
        2 and 4 counter-clockwise. Its text fixes the signs: rolling right
        raises motor 4 and lowers motor 2 (so ``u_phi`` = +roll), pitching
        *forward* raises motor 3 and lowers motor 1 (so the paper's
        ``u_theta`` is nose-down positive, = -pitch in FRD), and ``u_psi`` > 0
        raises the counter-clockwise motors 2 and 4 (= +yaw in FRD).
        With ``u_theta = -pitch`` the rows become the factors below.
        """
        return cls(
            roll_factors=[0.0, -1.0, 0.0, 1.0],
            pitch_factors=[1.0, 0.0, -1.0, 0.0],
            yaw_factors=[-1.0, 1.0, -1.0, 1.0],
            idle=idle,
        )

    def factors(self) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
        """The (roll, pitch, yaw) factors as given (before the 0.5 scale)."""
        return (
            tuple(2.0 * f for f in self._rf),
            tuple(2.0 * f for f in self._pf),
            tuple(2.0 * f for f in self._yf),
        )

    def mix(
        self, thrust: float, roll: float, pitch: float, yaw: float, yaw_share: float = 0.0
    ) -> MixResult:
        """Allocate thrust and torques to motors with air-mode priority.

        ``yaw_share`` in [0, 1] lets yaw go ahead of roll and pitch by that much:
        when the yaw asked does not fit in the headroom they leave, roll and pitch
        are shrunk together, by no more than the share, to the least that lets it
        fit. They are shrunk only where that gives yaw more or, at the top of the
        collective, gives back lift the air mode cut so that they fit (the
        collective is never moved past the one asked, and never for yaw).
        :class:`~companion.control.yaw_share.YawShare` decides the share from the
        flight.

        Non-finite inputs (NaN, +/-inf) are treated as zero, finite ones are
        clamped to their range (and a clamped request counts as saturated);
        every output is finite and in ``[idle, 1]``.
        """
        if self._quad:
            return self._mix_quad(thrust, roll, pitch, yaw, yaw_share)
        return self._mix_generic(thrust, roll, pitch, yaw, yaw_share)

    def _mix_generic(
        self, thrust: float, roll: float, pitch: float, yaw: float, yaw_share: float = 0.0
    ) -> MixResult:
        idle = self.idle
        t = _clamp_or_zero(thrust, 0.0, 1.0)
        r = _clamp_or_zero(roll, -1.0, 1.0)
        p = _clamp_or_zero(pitch, -1.0, 1.0)
        y = _clamp_or_zero(yaw, -1.0, 1.0)
        if -_TINY < y < _TINY:
            y = 0.0

        # 1. Roll and pitch: scale both together if their spread exceeds the range.
        d = [a * r + b * p for a, b in self._rp]
        spread = max(d) - min(d)
        rp_scale = 1.0
        span = 1.0 - idle
        if spread > span:
            rp_scale = span / spread
            d = [di * rp_scale for di in d]
        # 2. and 3. The collective shifted so they fit, yaw in the headroom left.
        t_eff, y_scale = self._fit(t, d, y)
        # 4. A yaw share: roll and pitch shrunk, by at most the share, until yaw fits.
        given = 0.0
        share = _clamp_or_zero(yaw_share, 0.0, 1.0)
        if y_scale < 1.0 and share > 0.0:
            f_fits = 1.0 - share
            d_fit = [di * f_fits for di in d]
            t_fit, ys_fit = self._fit(t, d_fit, y)
            if ys_fit >= 1.0:  # the least shrink that fits, by bisection
                f_short = 1.0
                for _ in range(_SHARE_STEPS):
                    f = 0.5 * (f_fits + f_short)
                    d_f = [di * f for di in d]
                    t_f, ys_f = self._fit(t, d_f, y)
                    if ys_f >= 1.0:
                        f_fits, d_fit, t_fit, ys_fit = f, d_f, t_f, ys_f
                    else:
                        f_short = f
            # Shrunk where it gives yaw more or, at the top of the collective, gives
            # back lift the air mode cut so roll and pitch fit (never more than asked).
            if ys_fit > y_scale or t_fit > t_eff:
                given = min(share, 1.0 - f_fits)
                rp_scale *= f_fits
                d, t_eff, y_scale = d_fit, t_fit, ys_fit
        ye = y * y_scale
        motors = [t_eff + di + k * ye for di, k in zip(d, self._yf)]
        lo_ok = idle + 1e-9
        hi_ok = 1.0 - 1e-9
        if min(motors) > lo_ok and max(motors) < hi_ok:
            sat = self._no_sat  # the common case: nothing touches a limit
        else:
            sat_l = [False] * len(motors)
            for i, m in enumerate(motors):
                if m <= lo_ok:
                    motors[i] = idle
                    sat_l[i] = True
                elif m >= hi_ok:
                    motors[i] = 1.0
                    sat_l[i] = True
            sat = tuple(sat_l)
        return MixResult(
            tuple(motors),
            (r * rp_scale, p * rp_scale, ye),
            (
                (rp_scale < 1.0 and r != 0.0) or 1.0 < abs(roll) < _INF,
                (rp_scale < 1.0 and p != 0.0) or 1.0 < abs(pitch) < _INF,
                (y_scale < 1.0 and y != 0.0) or 1.0 < abs(yaw) < _INF,
            ),
            sat,
            t_eff,
            given,
        )

    def _fit(self, t: float, d: list[float], y: float) -> tuple[float, float]:
        """Air mode's collective for the roll and pitch changes ``d`` (shifted so they
        fit in [idle, 1]), and the largest fraction of the yaw request ``y`` that
        fits on top."""
        idle = self.idle
        d_min = min(d)
        d_max = max(d)
        t_eff = t if t > idle else idle
        if t_eff + d_min < idle:
            t_eff = idle - d_min
        elif t_eff + d_max > 1.0:
            t_eff = 1.0 - d_max
        y_scale = 1.0
        if y != 0.0:
            hi = 1.0 - t_eff
            lo = idle - t_eff
            for di, k in zip(d, self._yf):
                k *= y  # this motor's change for the full yaw request
                if k == 0.0:
                    continue
                room = (hi - di) / k if k > 0.0 else (lo - di) / k
                if room < y_scale:
                    y_scale = room if room > 0.0 else 0.0
        return t_eff, y_scale

    def _mix_quad(
        self, thrust: float, roll: float, pitch: float, yaw: float, yaw_share: float = 0.0
    ) -> MixResult:
        # The same algorithm as _mix_generic, unrolled for four motors: this
        # runs once per IMU sample, and the unrolled form costs a quarter of the
        # list-based one (tests pin the two to identical results).
        idle = self.idle
        # In range is the common case; NaN fails every comparison and becomes 0.
        t = thrust if 0.0 <= thrust <= 1.0 else _clamp_or_zero(thrust, 0.0, 1.0)
        # A finite request beyond +/-1 is clamped (and counts as saturated); NaN
        # and infinities become 0 (no request).
        cr = cp = cy = False
        r = roll
        if not -1.0 <= r <= 1.0:
            r = _clamp_or_zero(r, -1.0, 1.0)
            cr = r != 0.0
        p = pitch
        if not -1.0 <= p <= 1.0:
            p = _clamp_or_zero(p, -1.0, 1.0)
            cp = p != 0.0
        y = yaw
        if not -1.0 <= y <= 1.0:
            y = _clamp_or_zero(y, -1.0, 1.0)
            cy = y != 0.0
        if -_TINY < y < _TINY:
            y = 0.0
        r0, r1, r2, r3 = self._rf
        p0, p1, p2, p3 = self._pf
        k0, k1, k2, k3 = self._yf
        d0 = r0 * r + p0 * p
        d1 = r1 * r + p1 * p
        d2 = r2 * r + p2 * p
        d3 = r3 * r + p3 * p
        d_min = min(d0, d1, d2, d3)
        d_max = max(d0, d1, d2, d3)
        rp_scale = 1.0
        span = 1.0 - idle
        if d_max - d_min > span:
            rp_scale = span / (d_max - d_min)
            d0 *= rp_scale
            d1 *= rp_scale
            d2 *= rp_scale
            d3 *= rp_scale
            d_min *= rp_scale
            d_max *= rp_scale
        t_eff = t if t > idle else idle
        if t_eff + d_min < idle:
            t_eff = idle - d_min
        elif t_eff + d_max > 1.0:
            t_eff = 1.0 - d_max
        y_scale = 1.0
        if y != 0.0:
            # Largest fraction of the yaw request each motor can take.
            hi = 1.0 - t_eff
            lo = idle - t_eff
            q0 = k0 * y
            q1 = k1 * y
            q2 = k2 * y
            q3 = k3 * y
            y_scale = min(
                1.0,
                (hi - d0) / q0 if q0 > 0.0 else (lo - d0) / q0,
                (hi - d1) / q1 if q1 > 0.0 else (lo - d1) / q1,
                (hi - d2) / q2 if q2 > 0.0 else (lo - d2) / q2,
                (hi - d3) / q3 if q3 > 0.0 else (lo - d3) / q3,
            )
            y_scale = y_scale if y_scale > 0.0 else 0.0
            if y_scale < 1.0 and yaw_share > 0.0:  # rare: the general path shares
                return self._mix_generic(thrust, roll, pitch, yaw, yaw_share)
        ye = y * y_scale
        m0 = t_eff + d0 + k0 * ye
        m1 = t_eff + d1 + k1 * ye
        m2 = t_eff + d2 + k2 * ye
        m3 = t_eff + d3 + k3 * ye
        lo_ok = idle + 1e-9
        hi_ok = 1.0 - 1e-9
        if min(m0, m1, m2, m3) > lo_ok and max(m0, m1, m2, m3) < hi_ok:
            motors: tuple[float, ...] = (m0, m1, m2, m3)
            sat = self._no_sat
        else:
            s0 = m0 <= lo_ok or m0 >= hi_ok
            s1 = m1 <= lo_ok or m1 >= hi_ok
            s2 = m2 <= lo_ok or m2 >= hi_ok
            s3 = m3 <= lo_ok or m3 >= hi_ok
            motors = (
                (idle if m0 <= lo_ok else 1.0) if s0 else m0,
                (idle if m1 <= lo_ok else 1.0) if s1 else m1,
                (idle if m2 <= lo_ok else 1.0) if s2 else m2,
                (idle if m3 <= lo_ok else 1.0) if s3 else m3,
            )
            sat = (s0, s1, s2, s3)
        return _new_tuple(
            MixResult,
            (
                motors,
                (r * rp_scale, p * rp_scale, ye),
                (
                    (rp_scale < 1.0 and r != 0.0) or cr,
                    (rp_scale < 1.0 and p != 0.0) or cp,
                    (y_scale < 1.0 and y != 0.0) or cy,
                ),
                sat,
                t_eff,
                0.0,
            ),
        )
