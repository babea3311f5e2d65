r"""The order-1 ultra-local model the outer loops share, and its estimate of ``F``.

Each outer loop (:mod:`~companion.control.attitude`,
:mod:`~companion.control.vertical`, :mod:`~companion.control.horizontal`) is an
iP on an ultra-local model of order 1 (the paper's Section II-C, ``m = 1``):

.. math::  \dot y = F + \alpha u, \qquad
           u = -\frac{\hat F - \dot y_r + K_P e}{\alpha}, \quad e = y - y_r

whose command ``u`` is the reference of the loop beneath it, never an actuator.
That inner loop follows ``u`` with a lag, and the paper's window average of
:math:`\dot y - \alpha u` teaches ``F`` that each command acted at once: the
estimate's loop is then an integrator around the inner loop's lag, which
oscillates unless the window is long against the lag or :math:`\alpha` is large
(``docs/research/outer.md`` shows it diverge on a 100 ms lag with a 20 ms window).

The estimate used here is the rate loop's lag-aware one
(:class:`companion.control.intelligent.IntelligentController`, not in the paper):

.. math::  \hat F = \overline{\dot y} - \alpha\, L_\tau\, \bar u

the window means (:class:`~companion.control.estimator.WindowEstimator`) with the
command's mean passed through a first-order lag :math:`\tau`, the inner closed
loop's expected lag (a design number of each loop, documented with its gains).
With a matched lag the error obeys :math:`\tau \ddot e + \dot e + K_P e = 0`
(:math:`\zeta = 1 / (2\sqrt{K_P \tau})`); with :math:`\tau = 0` it is the paper's
estimate and :math:`\dot e = -K_P e`.

Written out, the law is incremental: :math:`u = L_\tau \bar u - (\overline{\dot y}
- \dot y_r + K_P e) / \alpha`, the command the inner loop is taken to be delivering
plus a correction. ``F`` is never integrated, so nothing winds up; it is learnt
from the command really sent (after every limit).
"""

from __future__ import annotations

import math

from companion.control.estimator import WindowEstimator
from companion.control.identifier import DT_REL_TOL

__all__ = ["DT_MAX_S", "DT_MIN_S", "GRAVITY_M_S2", "LagAwareEstimate", "check_positive"]

GRAVITY_M_S2 = 9.80665
"""Standard gravity, m/s^2."""

DT_MIN_S = 1e-4
DT_MAX_S = 0.1
"""Each outer loop clamps ``dt_s`` to [DT_MIN_S, DT_MAX_S] (and counts it): slower
than 10 Hz no outer loop can hold its bandwidth, and the windows assume it."""


def check_positive(owner: object, names: tuple[str, ...], *, zero_ok: bool = False) -> None:
    """Raise ``ValueError`` naming ``Owner.field`` for the first of ``names`` that is
    not a finite number > 0 (>= 0 with ``zero_ok``)."""
    for name in names:
        v = getattr(owner, name)
        ok = isinstance(v, (int, float)) and math.isfinite(v) and (v >= 0.0 if zero_ok else v > 0.0)
        if not ok:
            need = "finite and >= 0" if zero_ok else "finite and > 0"
            raise ValueError(f"{type(owner).__name__}.{name} must be {need}, got {v!r}")


class LagAwareEstimate:
    r""":math:`\hat F = \overline{\dot y} - \alpha L_\tau \bar u` for one axis (order 1).

    Parameters
    ----------
    window_s
        The window ``T`` of the means, s.
    lag_s
        :math:`\tau`, the inner loop's lag, s (0: the paper's estimate).

    Each :meth:`update` adds the interval that just ended: its duration, the
    measured :math:`\dot y` at its end and the command applied during it (the one
    sent at the previous sample). Until the first interval, :attr:`f_hat` is the
    prior given to :meth:`reset`.
    """

    __slots__ = (
        "_est", "_lag_dt", "_lag_k", "_lag_s", "_rest_left_s", "_u_rest", "_window_s",
        "f_hat", "u_lagged", "y_dot_mean",
    )  # fmt: skip

    def __init__(self, window_s: float, lag_s: float) -> None:
        self._est = WindowEstimator(1, 1.0, window_s)  # alpha: its f_hat is not used
        self._window_s = window_s
        self._lag_s = lag_s
        self._lag_dt = -1.0
        self._lag_k = 1.0
        self.reset()

    def reset(self, u_prior: float = 0.0, f_prior: float = 0.0, *, at_rest: bool = False) -> None:
        """Forget the window. ``u_prior``: the command the inner loop is taken to be
        following (the lag's state); ``f_prior``: :attr:`f_hat` until the first
        interval.

        ``at_rest``: the window starts full, of a window's time at rest (no
        change in ``y``, the command ``u_prior`` held), which the new intervals
        push out as they arrive. The means then cover the whole window from the
        first interval, as the lag model assumes; a window filling from empty
        weighs its first intervals too much and costs the loop damping
        (``docs/research/outer.md``). Use it when the reset is made at rest (on
        the ground) and ``f_prior`` is ``-alpha u_prior``.
        """
        est = self._est
        est.reset()
        est.update(1.0, 0.0, 0.0)  # primes it: from now on every update is an interval
        self.u_lagged = u_prior
        self.y_dot_mean = 0.0
        self.f_hat = f_prior
        self._u_rest = u_prior
        self._rest_left_s = self._window_s if at_rest else 0.0

    def update(self, dt_s: float, y_dot: float, u_prev: float, alpha: float) -> float:
        r"""Add an interval; return :math:`\hat F` (units of :math:`\dot y`).

        Parameters
        ----------
        dt_s
            The interval, s (> 0).
        y_dot
            Measured :math:`\dot y` at its end.
        u_prev
            The command applied during it.
        alpha
            The loop's :math:`\alpha` now (it may be identified in flight).
        """
        est = self._est
        est.update(dt_s, y_dot, u_prev)
        u_mean, y_m = est.u_mean, est.y_m
        if self._rest_left_s > 0.0:  # part of the window is still the rest before the reset
            self._rest_left_s = rest = max(self._rest_left_s - dt_s, 0.0)
            share = rest / self._window_s
            y_m *= 1.0 - share
            u_mean += (self._u_rest - u_mean) * share
        tau = self._lag_s
        if tau > 0.0:
            if abs(dt_s - self._lag_dt) > DT_REL_TOL * dt_s:
                self._lag_dt = dt_s
                self._lag_k = -math.expm1(-dt_s / tau)
            self.u_lagged = u_a = self.u_lagged + (u_mean - self.u_lagged) * self._lag_k
        else:
            self.u_lagged = u_a = u_mean
        self.y_dot_mean = y_m
        self.f_hat = f = y_m - alpha * u_a
        return f
