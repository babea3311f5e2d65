r"""Intelligent controllers (iP, iPD) and the paper's three-axis MFC assembly.

Unit convention under which Table I is used
-------------------------------------------
* ``y`` is the body-axis angle in **radians** (the integral of the gyro rate),
  so :math:`\dot y` is the gyro rate in rad/s and the pilot's rate command is
  :math:`\dot y_r`;
* ``u`` is in **PWM microseconds of differential motor command** about the
  throttle point, as in the paper's mixer (equation (motors)) on an 8-bit
  flight controller driving 1000-2000 us ESCs. A full-scale normalised torque
  of 1 is 500 us (one motor at the top of its range, its opposite at the
  bottom, at mid throttle).

Why this reading: the paper asks that :math:`y^{(m)}`, ``F`` and
:math:`\alpha u` be "of the same order of magnitude" with :math:`\alpha = 1`.
For an F450 or a Tarot 650 one microsecond of differential command gives
about 0.2-0.35 rad/s^2 of angular acceleration: the same order as 1. In
deg/s it would be 13-18 deg/s^2 per us, a ratio the ``alpha``-mismatched
estimator loop cannot absorb (it limit-cycles: see
``tests/control/test_table1_units.py``).

Laws (the paper's equations (ipd) and (ip))
-------------------------------------------
.. math::
    \text{iPD } (m = 2):\; u = -\frac{\hat F - \ddot y_r + K_P e + K_D \dot e}{\alpha},
    \qquad
    \text{iP } (m = 1):\; u = -\frac{\hat F - \dot y_r + K_P e}{\alpha}

with :math:`e = y - y_r = \int (\omega - \omega_r)\,dt` (clamped to
``error_limit_rad`` so a long saturation does not leave a large angle to
catch up) and :math:`\dot e = \omega - \omega_r`. There is no integrator of
the command to wind up: ``u`` is recomputed from scratch every sample, and
``F`` is learnt from the command that was really applied.

Lag-aware estimate and online identification (the shipped configuration)
--------------------------------------------------------------------------
With ``actuator_tau_s`` and/or :class:`AlphaAdaptation` set, ``F`` is
estimated as :math:`\bar y^{(m)} - \alpha L_\tau \bar u` (the command
through a first-order actuator lag), and :math:`\alpha` and :math:`\tau`
are identified in flight by :class:`PlantIdentifier`
(:class:`IntelligentController` explains why; ``docs/gains.md`` gives the
evidence). Both are off by default, which is the paper's law exactly.

Reference derivatives
---------------------
The pilot's rate :math:`\omega_r` goes through a critically damped
second-order prefilter (natural frequency ``prefilter_hz``), discretised
exactly for a held input, which yields the filtered rate and its derivative
:math:`\ddot y_r` without differentiating a stepwise stick signal. With the
prefilter off, :math:`\ddot y_r` is the backward difference of the raw
reference.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

from companion.control.estimator import FEstimator, make_estimator
from companion.control.mixer import Mixer
from companion.control.pid import PidGains, RatePid

__all__ = [
    "AlphaAdaptation",
    "ControlOutput",
    "IntelligentController",
    "MfcAxisGains",
    "MfcController",
    "MfcGains",
    "PidController",
    "PlantIdentifier",
    "ReferencePrefilter",
]

Vec3 = tuple[float, float, float]
_ZERO3: Vec3 = (0.0, 0.0, 0.0)

LEARN_PERIOD_S = 0.004
"""The identifier runs at most this often (s): every sample at 250 Hz, every 4th at 1 kHz."""

_DT_REL_TOL = 1e-3
"""Discrete filter coefficients computed for one dt serve every dt within this
relative distance of it: intervals from timestamps jitter in their last bits
(and by a microsecond or so), and recomputing exponentials for that costs more
than the rest of a sample's arithmetic while changing the result by < 0.1 %."""


