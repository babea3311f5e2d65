r"""Estimators of ``F`` in the ultra-local model :math:`y^{(m)} = F + \alpha u`.

The controlled output ``y`` of each axis is the body-axis angle, i.e. the time
integral of the measured body rate; so :math:`\dot y` is the gyro rate
``omega`` (rad/s), measured by a sensor as the paper's Remark on
:math:`\dot e` requires, and for ``m = 2`` :math:`\ddot y` is the paper's finite
difference of the gyro rate.

Which sample of ``u`` enters
----------------------------
The window is made of sample *intervals*. The interval that ends at sample
``k`` is the time during which the command computed at sample ``k - 1`` was
applied, so it carries ``u[k-1]`` (the previous command), never ``u[k]``,
which depends on the estimate being formed. Callers pass the command that
was really applied (after saturation and mixing), so a saturated command
does not teach the estimator an effect that never happened.

Window average (the paper's estimator, O(1) per sample)
-------------------------------------------------------
Averaging ``y^(m) - alpha*u`` over intervals ``j`` of the window ``W``
(duration :math:`T_W = \sum dt_j`), time-weighted:

* ``m = 2``: the one-step differences :math:`(\omega_j - \omega_{j-1})/dt_j`
  weighted by :math:`dt_j` telescope, so
  :math:`\hat F = (\omega_k - \omega_{k-N}) / T_W - \alpha \bar u`;
* ``m = 1``: :math:`\hat F = \bar\omega - \alpha \bar u` with
  :math:`\bar\omega = \sum \omega_j dt_j / T_W`, each interval's rate taken
  at its end;

where :math:`\bar u = \sum u_j dt_j / T_W`. Both rules are exact on the
ultra-local model itself with ``F`` and ``u`` constant over an interval: for
``m = 1`` the rate is then constant over the interval (so its end sample is
its value), for ``m = 2`` it is linear (so the difference quotient is exact).
Running sums make each update O(1); they are recomputed from the ring every
4096 updates to stop floating-point drift.

Algebraic estimator (Fliess and Join)
-------------------------------------
Integrating the model against polynomial weights over the window
:math:`\sigma \in [0, T]` (oldest to newest) removes every derivative:

* ``m = 1``: :math:`\hat F = -\frac{6}{T^3}\int_0^T \big[(T - 2\sigma) y
  + \alpha \sigma (T - \sigma) u\big] d\sigma`
* ``m = 2``: :math:`\hat F = \frac{60}{T^5}\int_0^T \big[(T^2 - 6T\sigma +
  6\sigma^2) y - \frac{\alpha}{2} \sigma^2 (T - \sigma)^2 u\big] d\sigma`

with ``y`` the integrated rate (its offset cancels: the weights integrate
constants and ramps to zero). Each cell is integrated exactly (Gauss-Legendre),
O(N) per sample (N <= a few tens at 1 kHz): offered as an alternative, not the
default.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Literal

__all__ = ["AlgebraicEstimator", "FEstimator", "WindowEstimator", "make_estimator"]

_MAX_INTERVALS = 1024
_RESUM_EVERY = 4096


def _check_args(order: int, alpha: float, window_s: float) -> None:
    if order not in (1, 2):
        raise ValueError(f"order must be 1 or 2, got {order!r}")
    if not (math.isfinite(alpha) and alpha != 0.0):
        raise ValueError(f"alpha must be finite and non-zero, got {alpha!r}")
    if not (math.isfinite(window_s) and window_s > 0.0):
        raise ValueError(f"window_s must be > 0, got {window_s!r}")


class WindowEstimator:
    r"""Sliding-window average of :math:`y^{(m)} - \alpha u` (the paper's estimator).

    Parameters
    ----------
    order
        Derivation order ``m`` (1 or 2).
    alpha
        :math:`\alpha` in (output units/s^m) per command unit.
    window_s
        Window duration ``T`` in seconds (Table I: 0.02 s).
    """

    __slots__ = (
        "_alpha",
        "_buf",
        "_count",
        "_order",
        "_prev_rate",
        "_rate_start",
        "_s_rate",
        "_s_t",
        "_s_u",
        "_window_s",
        "f_hat",
        "u_mean",
        "y_m",
    )

    def __init__(self, order: int, alpha: float, window_s: float) -> None:
        _check_args(order, alpha, window_s)
        self._order = order
        self._alpha = alpha
        # Slightly below T so that N equal steps of T/N make exactly N intervals.
        self._window_s = window_s * (1.0 - 1e-9)
        # Each interval: (dt_s, rate at its end, u*dt, rate*dt)
        self._buf: deque[tuple[float, float, float, float]] = deque()
        self.reset()

    def reset(self) -> None:
        """Forget the window (e.g. on disarm)."""
        self._buf.clear()
        self._s_t = 0.0
        self._s_u = 0.0
        self._s_rate = 0.0
        self._prev_rate: float | None = None
        self._rate_start = 0.0
        self._count = 0
        self.f_hat = 0.0
        self.u_mean = 0.0
        self.y_m = 0.0

    def set_window(self, window_s: float) -> None:
        """Change the window's duration from the next update on: a shorter one drops
        its oldest intervals then; a longer one fills as the intervals come."""
        _check_args(self._order, self._alpha, window_s)
        self._window_s = window_s * (1.0 - 1e-9)

    def update(self, dt_s: float, rate: float, u_prev: float) -> float:
        r"""Add the interval that just ended and return the new estimate.

        Parameters
        ----------
        dt_s
            Duration of the interval, s (> 0, clamped by the caller).
        rate
            Measured rate at its end (:math:`\dot y`), rad/s.
        u_prev
            Command applied during it (computed at the previous sample).
        """
        prev = self._prev_rate
        self._prev_rate = rate
        if prev is None:
            self._rate_start = rate
            return self.f_hat
        udt = u_prev * dt_s
        wdt = rate * dt_s  # m = 1: the rate at the interval's end held over it
        buf = self._buf
        buf.append((dt_s, rate, udt, wdt))
        s_t = self._s_t + dt_s
        s_u = self._s_u + udt
        s_rate = self._s_rate + wdt
        # Drop the oldest intervals while the rest still cover the window. The
        # threshold is positive, so the newest interval is never dropped.
        thr = self._window_s
        while s_t - buf[0][0] >= thr:
            old = buf.popleft()
            s_t -= old[0]
            s_u -= old[2]
            s_rate -= old[3]
            self._rate_start = old[1]
        if len(buf) > _MAX_INTERVALS:  # absurdly small dt: bound the memory
            old = buf.popleft()
            s_t -= old[0]
            s_u -= old[2]
            s_rate -= old[3]
            self._rate_start = old[1]
        self._count += 1
        if self._count >= _RESUM_EVERY:
            self._count = 0
            s_t = math.fsum(b[0] for b in buf)
            s_u = math.fsum(b[2] for b in buf)
            s_rate = math.fsum(b[3] for b in buf)
        self._s_t = s_t
        self._s_u = s_u
        self._s_rate = s_rate
        self.u_mean = u_mean = s_u / s_t
        if self._order == 2:
            self.y_m = y_m = (rate - self._rate_start) / s_t
        else:
            self.y_m = y_m = s_rate / s_t
        self.f_hat = f = y_m - self._alpha * u_mean
        return f


# 3-point Gauss-Legendre nodes and weights on [0, 1]: exact for polynomials of
# degree <= 5, and every integrand below is a polynomial of degree <= 4 on a cell.
_GL_X = (0.5 - 0.5 * math.sqrt(0.6), 0.5, 0.5 + 0.5 * math.sqrt(0.6))
_GL_W = (5.0 / 18.0, 8.0 / 18.0, 5.0 / 18.0)


class AlgebraicEstimator:
    """Fliess-Join algebraic integral estimator of ``F`` (see module docstring).

    Same interface as :class:`WindowEstimator`; O(N) per update. ``y`` is
    rebuilt over the window from its start (``y = 0`` there: the weights cancel
    any offset), with the rate held (``m = 1``) or linear (``m = 2``) over each
    cell as in :class:`WindowEstimator`, and each cell's integral is computed
    exactly by Gauss-Legendre quadrature. So the estimate is exact on the
    ultra-local model with ``F`` constant over the window and ``u`` constant
    over each cell, and it carries no unbounded angle.
    """

    __slots__ = ("_alpha", "_buf", "_order", "_prev_rate", "_s_t", "_window_s", "f_hat")

    def __init__(self, order: int, alpha: float, window_s: float) -> None:
        _check_args(order, alpha, window_s)
        self._order = order
        self._alpha = alpha
        self._window_s = window_s * (1.0 - 1e-9)
        # Each cell: (dt_s, rate at its start, rate at its end, u applied)
        self._buf: deque[tuple[float, float, float, float]] = deque()
        self.reset()

    def reset(self) -> None:
        self._buf.clear()
        self._s_t = 0.0
        self._prev_rate: float | None = None
        self.f_hat = 0.0

    def set_window(self, window_s: float) -> None:
        """As :meth:`WindowEstimator.set_window`."""
        _check_args(self._order, self._alpha, window_s)
        self._window_s = window_s * (1.0 - 1e-9)

    def update(self, dt_s: float, rate: float, u_prev: float) -> float:
        prev = self._prev_rate
        self._prev_rate = rate
        if prev is None:
            return self.f_hat
        buf = self._buf
        buf.append((dt_s, prev, rate, u_prev))
        self._s_t += dt_s
        while self._s_t - buf[0][0] >= self._window_s or len(buf) > _MAX_INTERVALS:
            self._s_t -= buf.popleft()[0]
        T = math.fsum(b[0] for b in buf)
        a = self._alpha
        m2 = self._order == 2
        acc = 0.0
        sig0 = 0.0  # cell start, from the window start
        y0 = 0.0  # y at the cell start
        for d, w_a, w_b, u in buf:
            cell = 0.0
            for x, wq in zip(_GL_X, _GL_W):
                s_in = x * d
                sig = sig0 + s_in
                if m2:
                    y = y0 + w_a * s_in + 0.5 * (w_b - w_a) / d * s_in * s_in
                    q = sig * (T - sig)
                    f = (T * T - 6.0 * T * sig + 6.0 * sig * sig) * y - 0.5 * a * q * q * u
                else:
                    y = y0 + w_b * s_in
                    f = (T - 2.0 * sig) * y + a * sig * (T - sig) * u
                cell += wq * f
            acc += cell * d
            y0 += (0.5 * (w_a + w_b) if m2 else w_b) * d
            sig0 += d
        f_hat = 60.0 * acc / T**5 if m2 else -6.0 * acc / (T * T * T)
        self.f_hat = f_hat
        return f_hat


FEstimator = WindowEstimator | AlgebraicEstimator


def make_estimator(
    kind: Literal["window", "algebraic"], order: int, alpha: float, window_s: float
) -> FEstimator:
    """Build the estimator named by ``kind``."""
    if kind == "window":
        return WindowEstimator(order, alpha, window_s)
    if kind == "algebraic":
        return AlgebraicEstimator(order, alpha, window_s)
    raise ValueError(f"unknown estimator {kind!r}: expected 'window' or 'algebraic'")
