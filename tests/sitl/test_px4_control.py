"""PX4 v1.16's rate loop and allocation as the PX4 personality flies them."""

from __future__ import annotations

import math

import pytest

from sitl.px4_control import (
    PX4_V116_RATE_GAINS,
    ControlAllocator,
    Px4AxisGains,
    Px4RateLoop,
    RateControl,
    thrust_for_command,
)

QUAD_X = ((1.0, 1.0, 0.0), (-1.0, -1.0, 0.0), (1.0, -1.0, 0.0), (-1.0, 1.0, 0.0))
SPINS = ("ccw", "ccw", "cw", "cw")  # PX4's quad X order (CA_ROTOR0..3), 0 and 1 CCW


def test_px4_default_gains() -> None:
    roll, pitch, yaw = PX4_V116_RATE_GAINS
    assert (roll.p, roll.i, roll.d, roll.ff, roll.int_lim) == (0.15, 0.2, 0.003, 0.0, 0.3)
    assert pitch == roll
    assert (yaw.p, yaw.i, yaw.d) == (0.2, 0.1, 0.0)


def test_rate_control_pid_ff_and_the_k_gain() -> None:
    rc = RateControl([Px4AxisGains(p=0.1, i=0.0, d=0.01, ff=0.05, k=2.0)] * 3)
    tq = rc.update((0.5, 0.0, 0.0), (1.0, 0.0, 0.0), (10.0, 0.0, 0.0), 0.004, False)
    # K multiplies P and D (and I), not FF; D acts on the measured acceleration.
    assert tq[0] == pytest.approx(2 * 0.1 * 0.5 - 2 * 0.01 * 10.0 + 0.05 * 1.0)


def test_integrator_frozen_when_landed_and_in_a_saturated_direction() -> None:
    rc = RateControl()
    rc.update((0.0,) * 3, (1.0, 1.0, 1.0), (0.0,) * 3, 0.01, True)
    assert rc.integral == (0.0, 0.0, 0.0)
    rc.set_saturation((True, False, False), (False, True, False))
    rc.update((0.0,) * 3, (1.0, -1.0, 1.0), (0.0,) * 3, 0.01, False)
    i = rc.integral
    assert i[0] == 0.0 and i[1] == 0.0  # both pushed further into saturation
    # Yaw: I 0.1 * 1 rad/s * 10 ms, less the fall-off for 57 deg/s of error.
    factor = 1.0 - (1.0 / math.radians(400.0)) ** 2
    assert i[2] == pytest.approx(0.1 * 0.01 * factor)
    for _ in range(10_000):
        rc.update((0.0,) * 3, (0.0, 0.0, 1.0), (0.0,) * 3, 0.02, False)
    assert rc.integral[2] == pytest.approx(0.3)  # MC_YR_INT_LIM


def test_nan_setpoint_holds_the_current_rate_and_dt_comes_in_clamped() -> None:
    loop = Px4RateLoop(ControlAllocator(QUAD_X, SPINS))
    loop.filter_gyro((0.4, 0.0, 0.0), 0.001)
    tq = loop.torque((math.nan, 0.0, 0.0), 0.001, landed=False)
    assert tq[0] == pytest.approx(0.0, abs=1e-12)
    assert all(math.isfinite(v) for v in tq)


def test_allocation_scale_of_a_square_quad_x() -> None:
    alloc = ControlAllocator(QUAD_X, SPINS)
    roll, pitch, yaw = alloc.columns()
    s = 1.0 / math.sqrt(2.0)
    assert roll == pytest.approx((-s, s, s, -s))
    assert pitch == pytest.approx((s, -s, s, -s))
    assert yaw == pytest.approx((1.0, 1.0, -1.0, -1.0))
    res = alloc.allocate((0.1, 0.0, 0.0), 0.5)
    assert res.actuators == pytest.approx(
        (0.5 - 0.1 * s, 0.5 + 0.1 * s, 0.5 + 0.1 * s, 0.5 - 0.1 * s)
    )
    assert res.saturated_positive == res.saturated_negative == (False, False, False)


def test_airmode_off_never_raises_the_thrust_and_yaw_comes_last() -> None:
    alloc = ControlAllocator(QUAD_X, SPINS)
    low = alloc.allocate((0.5, 0.0, 0.0), 0.05)
    # Roll is cut to fit at the low collective rather than the collective raised.
    assert sum(low.actuators) / 4 == pytest.approx(0.05, abs=1e-9)
    assert low.saturated_positive[0] and low.unallocated[0] > 0.0
    high = alloc.allocate((0.0, 0.0, 0.8), 0.9)
    # Yaw may go 15 % past full before the collective is lowered: some yaw at full thrust.
    assert max(high.actuators) == pytest.approx(1.0)
    assert high.saturated_positive[2] and 0.0 < high.unallocated[2] < 0.8


def test_motor_commands_span_idle_to_full() -> None:
    alloc = ControlAllocator(QUAD_X, SPINS, idle=0.1)
    assert alloc.motor_commands((0.0, 1.0, 0.5, 0.5)) == pytest.approx((0.1, 1.0, 0.55, 0.55))
    assert thrust_for_command(0.55, 0.1) == pytest.approx(0.5)


def test_yaw_torque_is_low_passed_at_2_hz() -> None:
    loop = Px4RateLoop(ControlAllocator(QUAD_X, SPINS))
    loop.filter_gyro((0.0, 0.0, 0.0), 0.004)
    first = loop.torque((0.0, 0.0, 1.0), 0.004, landed=True)
    # P 0.2 * 1 rad/s through alpha = dt / (dt + 1 / (2 pi 2 Hz)).
    alpha = 0.004 / (0.004 + 1.0 / (2.0 * math.pi * 2.0))
    assert first[2] == pytest.approx(alpha * 0.2)