@dataclass(frozen=True)
class AlphaAdaptation:
    r"""Online identification of :math:`\alpha` (and the actuator lag) per axis.

    Settings of :class:`PlantIdentifier`, which explains the method.

    Attributes
    ----------
    alpha_min, alpha_max
        Bounds of :math:`\alpha`, same units as ``alpha``.
    margin
        :math:`\alpha / \hat b`; the loop is stable for :math:`b/\alpha` in
        (0, 2) with a matched actuator model, so > 1 errs on the safe side.
    memory_s
        Forgetting time of the slope, s.
    highpass_s
        Time constant separating fast ``u`` changes from slow ``F``, s.
    min_excitation
        Smallest :math:`|x|` (command units) that updates the slope.
    min_samples_weight
        :math:`\sum x^2` (command units squared) needed before the slope is used.
    tau_candidates_s
        Actuator lags to choose from, s; empty: only the axis's ``actuator_tau_s``.
    min_response
        Smallest :math:`|z|` (rad/s^m) that updates the slope: a vehicle that
        does not move (on the ground) teaches nothing, rather than "b = 0".
    margin_min
        0: the margin is constant. Otherwise the lowest margin a slow lag
        brings it to (:meth:`PlantIdentifier.margin_for`).
    """

    alpha_min: float
    alpha_max: float
    margin: float = 1.0
    memory_s: float = 2.0
    highpass_s: float = 0.05
    min_excitation: float = 10.0
    min_samples_weight: float = 2.0e4
    tau_candidates_s: tuple[float, ...] = ()
    min_response: float = 2.0
    margin_min: float = 0.0

    def __post_init__(self) -> None:
        vals = (self.alpha_min, self.alpha_max, self.margin, self.memory_s, self.highpass_s)
        if not all(math.isfinite(v) and v > 0.0 for v in vals):
            raise ValueError("alpha adaptation bounds, margin and times must be finite and > 0")
        if self.alpha_min > self.alpha_max:
            raise ValueError("alpha_min must not exceed alpha_max")
        if self.min_excitation < 0.0 or self.min_samples_weight < 0.0:
            raise ValueError("min_excitation and min_samples_weight must be >= 0")
        if not all(math.isfinite(t) and t >= 0.0 for t in self.tau_candidates_s):
            raise ValueError("tau_candidates_s must be finite and >= 0")
        if not 0.0 <= self.margin_min <= self.margin:
            raise ValueError("margin_min must be in [0, margin]")


@dataclass(frozen=True)
class MfcAxisGains:
    r"""One axis of the MFC controller (one row of Table I plus limits).

    Attributes
    ----------
    order
        ``m``: 2 for iPD, 1 for iP.
    alpha
        :math:`\alpha`, (rad/s^m) per command unit (us).
    window_s
        Estimation window ``T``, s.
    kp, kd
        Feedback gains, 1/s^m and 1/s^(m-1) (``kd`` unused when ``m = 1``).
    output_limit
        Saturation of ``u``, command units (us).
    error_limit_rad
        Bound on ``|e|``, rad.
    estimator
        ``"window"`` (the paper's average) or ``"algebraic"``.
    """

    order: int
    alpha: float
    window_s: float
    kp: float
    kd: float = 0.0
    output_limit: float = 500.0
    error_limit_rad: float = 0.5
    estimator: Literal["window", "algebraic"] = "window"
    actuator_tau_s: float = 0.0
    lag_scaled_gains: bool = False
    lag_scaling_authority_ref: float = 0.0
    """With ``lag_scaled_gains``, rad/s^m per full-scale command (0: off). A vehicle
    identified with more authority than this keeps more of ``kd`` on a slow lag:
    kd is multiplied by ``sqrt(authority / ref)``, at most back to the unscaled kd."""
    lag_scaling_max: float = math.inf
    """With ``lag_scaled_gains``, the largest factor (>= 1) a lag faster than
    ``actuator_tau_s`` may raise the gains by (``inf``: no cap)."""
    lag_scaling_min: float = 0.0
    """With ``lag_scaled_gains``, the smallest factor (<= 1) a lag slower than
    ``actuator_tau_s`` may cut the gains to (0: no floor)."""
    adapt: AlphaAdaptation | None = None

    def __post_init__(self) -> None:
        if self.adapt is not None and self.estimator != "window":
            raise ValueError("alpha adaptation needs the window estimator")
        if self.order not in (1, 2):
            raise ValueError(f"order must be 1 or 2, got {self.order}")
        if self.actuator_tau_s < 0.0:
            raise ValueError("actuator_tau_s must be >= 0")
        for name in (
            "alpha", "window_s", "kp", "kd", "output_limit", "error_limit_rad", "actuator_tau_s",
        ):  # fmt: skip
            v = getattr(self, name)
            if not math.isfinite(v):
                raise ValueError(f"{name} must be finite, got {v}")
        if self.alpha == 0.0 or self.window_s <= 0.0 or self.output_limit <= 0.0:
            raise ValueError("alpha must be non-zero; window_s and output_limit positive")
        if not self.lag_scaling_max >= 1.0:
            raise ValueError("lag_scaling_max must be >= 1 (it caps a raise, not a cut)")
        if not 0.0 <= self.lag_scaling_min <= 1.0:
            raise ValueError("lag_scaling_min must be in [0, 1] (it floors a cut, not a raise)")


@dataclass(frozen=True)
class MfcGains:
    """The three axes plus shared settings; Table I by default."""

    roll: MfcAxisGains = field(
        default_factory=lambda: MfcAxisGains(order=2, alpha=1.0, window_s=0.02, kp=3.0, kd=0.096)
    )
    pitch: MfcAxisGains = field(
        default_factory=lambda: MfcAxisGains(order=2, alpha=1.0, window_s=0.02, kp=2.7, kd=0.096)
    )
    yaw: MfcAxisGains = field(
        default_factory=lambda: MfcAxisGains(
            order=1, alpha=1.0, window_s=0.02, kp=2.7, output_limit=250.0
        )
    )
    command_full_scale: float = 500.0
    """Command units (us) that make a normalised torque of 1."""
    prefilter_hz: float | None = 20.0
    adapt_min_thrust: float = 0.15
    """Alpha adaptation learns only while the pilot's collective is at least this."""
    dt_min_s: float = 0.000125
    dt_max_s: float = 0.02

    def axes(self) -> tuple[MfcAxisGains, MfcAxisGains, MfcAxisGains]:
        return (self.roll, self.pitch, self.yaw)


