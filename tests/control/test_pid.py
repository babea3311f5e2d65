r"""PX4-style rate PID against hand-computed values.

tau = kp*e + I + kff*sp - kd*wdot_f,  I += ki*e*dt (clamped to +-i_limit, frozen in a
saturated direction),  wdot_f = first-order low-pass of (w - w_prev)/dt with
a = dt / (dt + 1/(2 pi f_c)).
"""

from __future__ import annotations

import math

import pytest

from companion.control import PidGains, RatePid
from tests.control.gains import pid_axis, pid_controller, px4_default_pid
from tests.control.plants import f450_mixer

AX = pid_axis(kp=0.5, ki=2.0, kd=0.01, kff=0.1, i_limit=0.3, d_lpf_hz=20.0)
GAINS = PidGains(AX, AX, AX)


def test_p_i_d_ff_by_hand() -> None:
    pid = RatePid(GAINS)
    dt = 0.01
    # Step 1: sp = 1, w = 0.2, e = 0.8. No derivative yet (not primed).
    # I = 2 * 0.8 * 0.01 = 0.016; tau = 0.5*0.8 + 0.016 + 0.1*1 = 0.516.
    out = pid.update(dt, (1.0, 1.0, 1.0), (0.2, 0.2, 0.2))
    assert out == pytest.approx((0.516, 0.516, 0.516), rel=1e-12)
    assert pid.integral == pytest.approx((0.016,) * 3, rel=1e-12)
    # Step 2: w = 0.4, e = 0.6; raw wdot = (0.4 - 0.2)/0.01 = 20;
    # a = 0.01 / (0.01 + 1/(40 pi)) = 0.01 / 0.0179577 = 0.556862;
    # wdot_f = 0.556862 * 20 = 11.13725; I = 0.016 + 0.012 = 0.028;
    # tau = 0.3 + 0.028 + 0.1 - 0.01 * 11.13725 = 0.316627.
    a = 0.01 / (0.01 + 1.0 / (2 * math.pi * 20.0))
    assert a == pytest.approx(0.556862, abs=1e-6)
    out = pid.update(dt, (1.0, 1.0, 1.0), (0.4, 0.4, 0.4))
    assert out[0] == pytest.approx(0.3 + 0.028 + 0.1 - 0.01 * a * 20.0, rel=1e-12)
    assert out[0] == pytest.approx(0.316627, abs=1e-6)
    # Step 3: w stays 0.4: raw = 0, wdot_f decays by (1 - a): 11.13725 * 0.443138 = 4.93534;
    # I = 0.028 + 0.012 = 0.040; tau = 0.3 + 0.040 + 0.1 - 0.0493534 = 0.3906466.
    out = pid.update(dt, (1.0, 1.0, 1.0), (0.4, 0.4, 0.4))
    assert out[0] == pytest.approx(0.3 + 0.040 + 0.1 - 0.01 * a * 20.0 * (1 - a), rel=1e-12)
    assert out[0] == pytest.approx(0.3906466, abs=1e-6)


def test_axes_are_independent_and_signed() -> None:
    pid = RatePid(px4_default_pid())
    # Roll error +1, pitch error -2, yaw error 0.5 (first step: P + I only).
    out = pid.update(0.004, (1.0, -2.0, 0.5), (0.0, 0.0, 0.0))
    assert out == pytest.approx(
        (0.15 * 1 + 0.2 * 1 * 0.004, 0.15 * -2 + 0.2 * -2 * 0.004, 0.2 * 0.5 + 0.1 * 0.5 * 0.004),
        rel=1e-12,
    )


def test_integrator_clamped_at_i_limit() -> None:
    g = pid_axis(kp=0.0, ki=10.0, kd=0.0, i_limit=0.3)
    pid = RatePid(PidGains(g, g, g))
    for _ in range(20):  # +0.1 per step
        out = pid.update(0.01, (1.0, -1.0, 0.0), (0.0, 0.0, 0.0))
    assert pid.integral == pytest.approx((0.3, -0.3, 0.0), abs=1e-15)
    assert out == pytest.approx((0.3, -0.3, 0.0), abs=1e-15)
    # Unwinds immediately when the error reverses: 0.3 - 0.1.
    pid.update(0.01, (-1.0, 1.0, 0.0), (0.0, 0.0, 0.0))
    assert pid.integral == pytest.approx((0.2, -0.2, 0.0), abs=1e-12)


def test_output_limited() -> None:
    pid = RatePid(px4_default_pid())
    assert pid.update(0.004, (100.0, -100.0, 100.0), (0.0, 0.0, 0.0)) == (1.0, -1.0, 1.0)


