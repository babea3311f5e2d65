r"""iP and iPD (IntelligentController) in closed loop: the designed error dynamics.

With a good estimate of F the laws (paper equations (ip), (ipd)) leave

* iP:  :math:`\dot e = -K_P e`  so  :math:`e(t) = e_0 e^{-K_P t}`;
* iPD: :math:`\ddot e + K_D \dot e + K_P e = 0`, with ``kp = 100``,
  ``kd = 20`` critically damped (double pole at -10):
  :math:`e(t) = e_0 (1 + 10 t) e^{-10 t}` from rest.

The plants carry an unknown drift: a constant plus a 2 Hz sinusoid and a
``-c*state`` term, which the controller never sees. The command computed at
a sample is applied over the next interval, so the analytic response starts
one sample after the error is set.

Residual error from the estimate's lag (F_hat is F averaged over the window,
late by T/2): ``|F - F_hat| <= max|dF/dt| * T/2``, seen by the error
dynamics with static gain ``1/kp``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import MfcAxisConfig
from companion.control import MfcAxisGains
from tests.control.gains import axis, law
from tests.control.plants import LoopResult, run_axis_loop

C_DRAG = 2.0  # the plant's -c*state term, 1/s
D0, D1, D_HZ = 5.0, 3.0, 2.0  # disturbance d(t) = D0 + D1 sin(2 pi D_HZ t)
REF_A, REF_HZ = 2.0, 1.0  # reference rate REF_A sin(2 pi REF_HZ t), rad/s
E0 = 0.1  # initial error, rad


def disturbance(t: float) -> float:
    return D0 + D1 * math.sin(2 * math.pi * D_HZ * t)


def ref_rate(t: float) -> float:
    return REF_A * math.sin(2 * math.pi * REF_HZ * t)


def ref_rate_dot(t: float) -> float:
    return REF_A * 2 * math.pi * REF_HZ * math.cos(2 * math.pi * REF_HZ * t)


def gains(order: int, window_s: float, kp: float = 100.0, kd: float = 20.0) -> MfcAxisGains:
    # Limits out of the way: this is the unsaturated law.
    return axis(
        order=order,
        alpha=1.0,
        window_s=window_s,
        kp=kp,
        kd=kd if order == 2 else 0.0,
        output_limit_us=1e9,
        error_limit_rad=10.0,
    )


def loop(
    order: int, b: float, dt: float, window_s: float, e0: float, duration_s: float
) -> LoopResult:
    return run_axis_loop(
        gains(order, window_s),
        b=b,
        c=C_DRAG,
        disturbance=disturbance,
        ref_rate=ref_rate,
        ref_rate_dot=ref_rate_dot,
        dt=dt,
        warmup_s=0.2,
        duration_s=duration_s,
        e0=e0,
    )


def max_df_dt(order: int) -> float:
    """Bound on |dF/dt| for the plant above (F = -c*state + d(t))."""
    w_d = 2 * math.pi * D_HZ
    w_r = 2 * math.pi * REF_HZ
    # order 1: state = y tracks y_r, |y'| <= REF_A; order 2: state = w, |w'| <= REF_A w_r.
    state_dot = REF_A if order == 1 else REF_A * w_r
    return D1 * w_d + C_DRAG * state_dot * 1.2


def test_ip_error_follows_designed_first_order_dynamics() -> None:
    dt, window, kp = 1e-4, 1e-3, 100.0
    r = loop(1, b=1.0, dt=dt, window_s=window, e0=E0, duration_s=0.06)
    analytic = E0 * np.exp(-kp * (r.t - dt))
    forced = max_df_dt(1) * window / 2 / kp  # ~2e-4 rad
    # 1 % of e0 for the Euler-vs-exponential and one-sample-delay effects
    # (kp*dt = 0.01), plus the lag residual.
    tol = 0.01 * E0 + forced
    np.testing.assert_allclose(r.e, analytic, rtol=0, atol=tol)
    # And it is really the designed decay: after 3 time constants e ~ 5 % e0.
    k3 = np.searchsorted(r.t, 3 / kp + dt)
    assert abs(r.e[k3] - E0 * math.exp(-3)) < tol


def test_ipd_error_follows_designed_critically_damped_dynamics() -> None:
    dt, window = 1e-4, 1e-3
    r = loop(2, b=1.0, dt=dt, window_s=window, e0=E0, duration_s=1.0)
    s = r.t - dt
    analytic = E0 * (1 + 10 * s) * np.exp(-10 * s)
    forced = max_df_dt(2) * window / 2 / 100.0  # ~1e-3 rad
    tol = 0.01 * E0 + forced
    np.testing.assert_allclose(r.e, analytic, rtol=0, atol=tol)
    # Critically damped: no zero crossing of the transient (beyond the residual).
    assert r.e.min() > -tol
    # e_dot is the gyro error: it follows -100 e0 t exp(-10 t), peak -e0*10/e at t = 0.1.
    np.testing.assert_allclose(r.e_dot, -100 * E0 * s * np.exp(-10 * s), rtol=0, atol=10 * tol)


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("rate_hz", [250.0, 1000.0])
@pytest.mark.parametrize("b_over_alpha", [1 / 3, 1.0, 3.0])
def test_same_gains_hold_when_the_plant_gain_changes(
    order: int, rate_hz: float, b_over_alpha: float
) -> None:
    """Table I window (0.02 s), kp = 100 (kd = 20), plant gain b = alpha/3 .. 3 alpha.

    The plant is linear and nothing saturates, so the free response to the
    initial error is the difference between a run with e0 and the same run
    with e0 = 0: it must stay within e0 and die out. The forced response
    (drift, reference) must stay bounded.
    """
    dt = 1.0 / rate_hz
    duration = 1.5 if order == 1 else 2.0
    r1 = loop(order, b_over_alpha, dt, 0.02, E0, duration)
    r0 = loop(order, b_over_alpha, dt, 0.02, 0.0, duration)
    free = r1.e - r0.e
    assert np.max(np.abs(free)) <= 1.05 * E0
    late = np.abs(free[r1.t > duration - 0.25])
    before = np.abs(free[(r1.t > duration - 0.5) & (r1.t <= duration - 0.25)])
    # Slowest case (iP, 250 Hz, b = 3 alpha: a Nyquist-rate mode at the edge of
    # what a 5-sample window absorbs) is at ~5 % after 1.2 s.
    assert late.max() <= 0.1 * E0
    assert late.max() <= before.max() + 1e-9  # still decaying, not a limit cycle
    # Forced error bounded (the matched case is ~max|F'| T/2 / kp = 4e-3 rad).
    assert np.max(np.abs(r0.e)) <= 0.05
    assert np.all(np.isfinite(r1.u))


def test_error_is_clamped_to_error_limit() -> None:
    g = axis(order=2, alpha=1.0, window_s=0.02, kp=3.0, kd=0.096, error_limit_rad=0.2)
    ctrl = law(g)
    for _ in range(100):
        ctrl.update(0.01, 5.0, 0.0, 0.0)  # 5 rad/s of error for 1 s
    assert ctrl.e == pytest.approx(0.2)
    for _ in range(100):
        ctrl.update(0.01, -5.0, 0.0, 0.0)
    assert ctrl.e == pytest.approx(-0.2)


def test_ipd_law_single_step_by_hand() -> None:
    """u = -(F_hat - ydd_r + kp e + kd e_dot) / alpha, saturated at output_limit_us."""
    g = axis(order=2, alpha=2.0, window_s=0.02, kp=3.0, kd=0.5, output_limit_us=100.0)
    ctrl = law(g)
    # First sample primes the estimator: F_hat = 0.
    # e_dot = 1.0 - 0.25 = 0.75; e = 0 + 0.75 * 0.01 = 0.0075;
    # u = -(0 - 2.0 + 3 * 0.0075 + 0.5 * 0.75) / 2 = -(-1.6025) / 2 = 0.80125.
    u = ctrl.update(0.01, 1.0, 0.25, 2.0)
    assert u == pytest.approx(0.80125, rel=1e-12)
    assert ctrl.u_prev == u
    # Second sample: rate 1.1, m = 2 window estimate over one interval:
    # F_hat = (1.1 - 1.0)/0.01 - 2.0 * 0.80125 = 10 - 1.6025 = 8.3975;
    # e_dot = 1.1 - 0.25 = 0.85; e = 0.0075 + 0.0085 = 0.016;
    # u = -(8.3975 - 2.0 + 0.048 + 0.425) / 2 = -3.43525.
    u = ctrl.update(0.01, 1.1, 0.25, 2.0)
    assert ctrl.f_hat == pytest.approx(8.3975, rel=1e-12)
    assert u == pytest.approx(-3.43525, rel=1e-12)
    # Saturation at +-output_limit_us.
    assert ctrl.update(0.01, -1000.0, 0.0, 0.0) == 100.0


def test_ip_law_single_step_by_hand() -> None:
    """u = -(F_hat - y_r' + kp e) / alpha (kd unused)."""
    g = axis(order=1, alpha=0.5, window_s=0.02, kp=2.0, kd=99.0)
    ctrl = law(g)
    # e = (0.3 - 1.0) * 0.004 = -0.0028; u = -(0 - 1.0 + 2 * -0.0028) / 0.5 = 2.0112.
    assert ctrl.update(0.004, 0.3, 1.0, 123.0) == pytest.approx(2.0112, rel=1e-12)
    # F_hat (m = 1) = 0.5 - 0.5 * 2.0112 = -0.5056; e = -0.0028 - 0.002 = -0.0048;
    # u = -(-0.5056 - 1.0 - 0.0096) / 0.5 = 3.0304.
    assert ctrl.update(0.004, 0.5, 1.0, 0.0) == pytest.approx(3.0304, rel=1e-12)


def test_reset_clears_controller_state() -> None:
    ctrl = law(gains(2, 0.02))
    for k in range(50):
        ctrl.update(0.004, math.sin(k), 0.3, 0.1)
    ctrl.reset()
    assert (ctrl.e, ctrl.e_dot, ctrl.f_hat, ctrl.u_prev) == (0.0, 0.0, 0.0, 0.0)
    fresh = law(gains(2, 0.02))
    for k in range(30):
        assert ctrl.update(0.004, math.cos(k), 0.1, 0.0) == fresh.update(
            0.004, math.cos(k), 0.1, 0.0
        )


@pytest.mark.parametrize(
    "kwargs",
    [
        {"order": 3},
        {"alpha": 0.0},
        {"window_s": 0.0},
        {"output_limit_us": 0.0},
        {"kp": math.nan},
        {"alpha": math.inf},
    ],
)
def test_axis_gains_reject_bad_values(kwargs: dict[str, float]) -> None:
    """The schema is where a gain is checked: the law's settings come only from it."""
    base = {"order": 2, "alpha": 1.0, "window_s": 0.02, "kp": 3.0}
    with pytest.raises(ValueError):
        MfcAxisConfig(**{**base, **kwargs})