class ReferencePrefilter:
    r"""Critically damped 2nd-order filters giving a smooth reference and its derivative.

    One filter per axis, sharing the natural frequency
    :math:`\omega_n = 2 \pi f_c`:
    :math:`\ddot x = \omega_n^2 (r - x) - 2 \omega_n \dot x`, discretised
    exactly for ``r`` held over the step (unconditionally stable for any dt):
    with :math:`z = x - r` and :math:`c = \dot z_0 + \omega_n z_0`,
    :math:`z(t) = (z_0 + c t) e^{-\omega_n t}` and
    :math:`\dot z(t) = (\dot z_0 - \omega_n c t) e^{-\omega_n t}`.
    The first sample initialises the output to the input, at rest.
    """

    __slots__ = ("_dt_last", "_ex", "_primed", "_v0", "_v1", "_v2", "_wn", "_x0", "_x1", "_x2")

    def __init__(self, cutoff_hz: float) -> None:
        if not (math.isfinite(cutoff_hz) and cutoff_hz > 0.0):
            raise ValueError(f"cutoff_hz must be > 0, got {cutoff_hz!r}")
        self._wn = 2.0 * math.pi * cutoff_hz
        self._dt_last = -1.0
        self._ex = 0.0
        self.reset()

    def reset(self) -> None:
        self._x0 = self._x1 = self._x2 = 0.0
        self._v0 = self._v1 = self._v2 = 0.0
        self._primed = False

    def update(self, dt_s: float, target: Vec3) -> tuple[Vec3, Vec3]:
        """Advance by ``dt_s`` toward ``target``; returns (reference, its derivative)."""
        r0, r1, r2, d0, d1, d2 = self.step(dt_s, target[0], target[1], target[2])
        return (r0, r1, r2), (d0, d1, d2)

    @property
    def rate(self) -> Vec3:
        return (self._x0, self._x1, self._x2)

    @property
    def rate_dot(self) -> Vec3:
        return (self._v0, self._v1, self._v2)

    def step(
        self, dt_s: float, t0: float, t1: float, t2: float
    ) -> tuple[float, float, float, float, float, float]:
        """:meth:`update` with flat arguments and result, for the per-sample path."""
        if not self._primed:
            self._primed = True
            self._x0, self._x1, self._x2 = t0, t1, t2
            self._v0 = self._v1 = self._v2 = 0.0
            return t0, t1, t2, 0.0, 0.0, 0.0
        wn = self._wn
        if abs(dt_s - self._dt_last) > _DT_REL_TOL * dt_s:  # the loop usually runs at a fixed rate
            self._dt_last = dt_s
            self._ex = math.exp(-wn * dt_s)
        ex = self._ex
        v0 = self._v0
        v1 = self._v1
        v2 = self._v2
        # Unrolled over the three axes: this runs once per IMU sample.
        z0 = self._x0 - t0
        z1 = self._x1 - t1
        z2 = self._x2 - t2
        c0 = v0 + wn * z0
        c1 = v1 + wn * z1
        c2 = v2 + wn * z2
        wdt = wn * dt_s
        self._x0 = x0 = t0 + (z0 + c0 * dt_s) * ex
        self._x1 = x1 = t1 + (z1 + c1 * dt_s) * ex
        self._x2 = x2 = t2 + (z2 + c2 * dt_s) * ex
        self._v0 = v0 = (v0 - wdt * c0) * ex
        self._v1 = v1 = (v1 - wdt * c1) * ex
        self._v2 = v2 = (v2 - wdt * c2) * ex
        return x0, x1, x2, v0, v1, v2


