"""A mission's path: its setpoints in time, against hand-computed answers."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from companion.errors import ConfigError
from companion.mission import Mission, MissionPath, Waypoint, load_mission
from companion.stacks import ARDUPILOT_STICK_PARAMS, PX4_STICK_PARAMS

CLIMB = PX4_STICK_PARAMS.limits()
"""PX4's defaults: a climb at most 3 m/s, a descent 1.5 m/s; its missions 3 m/s^2
and 4 m/s^3."""


def square(accel_m_s2: float = 2.0, jerk_m_s3: float | None = None, **first: float) -> Mission:
    """The hand-computed answers below are for the acceleration stepped (no jerk
    limit); the S-curve has its own tests."""
    return Mission(
        speed_m_s=2.0,
        accel_m_s2=accel_m_s2,
        jerk_m_s3=jerk_m_s3,
        waypoints=[
            Waypoint(north_m=0, east_m=0, up_m=5, **first),
            Waypoint(north_m=10, east_m=0, up_m=5),
            Waypoint(north_m=10, east_m=10, up_m=5, speed_m_s=5.0),
            Waypoint(north_m=10, east_m=10, up_m=-1, speed_m_s=5.0),
        ],
    )


def test_the_setpoint_moves_along_each_leg_from_rest_to_rest_and_holds_at_waypoints() -> None:
    # From N 100, E 200, 3 m up; 2 m/s^2.
    path = MissionPath(square(hold_s=1.0), (100.0, 200.0, -3.0), CLIMB)
    # Climb 5 m at 2 m/s (under the 3 m/s climb limit): 1 s speeding up over 1 m,
    # 1.5 s at 2 m/s, 1 s slowing down: 3.5 s.
    sp = path.at(0.5)
    assert sp.horizontal.position_ne_m == pytest.approx((100.0, 200.0))
    assert sp.vertical == pytest.approx((1.0, 3.0 + 0.25, 2.0))
    assert path.at(2.0).vertical == pytest.approx((2.0, 3.0 + 3.0, 0.0))
    assert path.at(3.25).vertical == pytest.approx((0.5, 8.0 - 0.0625, -2.0))
    # Held at the first waypoint for 1 s: no velocity.
    sp = path.at(4.0)
    assert sp.vertical == (0.0, pytest.approx(8.0), 0.0)
    assert sp.horizontal.velocity_ne_m_s == (0.0, 0.0)
    # 10 m north at 2 m/s from t = 4.5: 6 s, half way at 7.5 s.
    sp = path.at(7.5)
    assert sp.horizontal.position_ne_m == pytest.approx((105.0, 200.0))
    assert sp.horizontal.velocity_ne_m_s == pytest.approx((2.0, 0.0))
    assert sp.horizontal.accel_ne_m_s2 == pytest.approx((0.0, 0.0))
    # 10 m east at 5 m/s: too short to reach it: at most sqrt(2 * 10) m/s, 2 sqrt(10 / 2) s.
    t3 = 10.5 + 2.0 * math.sqrt(5.0)
    sp = path.at(10.5 + math.sqrt(5.0))
    assert sp.horizontal.velocity_ne_m_s == pytest.approx((0.0, math.sqrt(20.0)))
    assert sp.horizontal.position_ne_m == pytest.approx((110.0, 205.0))
    # Then down 6 m at 5 m/s, slowed to the 1.5 m/s descent limit: 6 / 1.5 + 1.5 / 2 s.
    assert path.arrivals_s == pytest.approx([3.5, 10.5, t3, t3 + 4.75])
    sp = path.at(t3 + 2.0)
    assert sp.vertical == pytest.approx((-1.5, 8.0 - 0.5625 - 1.5 * 1.25, 0.0))
    assert path.duration_s == pytest.approx(t3 + 4.75)


@pytest.mark.parametrize("accel_m_s2", [0.5, 2.5, 10.0])
def test_the_setpoint_is_continuous_and_never_faster_than_the_leg(accel_m_s2: float) -> None:
    path = MissionPath(square(accel_m_s2, hold_s=0.5), (0.0, 0.0, 0.0), CLIMB)
    ts = np.linspace(-0.5, path.duration_s + 0.5, 4001)
    pos = np.array([(*path.at(t).horizontal.position_ne_m, path.at(t).vertical.up_m) for t in ts])
    vel = np.array([(*path.at(t).horizontal.velocity_ne_m_s, path.at(t).vertical.climb_m_s)
                    for t in ts])  # fmt: skip
    step = float(ts[1] - ts[0])
    assert np.max(np.linalg.norm(np.diff(pos, axis=0), axis=1)) <= 5.0 * step + 1e-9
    assert np.max(np.linalg.norm(vel, axis=1)) <= 5.0 + 1e-9
    # From rest and to rest at each waypoint.
    for t in (0.0, *path.arrivals_s):
        sp = path.at(t)
        assert np.linalg.norm((*sp.horizontal.velocity_ne_m_s, sp.vertical.climb_m_s)) < 1e-9


@pytest.mark.parametrize("jerk_m_s3", [0.5, 4.0, 50.0])
@pytest.mark.parametrize("length_m", [0.05, 1.0, 10.0, 60.0])
def test_the_s_curve_keeps_its_limits_and_starts_without_a_jolt(
    jerk_m_s3: float, length_m: float
) -> None:
    mission = Mission(
        speed_m_s=5.0, accel_m_s2=2.5, jerk_m_s3=jerk_m_s3,
        waypoints=[Waypoint(north_m=length_m, east_m=0, up_m=0)],
    )  # fmt: skip
    path = MissionPath(mission, (0.0, 0.0, 0.0), CLIMB)
    ts = np.linspace(0.0, path.duration_s, 20001)
    dt = float(ts[1] - ts[0])
    x = np.array([path.at(t).horizontal.position_ne_m[0] for t in ts])
    v = np.array([path.at(t).horizontal.velocity_ne_m_s[0] for t in ts])
    a = np.array([path.at(t).horizontal.accel_ne_m_s2[0] for t in ts])
    assert x[0] == 0.0 and x[-1] == pytest.approx(length_m)
    assert v[0] == a[0] == 0.0 and abs(v[-1]) < 1e-9 and abs(a[-1]) < 1e-9
    assert np.max(v) <= 5.0 + 1e-9 and np.max(np.abs(a)) <= 2.5 + 1e-9
    assert np.max(np.abs(np.diff(a))) / dt <= jerk_m_s3 * (1.0 + 1e-6)  # no step in it
    # Each is the next one's derivative (trapezoidal rule over the grid; where the
    # acceleration has a corner the rule is off by up to j dt / 4).
    np.testing.assert_allclose(np.diff(x) / dt, 0.5 * (v[1:] + v[:-1]), atol=1e-6 * length_m)
    np.testing.assert_allclose(np.diff(v) / dt, 0.5 * (a[1:] + a[:-1]), atol=0.25 * jerk_m_s3 * dt)


def test_the_s_curve_takes_a_over_j_longer_per_leg() -> None:
    """A 10 m leg at 2 m/s, 2 m/s^2, 4 m/s^3: 10/2 + 2/2 + 2/4 s."""
    mission = Mission(
        speed_m_s=2.0, accel_m_s2=2.0, jerk_m_s3=4.0,
        waypoints=[Waypoint(north_m=10, east_m=0, up_m=0)],
    )  # fmt: skip
    path = MissionPath(mission, (0.0, 0.0, 0.0), CLIMB)
    assert path.duration_s == pytest.approx(6.5)
    assert path.at(0.25).horizontal.accel_ne_m_s2[0] == pytest.approx(1.0)  # 4 m/s^3 x 0.25 s
    assert path.at(3.25).horizontal.velocity_ne_m_s[0] == pytest.approx(2.0)


@pytest.mark.parametrize(
    ("params", "accel", "jerk"),
    [
        (PX4_STICK_PARAMS, 3.0, 4.0),  # MPC_ACC_HOR, MPC_JERK_AUTO
        (ARDUPILOT_STICK_PARAMS, 2.5, 1.0),  # WPNAV_ACCEL (cm/s^2), WPNAV_JERK
    ],
)
def test_a_file_without_acceleration_or_jerk_flies_the_stacks_own_missions(
    params: object, accel: float, jerk: float
) -> None:
    """A 10 m leg at 2 m/s: 10/2 + 2/a + a/j s (the acceleration reached)."""
    mission = Mission(speed_m_s=2.0, waypoints=[Waypoint(north_m=10, east_m=0, up_m=0)])
    assert mission.accel_m_s2 is None and mission.jerk_m_s3 is None
    limits = params.limits()  # type: ignore[attr-defined]
    path = MissionPath(mission, (0.0, 0.0, 0.0), limits)
    assert (path.accel_m_s2, path.jerk_m_s3) == (accel, jerk)
    peak = min(accel, math.sqrt(2.0 * jerk))  # v = a^2 / j at the peak, if short of a
    assert path.duration_s == pytest.approx(5.0 + 2.0 / peak + peak / jerk)
    # The stack's own, read from it: the file's, where it gives them.
    read = params.limits({"MPC_ACC_HOR": 2.0, "MPC_JERK_AUTO": 8.0,  # type: ignore[attr-defined]
                          "WPNAV_ACCEL": 200.0, "WPNAV_JERK": 8.0})  # fmt: skip
    assert MissionPath(mission, (0.0, 0.0, 0.0), read).jerk_m_s3 == 8.0
    given = mission.model_copy(update={"accel_m_s2": 1.0})
    assert MissionPath(given, (0.0, 0.0, 0.0), read).accel_m_s2 == 1.0


def test_after_the_end_it_holds_the_last_waypoint_and_counts_them() -> None:
    path = MissionPath(square(), (0.0, 0.0, 0.0), CLIMB)
    for t in (path.duration_s, 1e6):
        sp = path.at(t)
        assert sp.horizontal == ((0.0, 0.0), pytest.approx((10.0, 10.0)), (0.0, 0.0))
        assert sp.vertical == (0.0, pytest.approx(-1.0), 0.0)
    # Arrivals at 3.5, 9.5, 9.5 + 2 sqrt(5) and 4.75 s after it (2 m/s^2).
    assert [path.waypoints_reached(t) for t in (0.0, 3.5, 11.0, 100.0)] == [0, 1, 2, 4]
    assert path.target_at(0.0) == pytest.approx((0.0, 0.0, -5.0))
    assert path.target_at(11.0) == pytest.approx((10.0, 10.0, -5.0))
    assert path.at(-1.0).vertical.up_m == pytest.approx(0.0)  # before the start: the start


def test_a_waypoint_where_the_mission_starts_is_reached_at_once() -> None:
    path = MissionPath(
        Mission(waypoints=[Waypoint(north_m=0, east_m=0, up_m=0, hold_s=2)]),
        (1.0, 2.0, -3.0),
        CLIMB,
    )
    assert path.arrivals_s == [0.0] and path.duration_s == 2.0
    assert path.at(1.0).horizontal.position_ne_m == (1.0, 2.0)


def test_a_bad_mission_file_names_its_keys(tmp_path: Path) -> None:
    f = tmp_path / "m.yaml"
    f.write_text(
        "speed_m_s: 0\nwaypoints:\n  - {north_m: 1, east_m: .nan, up_m: 2, hold_s: -1}\n"
        "  - {north_m: 1, east_m: 0, up_m: 2, heading: 3}\n",
        encoding="utf-8",
    )
    with pytest.raises(ConfigError) as err:
        load_mission(f)
    text = str(err.value)
    for key in ("speed_m_s", "waypoints.0.east_m", "waypoints.0.hold_s", "waypoints.1.heading"):
        assert key in text, text
    f.write_text("waypoints: []\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="waypoints"):
        load_mission(f)


def test_a_leg_faster_than_the_loop_flies_is_refused(tmp_path: Path) -> None:
    f = tmp_path / "m.yaml"
    f.write_text("waypoints:\n  - {north_m: 9, east_m: 0, up_m: 2, speed_m_s: 12.5}\n")
    with pytest.raises(ConfigError, match=r"waypoints\.0\.speed_m_s.*less than or equal to 12"):
        load_mission(f)
    f.write_text("waypoints:\n  - {north_m: 9, east_m: 0, up_m: 2, speed_m_s: 12}\n")
    assert load_mission(f).waypoints[0].speed_m_s == 12.0
