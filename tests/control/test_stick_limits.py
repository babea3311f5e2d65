"""The stacks' stick shaping, against hand-computed answers and their own sources."""

from __future__ import annotations

import math

import pytest

from companion.control.stick_limits import (
    ClimbLimits,
    HorizontalShaper,
    LoiterStickAcceleration,
    MissionLimits,
    Px4DirectVelocity,
    Px4StickAcceleration,
    StickLimits,
    expo_past_deadband,
)
from companion.control.ultralocal import GRAVITY_M_S2

DT = 0.004
PX4 = Px4StickAcceleration(
    deadband=0.1, expo=0.6, speed_max_m_s=10.0, accel_m_s2=3.0, jerk_max_m_s3=8.0,
    tilt_max_deg=45.0,
)  # fmt: skip
"""PX4 v1.16's defaults (MPC_HOLD_DZ, MPC_XY_MAN_EXPO, MPC_VEL_MANUAL, MPC_ACC_HOR,
MPC_JERK_MAX, MPC_TILTMAX_AIR)."""
LOITER = LoiterStickAcceleration(
    deadband=0.04, speed_max_m_s=12.5, angle_deg=20.0, input_tc_s=0.15,
    brake_accel_m_s2=2.5, brake_jerk_m_s3=5.0, brake_delay_s=1.0, brake_gain_1_s=1.0,
)  # fmt: skip
"""ArduCopter 4.5's defaults (2/3 of ANGLE_MAX's 30 deg, LOIT_*, ATC_INPUT_TC, PSC_VELXY_P)."""


def run(shaper: HorizontalShaper, seconds: float, stick: tuple[float, float]) -> list[float]:
    """The speed setpoint after each step."""
    out = []
    for _ in range(round(seconds / DT)):
        v = shaper.update(DT, stick)
        out.append(math.hypot(*v))
    return out


@pytest.mark.parametrize(
    ("x", "deadband", "expo", "want"),
    [
        (0.05, 0.1, 0.6, 0.0),
        (1.0, 0.1, 0.6, 1.0),
        (-1.0, 0.1, 0.6, -1.0),
        (0.55, 0.1, 0.0, 0.5),
        (0.55, 0.1, 0.6, 0.4 * 0.5 + 0.6 * 0.125),  # PX4's math::expo after the deadzone
        (-0.55, 0.1, 1.0, -0.125),
        (math.nan, 0.1, 0.6, 0.0),
    ],
)
def test_a_deflection_past_the_deadband_through_the_expo(
    x: float, deadband: float, expo: float, want: float
) -> None:
    assert expo_past_deadband(x, deadband, expo) == pytest.approx(want)


def test_px4_full_stick_asks_its_acceleration_through_the_jerk_limit() -> None:
    s = PX4.shaper()
    run(s, 0.1, (1.0, 0.0))
    assert s.accel_ne_m_s2 == pytest.approx((8.0 * 0.1, 0.0), abs=1e-9)  # MPC_JERK_MAX
    # Full stick asks 2 MPC_ACC_HOR at rest, less the drag 2 A / V v: the acceleration
    # peaks below 6 m/s^2, and the speed reaches MPC_VEL_MANUAL and no further.
    speeds = run(s, 20.0, (1.0, 0.0))
    assert max(speeds) <= 10.0 + 1e-9
    assert speeds[-1] == pytest.approx(10.0, rel=0.01)
    assert s.velocity_ne_m_s[1] == 0.0


def test_px4_the_acceleration_asked_is_bounded_by_the_tilt_limit() -> None:
    low = Px4StickAcceleration(0.1, 0.6, 10.0, 5.0, 500.0, tilt_max_deg=10.0)
    s = low.shaper()
    for _ in range(round(1.0 / DT)):
        s.update(DT, (0.6, 0.8))
        assert math.hypot(*s.accel_ne_m_s2) <= GRAVITY_M_S2 * math.tan(math.radians(10.0)) + 1e-9


def test_px4_centred_sticks_brake_to_exactly_zero_and_never_reverse() -> None:
    s = PX4.shaper()
    s.reset((3.0, -4.0))
    first = None
    for _ in range(round(6.0 / DT)):
        v = s.update(DT, (0.0, 0.0))
        assert v[0] * 3.0 - v[1] * 4.0 >= 0.0  # never against the motion it had
        if v == (0.0, 0.0) and first is None:
            first = _
    assert first is not None and first * DT < 4.0
    assert s.velocity_ne_m_s == (0.0, 0.0) and s.accel_ne_m_s2 == (0.0, 0.0)


def test_direct_velocity_is_the_stick_times_the_speed() -> None:
    s = Px4DirectVelocity(0.1, 0.6, 8.0).shaper()
    assert s.update(DT, (0.6, -0.8)) == pytest.approx((4.8, -6.4))
    assert s.update(DT, (0.0, 0.0)) == (0.0, 0.0)


def test_loiter_full_stick_asks_its_lean_angle_and_reaches_loit_speed() -> None:
    s = LOITER.shaper()
    run(s, 2.0, (0.0, 1.0))
    # The lean angle's acceleration, reached through ATC_INPUT_TC, less the drag.
    a_max = GRAVITY_M_S2 * math.tan(math.radians(20.0))
    assert LOITER.accel_max_m_s2 == pytest.approx(a_max)
    assert 0.0 < s.accel_ne_m_s2[1] < a_max
    speeds = run(s, 40.0, (0.0, 1.0))
    assert max(speeds) <= 12.5 + 1e-9 and speeds[-1] == pytest.approx(12.5, rel=0.01)


def test_loiter_brakes_harder_after_its_delay_and_stops_at_zero() -> None:
    s = LOITER.shaper()
    s.reset((0.0, 5.0))
    run(s, 0.9, (0.0, 0.0))  # within LOIT_BRK_DELAY: the drag alone
    drag_only = -s.accel_ne_m_s2[1]
    assert drag_only == pytest.approx(LOITER.accel_max_m_s2 * s.velocity_ne_m_s[1] / 12.5, rel=0.05)
    run(s, 0.6, (0.0, 0.0))  # past it: the brake too (its jerk-limited rise)
    assert -s.accel_ne_m_s2[1] > drag_only
    run(s, 10.0, (0.0, 0.0))
    assert s.velocity_ne_m_s == (0.0, 0.0)


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: ClimbLimits(1.0, 0.0, 3.0, 1.5, 4.0, 3.0), "deadband"),
        (lambda: ClimbLimits(0.1, 0.0, 0.0, 1.5, 4.0, 3.0), "up_max_m_s"),
        (lambda: Px4StickAcceleration(0.1, 0.6, 10.0, 3.0, 8.0, 90.0), "tilt_max_deg"),
        (
            lambda: StickLimits(
                70.0, ClimbLimits(0.1, 0.0, 3, 1.5, 4, 3), PX4, MissionLimits(3.0, 4.0)
            ),
            "tilt_max_deg",
        ),
        (lambda: MissionLimits(3.0, 0.0), "jerk_m_s3"),
        (lambda: LoiterStickAcceleration(0.04, math.nan, 20.0, 0.15, 2.5, 5, 1, 1), "speed"),
    ],
)
def test_limits_out_of_range_are_refused(make: object, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        make()  # type: ignore[operator]