class PlantIdentifier:
    r"""Online estimate of one axis's input gain ``b`` and actuator lag.

    The window estimator forms, every sample, the window means
    :math:`\bar y^{(m)}` and :math:`\bar u` of :math:`y^{(m)} = F + b\,u_a`,
    where :math:`u_a` is the command after the actuators' (unknown) lag. Their
    fast parts, each minus its exponential average over ``highpass_s``
    (:math:`\tilde u`, :math:`z = \tilde y^{(m)}`), satisfy
    :math:`z \approx b\, L_\tau \tilde u` while ``F`` changes slowly next to the
    command, with :math:`L_\tau` a first-order lag. For every candidate lag
    :math:`\tau_i` a least-squares slope with exponential forgetting over
    ``memory_s`` is kept, :math:`\hat b_i = \sum z x_i / \sum x_i^2` with
    :math:`x_i = L_{\tau_i} \tilde u`; the candidate with the smallest residual
    :math:`\sum z^2 - (\sum z x_i)^2 / \sum x_i^2` gives the lag, its slope
    gives :math:`\alpha = \mathrm{clip}(\text{margin}\,\hat b_i,
    \alpha_{min}, \alpha_{max})`. Sums are updated only while the command moves
    (:math:`|\tilde u| \ge` ``min_excitation``), the vehicle answers
    (:math:`|z| \ge` ``min_response``) and the caller says the pilot flies
    (collective), so hover, the ground and noise teach it nothing; until
    ``min_samples_weight`` of excitation is gathered the configured
    ``alpha`` and ``actuator_tau_s`` stay.

    :attr:`margin` is alpha over the slope in use: the configured one unless
    ``margin_min`` lowers it for a slow lag (:meth:`margin_for`), which is
    where ``authority_ref`` and ``full_scale`` (the axis's
    ``lag_scaling_authority_ref`` and full-scale command) serve.
    """

    __slots__ = (
        "_authority_ref", "_cfg", "_dt", "_full_scale", "_hp", "_ks", "_lam", "_sxx", "_sxz",
        "_szz", "_taus", "_u_lp", "_x", "_y_lp", "alpha", "alpha0", "margin", "tau", "tau0",
    )  # fmt: skip

    def __init__(
        self,
        cfg: AlphaAdaptation,
        alpha: float,
        tau_s: float,
        *,
        authority_ref: float = 0.0,
        full_scale: float = 500.0,
    ) -> None:
        self._cfg = cfg
        self._taus = cfg.tau_candidates_s or (tau_s,)
        self.alpha0 = alpha
        self.tau0 = tau_s
        self._authority_ref = authority_ref
        self._full_scale = full_scale
        self._dt = -1.0
        self._hp = self._lam = 0.0
        self._ks = [0.0] * len(self._taus)
        self.reset()

    def reset(self) -> None:
        n = len(self._taus)
        self._x = [0.0] * n
        self._sxx = [0.0] * n
        self._sxz = [0.0] * n
        self._szz = 0.0
        self._u_lp = self._y_lp = 0.0
        self.alpha = self.alpha0
        self.tau = self.tau0
        self.margin = self._cfg.margin

    def margin_for(self, b: float, tau: float) -> float:
        r"""The margin for an identified slope ``b`` and lag ``tau``.

        With ``margin_min`` > 0 and ``tau`` slower than the axis's
        ``actuator_tau_s`` :math:`\tau_0`, the margin falls to
        :math:`\max(m_{min},\, m \max(\sqrt{\tau_0/\tau},\,
        \min(1, \sqrt{A_{ref}/A})))`, :math:`A = b` times the full-scale command
        (with ``authority_ref`` 0, the lag term alone). A lower margin is a larger
        loop gain: slow motors need it to stop a reversal's overshoot, and a
        vehicle with much authority can give it without saturating, while a
        weak one keeps the whole margin (docs/gains.md, point 7).
        """
        cfg = self._cfg
        tau0 = self.tau0
        if cfg.margin_min <= 0.0 or tau <= tau0 or tau0 <= 0.0:
            return cfg.margin
        h = math.sqrt(tau0 / tau)
        if self._authority_ref > 0.0:
            authority = b * self._full_scale
            if authority <= self._authority_ref:
                return cfg.margin
            h = max(h, math.sqrt(self._authority_ref / authority))
        m = cfg.margin * h
        return m if m > cfg.margin_min else cfg.margin_min

    def _set_dt(self, dt_s: float) -> None:
        cfg = self._cfg
        self._dt = dt_s
        self._hp = -math.expm1(-dt_s / cfg.highpass_s)
        self._lam = math.exp(-dt_s / cfg.memory_s)
        self._ks = [-math.expm1(-dt_s / t) if t > 0.0 else 1.0 for t in self._taus]

    def update(self, dt_s: float, u_mean: float, y_m: float, learn: bool) -> None:
        """Feed one sample's window means; updates :attr:`alpha` and :attr:`tau`."""
        cfg = self._cfg
        if abs(dt_s - self._dt) > _DT_REL_TOL * dt_s:
            self._set_dt(dt_s)
        hp = self._hp
        self._u_lp = u_lp = self._u_lp + (u_mean - self._u_lp) * hp
        self._y_lp = y_lp = self._y_lp + (y_m - self._y_lp) * hp
        ut = u_mean - u_lp
        x = self._x
        ks = self._ks
        for i in range(len(x)):
            xi = x[i]
            x[i] = xi + (ut - xi) * ks[i]
        if not learn or abs(ut) < cfg.min_excitation:
            return
        z = y_m - y_lp
        if abs(z) < cfg.min_response:
            return
        lam = self._lam
        self._szz = szz = lam * self._szz + z * z
        sxx = self._sxx
        sxz = self._sxz
        best = -1
        best_res = math.inf
        for i in range(len(x)):
            xi = x[i]
            sxx[i] = a = lam * sxx[i] + xi * xi
            sxz[i] = c = lam * sxz[i] + xi * z
            if a >= cfg.min_samples_weight and c > 0.0:
                res = szz - c * c / a
                if res < best_res:
                    best_res = res
                    best = i
        if best < 0:
            return
        b = sxz[best] / sxx[best]
        self.tau = tau = self._taus[best]
        self.margin = m = self.margin_for(b, tau)
        a = m * b
        self.alpha = cfg.alpha_max if a > cfg.alpha_max else max(a, cfg.alpha_min)


