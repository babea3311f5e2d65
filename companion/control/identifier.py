r"""Online identification of one axis's input gain and actuator lag.

Not in the paper, which takes :math:`\alpha` as a constant ("it is
meaningless to try to estimate alpha precisely", Section II-A). The shipped
controller identifies it, with the lag of the motors, because one gain set has
to fly every vehicle (``docs/research/gains.md#lag-in-estimate`` and
``#identified-online``): :class:`PlantIdentifier` fits the window means of
:math:`y^{(m)} = F + b\,u_a` (:math:`u_a` the command after a first-order lag)
and gives :math:`\alpha = \text{margin} \cdot \hat b` and the lag
:math:`\tau` that the law (:mod:`companion.control.intelligent`)
then uses in its estimate of ``F`` and, with ``lag_scaled_gains``, in its gains.

It runs off the path from sample to command: the law notes each sample's
window means (:meth:`PlantIdentifier.observe`), and the identification itself
(:meth:`PlantIdentifier.learn`) runs once the command has left, at most every
:data:`LEARN_PERIOD_S`; what it learns moves the next commands.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["DT_REL_TOL", "LEARN_PERIOD_S", "MAX_DELAY_S", "AlphaAdaptation", "PlantIdentifier"]

LEARN_PERIOD_S = 0.004
"""The identifier runs at most this often (s): every sample at 250 Hz, every 4th at 1 kHz."""

MAX_DELAY_S = 0.2
"""The longest loop delay a candidate may name, s."""

DT_REL_TOL = 1e-3
"""Discrete filter coefficients computed for one dt serve every dt within this
relative distance of it: intervals from timestamps jitter in their last bits
(and by a microsecond or so), and recomputing exponentials for that costs more
than the rest of a sample's arithmetic while changing the result by < 0.1 %."""


