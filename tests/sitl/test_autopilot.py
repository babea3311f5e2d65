"""Unit tests of the SITL's PX4-like autopilot logic (no network)."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest

from companion.profile import VehicleProfile, load_profile
from sitl.autopilot import Autopilot, AutopilotConfig
from sitl.personality import MavResult
from sitl.px4_modes import (
    AUTO_SUB_LAND,
    AUTO_SUB_LOITER,
    FlightMode,
    MainMode,
    mode_name,
    pack_custom_mode,
    unpack_custom_mode,
)
from sitl.streams import MessageStreams, StreamSpec

ROOT = Path(__file__).resolve().parents[2]
LEVEL = (0.0, 0.0, 0.0)


@pytest.fixture(scope="module")
def profile() -> VehicleProfile:
    return load_profile(ROOT / "vehicle_profiles" / "f450.yaml")


def make(profile: VehicleProfile, **cfg: object) -> Autopilot:
    return Autopilot(profile, AutopilotConfig(**cfg))  # type: ignore[arg-type]


def stream_setpoints(ap: Autopilot, t0: float, t1: float, hz: float = 20.0) -> float:
    t = t0
    while t <= t1:
        assert ap.on_actuator_target(t, (0.0, 0.0, 0.0, 0.5, 0, 0, 0, 0))
        t += 1.0 / hz
    return t1


# ----------------------------------------------------------------- mode packing


@pytest.mark.parametrize(
    ("main", "sub", "expected"),
    [
        (MainMode.OFFBOARD, 0, 6 << 16),
        (MainMode.MANUAL, 0, 1 << 16),
        (MainMode.AUTO, AUTO_SUB_LAND, (4 << 16) | (6 << 24)),
        (MainMode.AUTO, AUTO_SUB_LOITER, (4 << 16) | (3 << 24)),
    ],
)
def test_custom_mode_pack_unpack(main: int, sub: int, expected: int) -> None:
    assert pack_custom_mode(main, sub) == expected
    assert unpack_custom_mode(expected) == (main, sub)
    assert FlightMode(main, sub).custom_mode == expected


def test_pack_rejects_out_of_range() -> None:
    with pytest.raises(ValueError):
        pack_custom_mode(256, 0)


def test_mode_names_match_pymavlink() -> None:
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil
    from pymavlink.dialects.v20 import common

    for main, sub in [(6, 0), (1, 0), (5, 0), (7, 0), (2, 0), (3, 0), (4, 6), (4, 3)]:
        hb = common.MAVLink_heartbeat_message(2, 12, 1, pack_custom_mode(main, sub), 3, 3)
        assert mavutil.mode_string_v10(hb) == mode_name(main, sub)


def test_base_mode_bits(profile: VehicleProfile) -> None:
    ap = make(profile)
    assert ap.base_mode & 1
    assert not ap.base_mode & 128
    assert ap.arm(0.0) is MavResult.ACCEPTED
    assert ap.base_mode & 128
    assert ap.system_status == 4


# ---------------------------------------------------------------- offboard rules


def test_offboard_refused_without_setpoints(profile: VehicleProfile) -> None:
    ap = make(profile)
    assert ap.set_mode(1.0, MainMode.OFFBOARD) is MavResult.TEMPORARILY_REJECTED
    assert ap.mode.main == MainMode.MANUAL


def test_offboard_refused_with_stale_setpoints(profile: VehicleProfile) -> None:
    ap = make(profile)
    ap.on_actuator_target(1.0, (0, 0, 0, 0.5))
    assert ap.set_mode(1.6, MainMode.OFFBOARD) is MavResult.TEMPORARILY_REJECTED


def test_offboard_accepted_with_setpoints(profile: VehicleProfile) -> None:
    ap = make(profile)
    stream_setpoints(ap, 0.0, 1.0)
    assert ap.set_mode(1.0, MainMode.OFFBOARD) is MavResult.ACCEPTED
    assert ap.custom_mode == 6 << 16


@pytest.mark.parametrize(("test_stand", "expected_sub"), [(False, AUTO_SUB_LAND), (True, 3)])
def test_offboard_loss_fails_safe(
    profile: VehicleProfile, test_stand: bool, expected_sub: int
) -> None:
    ap = make(profile, offboard_timeout_s=0.5, test_stand=test_stand)
    stream_setpoints(ap, 0.0, 1.0)
    ap.set_mode(1.0, MainMode.OFFBOARD)
    assert ap.arm(1.0) is MavResult.ACCEPTED
    t = 1.0
    while t < 1.45:  # still within the timeout
        ap.update(t, LEVEL, LEVEL, landed=False)
        t += 0.001
    assert ap.mode.main == MainMode.OFFBOARD
    while t < 1.6:
        ap.update(t, LEVEL, LEVEL, landed=False)
        t += 0.001
    assert ap.mode == FlightMode(MainMode.AUTO, expected_sub)
    assert ap.failsafe == "offboard_loss"
    assert ap.armed
    kinds = [e.kind for e in ap.drain_events()]
    assert "failsafe" in kinds


def test_land_failsafe_disarms_on_touchdown(profile: VehicleProfile) -> None:
    ap = make(profile, offboard_timeout_s=0.5)
    stream_setpoints(ap, 0.0, 1.0)
    ap.set_mode(1.0, MainMode.OFFBOARD)
    ap.arm(1.0)
    ap.update(1.0, LEVEL, LEVEL, landed=False)
    motors = ap.update(2.0, LEVEL, LEVEL, climb_rate_m_s=0.0, landed=False)
    assert ap.mode.sub == AUTO_SUB_LAND
    # Descending slower than the land speed -> less than hover thrust, all motors running.
    assert all(m > 0.0 for m in motors)
    ap.update(2.5, LEVEL, LEVEL, landed=True)
    assert not ap.armed


# ------------------------------------------------------------------- arming


def test_arm_denied_when_crashed(profile: VehicleProfile) -> None:
    ap = make(profile)
    ap.update(0.0, LEVEL, LEVEL, landed=True, crashed=True)
    assert ap.arm(0.1) is MavResult.DENIED
    assert not ap.armed


def test_arm_in_air_only_in_offboard(profile: VehicleProfile) -> None:
    ap = make(profile)
    ap.update(0.0, LEVEL, LEVEL, landed=False)
    assert ap.arm(0.0) is MavResult.DENIED
    stream_setpoints(ap, 0.0, 0.5)
    assert ap.set_mode(0.5, MainMode.OFFBOARD) is MavResult.ACCEPTED
    assert ap.arm(0.5) is MavResult.ACCEPTED


def test_arm_in_offboard_needs_setpoints(profile: VehicleProfile) -> None:
    ap = make(profile)
    stream_setpoints(ap, 0.0, 0.5)
    ap.set_mode(0.5, MainMode.OFFBOARD)
    assert ap.arm(3.0) is MavResult.DENIED


def test_disarm_in_air_needs_force(profile: VehicleProfile) -> None:
    ap = make(profile)
    ap.arm(0.0)
    ap.update(0.1, LEVEL, LEVEL, landed=False)
    assert ap.disarm(0.1) is MavResult.DENIED
    assert ap.disarm(0.1, force=True) is MavResult.ACCEPTED
    assert not ap.armed


def test_disarmed_motors_are_zero(profile: VehicleProfile) -> None:
    ap = make(profile)
    stream_setpoints(ap, 0.0, 0.5)
    ap.set_mode(0.5, MainMode.OFFBOARD)
    assert ap.update(0.5, LEVEL, LEVEL, landed=True) == (0.0,) * 4


# ---------------------------------------------------------------- allocation


def offboard_armed(ap: Autopilot, t: float = 0.5) -> None:
    stream_setpoints(ap, 0.0, t)
    assert ap.set_mode(t, MainMode.OFFBOARD) is MavResult.ACCEPTED
    assert ap.arm(t) is MavResult.ACCEPTED


def test_positive_roll_raises_left_motors(profile: VehicleProfile) -> None:
    ap = make(profile)
    offboard_armed(ap)
    ap.on_actuator_target(0.5, (0.2, 0.0, 0.0, 0.5, 0, 0, 0, 0))
    motors = ap.update(0.5, LEVEL, LEVEL, landed=False)
    ys = [m.position_frd_m[1] for m in profile.frame.motors]
    left = [motors[i] for i, y in enumerate(ys) if y < 0]
    right = [motors[i] for i, y in enumerate(ys) if y > 0]
    assert min(left) > 0.5 > max(right)


def test_positive_pitch_raises_front_and_yaw_raises_ccw(profile: VehicleProfile) -> None:
    ap = make(profile)
    offboard_armed(ap)
    ap.on_actuator_target(0.5, (0.0, 0.2, 0.0, 0.5))
    motors = ap.update(0.5, LEVEL, LEVEL, landed=False)
    for m, spec in zip(motors, profile.frame.motors, strict=True):
        assert (m > 0.5) == (spec.position_frd_m[0] > 0)
    ap.on_actuator_target(0.5, (0.0, 0.0, 0.2, 0.5))
    motors = ap.update(0.501, LEVEL, LEVEL, landed=False)
    for m, spec in zip(motors, profile.frame.motors, strict=True):
        assert (m > 0.5) == (spec.spin == "ccw")


def test_paper_mixer_selected(profile: VehicleProfile) -> None:
    paper = profile.model_copy(
        update={"physics": profile.physics.model_copy(update={"mixer": "paper"})}
    )
    ap = make(paper)
    offboard_armed(ap)
    ap.on_actuator_target(0.5, (0.2, 0.0, 0.0, 0.5))
    motors = ap.update(0.5, LEVEL, LEVEL, landed=False)
    # Paper '+' frame: motor 4 (left) up, motor 2 (right) down, 1 and 3 unchanged
    # (PX4's collective 0.5 is half way from the armed idle to full).
    mid = paper.limits.motor_idle + (1.0 - paper.limits.motor_idle) * 0.5
    assert motors[3] > mid > motors[1]
    assert motors[0] == pytest.approx(mid) == motors[2]


def test_nan_setpoints_ignored_and_counted(profile: VehicleProfile) -> None:
    ap = make(profile)
    offboard_armed(ap)
    before = ap.update(0.5, LEVEL, LEVEL, landed=False)
    assert not ap.on_actuator_target(0.51, (math.nan, 0.0, 0.0, 0.5))
    assert not ap.on_rates_target(0.51, (0.0, math.inf, 0.0), 0.5)
    assert not ap.on_rates_target(0.51, (0.0, 0.0, 0.0), math.nan)
    assert ap.rejected_setpoints == 3
    after = ap.update(0.502, LEVEL, LEVEL, landed=False)
    assert after == pytest.approx(before)
    assert all(math.isfinite(m) for m in after)
    # A NaN setpoint does not refresh the offboard watchdog either.
    assert ap.setpoint_age_s(0.51) == pytest.approx(0.51 - 0.5)


def test_rates_target_tracked_by_internal_pid(profile: VehicleProfile) -> None:
    """A toy rigid body (ang. accel = gain * torque) follows a rate step through the loop."""
    ap = make(profile)
    offboard_armed(ap)
    gain_rad_s2 = (60.0, 60.0, 20.0)  # per unit of normalised torque
    rate = [0.0, 0.0, 0.0]
    target = (1.0, -0.5, 0.3)
    t, dt = 0.5, 0.001
    for _ in range(3000):
        ap.on_rates_target(t, target, 0.5)
        ap.update(t, tuple(rate), LEVEL, landed=False)
        tq = ap.last_torque_thrust
        for i in range(3):
            rate[i] += gain_rad_s2[i] * tq[i] * dt
        t += dt
    assert rate == pytest.approx(list(target), abs=0.03)


def test_stabilized_sticks_level(profile: VehicleProfile) -> None:
    ap = make(profile)
    ap.arm(0.0)
    sticks = (1500, 1500, 1500, 1500)
    motors = ap.update(0.0, LEVEL, LEVEL, landed=True, sticks_us=sticks)
    # Half throttle: half way from the armed idle (PWM_MAIN_MINn) to full.
    mid = profile.limits.motor_idle + (1.0 - profile.limits.motor_idle) * 0.5
    assert motors == pytest.approx((mid,) * 4)
    # Rolled right by 0.2 rad with centred sticks: the loop rolls back left.
    ap.update(0.001, LEVEL, (0.2, 0.0, 0.0), landed=False, sticks_us=sticks)
    assert ap.last_torque_thrust[0] < 0.0


# -------------------------------------------------------------- message intervals


def streams() -> MessageStreams:
    return MessageStreams(
        [StreamSpec(105, "HIGHRES_IMU", 0.02, imu_based=True), StreamSpec(65, "RC", 0.1)],
        imu_rate_hz=250.0,
    )


def test_message_interval_accept_and_deny() -> None:
    s = streams()
    assert s.set_interval(105, 4000) is MavResult.ACCEPTED  # 250 Hz = IMU rate
    assert s.set_interval(105, 1000) is MavResult.DENIED  # faster than the IMU
    assert s.interval_s(105) == pytest.approx(0.004)
    assert s.set_interval(65, 1000) is MavResult.ACCEPTED  # 1 kHz on a non-IMU stream
    assert s.set_interval(65, 999) is MavResult.DENIED  # above 1 kHz
    assert s.set_interval(65, -1) is MavResult.ACCEPTED
    assert s.interval_s(65) <= 0.0
    assert s.set_interval(65, 0) is MavResult.ACCEPTED
    assert s.interval_s(65) == pytest.approx(0.1)
    assert s.set_interval(999, 10000) is MavResult.DENIED
    assert s.set_interval(65, math.nan) is MavResult.DENIED


def test_stream_due_rate_is_exact() -> None:
    s = streams()
    s.set_interval(105, 8000)  # 125 Hz
    n = sum(s.due(105, k * 0.001) for k in range(2000))
    assert n == 250
    s.set_interval(65, -1)
    assert not any(s.due(65, k * 0.001) for k in range(100))


def test_a_rates_flight_after_arming_does_not_depend_on_the_samples_phase_before(
    profile: VehicleProfile,
) -> None:
    """Armed between two gyro samples at different phases (as the companion's arm
    command lands whenever it comes), the rate loop's output from arming on is the
    same, bit for bit, for the same samples and setpoints after arming."""
    rng = np.random.default_rng(3)
    after_gyro = rng.normal(0.0, 0.2, size=(200, 3)).tolist()
    after_sp = rng.normal(0.0, 1.0, size=(200, 3)).tolist()
    outputs = []
    for phase_s, arm_s in ((0.0, 0.401), (0.0015, 0.9)):
        ap = make(profile)
        t = phase_s
        while t < arm_s:  # disarmed, the gyro stream running as it does on a vehicle
            ap.on_rates_target(t, (0.0, 0.0, 0.0), 0.3)
            ap.update(t, rng.normal(0.0, 0.05, size=3).tolist(), LEVEL, landed=True)
            t += 0.004
        assert ap.set_mode(arm_s, MainMode.OFFBOARD) is MavResult.ACCEPTED
        assert ap.arm(arm_s) is MavResult.ACCEPTED
        out = []
        for k, (g, sp) in enumerate(zip(after_gyro, after_sp, strict=True)):
            ts = arm_s + k * 0.004
            ap.on_rates_target(ts, sp, 0.5)
            out.append(ap.update(ts, g, LEVEL, landed=k < 10))
        outputs.append(out)
    assert outputs[0] == outputs[1]