class IntelligentController:
    r"""One axis: iPD (``order = 2``) or iP (``order = 1``) with its ``F`` estimator.

    The law is chosen once, at construction: ``update`` is bound to the iPD or
    the iP form, so the per-sample path does not branch on the order.

    How the command enters the estimate
    -----------------------------------
    * ``actuator_tau_s = 0`` and no adaptation (the paper): the window average
      of :math:`y^{(m)} - \alpha u` with the applied command ``u``.
    * Otherwise :math:`\hat F = \bar y^{(m)} - \alpha\, L_\tau \bar u`: the
      window mean of the command passed through a first-order lag :math:`\tau`
      standing for the motors (and the gyro filter), so the estimator is not
      taught that a command acted before the rotors could deliver it. The
      law then inverts the model the vehicle really has, as incremental
      nonlinear dynamic inversion does: with :math:`\alpha = b` and the right
      lag the rate follows the reference acceleration through the actuator
      lag alone; for :math:`0 < b/\alpha < 2` it still converges.
    * With :class:`AlphaAdaptation`, :math:`\alpha` and :math:`\tau` come from
      a :class:`PlantIdentifier` fed with the same window means.
    """

    __slots__ = (
        "_alpha", "_authority_ref", "_e_lim", "_est", "_est_update", "_ident", "_kd", "_kd_eff",
        "_kp", "_kp_eff",
        "_lag_dt", "_lag_k", "_lag_max", "_lag_min",
        "_lag_scaled", "_lag_tau", "_lim", "_pending", "_pending_dt", "_plain", "_scale", "_tau",
        "_u_a", "adapting", "e", "e_dot", "f_hat", "order", "u_prev", "update",
    )  # fmt: skip

    def __init__(self, gains: MfcAxisGains, *, command_full_scale: float = 500.0) -> None:
        self.order = gains.order
        self._alpha = gains.alpha
        self._kp = gains.kp
        self._kd = gains.kd
        self._lim = gains.output_limit
        self._e_lim = gains.error_limit_rad
        self._scale = command_full_scale
        self._est: FEstimator = make_estimator(
            gains.estimator, gains.order, gains.alpha, gains.window_s
        )
        self._est_update = self._est.update
        self.update = self._update_ipd if gains.order == 2 else self._update_ip
        self._tau = gains.actuator_tau_s
        self._ident = (
            PlantIdentifier(
                gains.adapt,
                gains.alpha,
                gains.actuator_tau_s,
                authority_ref=gains.lag_scaling_authority_ref,
                full_scale=command_full_scale,
            )
            if gains.adapt is not None
            else None
        )
        self._plain = self._ident is None and self._tau <= 0.0
        self._lag_scaled = gains.lag_scaled_gains and self._ident is not None and self._tau > 0.0
        self._authority_ref = gains.lag_scaling_authority_ref
        self._lag_max = gains.lag_scaling_max
        self._lag_min = gains.lag_scaling_min
        self._lag_dt = self._lag_tau = -1.0
        self._lag_k = 0.0
        self.adapting = False
        self.reset()

    @property
    def alpha(self) -> float:
        """The alpha in use (the configured one unless adapted)."""
        return self._alpha if self._ident is None else self._ident.alpha

    @property
    def tau_s(self) -> float:
        """The actuator lag in use, s."""
        return self._tau if self._ident is None else self._ident.tau

    def reset(self) -> None:
        self._est.reset()
        if self._ident is not None:
            self._ident.reset()
        self._scale_gains()
        self._u_a = 0.0
        self._pending: tuple[float, float] | None = None
        self._pending_dt = 0.0
        self.f_hat = 0.0
        self.e = 0.0
        self.e_dot = 0.0
        self.u_prev = 0.0

    def _estimate(self, dt_s: float, rate: float, u_prev: float) -> tuple[float, float]:
        """``F_hat`` and the alpha to divide by, after the interval that just ended."""
        f = self._est_update(dt_s, rate, u_prev)
        if self._plain:
            return f, self._alpha
        est = self._est
        u_mean: float = est.u_mean  # type: ignore[union-attr]
        y_m: float = est.y_m  # type: ignore[union-attr]
        ident = self._ident
        if ident is None:
            tau = self._tau
            alpha = self._alpha
        else:
            # Identification runs in learn(), after the command has left: this
            # sample's data moves alpha and tau from the next sample on.
            self._pending_dt += dt_s
            self._pending = (u_mean, y_m)
            tau = ident.tau
            alpha = ident.alpha
        if tau > 0.0:
            if tau != self._lag_tau or abs(dt_s - self._lag_dt) > _DT_REL_TOL * dt_s:
                self._lag_dt = dt_s
                self._lag_tau = tau
                self._lag_k = -math.expm1(-dt_s / tau)
            self._u_a = u_a = self._u_a + (u_mean - self._u_a) * self._lag_k
        else:
            self._u_a = u_a = u_mean
        return y_m - alpha * u_a, alpha

    def learn(self) -> None:
        """Feed the identifier the latest window means, every :data:`LEARN_PERIOD_S`.

        The window means are 20 ms averages, so sampling them every 4 ms loses
        nothing the identifier uses, and at 1 kHz it costs a quarter as much.
        """
        p = self._pending
        # 0.9: sample intervals from timestamps jitter around 4 ms at 250 Hz.
        if p is not None and self._pending_dt >= 0.9 * LEARN_PERIOD_S and self._ident is not None:
            dt = self._pending_dt
            self._pending = None
            self._pending_dt = 0.0
            ident = self._ident
            tau = ident.tau
            alpha = ident.alpha
            ident.update(dt, p[0], p[1], self.adapting)
            if self._lag_scaled and (
                ident.tau != tau or (self._authority_ref > 0.0 and ident.alpha != alpha)
            ):
                self._scale_gains()

    def _scale_gains(self) -> None:
        """Gains for the lag in use (lag_scaled_gains): a gain on ``y^(m-1)``'s error
        scales as 1/tau, one on ``y^(m-2)``'s as 1/tau^2: iPD kd ~ 1/tau and
        kp ~ 1/tau^2, iP kp ~ 1/tau.

        With ``lag_scaling_authority_ref``, a slow lag on a vehicle with much
        authority (identified input gain times the full-scale command) takes
        back part of the kd cut: by ``sqrt(authority / ref)``, never beyond the
        unscaled kd. A strong vehicle can afford the faster error dynamics
        without saturating; a weak one, which saturates, keeps the full cut
        (docs/gains.md, point 6).

        A fast lag raises the gains by at most ``lag_scaling_max``: below the
        configured lag, the estimate's window and the reference prefilter, not
        the motors, bound how fast the error may be driven (docs/gains.md,
        point 8). A slow lag cuts them to no less than ``lag_scaling_min``: beyond the
        slowest lag worth scaling for, part of what the identifier calls lag is
        the loop's delays, which a cut in kd does not serve (point 10)."""
        ident = self._ident
        r = self._tau / ident.tau if self._lag_scaled else 1.0  # type: ignore[union-attr]
        if r > self._lag_max:
            r = self._lag_max
        elif r < self._lag_min:
            r = self._lag_min
        g = 1.0
        if self._authority_ref > 0.0 and r < 1.0 and ident is not None:
            authority = ident.alpha / ident.margin * self._scale  # rad/s^m, full scale
            if authority > self._authority_ref:
                g = min(1.0 / r, math.sqrt(authority / self._authority_ref))
        self._kd_eff = self._kd * r * g
        self._kp_eff = self._kp * (r * r if self.order == 2 else r)

    def _update_ipd(
        self,
        dt_s: float,
        rate: float,
        ref_rate: float,
        ref_rate_dot: float,
        applied: float | None = None,
    ) -> float:
        r"""iPD: :math:`u = -(\hat F - \ddot y_r + K_P e + K_D \dot e) / \alpha`.

        Parameters
        ----------
        dt_s
            Time since the previous sample, s.
        rate
            Measured body rate :math:`\dot y`, rad/s.
        ref_rate, ref_rate_dot
            :math:`\dot y_r` (rad/s) and :math:`\ddot y_r` (rad/s^2).
        applied
            The previous command as really applied, normalised (its share of
            ``command_full_scale``); ``None`` means the previous output was
            applied as computed.

        Returns
        -------
        float
            The saturated command, in command units.
        """
        u_prev = self.u_prev if applied is None else applied * self._scale
        f_hat, alpha = self._estimate(dt_s, rate, u_prev)
        self.f_hat = f_hat
        e_dot = rate - ref_rate
        e = self.e + e_dot * dt_s
        lim = self._e_lim
        e = lim if e > lim else (-lim if e < -lim else e)
        self.e = e
        self.e_dot = e_dot
        u = -(f_hat - ref_rate_dot + self._kp_eff * e + self._kd_eff * e_dot) / alpha
        lim = self._lim
        u = lim if u > lim else (-lim if u < -lim else u)
        self.u_prev = u
        return u

    def _update_ip(
        self,
        dt_s: float,
        rate: float,
        ref_rate: float,
        ref_rate_dot: float,
        applied: float | None = None,
    ) -> float:
        r"""iP: :math:`u = -(\hat F - \dot y_r + K_P e) / \alpha`; same arguments as iPD."""
        u_prev = self.u_prev if applied is None else applied * self._scale
        f_hat, alpha = self._estimate(dt_s, rate, u_prev)
        self.f_hat = f_hat
        e_dot = rate - ref_rate
        e = self.e + e_dot * dt_s
        lim = self._e_lim
        e = lim if e > lim else (-lim if e < -lim else e)
        self.e = e
        self.e_dot = e_dot
        u = -(f_hat - ref_rate + self._kp_eff * e) / alpha
        lim = self._lim
        u = lim if u > lim else (-lim if u < -lim else u)
        self.u_prev = u
        return u