@dataclass(frozen=True)
class AlphaAdaptation:
    r"""Online identification of :math:`\alpha` (and the actuator lag) per axis.

    Settings of :class:`PlantIdentifier`, which explains the method, built
    only from the validated configuration (``companion.config``'s
    ``AlphaAdaptConfig``, field for field under the same names: its schema holds
    the defaults, bounds and the rules between them).

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
    min_excitation_us
        Smallest :math:`|x|` (command units) that updates the slope.
    min_samples_weight_us2
        :math:`\sum x^2` (command units squared) needed before the slope is used.
    tau_candidates_s
        Actuator lags to choose from, s; empty: only the axis's ``actuator_tau_s``.
    min_response_rad_s2
        Smallest :math:`|z|` (rad/s^m) that updates the slope: a vehicle that
        does not move (on the ground) teaches nothing, rather than "b = 0".
    margin_min
        0: the margin is constant. Otherwise the lowest margin a slow lag
        brings it to (:meth:`PlantIdentifier.margin_for`).
    delay_candidates_s
        Pure delays of the loop to choose from (the link both ways, the
        autopilot's output path), s; empty: none identified (the command acts
        after its lag alone).
    delay_margin_slope, delay_margin_free_ratio, delay_margin_max
        With ``delay_margin_slope`` > 0, the margin rises by that much per unit
        of the identified delay over the identified lag beyond
        ``delay_margin_free_ratio``, up to ``delay_margin_max``
        (:meth:`PlantIdentifier.margin_for_delay`).
    """

    alpha_min: float
    alpha_max: float
    margin: float
    memory_s: float
    highpass_s: float
    min_excitation_us: float
    min_samples_weight_us2: float
    tau_candidates_s: tuple[float, ...]
    min_response_rad_s2: float
    margin_min: float
    delay_candidates_s: tuple[float, ...]
    delay_margin_slope: float
    delay_margin_free_ratio: float
    delay_margin_max: float


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
    (:math:`|\tilde u| \ge` ``min_excitation_us``), the vehicle answers
    (:math:`|z| \ge` ``min_response_rad_s2``) and the caller says the pilot flies
    (collective), so hover, the ground and noise teach it nothing; until
    ``min_samples_weight_us2`` of excitation is gathered the configured
    ``alpha`` and ``actuator_tau_s`` stay.

    :attr:`margin` is alpha over the slope in use: the configured one unless
    ``margin_min`` lowers it for a slow lag (:meth:`margin_for`), which is
    where ``authority_ref`` and ``full_scale`` (the axis's
    ``lag_scaling_authority_ref`` and full-scale command) serve.

    The loop's delay
    ----------------
    A companion's command reaches the motors a link round trip after the
    sample it answers. With ``delay_candidates_s`` the regressors are also
    tried delayed, :math:`x_{ij}(k) = x_i(k - d_j)` (the lag is linear, so a
    delayed input is a delayed output), and the pair with the smallest
    residual gives both the lag and :attr:`delay`; delays count in
    identification intervals (:data:`LEARN_PERIOD_S`). The law feeds its
    estimate of ``F`` the command that acted, one :attr:`delay` ago, and
    (``delay_margin_slope``) a longer delay raises the margin
    (:meth:`margin_for_delay`).
    """

    __slots__ = (
        "_authority_ref", "_cfg", "_delays", "_delays_s", "_dt", "_full_scale", "_hist",
        "_hist_i", "_hp", "_ks", "_lam", "_pending", "_pending_dt", "_sxx", "_sxz", "_szz",
        "_taus", "_u_lp", "_x", "_y_lp", "alpha", "alpha0", "delay", "margin", "tau", "tau0",
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
        # Delays count in identification intervals (LEARN_PERIOD_S apart at 250 Hz and
        # 1 kHz); the delay reported is the candidate's own value, exact, so what the
        # law does with it does not depend on the last bits of sample intervals.
        self._delays_s = cfg.delay_candidates_s or (0.0,)
        self._delays = tuple(round(d / LEARN_PERIOD_S) for d in self._delays_s)
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
        pairs = n * len(self._delays)
        self._x = [0.0] * n
        # The regressors of the last max(delay) + 1 intervals, newest at _hist_i.
        self._hist = [[0.0] * n for _ in range(max(self._delays) + 1)]
        self._hist_i = 0
        self._sxx = [0.0] * pairs  # per (lag i, delay j): index i * len(delays) + j
        self._sxz = [0.0] * pairs
        self._szz = 0.0
        self.delay = 0.0
        self._u_lp = self._y_lp = 0.0
        self._pending: tuple[float, float] | None = None
        self._pending_dt = 0.0
        self.alpha = self.alpha0
        self.tau = self.tau0
        self.margin = self._cfg.margin

    def observe(self, dt_s: float, u_mean: float, y_m: float) -> None:
        """Note one sample's window means for the next :meth:`learn` (on the
        command path: nothing more than that)."""
        self._pending_dt += dt_s
        self._pending = (u_mean, y_m)

    def learn(self, learning: bool) -> bool:
        """Feed :meth:`update` the latest window means, every :data:`LEARN_PERIOD_S`.

        The window means are 20 ms averages, so sampling them every 4 ms loses
        nothing the identifier uses, and at 1 kHz it costs a quarter as much.
        ``learning`` is the caller's say whether the pilot flies (see
        :meth:`update`). Returns whether :meth:`update` ran.
        """
        p = self._pending
        # 0.9: sample intervals from timestamps jitter around 4 ms at 250 Hz.
        if p is None or not self._pending_dt >= 0.9 * LEARN_PERIOD_S:
            return False
        dt = self._pending_dt
        self._pending = None
        self._pending_dt = 0.0
        self.update(dt, p[0], p[1], learning)
        return True

    def margin_for(self, b: float, tau: float) -> float:
        r"""The margin for an identified slope ``b`` and lag ``tau``.

        With ``margin_min`` > 0 and ``tau`` slower than the axis's
        ``actuator_tau_s`` :math:`\tau_0`, the margin falls to
        :math:`\max(m_{min},\, m \max(\sqrt{\tau_0/\tau},\,
        \min(1, \sqrt{A_{ref}/A})))`, :math:`A = b` times the full-scale command
        (with ``authority_ref`` 0, the lag term alone). A lower margin is a larger
        loop gain: slow motors need it to stop a reversal's overshoot, and a
        vehicle with much authority can give it without saturating, while a
        weak one keeps the whole margin (docs/research/gains.md#strong-vehicle-margin).
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

    def margin_for_delay(self, margin: float, delay_s: float, tau_s: float) -> float:
        r"""The margin with the loop's delay taken into account.

        With ``delay_margin_slope`` > 0: at least
        :math:`\min(m_{max},\, m + s \max(0, D / \tau - r_{free}))`. A lower margin is a
        larger loop gain, and the estimate's own loop (the command fed back
        through :math:`\hat F` with gain :math:`b/\alpha - 1`) loses its
        stability to a delay first: a margin towards 1 shrinks that gain.
        """
        cfg = self._cfg
        if cfg.delay_margin_slope <= 0.0:
            return margin
        over = delay_s / tau_s - cfg.delay_margin_free_ratio if tau_s > 0.0 else 0.0
        if over <= 0.0:
            return margin
        md = cfg.margin + cfg.delay_margin_slope * over
        if md > cfg.delay_margin_max:
            md = cfg.delay_margin_max
        return md if md > margin else margin

    def _set_dt(self, dt_s: float) -> None:
        cfg = self._cfg
        self._dt = dt_s
        self._hp = -math.expm1(-dt_s / cfg.highpass_s)
        self._lam = math.exp(-dt_s / cfg.memory_s)
        self._ks = [-math.expm1(-dt_s / t) if t > 0.0 else 1.0 for t in self._taus]

    def update(self, dt_s: float, u_mean: float, y_m: float, learn: bool) -> None:
        """Feed one sample's window means; updates :attr:`alpha` and :attr:`tau`."""
        cfg = self._cfg
        if abs(dt_s - self._dt) > DT_REL_TOL * dt_s:
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
        hist = self._hist
        n_hist = len(hist)
        if n_hist > 1:
            self._hist_i = h = (self._hist_i + 1) % n_hist
            hist[h] = list(x)
        if not learn or abs(ut) < cfg.min_excitation_us:
            return
        z = y_m - y_lp
        if abs(z) < cfg.min_response_rad_s2:
            return
        lam = self._lam
        self._szz = szz = lam * self._szz + z * z
        sxx = self._sxx
        sxz = self._sxz
        delays = self._delays
        nd = len(delays)
        h = self._hist_i
        best = -1
        best_res = math.inf
        w = cfg.min_samples_weight_us2
        for j in range(nd):
            xs = hist[(h - delays[j]) % n_hist] if n_hist > 1 else x
            for i in range(len(x)):
                xi = xs[i]
                k = i * nd + j
                sxx[k] = a = lam * sxx[k] + xi * xi
                sxz[k] = c = lam * sxz[k] + xi * z
                if a >= w and c > 0.0:
                    res = szz - c * c / a
                    if res < best_res:
                        best_res = res
                        best = k
        if best < 0:
            return
        b = sxz[best] / sxx[best]
        self.tau = tau = self._taus[best // nd]
        self.delay = delay = self._delays_s[best % nd]
        self.margin = m = self.margin_for_delay(self.margin_for(b, tau), delay, tau)
        a = m * b
        self.alpha = cfg.alpha_max if a > cfg.alpha_max else max(a, cfg.alpha_min)
