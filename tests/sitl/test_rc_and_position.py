"""Both SITL personalities without RC or a position: what the real stacks do.

PX4 (``sitl.autopilot``): COM_RC_LOSS_T, NAV_RCL_ACT, COM_RCL_EXCEPT, ACRO refused
without RC and the other manual modes taken as POSCTL in a failsafe, POSCTL /
AUTO.LOITER refused without a position.
ArduPilot (``sitl.ardupilot``): the radio failsafe (RC_FS_TIMEOUT, FS_THR_ENABLE,
FS_OPTIONS), LOITER / BRAKE refused without a position, the EKF failsafe.
No network: the autopilots are driven directly, as the runner drives them.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from companion.profile import VehicleProfile, load_profile
from sitl.ardupilot import ArduCopter, ArduCopterConfig
from sitl.ardupilot_modes import CopterMode
from sitl.autopilot import Autopilot, AutopilotConfig
from sitl.personality import MavResult
from sitl.px4_modes import MODE_LAND, MODE_LOITER, MODE_OFFBOARD, FlightMode, MainMode

ROOT = Path(__file__).resolve().parents[2]
LEVEL = (0.0, 0.0, 0.0)
STICKS = (1500, 1500, 1500, 1500, 1000, 1500, 1500, 1500)
THROTTLE_DOWN = (1500, 1500, 1000, 1500, 1000, 1500, 1500, 1500)
"""ArduCopter arms only with the throttle at idle (tests/sitl/test_real_stack_behaviours.py)."""
RATES = 128  # SET_ATTITUDE_TARGET: body rates + thrust


@pytest.fixture(scope="module")
def profile() -> VehicleProfile:
    return load_profile(ROOT / "vehicle_profiles" / "f450.yaml")


# ------------------------------------------------------------------------ PX4


def px4_flying(profile: VehicleProfile, mode: FlightMode, **cfg: object) -> Autopilot:
    """Armed in the air in ``mode`` at t = 1 s, RC seen until then (every 4 ms)."""
    ap = Autopilot(profile, AutopilotConfig(**cfg), initial_mode=FlightMode(MainMode.POSCTL))  # type: ignore[arg-type]
    t = 0.0
    while t < 1.0:
        ap.update(t, LEVEL, LEVEL, sticks_us=STICKS)
        t += 0.004
    assert ap.arm(t, force=True) is MavResult.ACCEPTED
    ap.update(t, LEVEL, LEVEL, sticks_us=STICKS)
    if mode == MODE_OFFBOARD:
        ap.on_rates_target(t, LEVEL, 0.5)
    assert ap.set_mode(t, mode.main, mode.sub) is MavResult.ACCEPTED
    return ap


def run_px4(ap: Autopilot, t0: float, t1: float, *, rc: bool, offboard: bool = False) -> None:
    t = t0
    while t < t1:
        if offboard:
            ap.on_rates_target(t, LEVEL, 0.5)
        ap.update(t, LEVEL, LEVEL, sticks_us=STICKS if rc else None)
        t += 0.004


def test_px4_rc_loss_in_posctl_lands_after_com_rc_loss_t(profile: VehicleProfile) -> None:
    ap = px4_flying(profile, FlightMode(MainMode.POSCTL))
    run_px4(ap, 1.004, 1.45, rc=False)  # 0.45 s of silence: not yet lost
    assert ap.mode.main == MainMode.POSCTL
    run_px4(ap, 1.45, 1.6, rc=False)
    assert ap.mode == MODE_LAND  # NAV_RCL_ACT 2 (Return), flown as Land
    assert ap.failsafe == "rc_loss"
    assert ap.system_status == 5  # CRITICAL
    kinds = [(e.kind, e.detail.get("cause")) for e in ap.drain_events()]
    assert ("failsafe", "rc_loss") in kinds


@pytest.mark.parametrize(("position", "expected"), [(True, MODE_LOITER), (False, MODE_LAND)])
def test_px4_nav_rcl_act_hold_needs_a_position(
    profile: VehicleProfile, position: bool, expected: FlightMode
) -> None:
    ap = px4_flying(profile, FlightMode(MainMode.ALTCTL), rc_loss_action=1)
    ap.position_valid = position
    run_px4(ap, 1.004, 1.6, rc=False)
    assert ap.mode == expected


def test_px4_acro_is_refused_without_rc(profile: VehicleProfile) -> None:
    ap = px4_flying(profile, MODE_LOITER, rc_loss_exceptions=2)  # hold exempt: it stays
    run_px4(ap, 1.004, 1.6, rc=False)
    assert ap.mode == MODE_LOITER
    assert ap.set_mode(1.6, MainMode.ACRO) is MavResult.TEMPORARILY_REJECTED
    assert ap.mode == MODE_LOITER
    assert ap.set_mode(1.6, MainMode.AUTO, 6) is MavResult.ACCEPTED  # land: always
    # RC back: the manual modes are there again.
    run_px4(ap, 1.6, 1.7, rc=True)
    assert ap.set_mode(1.7, MainMode.POSCTL) is MavResult.ACCEPTED
    assert ap.failsafe is None


@pytest.mark.parametrize(
    "main", [MainMode.MANUAL, MainMode.STABILIZED, MainMode.ALTCTL, MainMode.POSCTL]
)
def test_px4_manual_mode_without_sticks_shows_posctl_and_fails_safe(
    profile: VehicleProfile, main: MainMode
) -> None:
    """The real PX4 v1.16 SIH (no radio, no joystick) handed a manual mode: it keeps
    showing POSCTL (for ALTCTL, STABILIZED and MANUAL too), raises its failsafe
    (HEARTBEAT CRITICAL, "Failsafe activated") and descends."""
    ap = Autopilot(profile, AutopilotConfig(), initial_mode=MODE_LOITER)
    run_px4(ap, 0.0, 1.0, rc=False)
    assert ap.arm(1.0, force=True) is MavResult.ACCEPTED  # armed with no stick input at all
    run_px4(ap, 1.0, 1.6, rc=False)
    assert ap.mode == MODE_LOITER and ap.failsafe is None
    assert ap.set_mode(1.6, main) is MavResult.ACCEPTED
    assert ap.mode == FlightMode(MainMode.POSCTL)
    assert ap.failsafe == "manual_control_loss"
    assert ap.system_status == 5  # CRITICAL
    assert (2, "Failsafe activated") in ap.drain_statustexts()
    assert ("failsafe", "DESCEND") in [(e.kind, e.detail.get("action")) for e in ap.drain_events()]
    # It descends: level, the collective below the hover's until it sinks at
    # MPC_LAND_SPEED (the real stack: about 0.6 m/s).
    ap.update(1.604, LEVEL, LEVEL, climb_rate_m_s=0.0)
    assert ap.last_torque_thrust[3] < ap.config.hover_thrust
    # Sticks back: the failsafe ends, the mode stays.
    run_px4(ap, 1.608, 1.7, rc=True)
    assert ap.failsafe is None and ap.mode == FlightMode(MainMode.POSCTL)
    assert ap.system_status == 4


@pytest.mark.parametrize(
    ("mode", "exceptions", "expected"),
    [
        (MODE_OFFBOARD, 0, MODE_LAND),  # PX4's default: RC loss fails safe in offboard too
        (MODE_OFFBOARD, 4, MODE_OFFBOARD),  # COM_RCL_EXCEPT bit 2
        (MODE_LOITER, 0, MODE_LAND),
        (MODE_LOITER, 2, MODE_LOITER),  # bit 1
        (MODE_LAND, 0, MODE_LAND),
    ],
)
def test_px4_rc_loss_exceptions(
    profile: VehicleProfile, mode: FlightMode, exceptions: int, expected: FlightMode
) -> None:
    ap = px4_flying(profile, mode, rc_loss_exceptions=exceptions)
    run_px4(ap, 1.004, 1.8, rc=False, offboard=mode == MODE_OFFBOARD)
    assert ap.mode == expected


def test_px4_rc_lost_at_arming_is_no_failsafe_until_rc_comes_back(
    profile: VehicleProfile,
) -> None:
    """A vehicle flown with no radio: PX4 ignores the RC-loss action (as
    ``_manual_control_lost_at_arming``) until RC has been seen and lost again."""
    ap = Autopilot(profile, AutopilotConfig(), initial_mode=MODE_OFFBOARD)
    ap.on_rates_target(0.0, LEVEL, 0.5)
    assert ap.arm(0.0) is MavResult.ACCEPTED
    run_px4(ap, 0.0, 2.0, rc=False, offboard=True)
    assert ap.mode == MODE_OFFBOARD
    assert ap.set_mode(2.0, MainMode.AUTO, 3) is MavResult.ACCEPTED
    run_px4(ap, 2.0, 3.0, rc=False)
    assert ap.mode == MODE_LOITER
    run_px4(ap, 3.0, 3.1, rc=True)
    run_px4(ap, 3.1, 3.8, rc=False)
    assert ap.mode == MODE_LAND


def test_px4_without_a_position(profile: VehicleProfile) -> None:
    ap = px4_flying(profile, FlightMode(MainMode.POSCTL))
    ap.position_valid = False
    run_px4(ap, 1.004, 1.05, rc=True)
    assert ap.mode.main == MainMode.ALTCTL  # POSCTL falls back
    assert ap.set_mode(1.05, MainMode.POSCTL) is MavResult.TEMPORARILY_REJECTED
    assert ap.set_mode(1.05, MainMode.AUTO, 3) is MavResult.TEMPORARILY_REJECTED
    assert ap.set_mode(1.05, MainMode.AUTO, 6) is MavResult.ACCEPTED
    ap2 = px4_flying(profile, MODE_LOITER)
    ap2.position_valid = False
    run_px4(ap2, 1.004, 1.05, rc=True)
    assert ap2.mode == MODE_LAND
    assert ap2.failsafe == "position_loss"


# ------------------------------------------------------------------ ArduPilot


def copter_flying(
    profile: VehicleProfile, mode: CopterMode, *params: tuple[str, float]
) -> ArduCopter:
    """Armed in the air in ``mode`` at t = 1 s, RC seen until then (the throttle at
    idle, then at mid-stick from arming on)."""
    ap = ArduCopter(profile, ArduCopterConfig(params=params), initial_mode=CopterMode.ALT_HOLD)
    t = 0.0
    while t < 1.0:
        ap.update(t, LEVEL, LEVEL, sticks_us=THROTTLE_DOWN)
        t += 0.0025
    assert ap.arm(t) is MavResult.ACCEPTED
    ap.update(t, LEVEL, LEVEL, sticks_us=STICKS)
    assert ap.set_mode(t, mode) is MavResult.ACCEPTED
    return ap


def run_copter(
    ap: ArduCopter, t0: float, t1: float, *, rc: bool, landed: bool = False, guided: bool = False
) -> None:
    t = t0
    while t < t1:
        if guided:
            ap.on_attitude_target(t, RATES, LEVEL, 0.5)
        ap.update(t, LEVEL, LEVEL, sticks_us=STICKS if rc else None, landed=landed)
        t += 0.0025


def test_ardupilot_radio_failsafe_lands_after_rc_fs_timeout(profile: VehicleProfile) -> None:
    ap = copter_flying(profile, CopterMode.ALT_HOLD)
    run_copter(ap, 1.0025, 1.95, rc=False)
    assert ap.mode is CopterMode.ALT_HOLD and not ap.failsafe_radio
    run_copter(ap, 1.95, 2.1, rc=False)
    assert ap.failsafe_radio
    assert ap.mode is CopterMode.RTL  # FS_THR_ENABLE 1: shown as RTL, flown as Land here
    assert ap.system_status == 5
    assert (4, "Radio Failsafe") in ap.drain_statustexts()
    # SYS_STATUS: the receiver is still there, no longer healthy.
    assert ap.rc_receiver(2.1) == (True, True, False)
    # STABILIZE and ACRO are refused during it; ALT_HOLD holds with zero inputs.
    assert ap.set_mode(2.1, CopterMode.STABILIZE) is MavResult.FAILED
    assert ap.set_mode(2.1, CopterMode.ALT_HOLD) is MavResult.ACCEPTED
    # RC back: cleared.
    run_copter(ap, 2.1, 2.2, rc=True)
    assert not ap.failsafe_radio


@pytest.mark.parametrize(("position", "expected"), [(True, CopterMode.BRAKE),
                                                    (False, CopterMode.LAND)])  # fmt: skip
def test_ardupilot_fs_thr_enable_7_brakes_with_a_position(
    profile: VehicleProfile, position: bool, expected: CopterMode
) -> None:
    ap = copter_flying(profile, CopterMode.ALT_HOLD, ("FS_THR_ENABLE", 7))
    ap.position_valid = position
    run_copter(ap, 1.0025, 2.2, rc=False)
    assert ap.mode is expected


@pytest.mark.parametrize(("options", "expected"), [(16, CopterMode.RTL),
                                                   (16 | 4, CopterMode.GUIDED_NOGPS)])  # fmt: skip
def test_ardupilot_radio_failsafe_in_guided_continues_only_with_fs_options_bit_2(
    profile: VehicleProfile, options: int, expected: CopterMode
) -> None:
    ap = copter_flying(profile, CopterMode.GUIDED_NOGPS, ("FS_OPTIONS", options))
    run_copter(ap, 1.0025, 2.2, rc=False, guided=True)
    assert ap.failsafe_radio
    assert ap.mode is expected


def test_ardupilot_radio_failsafe_on_the_ground_disarms(profile: VehicleProfile) -> None:
    ap = copter_flying(profile, CopterMode.ALT_HOLD)
    ap.drain_statustexts()
    run_copter(ap, 1.0025, 2.2, rc=False, landed=True)
    assert not ap.armed
    assert (4, "Radio Failsafe - Disarming") in ap.drain_statustexts()
    assert ap.system_status == 5  # CRITICAL while the failsafe is on, disarmed too


def test_ardupilot_armed_without_ever_seeing_rc_fails_safe(profile: VehicleProfile) -> None:
    """ArduPilot's radio failsafe needs RC seen once, or the vehicle armed."""
    ap = ArduCopter(profile, ArduCopterConfig(), initial_mode=CopterMode.GUIDED_NOGPS)
    run_copter(ap, 0.0, 2.0, rc=False)
    assert not ap.failsafe_radio  # disarmed, never seen: nothing
    assert ap.arm(2.0) is MavResult.ACCEPTED
    run_copter(ap, 2.0, 2.1, rc=False, guided=True)
    assert ap.failsafe_radio and ap.mode is CopterMode.RTL


def test_ardupilot_position_modes(profile: VehicleProfile) -> None:
    ap = copter_flying(profile, CopterMode.LOITER)
    ap.position_valid = False
    run_copter(ap, 1.0025, 1.01, rc=True)
    assert ap.mode is CopterMode.LAND  # the EKF failsafe
    assert ap.failsafe == "ekf"
    for mode in (CopterMode.LOITER, CopterMode.BRAKE):
        assert ap.set_mode(1.01, mode) is MavResult.FAILED
    assert ap.set_mode(1.01, CopterMode.ALT_HOLD) is MavResult.ACCEPTED
