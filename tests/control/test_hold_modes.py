"""The altitude and position modes' sticks and holds, against analytic answers."""

from __future__ import annotations

import math

import pytest

from companion.control.attitude import DEFAULT_ATTITUDE_GAINS
from companion.control.hold_modes import TAKE_OVER_STILL_M_S, HoldMode, stick_ne
from companion.control.quaternion import Vec3, euler_to_quat
from companion.control.stick_limits import (
    ClimbLimits,
    MissionLimits,
    Px4DirectVelocity,
    Px4StickAcceleration,
    StickLimits,
)
from tests.control.outer_plant import PointMassPlant

LEVEL = (1.0, 0.0, 0.0, 0.0)
STILL = (0.0, 0.0, 0.0)
CENTRE = (0.0, 0.0, 0.0)
DT = 0.004

# PX4 v1.16's defaults (companion.stacks has them with their names; the law has none).
CLIMB = ClimbLimits(
    deadband=0.1, expo=0.6, up_max_m_s=3.0, down_max_m_s=1.5, accel_up_m_s2=4.0,
    accel_down_m_s2=3.0,
)  # fmt: skip
PX4_STICKS = Px4StickAcceleration(
    deadband=0.1, expo=0.6, speed_max_m_s=10.0, accel_m_s2=3.0, jerk_max_m_s3=8.0,
    tilt_max_deg=45.0,
)  # fmt: skip
MISSIONS = MissionLimits(accel_m_s2=3.0, jerk_m_s3=4.0)
LIMITS = StickLimits(35.0, CLIMB, PX4_STICKS, MISSIONS)
LINEAR = StickLimits(
    35.0,
    ClimbLimits(0.1, 0.0, 3.0, 1.5, 4.0, 3.0),
    Px4DirectVelocity(deadband=0.1, expo=0.0, speed_max_m_s=10.0),
    MISSIONS,
)
"""No expo and no shaping: the sticks' answers by hand."""


@pytest.mark.parametrize(
    ("throttle", "climb"),
    [
        (0.5, None),
        (0.54, None),  # inside the 10 % deadband: hold
        (0.46, None),
        (1.0, 3.0),
        (0.0, -1.5),
        (0.775, 0.5 * 3.0),  # x 0.55: (0.55 - 0.1) / 0.9, linear
        (math.nan, None),
    ],
)
def test_the_throttle_is_a_climb_rate_held_at_mid_stick(
    throttle: float, climb: float | None
) -> None:
    got = LINEAR.climb.climb_m_s(throttle)
    assert got == (None if climb is None else pytest.approx(climb))


def test_the_throttles_expo_is_the_stacks() -> None:
    # PX4's MPC_Z_MAN_EXPO 0.6: half way past the deadband asks 0.4 x 0.5 + 0.6 x 0.125.
    assert CLIMB.climb_m_s(0.775) == pytest.approx(0.275 * 3.0)
    assert CLIMB.climb_m_s(1.0) == pytest.approx(3.0)  # full stick is full climb


@pytest.mark.parametrize(
    ("x", "heading_deg", "stick"),
    [
        ((0.0, 0.0), 0.0, None),
        ((0.05, -0.05), 0.0, None),  # |x| 0.07 inside the deadband
        ((1.0, 0.0), 0.0, (0.0, 1.0)),  # roll right flies east, facing north
        ((0.0, -1.0), 0.0, (1.0, 0.0)),  # pitch below centre flies forward
        ((0.0, -1.0), 90.0, (0.0, 1.0)),  # forward, facing east
        ((0.0, 1.0), 180.0, (1.0, 0.0)),  # backwards, facing south: north
        ((1.0, -1.0), 0.0, (2**-0.5, 2**-0.5)),  # a diagonal: no further
        ((0.55, 0.0), 0.0, (0.0, 0.5)),  # half way past the deadband
    ],
)
def test_the_sticks_are_one_deflection_in_the_headings_frame(
    x: tuple[float, float], heading_deg: float, stick: tuple[float, float] | None
) -> None:
    got = stick_ne(*x, math.radians(heading_deg), 0.1, 0.0)
    if stick is None:
        assert got is None
    else:
        assert got == pytest.approx(stick, abs=1e-9)


def test_altitude_mode_holds_where_the_stick_came_back_and_pushes_up_below_it() -> None:
    mode = HoldMode(position=False, limits=LINEAR)
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
    accel_up = LINEAR.climb.accel_up_m_s2
    assert mode.setpoint.vertical == pytest.approx((held_ref + accel_up * 0.004, None, accel_up))
    for _ in range(200):
        mode.update(0.004, LEVEL, STILL, (0.0, 0.0, -4.5), STILL, CENTRE, 1.0, 0.0)
    assert mode.setpoint.vertical == (LINEAR.climb.up_max_m_s, None, 0.0)  # ... to full stick's


def test_altitude_mode_flies_the_sticks_as_angles() -> None:
    mode = HoldMode(position=False, limits=LINEAR)
    mode.reset(thrust=0.4)
    out = mode.update(0.004, LEVEL, STILL, (0.0, 0.0, -5.0), STILL, (1.0, 0.0, 0.0), 0.5, 0.0)
    kp = DEFAULT_ATTITUDE_GAINS.kp_roll_pitch_1_s
    assert out.rate_ref_frd_rad_s[0] == pytest.approx(kp * math.radians(35.0))