def test_anti_windup_freezes_only_the_saturated_direction() -> None:
    g = pid_axis(kp=0.0, ki=1.0, kd=0.0, i_limit=1.0)
    pid = RatePid(PidGains(g, g, g))
    pid.update(0.1, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))  # I = 0.1 on every axis
    pos = (True, False, False)
    neg = (False, True, False)
    pid.update(0.1, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0), pos, neg)
    # Roll saturated positive: frozen; pitch saturated negative only: grows; yaw grows.
    assert pid.integral == pytest.approx((0.1, 0.2, 0.2), rel=1e-12)
    pid.update(0.1, (-1.0, -1.0, -1.0), (0.0, 0.0, 0.0), pos, neg)
    # Now the errors are negative: roll may unwind, pitch is frozen.
    assert pid.integral == pytest.approx((0.0, 0.2, 0.1), abs=1e-12)


def test_nan_setpoint_falls_back_to_zero_error() -> None:
    g = pid_axis(kp=0.5, ki=2.0, kd=0.0, kff=0.0)
    pid = RatePid(PidGains(g, g, g))
    pid.update(0.01, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))  # I = 0.02
    out = pid.update(0.01, (math.nan, math.inf, 1.0), (0.3, 0.3, 0.0))
    # Roll and pitch: e = 0, integrator held, output = I only.
    assert out[0] == pytest.approx(0.02, rel=1e-12)
    assert out[1] == pytest.approx(0.02, rel=1e-12)
    assert out[2] == pytest.approx(0.5 + 0.04, rel=1e-12)
    assert pid.integral == pytest.approx((0.02, 0.02, 0.04), rel=1e-12)


def test_reset_forgets_integrator_and_derivative() -> None:
    pid = RatePid(GAINS)
    for k in range(10):
        pid.update(0.01, (1.0, 0.0, 0.0), (0.1 * k, 0.0, 0.0))
    pid.reset()
    assert pid.integral == (0.0, 0.0, 0.0)
    fresh = RatePid(GAINS)
    for k in range(5):
        args = (0.01, (0.5, 0.2, -0.1), (0.05 * k, 0.0, 0.1))
        assert pid.update(*args) == fresh.update(*args)


def test_gains_property_round_trips() -> None:
    assert RatePid(GAINS).gains == GAINS


def test_pid_controller_anti_windup_from_mixer_feedback() -> None:
    """A huge roll error saturates the mixer; from the next sample on the
    integrator stops growing in that direction."""
    ctrl = pid_controller(px4_default_pid(), f450_mixer())
    dt = 0.004
    for _ in range(10):
        out = ctrl.update(dt, (0.0, 0.0, 0.0), (50.0, 0.0, 0.0), 0.5)
    assert out.saturated_axes[0]
    assert out.torque[0] < 1.0
    # One step of integration (the first sample had no saturation feedback yet).
    assert ctrl._pid.integral[0] == pytest.approx(0.2 * 50.0 * dt, rel=1e-12)
    assert out.f_hat == (0.0, 0.0, 0.0)
    assert out.error == (-50.0, 0.0, 0.0)


def test_integrator_held_while_not_integrating() -> None:
    """``integrate=False`` holds the integrator where it is; P, FF and D still act."""
    pid = RatePid(GAINS)
    pid.update(0.01, (1.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    held = pid.integral
    assert held[0] == pytest.approx(2.0 * 1.0 * 0.01)
    out = pid.update(0.01, (1.0, 0.0, 0.0), (0.0, 0.0, 0.0), integrate=False)
    assert pid.integral == held
    assert out[0] == pytest.approx(0.5 * 1.0 + held[0] + 0.1 * 1.0)


def test_pid_controller_holds_its_integrator_on_the_ground() -> None:
    """On its legs a held roll stick is a rate error the vehicle cannot answer; the
    integrator must not wind up there and tip the vehicle at lift-off (PX4 holds it
    while landed). In the air it integrates again."""
    ctrl = pid_controller(px4_default_pid(), f450_mixer())
    ctrl.on_ground = True
    for _ in range(500):  # 2 s of a 1 rad/s roll request at 250 Hz
        ctrl.update(0.004, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 0.3)
    assert ctrl._pid.integral == (0.0, 0.0, 0.0)
    ctrl.on_ground = False
    ctrl.update(0.004, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 0.3)
    assert ctrl._pid.integral[0] == pytest.approx(px4_default_pid().roll.ki * 1.0 * 0.004)
