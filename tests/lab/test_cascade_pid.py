r"""PX4's default cascade, the outer-loop baseline (sitl/lab/cascade_pid.py).

Unit tests against analytic answers (the attitude P law, the velocity PID's step,
the tilt limit, altitude first, the integrators on the ground, non-finite inputs),
and one short flight in the lab (``sitl.lab.outer_flight``, ``outer_law="px4"``
over PX4's default rate PID). PX4 normalises the thrust 0..1 with
``MPC_THR_HOVER`` = 0.5: a vertical acceleration :math:`a` (up) asks
:math:`T_h (1 + a/g)`.
"""

from __future__ import annotations

import functools
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import PID_DEFAULT_CONTROLLER, MfcConfig, PidConfig, load_controller
from companion.control.attitude import AttitudeSetpoint
from companion.control.horizontal import HorizontalSetpoint
from companion.control.outer import OuterSetpoint
from companion.control.quaternion import body_z_ned, euler_to_quat
from companion.control.ultralocal import GRAVITY_M_S2 as G
from companion.control.vertical import VerticalSetpoint
from companion.profile import VehicleProfile, load_profile
from sitl.lab.cascade_pid import (
    PX4_DEFAULT_CASCADE,
    CascadeGains,
    CascadePid,
    PxAttitude,
    PxVertical,
    bodyz_to_quat,
    constrain_xy,
    limit_tilt,
)
from sitl.lab.outer_flight import SCENARIOS, outer_metrics, simulate_outer_flight

ROOT = Path(__file__).resolve().parents[2]
DEG = math.pi / 180.0
LEVEL = (1.0, 0.0, 0.0, 0.0)
ZERO3 = (0.0, 0.0, 0.0)
P = PX4_DEFAULT_CASCADE
HOLD_5M = OuterSetpoint(
    HorizontalSetpoint(position_ne_m=(0.0, 0.0)), VerticalSetpoint(up_m=5.0), yaw_rad=0.0
)
AT_5M = (0.0, 0.0, -5.0)


def tilt_of(q: tuple[float, float, float, float]) -> float:
    return math.acos(max(-1.0, min(1.0, body_z_ned(q)[2])))


def test_the_defaults_are_px4s() -> None:
    # mc_att_control_params.yaml, multicopter_position_control_{gain,limits,}_params.c
    assert (P.roll_p_1_s, P.pitch_p_1_s, P.yaw_p_1_s, P.yaw_weight) == (4.0, 4.0, 2.8, 0.4)
    assert P.roll_rate_max_rad_s == pytest.approx(220 * DEG)
    assert P.yaw_rate_max_rad_s == pytest.approx(200 * DEG)
    assert (P.xy_p_1_s, P.z_p_1_s) == (0.95, 1.0)
    assert (P.xy_vel_p_1_s, P.xy_vel_i_1_s2, P.xy_vel_d) == (1.8, 0.4, 0.2)
    assert (P.z_vel_p_1_s, P.z_vel_i_1_s2, P.z_vel_d) == (4.0, 2.0, 0.0)
    assert (P.hover_thrust, P.thrust_min, P.thrust_max, P.thrust_xy_margin) == (0.5, 0.12, 1, 0.3)
    assert P.tilt_max_rad == pytest.approx(45 * DEG)
    with pytest.raises(ValueError, match="yaw_weight"):
        CascadeGains(yaw_weight=1.5)
    with pytest.raises(ValueError, match="hover_thrust"):
        CascadeGains(hover_thrust=0.1)


# --- attitude --------------------------------------------------------------------------


@pytest.mark.parametrize("axis", [0, 1])
def test_attitude_p_on_a_roll_or_pitch_error(axis: int) -> None:
    """Rolled (pitched) by 0.1 rad, asked level: rate = -K 2 sin(0.05) on that axis."""
    angles = [0.0, 0.0, 0.0]
    angles[axis] = 0.1
    q = euler_to_quat(*angles)
    rates = PxAttitude().update(0.004, q, ZERO3, AttitudeSetpoint(0.0, 0.0, 0.0))
    expected = [0.0, 0.0, 0.0]
    expected[axis] = -4.0 * 2.0 * math.sin(0.05)
    assert rates == pytest.approx(expected, abs=1e-12)