def test_on_the_ground_only_the_vertical_loop_flies_and_nothing_is_held() -> None:
    mode = HoldMode(position=True, limits=LINEAR)
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
    mode = HoldMode(position=True, limits=LIMITS)
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
    # Full stick forward: no hold, and the velocity starts from the one the hold was flying.
    assert mode.setpoint.horizontal.position_ne_m is None
    assert math.dist(mode.setpoint.horizontal.velocity_ne_m_s, held_ref) < 0.01
    # ... then it is the stack's shaping of the stick (the PX4 acceleration-based's).
    shaper = PX4_STICKS.shaper()
    shaper.reset(held_ref)
    shaper.update(0.004, (1.0, 0.0))
    for _ in range(700):
        mode.update(0.004, LEVEL, STILL, (0.0, 1.0, -5.0), STILL, (0.0, -1.0, 0.0), 0.5, 0.0)
        want = shaper.update(0.004, (1.0, 0.0))
    assert mode.setpoint.horizontal.velocity_ne_m_s == pytest.approx(want, abs=1e-12)
    assert mode.setpoint.horizontal.accel_ne_m_s2 == pytest.approx(shaper.accel_ne_m_s2)
    assert mode.outer.horizontal.velocity_ref_ne_m_s == pytest.approx(want)  # flown whole


def test_non_finite_estimates_never_make_a_non_finite_command() -> None:
    mode = HoldMode(position=True, limits=LINEAR)
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
    mode = HoldMode(position=position, limits=LIMITS)
    mode.reset(thrust=plant.hover_thrust)
    return mode, plant


def centred_each_second(mode: HoldMode, plant: PointMassPlant, seconds: int) -> list[Vec3]:
    """Sticks centred, throttle mid: where the plant is after each second."""
    out: list[Vec3] = []
    for _ in range(seconds):
        fly_sticks(mode, plant, 1.0, CENTRE, 0.5)
        out.append((plant.p[0], plant.p[1], plant.p[2]))
    return out


def test_slammed_sticks_ask_what_the_stack_asks_and_released_it_stops_where_it_can() -> None:
    # Measured (DT 4 ms, the plant's defaults; PX4's acceleration-based sticks, 3 s
    # of full stick): 32.6 deg at most, 7.97 m/s at the release (the setpoint's
    # 7.98), 11.0 m on (the setpoint's own braking 10.1) and 0.00 m back. Before, a
    # ramp at 5 m/s^2 to 10 m/s: 36 deg, 10 m/s, 11.1 m on.
    mode, plant = hovering(position=True)
    fly_sticks(mode, plant, 1.0, CENTRE, 0.5)
    shaper = PX4_STICKS.shaper()
    for _ in range(round(3.0 / DT)):
        want = shaper.update(DT, (1.0, 0.0))
    tilts = fly_sticks(mode, plant, 3.0, (0.0, -1.0, 0.0), 0.5)  # full forward
    assert max(tilts) < 36.0
    assert plant.v[0] == pytest.approx(want[0], abs=0.3)  # what the stack's stick asks
    released_at = plant.p[0]
    run_on = 0.0
    for _ in range(round(6.0 / DT)):
        run_on += shaper.update(DT, (0.0, 0.0))[0] * DT
    north = [p[0] for p in centred_each_second(mode, plant, 8)]
    # It brakes as the setpoint does, a little more for the lag ...
    assert run_on < max(north) - released_at < run_on + 1.0
    # ... the hold locks where it stopped, and nothing pulls it back.
    hold = mode.setpoint.horizontal.position_ne_m
    assert hold is not None and hold[0] == pytest.approx(north[-1], abs=0.1)
    assert max(north) - north[-1] < 0.1


def test_the_throttle_released_in_a_climb_stops_above_and_holds_there() -> None:
    # Measured: before the ramps, released at 3 m/s the vehicle rose 1.0 m more
    # and came back down the 1.0 m; with them, 1.7 m more and 0.00 m back.
    mode, plant = hovering(position=False)
    fly_sticks(mode, plant, 3.0, CENTRE, 1.0)
    assert -plant.v[2] == pytest.approx(CLIMB.up_max_m_s, abs=0.1)
    released_at = -plant.p[2]
    up = [-p[2] for p in centred_each_second(mode, plant, 6)]
    braking = CLIMB.up_max_m_s**2 / (2.0 * CLIMB.accel_down_m_s2)
    assert braking < max(up) - released_at < braking + 0.5
    assert mode.setpoint.vertical.up_m == pytest.approx(up[-1], abs=0.05)
    assert max(up) - up[-1] < 0.05


