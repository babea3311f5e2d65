r"""The attitude loop (iP per body axis, alpha = 1) against closed-form answers.

Plants, integrated here:

* *kinematic*: the rate loop delivers its reference exactly, :math:`\omega = \omega_r`,
  held over each interval; the attitude is rotated by it exactly. There ``F = 0``
  and the paper's estimate (``inner_lag_s = 0``) finds it exactly, so a rotation
  about one axis obeys, sample by sample, :math:`\varepsilon_{k+1} = (1 - K
  \Delta t)\,\varepsilon_k`: the explicit-Euler image of :math:`e^{-K t}`. With
  :math:`h = K \Delta t` and :math:`(1 - h)^k = e^{-kh} e^{-k(-\ln(1-h) - h)}` and
  :math:`1 - e^{-x} \le x`, it differs from :math:`\varepsilon_0 e^{-Kt}` by at most
  :math:`|\varepsilon_0| e^{-Kt} k (-\ln(1 - h) - h) \approx K^2 \Delta t\, t\,
  e^{-Kt} |\varepsilon_0| / 2`.
* *lagged*: :math:`\dot\omega = (\omega_r - \omega)/\tau` (exact for a held
  reference), the rate loop as the default estimate models it. With the matched
  lag the error obeys :math:`\tau\ddot\varepsilon + \dot\varepsilon + K\varepsilon =
  0` from rest, up to the window's delay.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.control.attitude import (
    DEFAULT_ATTITUDE_GAINS,
    AttitudeGains,
    AttitudeLoop,
    AttitudeSetpoint,
    attitude_error_frd_rad,
)
from companion.control.quaternion import Quat, euler_to_quat, quat_log, quat_mul, yaw_rad
from tests.control.outer_plant import quat_exp_step

PAPER = dataclasses.replace(DEFAULT_ATTITUDE_GAINS, inner_lag_s=0.0)
"""The paper's estimate (no lag model): exact on the kinematic plant."""
UNLIMITED = dataclasses.replace(
    PAPER, rate_max_roll_pitch_rad_s=1e9, rate_max_yaw_rad_s=1e9
)  # the unsaturated law
DEG = math.pi / 180.0


def fly_kinematic(
    gains: AttitudeGains,
    q0: Quat,
    sp: AttitudeSetpoint,
    *,
    dt: float,
    n: int,
    rate_bias: tuple[float, float, float] = (0.0, 0.0, 0.0),
    lag_s: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, AttitudeLoop]:
    """Close the loop; returns (errors after each update, rate refs, the loop).

    ``rate_bias`` is added to what the rate loop delivers (an unknown constant F);
    ``lag_s`` > 0 makes the rate follow its reference through a first-order lag.
    """
    loop = AttitudeLoop(gains)
    q = q0
    w = [0.0, 0.0, 0.0]
    k = -math.expm1(-dt / lag_s) if lag_s > 0.0 else 1.0
    errs, refs = [], []
    for _ in range(n):
        u = loop.update(dt, q, (w[0], w[1], w[2]), sp)
        errs.append(loop.error_frd_rad)
        refs.append(u)
        if lag_s > 0.0:
            # Exact for a held reference: the angle gains the integral of the rate.
            w_new = [w[i] + (u[i] + rate_bias[i] - w[i]) * k for i in range(3)]
            mean = [u[i] + rate_bias[i] - (w_new[i] - w[i]) * lag_s / dt for i in range(3)]
            q = quat_exp_step(q, (mean[0], mean[1], mean[2]), dt)
            w = w_new
        else:
            w = [u[i] + rate_bias[i] for i in range(3)]
            q = quat_exp_step(q, (w[0], w[1], w[2]), dt)
    return np.array(errs), np.array(refs), loop


