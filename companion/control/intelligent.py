r"""The paper's law on one axis: the iPD and the iP with their estimate of ``F``.

The ultra-local model (the paper's Section II-A)
-------------------------------------------------
.. math::  y^{(m)} = F + \alpha u

``F`` subsumes everything the model leaves out (dynamics, disturbances) and
is estimated every sample; :math:`\alpha` is a constant (or, not in the paper,
identified online: :mod:`companion.control.identifier`). Here ``y`` is the
body-axis angle (the integral of the gyro rate), so :math:`\dot y` is the
gyro rate; units as in :mod:`companion.control.mfc`.

Laws (Section II-C, equations (ipd) and (ip))
---------------------------------------------
.. math::
    \text{iPD } (m = 2):\; u = -\frac{\hat F - \ddot y_r + K_P e + K_D \dot e}{\alpha},
    \qquad
    \text{iP } (m = 1):\; u = -\frac{\hat F - \dot y_r + K_P e}{\alpha}

with :math:`e = y - y_r = \int (\omega - \omega_r)\,dt` (clamped to
``error_limit_rad`` so a long saturation does not leave a large angle to
catch up) and :math:`\dot e = \omega - \omega_r`, the gyro's (the paper's
Remark on :math:`\dot e`). With a good :math:`\hat F` the error obeys
:math:`\ddot e + K_D \dot e + K_P e = 0` (iPD), :math:`\dot e + K_P e = 0`
(iP). ``u`` is saturated at ``output_limit_us``; there is no integrator of the
command to wind up: ``u`` is recomputed from scratch every sample, and ``F``
is learnt from the command that was really applied. The shipped controllers
fly the iPD with :math:`K_P = 0` (``docs/research/gains.md#no-angle-term``): its rate part,
an iP on the rate :math:`\dot y`.

Estimate of F (Section II-D)
----------------------------
The window average of :math:`y^{(m)} - \alpha u` over ``window_s``
(:class:`companion.control.estimator.WindowEstimator`, or the algebraic
alternative), fed the previous command as applied.

Lag-aware estimate (not in the paper; the shipped configuration)
----------------------------------------------------------------
With ``actuator_tau_s`` and/or identification (:class:`AlphaAdaptation`),
:math:`\hat F = \bar y^{(m)} - \alpha L_\tau \bar u`: the command through a
first-order actuator lag, :math:`\alpha` and :math:`\tau` identified in
flight, and with ``lag_scaled_gains`` the gains scaled with the identified lag
(:class:`IntelligentController` explains why; ``docs/research/gains.md`` gives the
evidence). Both are off by default, which is the paper's law exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from companion.control.estimator import FEstimator, make_estimator
from companion.control.identifier import DT_REL_TOL, AlphaAdaptation, PlantIdentifier

__all__ = ["IntelligentController", "MfcAxisGains"]

_U_HIST_LEN = 512
"""Command means kept for the delayed estimate: 0.2 s (the longest delay a
candidate may name) at up to 2.5 kHz; a longer delay uses the oldest."""


@dataclass(frozen=True)
class MfcAxisGains:
    r"""One axis of the MFC controller, as its configuration file gives it.

    Built only from the validated configuration (``companion.config``'s
    ``MfcAxisConfig``, field for field under the same names): the file's schema
    holds each gain's default, unit, bounds and the rules between them; this
    holds the values. ``order``: 2 for the iPD, 1 for the iP; ``alpha``, (rad/s^m)
    per command unit (us); ``window_s``, the estimation window; ``kp``, ``kd``,
    1/s^m and 1/s^(m-1) (``kd`` unused when ``m = 1``); ``output_limit_us``, the
    saturation of ``u``; ``error_limit_rad``, the bound on ``|e|``;
    ``estimator``, ``"window"`` (the paper's average) or ``"algebraic"``;
    ``actuator_tau_s``, the actuator lag in the estimate of ``F`` (0: none, the
    paper); ``alpha_adapt``, the online identification of ``alpha`` and the lag
    (None: off, the paper). With ``lag_scaled_gains``, ``kp`` and ``kd`` follow
    the identified lag (:class:`IntelligentController`): a vehicle identified
    with more authority than ``lag_scaling_authority_ref`` (rad/s^m per
    full-scale command; 0: off) keeps more of ``kd`` on a slow lag (``kd`` times
    ``sqrt(authority / ref)``, at most back to the unscaled ``kd``; with
    ``alpha_adapt.margin_min`` the same reference eases the margin's fall); a
    lag faster than ``actuator_tau_s`` raises the gains by at most
    ``lag_scaling_max`` (None: no cap), a slower one cuts them to at least
    ``lag_scaling_min`` (None: no floor); ``window_lag_scaled`` shortens the
    window by the factor the gains are raised by (the window's delay bounds the
    loop as the motors do). With an identified loop delay ``D``
    (``alpha_adapt.delay_candidates_s``), ``kd`` is at most
    ``delay_kd_limit / D`` (``kp`` by the square of the same cut; 0: off), so the
    phase a delay costs at the error dynamics' bandwidth stays bounded.
    """

    order: int
    alpha: float
    window_s: float
    kp: float
    kd: float
    output_limit_us: float
    error_limit_rad: float
    estimator: Literal["window", "algebraic"]
    actuator_tau_s: float
    alpha_adapt: AlphaAdaptation | None
    lag_scaled_gains: bool
    lag_scaling_authority_ref: float
    lag_scaling_max: float | None
    lag_scaling_min: float | None
    window_lag_scaled: bool
    delay_kd_limit: float


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
      a :class:`~companion.control.identifier.PlantIdentifier` fed with the
      same window means (:meth:`learn`).
    * With ``alpha_adapt.delay_candidates_s``, the identifier also names the loop's
      delay :math:`D` (a companion's link both ways): the command in the
      estimate is the window mean of one :math:`D` ago,
      :math:`\hat F = \bar y^{(m)} - \alpha L_\tau \bar u(t - D)`, the one
      that acted on the samples averaged; ``delay_kd_limit`` bounds kd by
      :math:`D`.
    """

    __slots__ = (
        "_alpha",
        "_authority_ref",
        "_delay_kd",
        "_delayed",
        "_e_lim",
        "_est",
        "_est_update",
        "_ident",
        "_kd",
        "_kd_eff",
        "_kp",
        "_kp_eff",
        "_lag_dt",
        "_lag_k",
        "_lag_max",
        "_lag_min",
        "_lag_scaled",
        "_lag_tau",
        "_lim",
        "_plain",
        "_scale",
        "_tau",
        "_u_a",
        "_u_hist",
        "_u_hist_i",
        "_window_s",
        "_window_scaled",
        "adapting",
        "e",
        "e_dot",
        "f_hat",
        "order",
        "u_prev",
        "update",
    )  # fmt: skip

    def __init__(self, gains: MfcAxisGains, *, command_full_scale_us: float) -> None:
        self.order = gains.order
        self._alpha = gains.alpha
        self._kp = gains.kp
        self._kd = gains.kd
        self._lim = gains.output_limit_us
        self._e_lim = gains.error_limit_rad
        self._scale = command_full_scale_us
        self._est: FEstimator = make_estimator(
            gains.estimator, gains.order, gains.alpha, gains.window_s
        )
        self._est_update = self._est.update
        self.update = self._update_ipd if gains.order == 2 else self._update_ip
        self._tau = gains.actuator_tau_s
        self._ident = (
            PlantIdentifier(
                gains.alpha_adapt,
                gains.alpha,
                gains.actuator_tau_s,
                authority_ref=gains.lag_scaling_authority_ref,
                full_scale=command_full_scale_us,
            )
            if gains.alpha_adapt is not None
            else None
        )
        self._plain = self._ident is None and self._tau <= 0.0
        self._lag_scaled = gains.lag_scaled_gains  # (so an identifier and a lag > 0)
        self._authority_ref = gains.lag_scaling_authority_ref
        self._lag_max = math.inf if gains.lag_scaling_max is None else gains.lag_scaling_max
        self._lag_min = 0.0 if gains.lag_scaling_min is None else gains.lag_scaling_min
        self._window_s = gains.window_s
        self._window_scaled = gains.window_lag_scaled
        self._lag_dt = self._lag_tau = -1.0
        self._lag_k = 0.0
        adapt = gains.alpha_adapt
        self._delayed = adapt is not None and bool(adapt.delay_candidates_s)
        self._delay_kd = gains.delay_kd_limit
        self.adapting = False
        """Whether the identifier may learn now (the caller's say: the pilot flies)."""
        self.reset()

    @property
    def alpha(self) -> float:
        """The alpha in use (the configured one unless adapted)."""
        return self._alpha if self._ident is None else self._ident.alpha

    @property
    def tau_s(self) -> float:
        """The actuator lag in use, s."""
        return self._tau if self._ident is None else self._ident.tau

    @property
    def delay_s(self) -> float:
        """The loop's delay in use, s (0: none identified)."""
        return 0.0 if self._ident is None else self._ident.delay

    def reset(self) -> None:
        self._est.reset()
        if self._ident is not None:
            self._ident.reset()
        self._scale_gains()
        self._u_a = 0.0
        self._u_hist = [0.0] * _U_HIST_LEN
        self._u_hist_i = 0
        self.f_hat = 0.0
        self.e = 0.0
        self.e_dot = 0.0
        self.u_prev = 0.0

    # ------------------------------------------------------------------ the laws

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
            ``command_full_scale_us``); ``None`` means the previous output was
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

    # ------------------------------------------------------- the estimate of F

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
            ident.observe(dt_s, u_mean, y_m)
            tau = ident.tau
            alpha = ident.alpha
            if self._delayed:
                u_mean = self._delayed_mean(u_mean, ident.delay, dt_s)
        if tau > 0.0:
            if tau != self._lag_tau or abs(dt_s - self._lag_dt) > DT_REL_TOL * dt_s:
                self._lag_dt = dt_s
                self._lag_tau = tau
                self._lag_k = -math.expm1(-dt_s / tau)
            self._u_a = u_a = self._u_a + (u_mean - self._u_a) * self._lag_k
        else:
            self._u_a = u_a = u_mean
        return y_m - alpha * u_a, alpha

    def _delayed_mean(self, u_mean: float, delay_s: float, dt_s: float) -> float:
        """Note this sample's command mean; return the one of ``delay_s`` ago
        (in samples of ``dt_s``; the oldest kept if longer)."""
        hist = self._u_hist
        self._u_hist_i = i = (self._u_hist_i + 1) % _U_HIST_LEN
        hist[i] = u_mean
        if delay_s <= 0.0 or dt_s <= 0.0:
            return u_mean
        n = round(delay_s / dt_s)
        if n >= _U_HIST_LEN:
            n = _U_HIST_LEN - 1
        return hist[(i - n) % _U_HIST_LEN]

    # ----------------------------------------------- identification and the gains

    def learn(self) -> None:
        """Run the identifier on the latest window means (at most every
        :data:`~companion.control.identifier.LEARN_PERIOD_S`) and rescale the
        gains if what it identified moves them. Call once the command has left."""
        ident = self._ident
        if ident is None:
            return
        tau = ident.tau
        alpha = ident.alpha
        delay = ident.delay
        if (
            ident.learn(self.adapting)
            and (self._lag_scaled or self._delay_kd > 0.0)
            and (
                ident.tau != tau
                or ident.delay != delay
                or (self._authority_ref > 0.0 and ident.alpha != alpha)
            )
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
        (docs/research/gains.md#strong-vehicle-kd).

        A fast lag raises the gains by at most ``lag_scaling_max``: below the
        configured lag, the estimate's window and the reference prefilter, not
        the motors, bound how fast the error may be driven
        (docs/research/gains.md#fast-lag-kd).
        A slow lag cuts them to no less than ``lag_scaling_min``: beyond the
        slowest lag worth scaling for, part of what the identifier calls lag is
        the loop's delays, which a cut in kd does not serve
        (docs/research/gains.md#slow-lag-floor)."""
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
        if self._window_scaled:
            self._est.set_window(self._window_s / r if r > 1.0 else self._window_s)
        kd = self._kd * r * g
        kp = self._kp * (r * r if self.order == 2 else r)
        if self._delay_kd > 0.0 and ident is not None and ident.delay > 0.0:
            cap = self._delay_kd / ident.delay
            if kd > cap:
                f = cap / kd
                kd = cap
                kp *= f * f if self.order == 2 else f
        self._kd_eff = kd
        self._kp_eff = kp