def test_attitude_p_on_a_heading_error_keeps_the_yaw_gain() -> None:
    """Heading error psi: the weight w scales the half angle and divides the gain,
    so the rate is (K_psi / w) 2 sin(w psi / 2), K_psi psi for small psi."""
    psi = 0.2
    rates = PxAttitude().update(0.004, LEVEL, ZERO3, AttitudeSetpoint(0.0, 0.0, psi))
    exact = 2.8 / 0.4 * 2.0 * math.sin(0.4 * psi / 2.0)
    assert rates == pytest.approx((0.0, 0.0, exact), abs=1e-12)
    assert rates[2] == pytest.approx(2.8 * psi, rel=1e-3)


def test_attitude_tilt_first_and_the_rate_limits() -> None:
    att = PxAttitude()
    # 90 deg of roll error: 4 x 2 sin(45 deg) = 5.66 rad/s > 220 deg/s: clamped.
    rates = att.update(0.004, LEVEL, ZERO3, AttitudeSetpoint(math.pi / 2, 0.0, 0.0))
    assert rates[0] == pytest.approx(220 * DEG)
    assert att.saturated == (True, False, False)
    # A yaw-rate feedforward about the vertical, level: all on body z.
    rates = att.update(0.004, LEVEL, ZERO3, AttitudeSetpoint(0.0, 0.0, None, 0.5))
    assert rates == pytest.approx((0.0, 0.0, 0.5), abs=1e-12)


# --- velocity, position, thrust ----------------------------------------------------------


def test_velocity_pid_step_response() -> None:
    """At rest, asked 1 m/s north (no position) and 1 m/s up: the first output is
    the P part (the derivative starts at 0), then the integrator adds Ki e k dt."""
    c = CascadePid()
    sp = OuterSetpoint(
        HorizontalSetpoint(velocity_ne_m_s=(1.0, 0.0)), VerticalSetpoint(climb_m_s=1.0), 0.0
    )
    dt = 0.01
    for k in range(101):
        out = c.update(dt, LEVEL, ZERO3, AT_5M, ZERO3, sp)
        acc_n = 1.8 * 1.0 + 0.4 * 1.0 * k * dt
        acc_up = 4.0 * 1.0 + 2.0 * 1.0 * k * dt
        t_z = 0.5 * (1.0 + acc_up / G)
        assert out.attitude_setpoint.pitch_rad == pytest.approx(-math.atan(acc_n / G), abs=1e-9)
        assert out.attitude_setpoint.roll_rad == pytest.approx(0.0, abs=1e-12)
        assert out.level_thrust == pytest.approx(t_z, abs=1e-9)
        assert out.thrust == pytest.approx(t_z * math.hypot(1.0, acc_n / G), abs=1e-9)
    assert c.horizontal.integral_m_s2[0] == pytest.approx(0.4 * 1.01, abs=1e-9)


def test_position_p_gives_the_velocity_reference() -> None:
    c = CascadePid()
    out = c.update(0.01, LEVEL, ZERO3, (-1.0, 0.0, -4.0), ZERO3, HOLD_5M)
    assert c.horizontal.velocity_ref_ne_m_s == pytest.approx((0.95, 0.0))
    assert out.attitude_setpoint.pitch_rad == pytest.approx(-math.atan(0.95 * 1.8 / G))
    # 1 m low: 1 m/s up asked, 4 m/s^2.
    assert out.level_thrust == pytest.approx(0.5 * (1.0 + 4.0 / G))


def test_hovering_at_the_setpoint_asks_the_hover_thrust_level() -> None:
    out = CascadePid().update(0.01, LEVEL, ZERO3, AT_5M, ZERO3, HOLD_5M)
    assert out.rate_ref_frd_rad_s == pytest.approx(ZERO3, abs=1e-12)
    assert out.thrust == pytest.approx(0.5)
    assert not out.tilt_limited and not out.fault


def test_the_tilt_is_limited_to_45_deg() -> None:
    """100 m away: 12 m/s asked (MPC_XY_VEL_MAX), 21.6 m/s^2 (66 deg): held at 45 deg,
    the collective 0.5 / cos 45 deg (within the 1.0 maximum: no thrust clamp)."""
    c = CascadePid()
    out = c.update(0.01, LEVEL, ZERO3, (-100.0, 0.0, -5.0), ZERO3, HOLD_5M)
    assert c.horizontal.velocity_ref_ne_m_s == pytest.approx((12.0, 0.0))
    q_sp = euler_to_quat(out.attitude_setpoint.roll_rad, out.attitude_setpoint.pitch_rad, 0.0)
    assert tilt_of(q_sp) == pytest.approx(45 * DEG)
    assert out.tilt_limited
    assert out.thrust == pytest.approx(0.5 / math.cos(45 * DEG))
    assert out.level_thrust == pytest.approx(0.5)


