"""The rules both autopilot personalities share (``sitl.personality``), checked on both."""

from __future__ import annotations

from pathlib import Path

import pytest

from companion.profile import VehicleProfile, load_profile
from sitl.ardupilot import ArduCopter, ArduCopterConfig
from sitl.autopilot import Autopilot, AutopilotConfig
from sitl.personality import MavResult, Personality, clip, stick_unit, throttle_unit

ROOT = Path(__file__).resolve().parents[2]
LEVEL = (0.0, 0.0, 0.0)
STICKS = (1500, 1500, 1500, 1500)


@pytest.fixture(scope="module")
def profile() -> VehicleProfile:
    return load_profile(ROOT / "vehicle_profiles" / "f450.yaml")


def make(stack: str, profile: VehicleProfile) -> Autopilot | ArduCopter:
    if stack == "px4":
        return Autopilot(profile, AutopilotConfig())
    # Radio failsafe off: these tests fly without RC unless they say otherwise.
    return ArduCopter(profile, ArduCopterConfig(params=(("FS_THR_ENABLE", 0.0),)))


STACKS = ("px4", "ardupilot")
REFUSAL = {"px4": MavResult.DENIED, "ardupilot": MavResult.FAILED}


@pytest.mark.parametrize("stack", STACKS)
def test_arming_twice_is_accepted_once_recorded(stack: str, profile: VehicleProfile) -> None:
    ap = make(stack, profile)
    assert isinstance(ap, Personality)
    assert ap.arm(0.0) is MavResult.ACCEPTED
    assert ap.arm(0.1) is MavResult.ACCEPTED
    assert [e.kind for e in ap.drain_events()] == ["armed"]
    assert ap.drain_events() == []


@pytest.mark.parametrize("stack", STACKS)
def test_disarm_in_the_air_needs_force(stack: str, profile: VehicleProfile) -> None:
    ap = make(stack, profile)
    assert ap.disarm(0.0) is MavResult.ACCEPTED  # already disarmed
    assert ap.arm(0.0) is MavResult.ACCEPTED
    ap.update(0.001, LEVEL, LEVEL, landed=False)
    assert ap.disarm(0.01) is REFUSAL[stack]
    assert ap.armed
    assert ap.disarm(0.02, force=True) is MavResult.ACCEPTED
    assert ap.motors == (0.0,) * profile.n_motors
    kinds = [(e.kind, e.detail.get("reason")) for e in ap.drain_events()]
    assert kinds == [("armed", None), ("disarm_denied", "in air"), ("disarmed", "command")]


@pytest.mark.parametrize("stack", STACKS)
def test_a_crash_disarms_holds_the_motors_and_refuses_arming(
    stack: str, profile: VehicleProfile
) -> None:
    ap = make(stack, profile)
    assert ap.arm(0.0) is MavResult.ACCEPTED
    ap.update(0.001, LEVEL, LEVEL, landed=False, crashed=True)
    assert ap.crashed and not ap.armed
    assert ap.update(0.002, LEVEL, LEVEL) == (0.0,) * profile.n_motors
    assert ap.arm(0.003, force=True) is REFUSAL[stack]
    kinds = [(e.kind, e.detail.get("reason")) for e in ap.drain_events()]
    assert kinds == [("armed", None), ("crashed", None), ("disarmed", "crash"),
                     ("arm_denied", "crashed")]  # fmt: skip


@pytest.mark.parametrize("stack", STACKS)
def test_rc_is_lost_after_the_stacks_own_timeout(stack: str, profile: VehicleProfile) -> None:
    ap = make(stack, profile)
    assert ap.rc_lost(0.0)  # none ever
    ap.update(1.0, LEVEL, LEVEL, sticks_us=STICKS)
    timeout = ap.rc_timeout_s
    assert timeout == (0.5 if stack == "px4" else 1.0)  # COM_RC_LOSS_T, RC_FS_TIMEOUT
    assert not ap.rc_lost(1.0 + timeout)
    assert ap.rc_lost(1.0 + timeout + 0.001)


@pytest.mark.parametrize("stack", STACKS)
def test_landed_state_follows_the_land_detector_and_the_stacks_land_mode(
    stack: str, profile: VehicleProfile
) -> None:
    ap = make(stack, profile)
    assert ap.landed_state == 1  # ON_GROUND
    assert ap.arm(0.0) is MavResult.ACCEPTED
    ap.update(0.001, LEVEL, LEVEL, landed=False)
    assert ap.landed_state == 2  # IN_AIR
    land = (4, 6) if stack == "px4" else (9,)
    assert ap.set_mode(0.002, *land) is MavResult.ACCEPTED
    assert ap.landed_state == 4  # LANDING
    assert ap.custom_mode == ap.mode.custom_mode


def test_stick_maps() -> None:
    assert clip(2.0, -1.0, 1.0) == 1.0 and clip(-2.0, -1.0, 1.0) == -1.0
    assert stick_unit(1500) == 0.0 and stick_unit(2000) == 1.0 and stick_unit(900) == -1.0
    assert throttle_unit(1000) == 0.0 and throttle_unit(1500) == 0.5 and throttle_unit(2100) == 1.0