@pytest.mark.parametrize(("axis", "kp"), [(0, PAPER.kp_roll_pitch_1_s), (2, PAPER.kp_yaw_1_s)])
def test_perfect_f_error_decays_as_exp_minus_kp_t(axis: int, kp: float) -> None:
    dt, n, e0 = 0.002, 1000, 0.3
    if axis == 0:  # rolled 0.3 rad, asked for level
        q0, sp = euler_to_quat(e0, 0.0, 0.0), AttitudeSetpoint(0.0, 0.0, 0.0)
        weight = 1.0
    else:  # heading 0.3 rad, asked for 0: weighted in the error, the gain restored
        q0, sp = euler_to_quat(0.0, 0.0, e0), AttitudeSetpoint(0.0, 0.0, 0.0)
        weight = PAPER.yaw_weight
    errs, _, loop = fly_kinematic(UNLIMITED, q0, sp, dt=dt, n=n)
    k = np.arange(n)
    eps = errs[:, axis] / weight
    # The discrete law exactly (F_hat is exactly 0 here), the other axes untouched...
    np.testing.assert_allclose(eps, -e0 * (1.0 - kp * dt) ** k, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(np.delete(errs, axis, axis=1), 0.0, atol=1e-12)
    np.testing.assert_allclose(loop.f_hat, 0.0, atol=1e-12)
    # ...and the continuous answer within the Euler bound (docstring).
    t = k * dt
    h = kp * dt
    bound = e0 * np.exp(-kp * t) * k * (-math.log1p(-h) - h) + 1e-12
    assert np.all(np.abs(eps + e0 * np.exp(-kp * t)) <= bound)


def test_matched_lag_gives_the_designed_second_order_response() -> None:
    g = DEFAULT_ATTITUDE_GAINS
    kp, tau, e0, dt, n = g.kp_roll_pitch_1_s, g.inner_lag_s, 0.2, 0.002, 1500
    errs, _, _ = fly_kinematic(
        # A short window, so the estimate's own lag is small against the designed
        # dynamics (the shipped 0.1 s window trades that for a quieter estimate).
        dataclasses.replace(g, rate_max_roll_pitch_rad_s=1e9, window_s=0.02),
        euler_to_quat(e0, 0.0, 0.0),
        AttitudeSetpoint(0.0, 0.0, 0.0),
        dt=dt,
        n=n,
        lag_s=tau,
    )
    t = np.arange(n) * dt
    sigma = 1.0 / (2.0 * tau)
    omega = math.sqrt(4.0 * kp * tau - 1.0) / (2.0 * tau)  # underdamped: zeta 0.88
    analytic = -e0 * np.exp(-sigma * t) * (np.cos(omega * t) + sigma / omega * np.sin(omega * t))
    # The window (20 ms) lags the estimate by ~10 ms against a 250 ms time constant:
    # 2.2 % of e0 at most (measured). Bound: 3 %.
    assert np.max(np.abs(errs[:, 0] - analytic)) < 0.03 * e0
    assert abs(errs[-1, 0]) < 1e-4


@pytest.mark.parametrize("gains", [PAPER, DEFAULT_ATTITUDE_GAINS], ids=["paper", "lag-aware"])
def test_a_constant_unknown_f_is_rejected_with_zero_steady_error(gains: AttitudeGains) -> None:
    # The rate loop delivers 0.5 rad/s more roll and 0.2 less yaw than asked. A plain
    # P law would settle at -bias / kp (0.125 rad on roll); the iP learns it as F.
    bias = (0.5, 0.0, -0.2)
    errs, _, loop = fly_kinematic(
        gains,
        euler_to_quat(0.1, 0.0, 0.0),
        AttitudeSetpoint(0.0, 0.0, 0.0),
        dt=0.004,
        n=1500,
        rate_bias=bias,
        lag_s=gains.inner_lag_s,
    )
    np.testing.assert_allclose(errs[-1], 0.0, atol=1e-6)
    np.testing.assert_allclose(loop.f_hat, bias, atol=1e-6)


@pytest.mark.parametrize(
    ("yaw_now", "yaw_sp", "sign"), [(170.0, -170.0, 1.0), (-170.0, 170.0, -1.0)]
)
def test_a_heading_error_across_pi_turns_the_short_way(
    yaw_now: float, yaw_sp: float, sign: float
) -> None:
    g = DEFAULT_ATTITUDE_GAINS
    loop = AttitudeLoop(g)
    u = loop.update(
        0.01,
        euler_to_quat(0.0, 0.0, yaw_now * DEG),
        (0.0, 0.0, 0.0),
        AttitudeSetpoint(0.0, 0.0, yaw_sp * DEG),
    )
    # 20 deg the short way, weighted in the error, the full yaw gain in the rate.
    np.testing.assert_allclose(
        loop.error_frd_rad, (0.0, 0.0, sign * g.yaw_weight * 20 * DEG), atol=1e-12
    )
    np.testing.assert_allclose(u, (0.0, 0.0, sign * g.kp_yaw_1_s * 20 * DEG), atol=1e-12)


def test_a_90_deg_roll_gives_a_saturated_finite_rate() -> None:
    g = DEFAULT_ATTITUDE_GAINS
    loop = AttitudeLoop(g)
    u = loop.update(
        0.01, euler_to_quat(90 * DEG, 0.0, 0.3), (0.0, 0.0, 0.0), AttitudeSetpoint(0.0, 0.0, 0.3)
    )
    assert u[0] == -g.rate_max_roll_pitch_rad_s
    assert loop.saturated == (True, False, False)
    np.testing.assert_allclose(u[1:], 0.0, atol=1e-12)
    assert loop.error_frd_rad[0] == pytest.approx(-math.pi / 2)


def test_upside_down_is_finite_and_saturated() -> None:
    g = DEFAULT_ATTITUDE_GAINS
    loop = AttitudeLoop(g)
    u = loop.update(0.01, euler_to_quat(math.pi, 0.0, 0.0), (0.0, 0.0, 0.0), AttitudeSetpoint())
    assert all(math.isfinite(x) for x in u)
    assert abs(u[0]) == g.rate_max_roll_pitch_rad_s or abs(u[1]) == g.rate_max_roll_pitch_rad_s


def test_tilt_comes_first_the_heading_by_its_weight() -> None:
    # 40 deg of roll and 90 deg of heading to fix: the tilt error is the whole roll,
    # the yaw error only the weighted share of the heading.
    q = euler_to_quat(40 * DEG, 0.0, 0.0)
    q_sp = euler_to_quat(0.0, 0.0, 90 * DEG)
    for w in (0.0, 0.4, 1.0):
        e = attitude_error_frd_rad(q, q_sp, w)
        # What the error asks for, applied to q, is level at a heading of w * 90 deg.
        q_to = quat_mul(q, _exp(e))
        assert 1.0 - 2.0 * (q_to[1] ** 2 + q_to[2] ** 2) == pytest.approx(1.0)
        assert yaw_rad(q_to) == pytest.approx(w * 90 * DEG, abs=1e-9)
    # Weight 1 is the full attitude error.
    full = quat_log(quat_mul((q[0], -q[1], -q[2], -q[3]), q_sp))
    np.testing.assert_allclose(attitude_error_frd_rad(q, q_sp, 1.0), full, atol=1e-12)


def _exp(v: np.ndarray | tuple[float, float, float]) -> Quat:
    th = math.sqrt(sum(c * c for c in v))
    if th < 1e-15:
        return (1.0, 0.0, 0.0, 0.0)
    s = math.sin(th / 2) / th
    return (math.cos(th / 2), s * v[0], s * v[1], s * v[2])


def test_yaw_rate_feedforward_is_about_the_vertical_in_body_axes() -> None:
    # Rolled 30 deg, asked for that roll, no heading: the error is zero and the rate
    # reference is the feedforward r about NED down, r (0, sin 30, cos 30) in FRD.
    r = 0.7
    loop = AttitudeLoop()
    u = loop.update(
        0.01,
        euler_to_quat(30 * DEG, 0.0, 1.0),
        (0.0, 0.0, 0.0),
        AttitudeSetpoint(30 * DEG, 0.0, None, r),
    )
    np.testing.assert_allclose(loop.error_frd_rad, 0.0, atol=1e-12)
    np.testing.assert_allclose(u, (0.0, r * 0.5, r * math.cos(30 * DEG)), atol=1e-12)


def test_non_finite_inputs_give_finite_safe_outputs_and_the_flag() -> None:
    loop = AttitudeLoop()
    q = euler_to_quat(0.2, 0.0, 0.0)
    # Estimate not a rotation: zero rates (hold), flagged.
    assert loop.update(0.01, (math.nan, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0), AttitudeSetpoint()) == (
        0.0,
        0.0,
        0.0,
    )
    assert loop.fault
    assert loop.update(0.01, (0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), AttitudeSetpoint()) == (
        0.0,
        0.0,
        0.0,
    )
    # Setpoint non-finite: level at the current heading.
    u = loop.update(0.01, q, (0.0, 0.0, 0.0), AttitudeSetpoint(math.nan, 0.0, 0.0))
    assert loop.fault
    assert u[0] < 0.0 and all(math.isfinite(x) for x in u)
    # A valid sample clears the flag; non-finite rates keep the law running, flagged.
    loop.update(0.01, q, (0.0, 0.0, 0.0), AttitudeSetpoint())
    assert not loop.fault
    u = loop.update(0.01, q, (math.inf, 0.0, 0.0), AttitudeSetpoint())
    assert loop.fault and all(math.isfinite(x) for x in u)
    assert loop.nonfinite_events == 4


finite_or_not = st.one_of(
    st.floats(-1e6, 1e6), st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -1e308])
)


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(*[finite_or_not] * 12), min_size=1, max_size=4))
def test_never_a_non_finite_or_unbounded_rate(samples: list[tuple[float, ...]]) -> None:
    g = DEFAULT_ATTITUDE_GAINS
    loop = AttitudeLoop(g)
    for s in samples:
        sp = AttitudeSetpoint(s[8], s[9], s[10], s[11])
        u = loop.update(abs(s[0]), (s[1], s[2], s[3], s[4]), (s[5], s[6], s[7]), sp)
        assert all(math.isfinite(x) for x in u)
        assert abs(u[0]) <= g.rate_max_roll_pitch_rad_s
        assert abs(u[1]) <= g.rate_max_roll_pitch_rad_s
        assert abs(u[2]) <= g.rate_max_yaw_rad_s