def test_thrust_saturation_keeps_the_vertical_first() -> None:
    """Asked 3 m/s up from rest (1.11 of thrust) and 2 m/s north: the vertical gets
    sqrt(1 - 0.3^2) (MPC_THR_XY_MARG kept for the horizontal), the horizontal the
    0.3 left; the collective is the maximum. Without a horizontal demand the
    vertical takes all of it."""
    c = CascadePid()
    sp = OuterSetpoint(
        HorizontalSetpoint(velocity_ne_m_s=(2.0, 0.0)), VerticalSetpoint(climb_m_s=3.0), 0.0
    )
    out = c.update(0.01, LEVEL, ZERO3, AT_5M, ZERO3, sp)
    tz = math.sqrt(1.0 - 0.3**2)
    assert out.level_thrust == pytest.approx(tz)
    assert out.thrust == pytest.approx(1.0)
    assert out.tilt_limited
    assert -out.attitude_setpoint.pitch_rad == pytest.approx(math.atan(0.3 / tz))
    assert c.vertical.saturated
    # The vertical integrator does not wind up while the thrust is at its maximum.
    assert c.vertical.integral_m_s2 == 0.0
    c = CascadePid()
    out = c.update(0.01, LEVEL, ZERO3, AT_5M, ZERO3, sp._replace(horizontal=HorizontalSetpoint()))
    assert out.level_thrust == pytest.approx(1.0) and out.thrust == pytest.approx(1.0)
    assert out.attitude_setpoint.pitch_rad == pytest.approx(0.0, abs=1e-12)


def test_vertical_alone_and_its_anti_windup_at_thrust_min() -> None:
    v = PxVertical()
    # 10 m too high: 1.5 m/s down asked (MPC_Z_VEL_MAX_DN), 6 m/s^2 down: 0.19 > 0.12.
    t = v.update(0.01, -15.0, 0.0, VerticalSetpoint(up_m=5.0))
    assert t == pytest.approx(0.5 * (1.0 - 6.0 / G))
    # Falling at 5 m/s too slowly... asked 1.5 m/s down while climbing at 3 m/s: the
    # thrust is at MPC_THR_MIN and the integrator does not push it further down.
    for _ in range(50):
        t = v.update(0.01, -15.0, -3.0, VerticalSetpoint(up_m=5.0))
    assert t == pytest.approx(0.12)
    assert v.saturated
    i_before = v.integral_m_s2
    v.update(0.01, -15.0, -3.0, VerticalSetpoint(up_m=5.0))
    assert v.integral_m_s2 == i_before
    # Tilted by 30 deg: the collective is the vertical thrust over cos 30 deg.
    v.reset()
    t = v.update(0.01, -5.0, 0.0, VerticalSetpoint(up_m=5.0), cos_tilt=math.cos(30 * DEG))
    assert t == pytest.approx(0.5 / math.cos(30 * DEG))


def test_integrators_are_held_on_the_ground() -> None:
    c = CascadePid()
    c.vertical.on_ground = True
    away = (3.0, -2.0, 0.0)  # on the ground, 3 m off in north and east
    sp_down = OuterSetpoint(
        HorizontalSetpoint(position_ne_m=(0.0, 0.0)), VerticalSetpoint(up_m=0.0), 0.0
    )
    for _ in range(100):
        c.update(0.01, LEVEL, ZERO3, away, ZERO3, sp_down)
        c.vertical.update(0.01, 0.0, 0.0, VerticalSetpoint(up_m=-1.0))
    assert c.horizontal.integral_m_s2 == (0.0, 0.0)
    assert c.vertical.integral_m_s2 == 0.0
    # Asked to climb (the take-off): the vertical integrator runs, as in PX4's
    # take-off ramp; the horizontal ones stay held.
    sp_up = sp_down._replace(vertical=VerticalSetpoint(climb_m_s=1.0))
    for _ in range(100):
        c.update(0.01, LEVEL, ZERO3, away, ZERO3, sp_up)
    assert c.vertical.integral_m_s2 == pytest.approx(-2.0 * 1.0 * 1.0)
    assert c.vertical.hover_thrust == pytest.approx(0.5 * (1.0 + 2.0 / G))
    assert c.horizontal.integral_m_s2 == (0.0, 0.0)
    c.vertical.on_ground = False
    c.update(0.01, LEVEL, ZERO3, away, ZERO3, sp_up)
    assert c.horizontal.integral_m_s2 != (0.0, 0.0)