class ControlOutput(NamedTuple):
    """What a rate controller produced for one sample."""

    torque: Vec3
    """Normalised roll/pitch/yaw torque realised by the mixer, [-1, 1]."""
    thrust: float
    """Collective realised by the mixer, [0, 1]."""
    motors: tuple[float, ...]
    """Per-motor commands, [idle, 1]."""
    saturated_axes: tuple[bool, bool, bool]
    saturated_motors: tuple[bool, ...]
    u: Vec3
    """Law outputs before mixing, in the law's command units."""
    f_hat: Vec3
    """Estimates of F (rad/s^m); zeros for the PID."""
    error: Vec3
    """Rate tracking error omega - omega_r against the (filtered) reference, rad/s."""
    held: bool
    """True when this output repeats the last valid one (non-finite input)."""


def _hold_output(last: ControlOutput | None, mixer: Mixer) -> ControlOutput:
    if last is None:
        mix = mixer.mix(0.0, 0.0, 0.0, 0.0)
        return ControlOutput(
            _ZERO3, mix.thrust, mix.motors, (False,) * 3, mix.saturated_motors, _ZERO3, _ZERO3,
            _ZERO3, True,
        )  # fmt: skip
    return last._replace(held=True)


_new_tuple = tuple.__new__  # see companion.control.mixer: cheaper than NamedTuple(...)
_isfinite = math.isfinite