def test_engaged_while_moving_the_setpoints_start_from_the_estimated_velocity() -> None:
    mode = HoldMode(position=True, limits=LIMITS)
    mode.reset(thrust=0.4)
    moving = (3.0, -4.0, -1.0)  # 5 m/s north-west, climbing 1 m/s
    mode.update(DT, LEVEL, STILL, (0.0, 0.0, -5.0), moving, CENTRE, 0.5, 0.0)
    h, v = mode.setpoint.horizontal, mode.setpoint.vertical
    assert h.position_ne_m is None and v.up_m is None  # not held yet: braking
    assert h.velocity_ne_m_s == pytest.approx((3.0, -4.0), abs=0.01)
    assert h.accel_ne_m_s2[0] < 0.0 < h.accel_ne_m_s2[1]  # against the motion
    assert v.climb_m_s == pytest.approx(1.0 - CLIMB.accel_down_m_s2 * DT)
    assert v.climb_accel_m_s2 == pytest.approx(-CLIMB.accel_down_m_s2)
    for _ in range(round(4.0 / DT)):  # both setpoints are back at zero
        mode.update(DT, LEVEL, STILL, (0.0, 0.0, -5.0), moving, CENTRE, 0.5, 0.0)
    assert mode.setpoint.horizontal.position_ne_m == (0.0, 0.0)
    assert mode.setpoint.vertical.up_m == pytest.approx(5.0)


def test_engaged_at_an_absurd_estimated_speed_the_setpoints_start_from_the_sticks_bounds() -> None:
    mode = HoldMode(position=True, limits=LINEAR)
    mode.reset(thrust=0.4)
    absurd = (300.0, -400.0, -90.0)
    mode.update(DT, LEVEL, STILL, (0.0, 0.0, -5.0), absurd, (0.0, -1.0, 0.0), 1.0, 0.0)
    h, v = mode.setpoint.horizontal, mode.setpoint.vertical
    assert math.hypot(*h.velocity_ne_m_s) == pytest.approx(10.0)
    assert v.climb_m_s == pytest.approx(3.0)


def test_engaged_holding_still_it_holds_where_it_is_at_once() -> None:
    # An autopilot's hover wanders ~0.1 m/s: braking that along PX4's drag took a
    # second, and the vehicle drifted that second (0.26 m RMS on the real PX4).
    mode = HoldMode(position=True, limits=LIMITS)
    mode.reset(thrust=0.4)
    slow = (0.9 * TAKE_OVER_STILL_M_S, 0.0, -0.9 * TAKE_OVER_STILL_M_S)
    mode.update(DT, LEVEL, STILL, (1.0, 2.0, -5.0), slow, CENTRE, 0.5, 0.0)
    assert mode.setpoint.horizontal.position_ne_m == (1.0, 2.0)
    assert mode.setpoint.vertical.up_m == 5.0


def take_over(plant: PointMassPlant, **reset: object) -> tuple[float, float]:
    """Engage on a plant the autopilot held still (its tilt against a steady wind, its
    collective); (the largest tilt change in the first 0.5 s, deg; the altitude lost
    in 2 s, m)."""
    mode = HoldMode(position=True, limits=LIMITS)
    mode.reset(**reset)  # type: ignore[arg-type]
    tilt0 = math.degrees(math.acos(1.0 - 2.0 * (plant.q[1] ** 2 + plant.q[2] ** 2)))
    up0 = -plant.p[2]
    change, lost = 0.0, 0.0
    for k in range(round(2.0 / DT)):
        fly_sticks(mode, plant, DT, CENTRE, 0.5)
        tilt = math.degrees(math.acos(min(1.0, 1.0 - 2.0 * (plant.q[1] ** 2 + plant.q[2] ** 2))))
        if k * DT <= 0.5:
            change = max(change, abs(tilt - tilt0))
        lost = max(lost, up0 + plant.p[2])
    return change, lost


def held_by_the_autopilot() -> PointMassPlant:
    """A hover against a 1 m/s^2 wind from the west, hover thrust 0.5 (PX4 SIH's)."""
    wind = 1.0
    plant = PointMassPlant(hover_thrust=0.5, wind_accel_ned=(0.0, wind, 0.0))
    plant.p[2] = -15.0
    lean = math.atan(wind / 9.80665)
    plant.q = euler_to_quat(-lean, 0.0, 0.0)  # rolled left into it ...
    cos_lean = math.cos(lean)
    plant.thrust = 0.5 * (1.0 / cos_lean) ** 0.5  # ... its thrust holding the altitude
    return plant


def test_engaging_from_the_autopilots_hold_starts_from_the_vehicles_state() -> None:
    # Taking over at the collective and the tilt the autopilot flew: measured 0.01
    # deg of tilt change and no altitude lost. At the vertical loop's prior (0.3)
    # and level, as before: 3.7 deg and 0.53 m (the real PX4: 11 deg and 0.48 m);
    # at the right collective but level: 4.4 deg.
    plant = held_by_the_autopilot()
    good = take_over(plant, thrust=plant.thrust, hover_thrust=0.5, q_wxyz=plant.q)
    assert good[0] < 0.5 and good[1] < 0.02
    bad = take_over(held_by_the_autopilot(), thrust=None)
    assert bad[0] > 3.0 and bad[1] > 0.4
    level = held_by_the_autopilot()
    assert take_over(level, thrust=level.thrust, hover_thrust=0.5)[0] > 3.0