def test_non_finite_inputs_give_a_safe_output() -> None:
    c = CascadePid()
    # Position not finite: level, the hover collective, nothing integrated.
    out = c.update(0.01, LEVEL, ZERO3, (math.nan, 0.0, -5.0), ZERO3, HOLD_5M)
    assert out.fault and c.vertical.nonfinite_events == 1
    assert out.rate_ref_frd_rad_s == ZERO3 and out.thrust == pytest.approx(0.5)
    assert c.horizontal.integral_m_s2 == (0.0, 0.0) and c.vertical.integral_m_s2 == 0.0
    # Attitude not a rotation: zero rates.
    out = c.update(0.01, (math.nan, 0.0, 0.0, 0.0), ZERO3, AT_5M, ZERO3, HOLD_5M)
    assert out.rate_ref_frd_rad_s == ZERO3 and c.attitude.fault
    # Setpoint not finite: brake (zero velocity asked), finite.
    bad = OuterSetpoint(HorizontalSetpoint(position_ne_m=(math.inf, 0.0)), VerticalSetpoint())
    out = c.update(0.01, LEVEL, ZERO3, AT_5M, (1.0, 0.0, 0.0), bad)
    assert out.fault and out.attitude_setpoint.pitch_rad > 0.0  # leaning back
    # dt not > 0: the safe output.
    out = c.update(-1.0, LEVEL, ZERO3, AT_5M, ZERO3, HOLD_5M)
    assert out.fault and out.rate_ref_frd_rad_s == ZERO3
    out = c.update(0.01, LEVEL, ZERO3, AT_5M, ZERO3, HOLD_5M)
    assert not out.fault


finite_or_not = st.one_of(
    st.floats(-1e4, 1e4), st.sampled_from([math.nan, math.inf, -math.inf, 1e308])
)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(*[finite_or_not] * 16), min_size=1, max_size=4))
def test_never_a_non_finite_output(samples: list[tuple[float, ...]]) -> None:
    c = CascadePid()
    for s in samples:
        sp = OuterSetpoint(
            HorizontalSetpoint((s[11], s[12]), (s[12], s[11])),
            VerticalSetpoint(s[13], s[14]),
            None if s[15] > 0 else s[15],
        )
        out = c.update(
            abs(s[0]), (s[1], s[2], s[3], s[4]), (s[5], s[6], s[7]), (s[8], s[9], s[10]),
            (s[10], s[9], s[8]), sp,
        )  # fmt: skip
        assert all(math.isfinite(x) for x in out.rate_ref_frd_rad_s)
        assert math.isfinite(out.thrust) and P.thrust_min <= out.thrust <= P.thrust_max
        assert math.isfinite(out.attitude_setpoint.roll_rad + out.attitude_setpoint.pitch_rad)
        t = c.vertical.update(abs(s[0]), s[8], s[10], VerticalSetpoint(s[13], s[14]), cos_tilt=s[1])
        assert math.isfinite(t) and P.thrust_min <= t <= P.thrust_max
        r = c.attitude.update(s[0], (s[1], s[2], s[3], s[4]), ZERO3, AttitudeSetpoint(s[5], s[6]))
        assert all(math.isfinite(x) for x in r)


def test_the_geometry_helpers() -> None:
    # constrain_xy: the first vector first, then as much of the second as fits.
    assert constrain_xy((3.0, 0.0), (0.0, 10.0), 5.0) == pytest.approx((3.0, 4.0))
    assert constrain_xy((6.0, 0.0), (0.0, 1.0), 5.0) == pytest.approx((5.0, 0.0))
    assert constrain_xy((1.0, 1.0), (1.0, 0.0), 5.0) == pytest.approx((2.0, 1.0))
    # limit_tilt keeps the azimuth.
    v = (math.sin(60 * DEG) * 0.6, math.sin(60 * DEG) * 0.8, math.cos(60 * DEG))
    out, limited = limit_tilt(v, 45 * DEG)
    assert limited and out[2] == pytest.approx(math.cos(45 * DEG))
    assert out[1] / out[0] == pytest.approx(0.8 / 0.6)
    # bodyz_to_quat: body z where asked, the heading kept.
    for yaw in (0.0, 1.0, -2.5):
        assert bodyz_to_quat((0.0, 0.0, 1.0), yaw) == pytest.approx(euler_to_quat(0, 0, yaw))
        q = euler_to_quat(0.2, -0.3, yaw)
        assert bodyz_to_quat(body_z_ned(q), yaw) == pytest.approx(q, abs=1e-12)


