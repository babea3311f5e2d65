"""The altitude and position modes' sticks and holds, against analytic answers."""

from __future__ import annotations

import math

import pytest

from companion.control.attitude import DEFAULT_ATTITUDE_GAINS
from companion.control.hold_modes import (
    CLIMB_MAX_DOWN_M_S,
    CLIMB_MAX_UP_M_S,
    VELOCITY_MAX_M_S,
    HoldMode,
    stick_climb_m_s,
    stick_velocity_ne_m_s,
)

LEVEL = (1.0, 0.0, 0.0, 0.0)
STILL = (0.0, 0.0, 0.0)
CENTRE = (0.0, 0.0, 0.0)


@pytest.mark.parametrize(
    ("throttle", "climb"),
    [
        (0.5, None),
        (0.54, None),  # inside the 10 % deadband: hold
        (0.46, None),
        (1.0, CLIMB_MAX_UP_M_S),
        (0.0, -CLIMB_MAX_DOWN_M_S),
        (0.775, 0.5 * CLIMB_MAX_UP_M_S),  # x 0.55: (0.55 - 0.1) / 0.9
        (math.nan, None),
    ],
)
def test_the_throttle_is_a_climb_rate_held_at_mid_stick(
    throttle: float, climb: float | None
) -> None:
    got = stick_climb_m_s(throttle)
    assert got == (None if climb is None else pytest.approx(climb))


@pytest.mark.parametrize(
    ("x", "heading_deg", "vel"),
    [
        ((0.0, 0.0), 0.0, None),
        ((0.05, -0.05), 0.0, None),  # |x| 0.07 inside the deadband
        ((1.0, 0.0), 0.0, (0.0, VELOCITY_MAX_M_S)),  # roll right flies east, facing north
        ((0.0, -1.0), 0.0, (VELOCITY_MAX_M_S, 0.0)),  # pitch below centre flies forward
        ((0.0, -1.0), 90.0, (0.0, VELOCITY_MAX_M_S)),  # forward, facing east
        ((0.0, 1.0), 180.0, (VELOCITY_MAX_M_S, 0.0)),  # backwards, facing south: north
        ((1.0, -1.0), 0.0, (VELOCITY_MAX_M_S / 2**0.5, VELOCITY_MAX_M_S / 2**0.5)),
    ],
)
def test_the_sticks_are_a_velocity_in_the_headings_frame(
    x: tuple[float, float], heading_deg: float, vel: tuple[float, float] | None
) -> None:
    got = stick_velocity_ne_m_s(*x, math.radians(heading_deg))
    if vel is None:
        assert got is None
    else:
        assert got == pytest.approx(vel, abs=1e-9)


def test_altitude_mode_holds_where_the_stick_came_back_and_pushes_up_below_it() -> None:
    mode = HoldMode(position=False)
    mode.reset(thrust=0.4)
    first = mode.update(0.004, LEVEL, STILL, (0.0, 0.0, -5.0), STILL, CENTRE, 0.5, 0.0)
    assert mode.setpoint.vertical.up_m == pytest.approx(5.0)
    assert first.thrust == pytest.approx(0.4, abs=0.01)  # no error: the collective it took over at
    for _ in range(50):  # half a metre below the hold, not moving: more collective
        out = mode.update(0.004, LEVEL, STILL, (0.0, 0.0, -4.5), STILL, CENTRE, 0.5, 0.0)
    assert out.thrust > first.thrust + 0.02
    assert mode.setpoint.vertical.up_m == pytest.approx(5.0)  # still the same hold
    mode.update(0.004, LEVEL, STILL, (0.0, 0.0, -4.5), STILL, CENTRE, 1.0, 0.0)
    assert mode.setpoint.vertical == (CLIMB_MAX_UP_M_S, None, 0.0)  # climbing: no hold


def test_altitude_mode_flies_the_sticks_as_angles() -> None:
    mode = HoldMode(position=False)
    mode.reset(thrust=0.4)
    out = mode.update(0.004, LEVEL, STILL, (0.0, 0.0, -5.0), STILL, (1.0, 0.0, 0.0), 0.5, 0.0)
    kp = DEFAULT_ATTITUDE_GAINS.kp_roll_pitch_1_s
    assert out.rate_ref_frd_rad_s[0] == pytest.approx(kp * math.radians(35.0))


def test_on_the_ground_only_the_vertical_loop_flies_and_nothing_is_held() -> None:
    mode = HoldMode(position=True)
    mode.on_ground = True
    mode.reset(thrust=0.0)
    tilted = (math.cos(0.1), math.sin(0.1), 0.0, 0.0)
    thrusts = []
    for _ in range(100):  # throttle up: a climb the vehicle on its legs does not make
        out = mode.update(0.004, tilted, STILL, STILL, STILL, (1.0, 1.0, 0.0), 0.9, 1.0)
        assert out.rate_ref_frd_rad_s == (0.0, 0.0, 0.0)
        thrusts.append(out.thrust)
    assert thrusts[-1] > thrusts[0] + 0.1  # the collective rises until it lifts off
    assert mode.setpoint.vertical.up_m is None and mode.setpoint.horizontal.position_ne_m is None


def test_position_mode_holds_where_the_sticks_came_back_and_leans_towards_it() -> None:
    mode = HoldMode(position=True)
    mode.reset(thrust=0.4)
    mode.update(0.004, LEVEL, STILL, (0.0, 0.0, -5.0), STILL, CENTRE, 0.5, 0.0)
    assert mode.setpoint.horizontal.position_ne_m == (0.0, 0.0)
    for _ in range(50):  # a metre east of the hold, facing north: roll left
        out = mode.update(0.004, LEVEL, STILL, (0.0, 1.0, -5.0), STILL, CENTRE, 0.5, 0.0)
    assert out.rate_ref_frd_rad_s[0] < -0.05
    assert mode.setpoint.horizontal.position_ne_m == (0.0, 0.0)
    mode.update(0.004, LEVEL, STILL, (0.0, 1.0, -5.0), STILL, (0.0, -1.0, 0.0), 0.5, 0.0)
    assert mode.setpoint.horizontal.velocity_ne_m_s == pytest.approx((VELOCITY_MAX_M_S, 0.0))
    assert mode.setpoint.horizontal.position_ne_m is None
    # ... and the velocity loop flies the whole of it: its bound is above full stick.
    assert mode.outer.horizontal.velocity_ref_ne_m_s == pytest.approx((VELOCITY_MAX_M_S, 0.0))


def test_non_finite_estimates_never_make_a_non_finite_command() -> None:
    mode = HoldMode(position=True)
    mode.reset(thrust=0.4)
    nan3 = (math.nan, math.nan, math.nan)
    for q in (LEVEL, (math.nan, 0.0, 0.0, 0.0)):
        out = mode.update(0.004, q, nan3, nan3, nan3, (math.nan, 0.0, 0.0), math.nan, math.nan)
        assert all(math.isfinite(v) for v in (*out.rate_ref_frd_rad_s, out.thrust))
