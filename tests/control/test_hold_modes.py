"""The altitude and position modes' sticks and holds, against analytic answers."""

from __future__ import annotations

import math

import pytest

from companion.control.attitude import DEFAULT_ATTITUDE_GAINS
from companion.control.hold_modes import (
    ACCEL_DOWN_MAX_M_S2,
    ACCEL_HORIZONTAL_MAX_M_S2,
    ACCEL_UP_MAX_M_S2,
    CLIMB_MAX_DOWN_M_S,
    CLIMB_MAX_UP_M_S,
    VELOCITY_MAX_M_S,
    HoldMode,
    stick_climb_m_s,
    stick_velocity_ne_m_s,
)
from companion.control.quaternion import Vec3
from tests.control.outer_plant import PointMassPlant

LEVEL = (1.0, 0.0, 0.0, 0.0)
STILL = (0.0, 0.0, 0.0)
CENTRE = (0.0, 0.0, 0.0)
DT = 0.004


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
    held_ref = mode.outer.vertical.climb_ref_m_s  # K_z x 0.5 m
    mode.update(0.004, LEVEL, STILL, (0.0, 0.0, -4.5), STILL, CENTRE, 1.0, 0.0)
    # Climbing: no hold, and the climb ramps from the one the hold was flying.
    assert mode.setpoint.vertical == pytest.approx(
        (held_ref + ACCEL_UP_MAX_M_S2 * 0.004, None, ACCEL_UP_MAX_M_S2)
    )
    for _ in range(200):
        mode.update(0.004, LEVEL, STILL, (0.0, 0.0, -4.5), STILL, CENTRE, 1.0, 0.0)
    assert mode.setpoint.vertical == (CLIMB_MAX_UP_M_S, None, 0.0)  # ... to full stick's


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
    held_ref = mode.outer.horizontal.velocity_ref_ne_m_s  # K_x x 1 m, west
    assert held_ref[1] < -0.5
    mode.update(0.004, LEVEL, STILL, (0.0, 1.0, -5.0), STILL, (0.0, -1.0, 0.0), 0.5, 0.0)
    # Full stick forward: no hold, and the velocity ramps from the one the hold was flying.
    assert mode.setpoint.horizontal.position_ne_m is None
    assert math.dist(mode.setpoint.horizontal.velocity_ne_m_s, held_ref) == pytest.approx(
        ACCEL_HORIZONTAL_MAX_M_S2 * 0.004
    )
    for _ in range(700):
        mode.update(0.004, LEVEL, STILL, (0.0, 1.0, -5.0), STILL, (0.0, -1.0, 0.0), 0.5, 0.0)
    assert mode.setpoint.horizontal.velocity_ne_m_s == pytest.approx((VELOCITY_MAX_M_S, 0.0))
    assert mode.setpoint.horizontal.accel_ne_m_s2 == (0.0, 0.0)
    # ... and the velocity loop flies the whole of it: its bound is above full stick.
    assert mode.outer.horizontal.velocity_ref_ne_m_s == pytest.approx((VELOCITY_MAX_M_S, 0.0))


def test_non_finite_estimates_never_make_a_non_finite_command() -> None:
    mode = HoldMode(position=True)
    mode.reset(thrust=0.4)
    nan3 = (math.nan, math.nan, math.nan)
    for q in (LEVEL, (math.nan, 0.0, 0.0, 0.0)):
        out = mode.update(0.004, q, nan3, nan3, nan3, (math.nan, 0.0, 0.0), math.nan, math.nan)
        assert all(math.isfinite(v) for v in (*out.rate_ref_frd_rad_s, out.thrust))


def fly_sticks(
    mode: HoldMode, plant: PointMassPlant, seconds: float, deflection: Vec3, throttle: float
) -> list[float]:
    """Fly the sticks on the plant; the tilt asked each sample, deg."""
    tilts = []
    for _ in range(round(seconds / DT)):
        w, p, v = plant.w, plant.p, plant.v
        out = mode.update(
            DT, plant.q, (w[0], w[1], w[2]), (p[0], p[1], p[2]), (v[0], v[1], v[2]),
            deflection, throttle, 0.0,
        )  # fmt: skip
        plant.step(DT, out.rate_ref_frd_rad_s, out.thrust)
        sp = mode.attitude_setpoint
        tilts.append(0.0 if sp is None else math.degrees(math.hypot(sp.roll_rad, sp.pitch_rad)))
    return tilts


def hovering(position: bool) -> tuple[HoldMode, PointMassPlant]:
    plant = PointMassPlant()
    plant.p[2] = -5.0
    mode = HoldMode(position=position)
    mode.reset(thrust=plant.hover_thrust)
    return mode, plant


def centred_each_second(mode: HoldMode, plant: PointMassPlant, seconds: int) -> list[Vec3]:
    """Sticks centred, throttle mid: where the plant is after each second."""
    out: list[Vec3] = []
    for _ in range(seconds):
        fly_sticks(mode, plant, 1.0, CENTRE, 0.5)
        out.append((plant.p[0], plant.p[1], plant.p[2]))
    return out


