r"""Estimators of F in y^(m) = F + alpha*u against exact answers on synthetic plants.

Sample convention (estimator docstring): the interval that ends at sample k
carries the command computed at sample k-1, which the caller passes as
``u_prev``. So with ``u[k]`` the command applied during the interval
(t_k, t_{k+1}]:

* m = 2: ``rate[k+1] = rate[k] + dt_k * (F + alpha*u[k])`` is exact for a
  piecewise-constant u, and ``update(dt_k, rate[k+1], u[k])`` is the call;
* m = 1: the rate over (t_k, t_{k+1}] is ``F + alpha*u[k]``, sampled at
  its end, and the same call applies.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.control import AlgebraicEstimator, WindowEstimator, make_estimator
from tests.control.plants import timestamps_dt

Estimator = type[WindowEstimator] | type[AlgebraicEstimator]

ALPHA = 0.7  # deliberately not 1, so an alpha slip shows
F_TRUE = -3.25


def drive_constant_f(
    est: WindowEstimator | AlgebraicEstimator,
    order: int,
    dts: np.ndarray,
    u: np.ndarray,
    f: float = F_TRUE,
    alpha: float = ALPHA,
    rate0: float = 0.4,
) -> np.ndarray:
    """Feed the exact ultra-local plant; returns the estimate after each update."""
    rate = rate0
    out = [est.update(0.004, rate, 0.0)]  # first sample only primes
    for dt, uk in zip(dts, u):
        rate = rate + dt * (f + alpha * uk) if order == 2 else f + alpha * uk
        out.append(est.update(float(dt), rate, float(uk)))
    return np.array(out)


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("rate_hz", [250.0, 1000.0])
def test_window_estimator_recovers_constant_f_exactly(order: int, rate_hz: float) -> None:
    rng = np.random.default_rng(1234 + order)
    n = 400
    u = rng.uniform(-60.0, 60.0, n)  # us of differential command, arbitrary
    est = WindowEstimator(order, ALPHA, 0.02)
    f_hat = drive_constant_f(est, order, timestamps_dt(rate_hz, n), u)
    assert f_hat[0] == 0.0  # priming sample: nothing estimated yet
    # Exact on the model itself: from the first full interval on (so a
    # fortiori after the window fills), up to rounding.
    np.testing.assert_allclose(f_hat[1:], F_TRUE, rtol=1e-9)
    assert est.f_hat == f_hat[-1]


@pytest.mark.parametrize("order", [1, 2])
def test_window_estimator_exact_with_jittered_timestamps(order: int) -> None:
    rng = np.random.default_rng(99)
    n = 600
    dts = 0.001 * (1.0 + rng.uniform(-0.4, 0.4, n))  # +-40 % jitter
    u = rng.uniform(-100.0, 100.0, n)
    f_hat = drive_constant_f(WindowEstimator(order, ALPHA, 0.02), order, dts, u)
    # Time weighting makes the answer exact whatever the interval lengths.
    np.testing.assert_allclose(f_hat[1:], F_TRUE, rtol=1e-9)


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize(("rate_hz", "n_expected"), [(250.0, 5), (1000.0, 20)])
def test_window_holds_t_over_dt_intervals(order: int, rate_hz: float, n_expected: int) -> None:
    """0.02 s at 250 Hz is 5 intervals, at 1 kHz 20 (timestamps k/rate_hz).

    Tell the estimator about one command the plant never received (u_prev off
    by 10 at one interval): the estimate is off by exactly
    alpha * 10 * dt / T for as long as that interval is in the window.
    """
    n = 80
    dts = timestamps_dt(rate_hz, n)
    u_plant = np.full(n, 5.0)
    u_told = u_plant.copy()
    j = 30
    u_told[j] += 10.0
    est = WindowEstimator(order, ALPHA, 0.02)
    rate = 0.0
    est.update(dts[0], rate, 0.0)
    f_hat = []
    for k in range(n):
        rate = (
            rate + dts[k] * (F_TRUE + ALPHA * u_plant[k])
            if order == 2
            else F_TRUE + ALPHA * u_plant[k]
        )
        f_hat.append(est.update(float(dts[k]), rate, float(u_told[k])))
    dev = np.array(f_hat) - F_TRUE
    affected = np.flatnonzero(np.abs(dev) > 1e-6)
    np.testing.assert_array_equal(affected, np.arange(j, j + n_expected))
    np.testing.assert_allclose(dev[affected], -ALPHA * 10.0 / n_expected, rtol=1e-6)


@pytest.mark.parametrize("order", [1, 2])
def test_set_window_changes_how_many_intervals_the_estimate_holds(order: int) -> None:
    """At 1 kHz, 0.02 s then 0.01 s from update 40 on: one command the plant never
    received (off by 10, at update 60) moves the estimate by alpha * 10 / 10 for 10
    updates. Back to 0.02 s at update 90, the window fills again interval by
    interval: a second slip at update 100 is held for 20 updates, by alpha * 10 / 20."""
    n = 140
    dts = np.full(n, 0.001)
    u_told = np.full(n, 5.0)
    u_told[60] += 10.0
    u_told[100] += 10.0
    est = WindowEstimator(order, ALPHA, 0.02)
    rate = 0.0
    est.update(0.001, rate, 0.0)
    dev = []
    for k in range(n):
        if k == 40:
            est.set_window(0.01)
        if k == 90:
            est.set_window(0.02)
        rate = rate + 0.001 * (F_TRUE + ALPHA * 5.0) if order == 2 else F_TRUE + ALPHA * 5.0
        dev.append(est.update(float(dts[k]), rate, float(u_told[k])) - F_TRUE)
    d = np.array(dev)
    affected = np.flatnonzero(np.abs(d) > 1e-6)
    np.testing.assert_array_equal(affected, np.r_[np.arange(60, 70), np.arange(100, 120)])
    np.testing.assert_allclose(d[60:70], -ALPHA * 10.0 / 10, rtol=1e-6)
    np.testing.assert_allclose(d[100:120], -ALPHA * 10.0 / 20, rtol=1e-6)
    with pytest.raises(ValueError, match="window_s"):
        est.set_window(0.0)


def test_window_estimator_slowly_varying_f_m2_is_the_window_average() -> None:
    """m = 2, F = F0 + A sin(2 pi f t), f = 1 Hz, T = 0.02 s, 1 kHz.

    The plant integrates F exactly over each interval, so the estimate is
    the mean of F over the last T:
    ``F0 + A (cos w(t-T) - cos w t) / (w T)`` = ``F0 + A sinc(wT/2) sin(w(t-T/2))``.
    """
    f0, A, freq, T, dt = 2.0, 5.0, 1.0, 0.02, 0.001
    w = 2 * math.pi * freq
    n = 2000
    rng = np.random.default_rng(7)
    u = rng.uniform(-50.0, 50.0, n)
    est = WindowEstimator(2, ALPHA, T)
    rate = 0.0
    est.update(dt, rate, 0.0)
    ts, f_hat = [], []
    for k in range(n):
        t0, t1 = k * dt, (k + 1) * dt
        int_f = f0 * dt - A / w * (math.cos(w * t1) - math.cos(w * t0))
        rate += int_f + ALPHA * u[k] * dt
        f_hat.append(est.update(dt, rate, float(u[k])))
        ts.append(t1)
    t = np.array(ts)[40:]  # window full
    f_hat_a = np.array(f_hat)[40:]
    expected = f0 + A * (np.cos(w * (t - T)) - np.cos(w * t)) / (w * T)
    np.testing.assert_allclose(f_hat_a, expected, rtol=0, atol=1e-9 * (f0 + A))
    # It lags by T/2: close to F(t - T/2) (within A*(wT)^2/24 = 3.3e-3) ...
    lagged = f0 + A * np.sin(w * (t - T / 2))
    assert np.max(np.abs(f_hat_a - lagged)) <= A * (w * T) ** 2 / 24 * 1.01
    # ... and within 1.1 * A * w * T/2 (= 0.35) of F(t).
    now = f0 + A * np.sin(w * t)
    err_now = np.max(np.abs(f_hat_a - now))
    assert err_now <= 1.1 * A * w * T / 2
    assert err_now >= 0.9 * A * w * T / 2  # the lag is really there


def test_window_estimator_slowly_varying_f_m1_is_the_sample_mean() -> None:
    """m = 1 with uniform dt: the mean of F at the N interval ends.

    Those ends sit on average (N-1) dt / 2 = T/2 - dt/2 before now.
    """
    f0, A, freq, T, dt = -1.0, 4.0, 1.0, 0.02, 0.001
    w = 2 * math.pi * freq
    N = 20
    n = 1500
    rng = np.random.default_rng(8)
    u = rng.uniform(-50.0, 50.0, n)
    est = WindowEstimator(1, ALPHA, T)
    est.update(dt, 0.0, 0.0)
    t_end = (np.arange(n) + 1) * dt
    F = f0 + A * np.sin(w * t_end)
    f_hat = np.array([est.update(dt, F[k] + ALPHA * u[k], float(u[k])) for k in range(n)])
    expected = np.array([F[k - N + 1 : k + 1].mean() for k in range(N, n)])
    np.testing.assert_allclose(f_hat[N:], expected, rtol=0, atol=1e-9 * (abs(f0) + A))
    t = t_end[N:]
    lagged = f0 + A * np.sin(w * (t - T / 2))
    # dt/2 of residual lag plus the averaging curvature.
    assert np.max(np.abs(f_hat[N:] - lagged)) <= A * w * dt / 2 + A * (w * T) ** 2 / 24
    assert np.max(np.abs(f_hat[N:] - F[N:])) <= 1.1 * A * w * T / 2


@pytest.mark.parametrize("cls", [WindowEstimator, AlgebraicEstimator])
@pytest.mark.parametrize("order", [1, 2])
def test_reset_forgets(cls: Estimator, order: int) -> None:
    """After reset() the estimator behaves exactly like a new one."""
    rng = np.random.default_rng(3)
    est = cls(order, ALPHA, 0.02)
    drive_constant_f(est, order, np.full(100, 0.001), rng.uniform(-9, 9, 100), f=50.0)
    assert est.f_hat != 0.0
    est.reset()
    assert est.f_hat == 0.0
    dts = np.full(60, 0.001)
    u = rng.uniform(-9, 9, 60)
    after_reset = drive_constant_f(est, order, dts, u, f=-2.0)
    fresh = drive_constant_f(cls(order, ALPHA, 0.02), order, dts, u, f=-2.0)
    assert after_reset[0] == 0.0  # the first sample primes again
    np.testing.assert_array_equal(after_reset, fresh)
    if cls is WindowEstimator:
        np.testing.assert_allclose(after_reset[1:], -2.0, rtol=1e-9)


# ---------------------------------------------------------------------------
# Algebraic (Fliess-Join) estimator.
#
# Its kernel integrals are evaluated with the midpoint rule on the N intervals
# of the window, so it is not exact: for m = 1 the midpoint rule on the
# quadratic kernel terms gives a relative error of 1/N^2 (a ramp y = F*sigma
# yields F*(1 - 1/N^2) exactly); for m = 2 the quartic terms give about
# 10/N^2. The stated tolerances below are 1.5x those bounds, applied to
# |F| + |alpha*u|max. They are loose at 250 Hz (N = 5) by necessity.


def _algebraic_tol(order: int, n_window: int, scale: float) -> float:
    return 1.5 * (1.0 if order == 1 else 10.0) / n_window**2 * scale


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("rate_hz", [250.0, 1000.0])
def test_algebraic_estimator_constant_f_random_input(order: int, rate_hz: float) -> None:
    rng = np.random.default_rng(42 + order)
    n = 300
    u_max = 20.0
    u = rng.uniform(-u_max, u_max, n)
    est = AlgebraicEstimator(order, ALPHA, 0.02)
    f_hat = drive_constant_f(est, order, timestamps_dt(rate_hz, n), u)
    N = round(0.02 * rate_hz)
    tol = _algebraic_tol(order, N, abs(F_TRUE) + ALPHA * u_max)
    np.testing.assert_allclose(f_hat[N + 1 :], F_TRUE, rtol=0, atol=tol)


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("rate_hz", [250.0, 1000.0])
def test_algebraic_estimator_ignores_the_angle_offset(order: int, rate_hz: float) -> None:
    """The docstring says y's offset cancels. Hold the rate at 10 rad/s with u = 0
    for one second: F = 10 for m = 1 (y' = F), F = 0 for m = 2 (y'' = 0),
    while the integrated angle y climbs to 10 rad. The estimate must not
    follow y. For m = 2, y is linear, its midpoint samples are exact, and only
    the quadrature bound is allowed.
    """
    n = round(rate_hz)
    N = round(0.02 * rate_hz)
    f_true = 10.0 if order == 1 else 0.0
    est = AlgebraicEstimator(order, ALPHA, 0.02)
    f_hat = drive_constant_f(
        est, order, timestamps_dt(rate_hz, n), np.zeros(n), f=f_true, rate0=10.0
    )
    tol = _algebraic_tol(order, N, 10.0)
    np.testing.assert_allclose(f_hat[N + 1 :], f_true, rtol=0, atol=tol)


def test_algebraic_estimator_m1_slowly_varying_f_lags_half_a_window() -> None:
    """Symmetric kernel sigma*(T - sigma): a weighted mean of F centred near t - T/2."""
    f0, A, freq, T, dt = 2.0, 5.0, 1.0, 0.02, 0.001
    w = 2 * math.pi * freq
    n = 1500
    rng = np.random.default_rng(11)
    u = rng.uniform(-5.0, 5.0, n)
    est = AlgebraicEstimator(1, ALPHA, T)
    est.update(dt, 0.0, 0.0)
    t_end = (np.arange(n) + 1) * dt
    F = f0 + A * np.sin(w * t_end)
    fh = np.array([est.update(dt, F[k] + ALPHA * u[k], float(u[k])) for k in range(n)])[40:]
    t = t_end[40:]
    # Lag T/2 - dt/2 as for the window mean, plus the 1/N^2 quadrature error
    # on |F| + |alpha u|: 0.02 + 1.5 * (7 + 3.5) / 400 = 0.06.
    lagged = f0 + A * np.sin(w * (t - T / 2 + dt / 2))
    np.testing.assert_allclose(fh, lagged, rtol=0, atol=0.06)


# ---------------------------------------------------------------------------
# Construction.


@pytest.mark.parametrize("cls", [WindowEstimator, AlgebraicEstimator])
@pytest.mark.parametrize(
    ("order", "alpha", "window"),
    [(3, 1.0, 0.02), (0, 1.0, 0.02), (1, 0.0, 0.02), (1, math.nan, 0.02), (2, 1.0, 0.0),
     (2, 1.0, -0.02), (2, 1.0, math.inf)],
)  # fmt: skip
def test_estimator_rejects_bad_parameters(
    cls: Estimator, order: int, alpha: float, window: float
) -> None:
    with pytest.raises(ValueError):
        cls(order, alpha, window)


def test_make_estimator() -> None:
    assert isinstance(make_estimator("window", 2, 1.0, 0.02), WindowEstimator)
    assert isinstance(make_estimator("algebraic", 1, 1.0, 0.02), AlgebraicEstimator)
    with pytest.raises(ValueError, match="unknown estimator"):
        make_estimator("kalman", 1, 1.0, 0.02)  # type: ignore[arg-type]