def test_reset_forgets_the_estimate() -> None:
    _, _, loop = fly_kinematic(
        PAPER,
        euler_to_quat(0.1, 0.0, 0.0),
        AttitudeSetpoint(0.0, 0.0, 0.0),
        dt=0.004,
        n=50,
        rate_bias=(0.5, 0.0, 0.0),
    )
    assert loop.f_hat[0] == pytest.approx(0.5)
    loop.reset()
    assert loop.f_hat == (0.0, 0.0, 0.0)
    loop.update(0.004, (1.0, 0.0, 0.0, 0.0), (0.3, 0.0, 0.0), AttitudeSetpoint(0.0, 0.0, 0.0))
    assert loop.f_hat == (0.0, 0.0, 0.0)  # the first sample after a reset only primes


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("kp_roll_pitch_1_s", 0.0, r"AttitudeGains\.kp_roll_pitch_1_s must be finite and > 0"),
        ("kp_yaw_1_s", math.nan, r"AttitudeGains\.kp_yaw_1_s must be finite and > 0"),
        ("rate_max_yaw_rad_s", math.inf, r"AttitudeGains\.rate_max_yaw_rad_s"),
        ("window_s", -0.02, r"AttitudeGains\.window_s"),
        ("inner_lag_s", -0.01, r"AttitudeGains\.inner_lag_s must be finite and >= 0"),
        ("yaw_weight", 1.5, r"AttitudeGains\.yaw_weight must be in \(0, 1\]"),
    ],
)
def test_gains_validation_names_the_field(field: str, value: float, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        AttitudeGains(**{field: value})