def test_slammed_sticks_are_ramped_and_released_at_speed_the_vehicle_stops_where_it_can() -> None:
    # Measured (DT 4 ms, the plant's defaults): before the ramps, full stick asked
    # the 45 deg tilt limit at once, and released at 10 m/s the vehicle ran 6.5 m
    # on and was pulled the 6.5 m back to where the sticks came back; with them,
    # 36 deg at most (34 in the first second), 11.1 m on and 0.01 m back.
    mode, plant = hovering(position=True)
    fly_sticks(mode, plant, 1.0, CENTRE, 0.5)
    tilts = fly_sticks(mode, plant, 4.0, (0.0, -1.0, 0.0), 0.5)  # full forward
    assert max(tilts) < 40.0
    assert plant.v[0] == pytest.approx(VELOCITY_MAX_M_S, abs=0.3)
    released_at = plant.p[0]
    north = [p[0] for p in centred_each_second(mode, plant, 8)]
    # It brakes along the ramp: v^2 / 2a past the release, a little more for the lag ...
    braking = VELOCITY_MAX_M_S**2 / (2.0 * ACCEL_HORIZONTAL_MAX_M_S2)
    assert braking < max(north) - released_at < braking + 1.5
    # ... the hold locks where it stopped, and nothing pulls it back.
    hold = mode.setpoint.horizontal.position_ne_m
    assert hold is not None and hold[0] == pytest.approx(north[-1], abs=0.1)
    assert max(north) - north[-1] < 0.1


def test_the_throttle_released_in_a_climb_stops_above_and_holds_there() -> None:
    # Measured: before the ramps, released at 3 m/s the vehicle rose 1.0 m more
    # and came back down the 1.0 m; with them, 1.7 m more and 0.00 m back.
    mode, plant = hovering(position=False)
    fly_sticks(mode, plant, 3.0, CENTRE, 1.0)
    assert -plant.v[2] == pytest.approx(CLIMB_MAX_UP_M_S, abs=0.1)
    released_at = -plant.p[2]
    up = [-p[2] for p in centred_each_second(mode, plant, 6)]
    braking = CLIMB_MAX_UP_M_S**2 / (2.0 * ACCEL_DOWN_MAX_M_S2)
    assert braking < max(up) - released_at < braking + 0.5
    assert mode.setpoint.vertical.up_m == pytest.approx(up[-1], abs=0.05)
    assert max(up) - up[-1] < 0.05


def test_engaged_while_moving_the_ramps_start_from_the_estimated_velocity() -> None:
    mode = HoldMode(position=True)
    mode.reset(thrust=0.4)
    moving = (3.0, -4.0, -1.0)  # 5 m/s north-west, climbing 1 m/s
    mode.update(DT, LEVEL, STILL, (0.0, 0.0, -5.0), moving, CENTRE, 0.5, 0.0)
    h, v = mode.setpoint.horizontal, mode.setpoint.vertical
    assert h.position_ne_m is None and v.up_m is None  # not held yet: braking
    step = ACCEL_HORIZONTAL_MAX_M_S2 * DT / 5.0
    assert h.velocity_ne_m_s == pytest.approx((3.0 * (1 - step), -4.0 * (1 - step)))
    assert h.accel_ne_m_s2 == pytest.approx((-3.0, 4.0))  # 5 m/s^2 against the motion
    assert v.climb_m_s == pytest.approx(1.0 - ACCEL_DOWN_MAX_M_S2 * DT)
    assert v.climb_accel_m_s2 == pytest.approx(-ACCEL_DOWN_MAX_M_S2)
    for _ in range(300):  # 1.2 s: both ramps are back at zero
        mode.update(DT, LEVEL, STILL, (0.0, 0.0, -5.0), moving, CENTRE, 0.5, 0.0)
    assert mode.setpoint.horizontal.position_ne_m == (0.0, 0.0)
    assert mode.setpoint.vertical.up_m == pytest.approx(5.0)


def test_engaged_at_an_absurd_estimated_speed_the_ramps_start_from_the_sticks_bounds() -> None:
    mode = HoldMode(position=True)
    mode.reset(thrust=0.4)
    absurd = (300.0, -400.0, -90.0)
    mode.update(DT, LEVEL, STILL, (0.0, 0.0, -5.0), absurd, CENTRE, 0.5, 0.0)
    h, v = mode.setpoint.horizontal, mode.setpoint.vertical
    assert math.hypot(*h.velocity_ne_m_s) == pytest.approx(
        VELOCITY_MAX_M_S - ACCEL_HORIZONTAL_MAX_M_S2 * DT
    )
    assert v.climb_m_s == pytest.approx(CLIMB_MAX_UP_M_S - ACCEL_DOWN_MAX_M_S2 * DT)
