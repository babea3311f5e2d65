"""The lab's outer scenarios reach the product as a user's input does: a plan the
position mode flies, or the sticks of the altitude mode (sitl/lab/outer_plan.py)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from companion.config import load_controller
from companion.control.hold_modes import TAKEOFF_CLIMB_M_S
from companion.profile import VehicleProfile, load_profile
from sitl.lab.inprocess import px4_stick_limits
from sitl.lab.outer_flight import SCENARIOS, simulate_outer_flight
from sitl.lab.outer_plan import PLAN_LIFT_OFF_S, AnglePilot, ScenarioPlan
from sitl.pilot import PilotView

ROOT = Path(__file__).resolve().parents[2]


def _f450() -> VehicleProfile:
    return load_profile(ROOT / "vehicle_profiles" / "f450.yaml", simulated=True)


def test_a_plan_climbs_from_where_it_starts_then_flies_the_scenario_in_the_local_frame() -> None:
    sc = SCENARIOS["square"]
    origin = (0.2, -0.1, 0.3)  # NED: where the estimate put the vehicle, 0.3 m down
    path = ScenarioPlan(sc).path(origin, px4_stick_limits()[0])
    # On the legs the waypoint flown to is above: the position mode takes off.
    assert path.target_at(0.0) == pytest.approx((0.0, 0.0, -sc.hold_up_m))
    climbing = path.at(2.0)
    assert climbing.vertical.up_m == pytest.approx(-0.3 + 2.0 * TAKEOFF_CLIMB_M_S)
    assert climbing.vertical.climb_m_s == TAKEOFF_CLIMB_M_S
    assert climbing.horizontal.position_ne_m == pytest.approx((0.0, 0.0))
    assert path.at(7.0).vertical.up_m == sc.hold_up_m
    assert path.start_s == pytest.approx(sc.start_s - PLAN_LIFT_OFF_S)
    # Two seconds into the square: 4 m north of the start, at 2 m/s north.
    sp = path.at(path.start_s + 2.0)
    assert sp.horizontal.position_ne_m == pytest.approx((4.0, 0.0))
    assert sp.horizontal.velocity_ne_m_s == pytest.approx((2.0, 0.0))
    assert sp.vertical.up_m == pytest.approx(sc.hold_up_m)
    assert path.waypoints_reached(1e3) == 0


def test_the_angle_pilot_climbs_at_the_take_off_rate_then_holds_the_sticks_asked() -> None:
    sc = SCENARIOS["angle-sticks"]
    limits = px4_stick_limits()[0]
    pilot = AnglePilot(sc, limits)

    def view(t: float, up: float) -> PilotView:
        return PilotView(t_s=t, roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0,
                         rate_frd_rad_s=(0.0, 0.0, 0.0), altitude_m=up, climb_rate_m_s=0.0,
                         hover_throttle=0.5)  # fmt: skip

    climb = pilot.sticks(view(1.0, 0.0))
    asked = limits.climb.climb_m_s((climb.throttle_us - 1000) / 1000.0)
    assert asked == pytest.approx(TAKEOFF_CLIMB_M_S, abs=0.02)
    assert pilot.sticks(view(5.0, sc.hold_up_m)).throttle_us == 1500  # there: centred
    # 2.5 s into the scenario: the 15 deg roll, at full stick's tilt.
    roll = pilot.sticks(view(sc.start_s + 2.5, sc.hold_up_m))
    x = (roll.roll_us - 1500) / 500.0
    assert x * limits.tilt_max_deg == pytest.approx(15.0, abs=0.1)
    assert (roll.pitch_us, roll.throttle_us) == (1500, 1500)


def test_an_outer_flight_is_flown_by_the_products_flight_modes() -> None:
    """The angle scenario through the altitude mode: what the attitude loop was asked
    is the pilot's stick (15 deg of roll), the altitude the mode's own hold; and no
    failsafe of the product fired."""
    sc = SCENARIOS["angle-sticks"].with_duration(16.0)
    fl = simulate_outer_flight(_f450(), load_controller(), sc)
    c = fl.columns
    assert fl.meta["failsafes"] == []
    t = c["t_s"]
    doublet = (t > sc.start_s + 2.3) & (t < sc.start_s + 3.4)
    roll_sp = np.degrees(c["sp_att_rad"][doublet, 0])
    assert np.all(np.abs(roll_sp - 15.0) < 0.1), (roll_sp.min(), roll_sp.max())
    held = c["sp_up_m"][t > sc.start_s]
    assert np.all(np.isfinite(held)) and abs(float(held[-1]) - sc.hold_up_m) < 0.5
    # The heading is the yaw stick's rate: no heading setpoint is recorded.
    assert np.all(np.isnan(c["sp_att_rad"][doublet, 2]))
    assert math.isclose(fl.meta["start_s"], sc.start_s)