def _all_finite(dt_s: float, a: Vec3, b: Vec3, thrust: float) -> bool:
    # Summing is the cheapest finiteness test: inf/nan anywhere poisons the sum.
    return math.isfinite(dt_s + a[0] + a[1] + a[2] + b[0] + b[1] + b[2] + thrust)


class MfcController:
    """Roll iPD, pitch iPD, yaw iP, saturated and mixed: the paper's scheme.

    Parameters
    ----------
    gains
        The controller configuration (Table I by default).
    mixer
        Motor allocation from the vehicle's geometry (or the paper's equation).
    """

    def __init__(self, gains: MfcGains, mixer: Mixer) -> None:
        self.gains = gains
        self.mixer = mixer
        self._axes = tuple(
            IntelligentController(g, command_full_scale=gains.command_full_scale)
            for g in gains.axes()
        )
        self._applied: Vec3 = _ZERO3
        self._filter = ReferencePrefilter(gains.prefilter_hz) if gains.prefilter_hz else None
        self._any_adapt = any(g.adapt is not None for g in gains.axes())
        self._adapt_thrust = gains.adapt_min_thrust
        self._wn = 2.0 * math.pi * gains.prefilter_hz if gains.prefilter_hz else 0.0
        self._prev_ref: Vec3 | None = None
        self._full_scale = gains.command_full_scale
        self._scale = 1.0 / gains.command_full_scale
        self._dt_min = gains.dt_min_s
        self._dt_max = gains.dt_max_s
        self._mix = mixer.mix_fn
        self._last: ControlOutput | None = None
        self.nonfinite_events = 0
        self.dt_clamped_events = 0
        self.on_ground = False
        """Set while the autopilot reports the vehicle on the ground: the identifiers
        then learn nothing, whatever the collective. On the ground the command
        answers the gyro's noise and the "response" is that noise again, which a
        least-squares slope reads as a small input gain, the most aggressive alpha
        (docs/gains.md, point 9). Not reset by :meth:`reset`: it is the
        autopilot's state, not the controller's."""

    def reset(self) -> None:
        """Forget all state (call on disarm or hand-back)."""
        for a in self._axes:
            a.reset()
        if self._filter is not None:
            self._filter.reset()
        self._prev_ref = None
        self._applied = _ZERO3
        self._last = None

    @property
    def reference_rate_dot(self) -> Vec3:
        """Derivative of the prefiltered pilot rate after the last update, rad/s^2
        (zeros without a prefilter): what a feed-forward on the reference uses."""
        f = self._filter
        return f.rate_dot if f is not None else _ZERO3

    def learn(self) -> None:
        """Online identification for the sample just processed.

        Call after each :meth:`update`, once its command has been sent: it
        does not change that command, only the next ones, and keeping it off
        the path from sample to command keeps the loop's latency low.
        """
        if self._any_adapt:
            for a in self._axes:
                a.learn()

    def update(
        self, dt_s: float, rate_frd_rad_s: Vec3, rate_ref_rad_s: Vec3, thrust: float
    ) -> ControlOutput:
        """One control update from one IMU sample.

        Parameters
        ----------
        dt_s
            Time since the previous sample (from sample timestamps), s; clamped
            to ``[dt_min_s, dt_max_s]``.
        rate_frd_rad_s
            Measured body rates, rad/s.
        rate_ref_rad_s
            Pilot's body-rate command, rad/s.
        thrust
            Pilot's collective, [0, 1].
        """
        w0, w1, w2 = rate_frd_rad_s
        q0, q1, q2 = rate_ref_rad_s
        # One sum tests everything: a nan or inf anywhere poisons it (so does
        # an absurd magnitude near 1e308, which is no valid rate either).
        if not _isfinite(dt_s + w0 + w1 + w2 + q0 + q1 + q2 + thrust):
            self.nonfinite_events += 1
            return _hold_output(self._last, self.mixer)
        if dt_s < self._dt_min or dt_s > self._dt_max:
            self.dt_clamped_events += 1
            dt_s = self._dt_min if dt_s < self._dt_min else self._dt_max
        if self._filter is not None:
            r0, r1, r2, d0, d1, d2 = self._filter.step(dt_s, q0, q1, q2)
        else:
            r0, r1, r2 = q0, q1, q2
            prev = self._prev_ref
            if prev is None:
                d0 = d1 = d2 = 0.0
            else:
                d0 = (r0 - prev[0]) / dt_s
                d1 = (r1 - prev[1]) / dt_s
                d2 = (r2 - prev[2]) / dt_s
            self._prev_ref = rate_ref_rad_s
        a0, a1, a2 = self._axes
        if self._any_adapt:
            on = thrust >= self._adapt_thrust and not self.on_ground
            a0.adapting = a1.adapting = a2.adapting = on
        # Teach the estimators what was applied last time, not what was asked.
        p0, p1, p2 = self._applied
        u0 = a0.update(dt_s, w0, r0, d0, p0)
        u1 = a1.update(dt_s, w1, r1, d1, p1)
        u2 = a2.update(dt_s, w2, r2, d2, p2)
        s = self._scale
        motors, achieved, sat_axes, sat_motors, thrust_eff = self._mix(
            thrust, u0 * s, u1 * s, u2 * s
        )
        self._applied = achieved
        out: ControlOutput = _new_tuple(
            ControlOutput,
            (
                achieved,
                thrust_eff,
                motors,
                sat_axes,
                sat_motors,
                (u0, u1, u2),
                (a0.f_hat, a1.f_hat, a2.f_hat),
                (a0.e_dot, a1.e_dot, a2.e_dot),
                False,
            ),
        )
        self._last = out
        return out