# --- in the lab ------------------------------------------------------------------------


@functools.cache
def _f450() -> VehicleProfile:
    return load_profile(ROOT / "vehicle_profiles" / "f450.yaml", simulated=True)


@functools.cache
def _px4_rates() -> MfcConfig | PidConfig:
    return load_controller(PID_DEFAULT_CONTROLLER)


HOLD_S = 15.0
HOLD_BOUND_M = 0.5
"""Measured over 14-15 s, seed 20200318, 2026-11-29: 0.14 m horizontal RMS, 0.10 m
vertical (``python -m sitl.lab.outer_flight --outer px4 --profile f450 --duration 15``).
Loose: a regression check that the baseline flies, not a figure of merit."""


def test_px4_default_cascade_holds_the_f450() -> None:
    sc = SCENARIOS["position-hold"].with_duration(HOLD_S)
    fl = simulate_outer_flight(_f450(), _px4_rates(), sc, outer_law="px4")
    m = outer_metrics(fl, sc)
    assert fl.meta["outer_law"] == "px4"
    assert not m["crashed"]
    assert m["lift_off_s"] is not None and m["lift_off_s"] < 3.0
    assert m["pos_rms_h_m"] < HOLD_BOUND_M
    assert m["pos_rms_v_m"] < HOLD_BOUND_M
    assert -fl.columns["pos_ned_m"][-1, 2] == pytest.approx(5.0, abs=0.5)
    # One: the first sample after engaging has dt 0 (as for the MFC loops).
    assert fl.meta["outer_nonfinite_events"] <= 1
    # The integrator's hover collective comes to the vehicle's (0.566), from 0.5.
    assert m["hover_thrust_estimate"] == pytest.approx(m["hover_motor_command"], abs=0.05)


def test_an_unknown_outer_law_is_refused() -> None:
    sc = SCENARIOS["position-hold"].with_duration(1.0)
    with pytest.raises(ValueError, match="outer_law"):
        simulate_outer_flight(_f450(), _px4_rates(), sc, outer_law="ardupilot")


HOLD_STICKS = """\
duration_s: 8
altitude_m: 3
segments:
  - {t_s: 0.0, rate_deg_s: [0, 0, 0]}
"""


def test_px4_default_cascade_flies_the_products_position_mode(tmp_path: Path) -> None:
    """The flight core's position mode flies injected outer loops (``outer_law``),
    PX4's default cascade here, through the same ``OuterLaw`` interface as its own
    MFC loops: the vehicle, handed over in the air with the sticks centred, holds."""
    from companion.control.outer import OuterLaw
    from sitl.lab.simulate import simulate_flight
    from sitl.scenario import load_scenario

    sticks = tmp_path / "sticks.yaml"
    sticks.write_text(HOLD_STICKS, encoding="utf-8")
    scenario = tmp_path / "scenario.yaml"
    scenario.write_text(
        f"name: px4-cascade-hold\nseed: 7\npilot: {sticks}\nfree_flight: true\n",
        encoding="utf-8",
    )
    sc = load_scenario(str(scenario)).model_copy(update={"duration_s": 6.0})
    made: list[OuterLaw] = []

    def px4_cascade() -> OuterLaw:
        made.append(CascadePid())
        return made[-1]

    flights = {
        law: simulate_flight(
            _f450(), load_controller(), sc, mode="position",
            outer_law=px4_cascade if law == "px4" else None,
        )
        for law in ("mfc", "px4")
    }  # fmt: skip
    assert len(made) == 1  # built once, by the mode
    for law, fl in flights.items():
        c = fl.columns
        assert not fl.meta["failsafes"], (law, fl.meta["failsafes"])
        alt = np.asarray(c["altitude_m"])
        assert np.min(alt[len(alt) // 2 :]) > 1.0, law  # it flew, and still flies
    # Not the MFC loops under another name: the collectives part.
    a, b = (np.asarray(flights[k].columns["thrust"]) for k in ("mfc", "px4"))
    assert np.max(np.abs(a - b)) > 1e-3