class PidController:
    """The PX4-style PID with the same interface as :class:`MfcController`."""

    def __init__(
        self, gains: PidGains, mixer: Mixer, *, dt_min_s: float = 0.000125, dt_max_s: float = 0.02
    ) -> None:
        self.gains = gains
        self.mixer = mixer
        self._pid = RatePid(gains)
        self._dt_min = dt_min_s
        self._dt_max = dt_max_s
        self._last: ControlOutput | None = None
        self._sat_pos = (False, False, False)
        self._sat_neg = (False, False, False)
        self.nonfinite_events = 0
        self.dt_clamped_events = 0
        self.on_ground = False
        """Same attribute as :attr:`MfcController.on_ground`; the PID learns nothing anyway."""

    def reset(self) -> None:
        self._pid.reset()
        self._last = None
        self._sat_pos = self._sat_neg = (False, False, False)

    @property
    def reference_rate_dot(self) -> Vec3:
        """No reference prefilter: zeros (same interface as :class:`MfcController`)."""
        return _ZERO3

    def learn(self) -> None:
        """Nothing to learn: same interface as :meth:`MfcController.learn`."""

    def update(
        self, dt_s: float, rate_frd_rad_s: Vec3, rate_ref_rad_s: Vec3, thrust: float
    ) -> ControlOutput:
        """Same contract as :meth:`MfcController.update`."""
        if not _all_finite(dt_s, rate_frd_rad_s, rate_ref_rad_s, thrust):
            self.nonfinite_events += 1
            return _hold_output(self._last, self.mixer)
        if dt_s < self._dt_min or dt_s > self._dt_max:
            self.dt_clamped_events += 1
            dt_s = self._dt_min if dt_s < self._dt_min else self._dt_max
        u = self._pid.update(dt_s, rate_ref_rad_s, rate_frd_rad_s, self._sat_pos, self._sat_neg)
        mix = self.mixer.mix(thrust, u[0], u[1], u[2])
        sat = mix.saturated_axes
        self._sat_pos = (sat[0] and u[0] > 0, sat[1] and u[1] > 0, sat[2] and u[2] > 0)
        self._sat_neg = (sat[0] and u[0] < 0, sat[1] and u[1] < 0, sat[2] and u[2] < 0)
        r = rate_ref_rad_s
        w = rate_frd_rad_s
        out = ControlOutput(
            mix.achieved,
            mix.thrust,
            mix.motors,
            sat,
            mix.saturated_motors,
            u,
            _ZERO3,
            (w[0] - r[0], w[1] - r[1], w[2] - r[2]),
            False,
        )
        self._last = out
        return out
