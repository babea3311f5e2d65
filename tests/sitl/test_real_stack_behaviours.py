"""What the real PX4 v1.16 and ArduCopter 4.5.6 SITL showed, reproduced by the personalities.

Flown against the real stacks (``sitl/lab/realstack``; docs/research/realstack.md):

* PX4 SIH has no radio: a ground station's ``MANUAL_CONTROL`` (any sysid) is its
  stick input; it streams its own ``MANUAL_CONTROL`` back on request (sysid 1,
  ``enabled_extensions`` 252), sends no ``RC_CHANNELS``; when the joystick stops for
  ``COM_RC_LOSS_T`` the stream stops, SYS_STATUS's RC bit goes from present and
  healthy to not present, and RC loss is acted on.
* ArduCopter keeps streaming ``RC_CHANNELS`` with the last values after the radio is
  lost, clears the receiver's health in SYS_STATUS after ``RC_FS_TIMEOUT``, shows
  CRITICAL and says "Radio Failsafe".
* ArduCopter refuses to arm until its EKF has an altitude estimate ("Arm: Need Alt
  Estimate") and, in a mode that needs one, a position ("PreArm: Need Position
  Estimate"); SYS_STATUS's pre-arm bit is healthy only when its checks pass.
* PX4 answers a request for its ``MANUAL_CONTROL`` stream with one frame at once
  (x 0, y 0, z 500, r 0, ``enabled_extensions`` 252), a joystick there or not.
* ArduCopter refuses to arm with the throttle up: "Arm: Throttle (RC3) is not
  neutral" in GUIDED_NOGPS at 1100, 1250, 1400 and 1500 us, armed at 1000 us
  (``RC3_MIN`` 1000); "Arm: Throttle too high" where its own checks run first.
* ArduCopter taking off in GUIDED_NOGPS with ``GUID_OPTIONS`` 8 says "Internal
  Errors 0x100000" once and flies on.
* ArduCopter with no GUIDED target for ``GUID_TIMEOUT`` (the companion killed)
  levels and holds, in GUIDED_NOGPS, flying.
* PX4 with no offboard setpoint for ``COM_OF_LOSS_T`` (the companion killed) says
  "Failsafe activated", shows CRITICAL and flies ``COM_OBL_RC_ACT``'s mode
  (Position mode, POSCTL) while the joystick is there.
* PX4 shows an accepted arming or mode change at its next 1 Hz HEARTBEAT;
  ArduCopter sends a HEARTBEAT with the new mode at once, also when the mode is
  its own failsafe's (RTL on a lost radio).

Each face runs in this process on a real UDP socket with a ground station
(``tests/sitl/udp_client.py``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink2

from companion.profile import VehicleProfile, load_profile
from sitl.ardupilot import ArduCopter, ArduCopterConfig
from sitl.ardupilot_face import ArduPilotFace, ardupilot_streams
from sitl.ardupilot_modes import CopterMode
from sitl.autopilot import Autopilot, AutopilotConfig, Joystick, joystick_channels
from sitl.frames import quat_to_euler_rad
from sitl.imu import Imu
from sitl.mavlink_link import parse_endpoint
from sitl.personality import FirmwareVersion, MavResult
from sitl.physics import Quadrotor
from sitl.px4_face import Px4Face, px4_streams
from sitl.px4_modes import MODE_LAND, MODE_LOITER, MODE_OFFBOARD, FlightMode, MainMode
from sitl.px4_params import Px4Params
from sitl.rotors import hover_motor_command
from sitl.runner import joystick_from_channels
from tests.sitl.plant import autopilot_on_imu
from tests.sitl.udp_client import Client

ROOT = Path(__file__).resolve().parents[2]
LEVEL = (0.0, 0.0, 0.0)
RC_BIT = mavlink2.MAV_SYS_STATUS_SENSOR_RC_RECEIVER
PREARM_BIT = mavlink2.MAV_SYS_STATUS_PREARM_CHECK
MANUAL_CONTROL = mavlink2.MAVLINK_MSG_ID_MANUAL_CONTROL
RATES = 128  # ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE: body rates + thrust


@pytest.fixture(scope="module")
def profile() -> VehicleProfile:
    return load_profile(ROOT / "vehicle_profiles" / "f450.yaml")


def px4_face(profile: VehicleProfile, client: Client) -> Px4Face:
    ap = Autopilot(profile, AutopilotConfig(rc_loss_timeout_s=1.0))
    face = Px4Face(parse_endpoint(f"udpout:127.0.0.1:{client.port}"), ap, px4_streams(250))
    face.rc_fitted = False  # PX4 SIH: no receiver
    return face.open()


def publish(face: Any, client: Client, t_s: float) -> list[Any]:
    face.snapshot.t_s = t_s
    face.publish(t_s, imu_sample=False, wall_s=t_s)
    return [m for m in client.received(0.02) if m.get_type() != "BAD_DATA"]


def sys_status(msgs: list[Any]) -> Any:
    (st,) = [m for m in msgs if m.get_type() == "SYS_STATUS"]
    return st


# ------------------------------------------------------------------ PX4 joystick


def test_the_pilots_channels_as_a_joystick_and_back() -> None:
    chans = (1600, 1400, 1650, 1300, 2000, 1000)
    j = joystick_from_channels(chans)
    # x pitch forward +: a low pitch channel (stick forward, nose down) is +x.
    assert (j.x, j.y, j.z, j.r) == (200, 200, 650, -400)
    assert j.enabled_extensions == 4 | 8 and j.aux[:2] == (1000, -1000)
    assert joystick_channels(j)[:6] == chans


def test_px4_takes_a_joystick_streams_it_back_and_sends_no_rc_channels(
    profile: VehicleProfile, client: Client
) -> None:
    face = px4_face(profile, client)
    ap = face.autopilot
    try:
        client.mav.command_long_send(
            1, 1, mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, 0, MANUAL_CONTROL, 20_000, 0, 0, 0, 0, 0
        )
        assert [m.result for m in client.exchange(face) if m.get_type() == "COMMAND_ACK"] == [0]
        # A ground station's joystick, from its own sysid (255): aux1 high.
        client.mav.manual_control_send(1, 100, -200, 600, 50, 0, 0, 4, 0, 0, 1000)
        client.send_last(face)
        face.poll(0.0)
        assert ap._last_sticks[:5] == (1400, 1450, 1600, 1525, 2000)
        msgs = publish(face, client, 0.0)
        (mc,) = [m for m in msgs if m.get_type() == "MANUAL_CONTROL"]
        assert mc.get_srcSystem() == 1 and mc.get_srcComponent() == 1 and mc.target == 1
        assert (mc.x, mc.y, mc.z, mc.r, mc.enabled_extensions, mc.aux1) == (
            100, -200, 600, 50, 252, 1000,
        )  # fmt: skip
        assert not [m for m in msgs if m.get_type() == "RC_CHANNELS"]
        st = sys_status(msgs)
        assert st.onboard_control_sensors_present & RC_BIT
        assert st.onboard_control_sensors_health & RC_BIT
        # The joystick stops: after COM_RC_LOSS_T (1 s) no more MANUAL_CONTROL, the RC
        # bit not present.
        msgs = publish(face, client, 1.1)
        assert not [m for m in msgs if m.get_type() == "MANUAL_CONTROL"]
        assert not sys_status(msgs).onboard_control_sensors_present & RC_BIT
    finally:
        face.close()


def test_px4_acts_on_a_lost_joystick(profile: VehicleProfile) -> None:
    ap = Autopilot(profile, AutopilotConfig(rc_loss_timeout_s=1.0))
    t = 0.0
    while t < 1.0:
        ap.on_manual_control(t, Joystick(0, 0, 500, 0))
        ap.update(t, LEVEL, LEVEL, landed=False)
        t += 0.01
    assert ap.arm(t, force=True) is MavResult.ACCEPTED
    assert ap.set_mode(t, MainMode.POSCTL) is MavResult.ACCEPTED
    t0 = t
    while t < t0 + 1.2:
        ap.update(t, LEVEL, LEVEL, landed=False)
        t += 0.004
    assert ap.mode == MODE_LAND and ap.failsafe == "rc_loss"  # NAV_RCL_ACT 2, flown as Land


def test_px4_ignores_a_joystick_when_told_rc_only(profile: VehicleProfile) -> None:
    ap = Autopilot(profile, AutopilotConfig())
    ap.params.set("COM_RC_IN_MODE", 0)
    assert not ap.on_manual_control(0.0, Joystick(0, 0, 500, 0))
    ap.params.set("COM_RC_IN_MODE", 1)
    assert ap.on_manual_control(0.0, Joystick(0, 0, 500, 0))
    assert not ap.on_manual_control(0.0, Joystick(0, 0, 1500, 0))  # z beyond 0..1000


def test_px4_prearm_bit(profile: VehicleProfile, client: Client) -> None:
    face = px4_face(profile, client)
    try:
        st = sys_status(publish(face, client, 0.0))
        assert st.onboard_control_sensors_present & PREARM_BIT
        assert st.onboard_control_sensors_health & PREARM_BIT
    finally:
        face.close()


# ------------------------------------------------------------ ArduCopter radio loss


def copter_face(profile: VehicleProfile, client: Client, **cfg: Any) -> ArduPilotFace:
    ap = ArduCopter(profile, ArduCopterConfig(**cfg), initial_mode=CopterMode.ALT_HOLD)
    face = ArduPilotFace(
        parse_endpoint(f"udpout:127.0.0.1:{client.port}"), ap, ardupilot_streams(400.0)
    )
    face.rc_lost_freezes = True
    return face.open()


STICKS = (1520, 1480, 1500, 1510, 1000, 1000)


@contextmanager
def armed_copter(profile: VehicleProfile, client: Client) -> Iterator[tuple[ArduPilotFace, float]]:
    """A :func:`copter_face` given 1 s of ``STICKS``, then armed: the face and the time
    it armed; closed after."""
    face = copter_face(profile, client)
    try:
        ap, t = face.autopilot, 0.0
        while t < 1.0:
            ap.update(t, LEVEL, LEVEL, landed=False, sticks_us=STICKS)
            t += 0.0025
        assert ap.arm(t, force=True) is MavResult.ACCEPTED
        face.snapshot.sticks_us = STICKS
        yield face, t
    finally:
        face.close()


def test_ardupilot_radio_lost_keeps_rc_channels_frozen_and_fails_safe(
    profile: VehicleProfile, client: Client
) -> None:
    with armed_copter(profile, client) as (face, t):
        ap = face.autopilot
        before = [m for m in publish(face, client, t) if m.get_type() == "RC_CHANNELS"]
        assert before[0].chancount == 6 and before[0].chan1_raw == 1520
        # Radio lost (the rc-lost fault): ArduPilot keeps the last values.
        face.rc_lost = True
        face.snapshot.sticks_us = (1900,) * 6
        t_lost = t
        while t < t_lost + 1.2:
            ap.update(t, LEVEL, LEVEL, landed=False)
            t += 0.0025
        msgs = publish(face, client, t + 0.2)
        (rc,) = [m for m in msgs if m.get_type() == "RC_CHANNELS"]
        assert (rc.chancount, rc.chan1_raw, rc.chan2_raw, rc.rssi) == (
            6, 1520, 1480, before[0].rssi,
        )  # fmt: skip
        st = sys_status(msgs)
        assert st.onboard_control_sensors_present & RC_BIT
        assert not st.onboard_control_sensors_health & RC_BIT  # after RC_FS_TIMEOUT
        (hb,) = [m for m in msgs if m.get_type() == "HEARTBEAT"]
        assert hb.system_status == mavlink2.MAV_STATE_CRITICAL
        assert hb.custom_mode == CopterMode.RTL  # FS_THR_ENABLE 1
        texts = [m.text for m in msgs if m.get_type() == "STATUSTEXT"]
        assert "Radio Failsafe" in texts


# ----------------------------------------------------------- ArduCopter arming


def test_ardupilot_refuses_to_arm_until_its_ekf_is_ready(
    profile: VehicleProfile, client: Client
) -> None:
    face = copter_face(profile, client, ekf_alt_ready_s=3.0, ekf_position_ready_s=45.0)
    ap = face.autopilot
    try:
        st = sys_status(publish(face, client, 2.5))
        assert st.onboard_control_sensors_present & PREARM_BIT
        assert not st.onboard_control_sensors_health & PREARM_BIT
        assert ap.arm(2.5) is MavResult.FAILED
        assert (2, "Arm: Need Alt Estimate") in ap.drain_statustexts()
        # A mode that needs a position waits for the position estimate.
        assert ap.set_mode(3.5, CopterMode.LOITER) is MavResult.ACCEPTED
        assert ap.arm(3.5) is MavResult.FAILED
        assert (2, "PreArm: Need Position Estimate") in ap.drain_statustexts()
        assert ap.set_mode(3.5, CopterMode.ALT_HOLD) is MavResult.ACCEPTED
        assert sys_status(publish(face, client, 3.5)).onboard_control_sensors_health & PREARM_BIT
        assert ap.arm(3.5) is MavResult.ACCEPTED
        ap.disarm(3.6)
        assert ap.set_mode(46.0, CopterMode.LOITER) is MavResult.ACCEPTED
        assert ap.arm(46.0) is MavResult.ACCEPTED
    finally:
        face.close()


def test_ardupilot_ekf_warmup_is_off_by_default(profile: VehicleProfile) -> None:
    ap = ArduCopter(profile, ArduCopterConfig(), initial_mode=CopterMode.GUIDED_NOGPS)
    assert ap.arm(0.0) is MavResult.ACCEPTED


def test_heartbeat_critical_in_every_failsafe(profile: VehicleProfile) -> None:
    px4 = Autopilot(profile, AutopilotConfig())
    px4.failsafe = "offboard_loss"
    assert px4.system_status == 5  # disarmed too
    ap = ArduCopter(profile, ArduCopterConfig())
    ap.failsafe_radio = True
    assert ap.system_status == 5
    assert FlightMode(MainMode.POSCTL).name == "POSCTL"


# ------------------------------------------------- PX4's answer to the stream request


def request_manual_control(face: Px4Face, client: Client, interval_us: float) -> None:
    client.mav.command_long_send(
        1, 1, mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, 0, MANUAL_CONTROL, interval_us, 0, 0, 0, 0, 0
    )
    assert [m.result for m in client.exchange(face) if m.get_type() == "COMMAND_ACK"] == [0]


def manual_controls(msgs: list[Any]) -> list[Any]:
    return [m for m in msgs if m.get_type() == "MANUAL_CONTROL"]


def test_px4_answers_the_manual_control_request_with_one_frame_without_a_joystick(
    profile: VehicleProfile, client: Client
) -> None:
    face = px4_face(profile, client)
    try:
        request_manual_control(face, client, 20_000)
        (mc,) = manual_controls(publish(face, client, 0.0))
        assert (mc.get_srcSystem(), mc.get_srcComponent(), mc.target) == (1, 1, 1)
        assert (mc.x, mc.y, mc.z, mc.r, mc.enabled_extensions) == (0, 0, 500, 0, 252)
        assert (mc.aux1, mc.aux2, mc.aux3, mc.aux4, mc.aux5, mc.aux6) == (0,) * 6
        # No joystick: nothing more, and asking again while the stream is on sends none.
        assert not manual_controls(publish(face, client, 0.02))
        request_manual_control(face, client, 20_000)
        assert not manual_controls(publish(face, client, 0.04) + publish(face, client, 1.0))
        # Off, then asked for again: a new stream, a new first frame.
        request_manual_control(face, client, -1)
        request_manual_control(face, client, 20_000)
        assert len(manual_controls(publish(face, client, 1.1))) == 1
        assert not manual_controls(publish(face, client, 1.2))
    finally:
        face.close()


# ------------------------------------------------------ ArduCopter's throttle at arming


def copter_with_throttle(
    profile: VehicleProfile, mode: CopterMode, throttle_us: int, *params: tuple[str, float]
) -> ArduCopter:
    """Disarmed in ``mode``, the radio's sticks centred but the throttle at ``throttle_us``."""
    ap = ArduCopter(profile, ArduCopterConfig(params=params), initial_mode=mode)
    for k in range(5):
        ap.update(k * 0.0025, LEVEL, LEVEL, landed=True, sticks_us=(1500, 1500, throttle_us, 1500))
    return ap


NOT_NEUTRAL = "Arm: Throttle (RC3) is not neutral"
TOO_HIGH = "Arm: Throttle too high"


@pytest.mark.parametrize(
    ("mode", "throttle_us", "refusal"),
    [
        # Measured on ArduCopter 4.5.6 (RC3_MIN 1000): GUIDED_NOGPS, armed from the GCS.
        (CopterMode.GUIDED_NOGPS, 1000, None),
        (CopterMode.GUIDED_NOGPS, 1100, NOT_NEUTRAL),
        (CopterMode.GUIDED_NOGPS, 1250, NOT_NEUTRAL),
        (CopterMode.GUIDED_NOGPS, 1400, NOT_NEUTRAL),
        (CopterMode.GUIDED_NOGPS, 1500, NOT_NEUTRAL),
        (CopterMode.GUIDED_NOGPS, 1900, NOT_NEUTRAL),  # no "too high" from the GCS in guided
        (CopterMode.GUIDED, 1500, NOT_NEUTRAL),
        # Within RC3_DZ (30 us) above RC3_MIN the throttle reads zero.
        (CopterMode.GUIDED_NOGPS, 1030, None),
        (CopterMode.GUIDED_NOGPS, 1031, NOT_NEUTRAL),
        # A climb-rate mode: above the mid-stick dead band (THR_DZ) asks a climb first.
        (CopterMode.ALT_HOLD, 1000, None),
        (CopterMode.ALT_HOLD, 1100, NOT_NEUTRAL),
        (CopterMode.ALT_HOLD, 1500, NOT_NEUTRAL),
        (CopterMode.ALT_HOLD, 1700, TOO_HIGH),
        (CopterMode.LOITER, 1700, TOO_HIGH),
        # Manual throttle: anything above zero is too high.
        (CopterMode.STABILIZE, 1000, None),
        (CopterMode.STABILIZE, 1100, TOO_HIGH),
        (CopterMode.ACRO, 1100, TOO_HIGH),
    ],
    ids=lambda v: v.name if isinstance(v, CopterMode) else None,
)
def test_ardupilot_refuses_to_arm_with_the_throttle_up(
    profile: VehicleProfile, mode: CopterMode, throttle_us: int, refusal: str | None
) -> None:
    ap = copter_with_throttle(profile, mode, throttle_us)
    assert ap.prearm_ok(0.01)  # an arming check, not a pre-arm one: SYS_STATUS says ready
    if refusal is None:
        assert ap.arm(0.01) is MavResult.ACCEPTED
        assert ap.drain_statustexts() == []
    else:
        assert ap.arm(0.01) is MavResult.FAILED
        assert ap.drain_statustexts() == [(2, refusal)]
        assert not ap.armed


@pytest.mark.parametrize(
    "params",
    [
        (("ARMING_CHECK", 0.0),),  # no checks
        (("ARMING_CHECK", 2.0),),  # checks, but not RC (bit 6)
        (("RC_OPTIONS", 0.0),),  # bit 5 off: the throttle need not be idle...
    ],
)
def test_ardupilot_throttle_arming_check_follows_its_parameters(
    profile: VehicleProfile, params: tuple[tuple[str, float], ...]
) -> None:
    ap = copter_with_throttle(profile, CopterMode.GUIDED_NOGPS, 1500, *params)
    assert ap.arm(0.01) is MavResult.ACCEPTED


def test_ardupilot_throttle_arming_check_needs_a_radio(profile: VehicleProfile) -> None:
    # ...and Copter's own "too high" still runs without bit 5 (RC_OPTIONS 0).
    ap = copter_with_throttle(profile, CopterMode.ALT_HOLD, 1700, ("RC_OPTIONS", 0.0))
    assert ap.arm(0.01) is MavResult.FAILED
    assert ap.drain_statustexts() == [(2, TOO_HIGH)]
    # Force-arming (param2 2989) skips it; no radio frame within a second: not checked.
    assert ap.arm(0.02, force=True) is MavResult.ACCEPTED
    ap = copter_with_throttle(profile, CopterMode.GUIDED_NOGPS, 1500)
    assert ap.arm(1.5) is MavResult.ACCEPTED
    assert ArduCopter(profile, initial_mode=CopterMode.STABILIZE).arm(0.0) is MavResult.ACCEPTED


# ------------------------------------ ArduCopter: GUIDED_NOGPS, thrust as thrust, alone


def fly_guided_thrust(
    profile: VehicleProfile, *, targets_until_s: float, end_s: float
) -> tuple[ArduCopter, list[tuple[int, str]], Any]:
    """Take off in GUIDED_NOGPS with ``GUID_OPTIONS`` 8 (thrust 0.7 for 1 s, then the
    hover throttle), roll at 0.5 rad/s from 2 s to 2.2 s, and send no target after
    ``targets_until_s`` (the companion killed); fly to ``end_s``. Returns the
    autopilot, its STATUSTEXTs and the vehicle's last state."""
    quad = Quadrotor(profile, rng=np.random.default_rng(1), dt_s=0.001)
    imu = Imu(profile.physics.imu, rng=np.random.default_rng(2), dt_s=0.001)
    ap = ArduCopter(
        profile,
        ArduCopterConfig(
            hover_motor_cmd=hover_motor_command(profile),
            params=(("FS_THR_ENABLE", 0.0), ("GUID_OPTIONS", 8.0)),  # no radio here
        ),
        initial_mode=CopterMode.GUIDED_NOGPS,
    )
    assert ap.arm(0.0) is MavResult.ACCEPTED
    texts: list[tuple[int, str]] = []
    motors: tuple[float, ...] = (0.0,) * 4
    while quad.t_s < end_s:
        t = quad.t_s
        if t < targets_until_s and quad.steps % 4 == 0:  # 250 Hz, a companion's rate
            thrust = 0.7 if t < 1.0 else ap.hover_throttle
            ap.on_attitude_target(t, RATES, (0.5 if 2.0 <= t < 2.2 else 0.0, 0.0, 0.0), thrust)
        out = autopilot_on_imu(ap, imu, quad)
        if out is not None:
            motors = out
            texts += ap.drain_statustexts()
        quad.step(motors)
    return ap, texts, quad.state


def test_ardupilot_thrust_take_off_raises_an_internal_error_once_and_flies_on(
    profile: VehicleProfile,
) -> None:
    ap, texts, st = fly_guided_thrust(profile, targets_until_s=4.0, end_s=4.0)
    assert texts == [(2, "Internal Errors 0x100000")]
    assert ap.armed and ap.mode is CopterMode.GUIDED_NOGPS
    assert -st.pos_ned_m[2] > 1.0 and not st.crashed
    # The error stays until a reboot: landed and disarmed, it refuses to arm again.
    ap.update(5.0, LEVEL, LEVEL, landed=True)
    assert ap.disarm(5.0) is MavResult.ACCEPTED
    assert not ap.prearm_ok(5.0)
    assert ap.arm(5.0) is MavResult.FAILED
    assert ap.drain_statustexts() == [(2, "PreArm: Internal errors 0x100000 l:57 flow_of_ctrl")]
    assert ap.arm(5.0, force=True) is MavResult.ACCEPTED


def test_ardupilot_climb_rate_take_off_raises_no_internal_error(profile: VehicleProfile) -> None:
    ap = ArduCopter(
        profile, ArduCopterConfig(params=(("FS_THR_ENABLE", 0.0),)),
        initial_mode=CopterMode.GUIDED_NOGPS,
    )  # fmt: skip
    assert ap.arm(0.0) is MavResult.ACCEPTED
    ap.on_attitude_target(0.0, RATES, LEVEL, 0.9)  # GUID_OPTIONS 0: climb at 2 m/s
    for k in range(100):
        ap.update(k * 0.0025, LEVEL, LEVEL, landed=True)
    assert ap.drain_statustexts() == []
    assert ap.prearm_ok(1.0)


def test_ardupilot_left_without_targets_levels_and_holds_in_guided_nogps(
    profile: VehicleProfile,
) -> None:
    """The companion killed while engaged: GUID_TIMEOUT (3 s) later the vehicle is
    level, in GUIDED_NOGPS, flying, as the real ArduCopter 4.5.6 was (silently)."""
    ap, texts, st = fly_guided_thrust(profile, targets_until_s=2.3, end_s=9.0)
    assert texts == [(2, "Internal Errors 0x100000")]  # nothing about the timeout
    assert [e.kind for e in ap.drain_events()].count("guided_timeout") == 1
    assert ap.armed and ap.mode is CopterMode.GUIDED_NOGPS and not st.landed
    roll, pitch, _ = quat_to_euler_rad(st.q_wxyz)
    assert abs(roll) < math.radians(2.0) and abs(pitch) < math.radians(2.0)
    assert max(abs(r) for r in st.rate_frd_rad_s) < math.radians(5.0)
    assert abs(st.vel_ned_m_s[2]) < 0.3  # holding its height, not sinking


# --------------------------------------------------------------- ArduCopter signing


def test_ardupilot_setup_signing_is_not_handled_by_the_sitl(
    profile: VehicleProfile, client: Client
) -> None:
    """The SITL signs only with a key given at start (``sitl run --signing-key``):
    SETUP_SIGNING changes nothing (ArduCopter 4.5.6 takes it disarmed:
    docs/research/ardupilot.md)."""
    face = copter_face(profile, client)
    try:
        client.mav.setup_signing_send(1, 1, [7] * 32, 1)
        client.send_last(face)
        face.poll(0.0)
        assert face.messages_received == 1
        assert not face.mav.signing.sign_outgoing and face.mav.signing.secret_key is None
    finally:
        face.close()


# ------------------------------------------------------ PX4: the companion killed


def px4_in_offboard(
    profile: VehicleProfile, firmware: FirmwareVersion, *, joystick: bool
) -> tuple[Autopilot, float]:
    """Flying in OFFBOARD on body rates for 1 s, the joystick's frames coming (or none)."""
    ap = Autopilot(profile, AutopilotConfig(), params=Px4Params(firmware))
    t = 0.0
    while t < 1.0:
        ap.on_rates_target(t, LEVEL, 0.5)
        if joystick:
            ap.on_manual_control(t, Joystick(0, 0, 500, 0))
        if abs(t - 0.5) < 1e-9:
            assert ap.set_mode(t, MainMode.OFFBOARD) is MavResult.ACCEPTED
            assert ap.arm(t) is MavResult.ACCEPTED
        ap.update(t, LEVEL, LEVEL, landed=False)
        t = round(t + 0.02, 6)
    assert ap.mode == MODE_OFFBOARD and ap.armed
    ap.drain_statustexts()
    return ap, t


def without_setpoints(ap: Autopilot, t0: float, t1: float, *, joystick: bool) -> float:
    t = t0
    while t < t1:
        if joystick:
            ap.on_manual_control(t, Joystick(0, 0, 500, 0))
        ap.update(t, LEVEL, LEVEL, landed=False)
        t = round(t + 0.02, 6)
    return t


PX4_116 = FirmwareVersion(1, 16, 0)


def test_px4_killed_companion_with_a_joystick_falls_back_to_position_mode(
    profile: VehicleProfile,
) -> None:
    ap, t = px4_in_offboard(profile, PX4_116, joystick=True)
    t = without_setpoints(ap, t, t + 0.96, joystick=True)  # within COM_OF_LOSS_T (1 s)
    assert ap.mode == MODE_OFFBOARD and ap.failsafe is None
    t = without_setpoints(ap, t, t + 0.1, joystick=True)
    assert ap.mode == FlightMode(MainMode.POSCTL)  # COM_OBL_RC_ACT 0: Position mode
    assert ap.failsafe == "offboard_loss" and ap.system_status == 5  # CRITICAL
    assert ap.drain_statustexts() == [(2, "Failsafe activated")]
    assert ap.armed
    # The fallback lasts while the setpoints do not come: when they do, OFFBOARD again.
    ap.on_rates_target(t, LEVEL, 0.5)
    ap.update(t, LEVEL, LEVEL, landed=False)
    assert ap.mode == MODE_OFFBOARD and ap.failsafe is None and ap.system_status == 4


@pytest.mark.parametrize(
    ("firmware", "joystick", "params", "expected"),
    [
        (PX4_116, True, (("COM_OBL_RC_ACT", 1),), FlightMode(MainMode.ALTCTL)),
        (PX4_116, True, (("COM_OBL_RC_ACT", 2),), FlightMode(MainMode.STABILIZED)),
        (PX4_116, True, (("COM_OBL_RC_ACT", 4),), MODE_LAND),
        (PX4_116, True, (("COM_OBL_RC_ACT", 5),), MODE_LOITER),
        # No stick input: the manual modes cannot run, PX4 >= 1.14 falls through to Hold.
        (PX4_116, False, (), MODE_LOITER),
        # PX4 1.13 without RC: COM_OBL_ACT (0 Land, 1 Hold); with it, COM_OBL_RC_ACT.
        (FirmwareVersion(1, 13, 3), False, (), MODE_LAND),
        (FirmwareVersion(1, 13, 3), False, (("COM_OBL_ACT", 1),), MODE_LOITER),
        (FirmwareVersion(1, 13, 3), True, (), FlightMode(MainMode.POSCTL)),
    ],
)
def test_px4_offboard_loss_flies_com_obl_rc_act(
    profile: VehicleProfile,
    firmware: FirmwareVersion,
    joystick: bool,
    params: tuple[tuple[str, int], ...],
    expected: FlightMode,
) -> None:
    ap, t = px4_in_offboard(profile, firmware, joystick=joystick)
    for name, value in params:
        ap.params.set(name, value)
    without_setpoints(ap, t, t + 1.1, joystick=joystick)
    assert ap.mode == expected and ap.failsafe == "offboard_loss" and ap.armed


@pytest.mark.parametrize(("value", "kind"), [(6, "TERMINATE"), (7, "DISARM")])
def test_px4_offboard_loss_terminates_or_disarms(
    profile: VehicleProfile, value: int, kind: str
) -> None:
    ap, t = px4_in_offboard(profile, PX4_116, joystick=True)
    ap.params.set("COM_OBL_RC_ACT", value)
    ap.drain_events()
    without_setpoints(ap, t, t + 1.1, joystick=True)
    assert not ap.armed and ap.failsafe == "offboard_loss"
    assert [e.detail.get("action") for e in ap.drain_events() if e.kind == "failsafe"] == [kind]


def test_px4_offboard_fallback_without_a_position_is_altitude_mode(
    profile: VehicleProfile,
) -> None:
    ap, t = px4_in_offboard(profile, PX4_116, joystick=True)
    ap.position_valid = False
    without_setpoints(ap, t, t + 1.1, joystick=True)
    assert ap.mode == FlightMode(MainMode.ALTCTL)


def test_px4_offboard_fallback_ends_with_a_mode_change(profile: VehicleProfile) -> None:
    ap, t = px4_in_offboard(profile, PX4_116, joystick=True)
    t = without_setpoints(ap, t, t + 1.1, joystick=True)
    assert ap.mode == FlightMode(MainMode.POSCTL)
    assert ap.set_mode(t, MainMode.ALTCTL) is MavResult.ACCEPTED  # the pilot's choice
    ap.on_rates_target(t, LEVEL, 0.5)
    ap.update(t, LEVEL, LEVEL, landed=False)
    assert ap.mode == FlightMode(MainMode.ALTCTL) and ap.failsafe is None


# ------------------------------------------------- when a new state is announced


def heartbeats(msgs: list[Any]) -> list[Any]:
    return [m for m in msgs if m.get_type() == "HEARTBEAT"]


def test_px4_shows_an_accepted_arming_and_mode_at_its_next_1hz_heartbeat(
    profile: VehicleProfile, client: Client
) -> None:
    # The real PX4: SET_MODE at 2.013 s, its ACK at 2.015 s, a heartbeat at 2.023 s
    # still in the old mode and the next, at 3.033 s, in the new one
    # (docs/research/realstack.md#engaged-edge).
    face = px4_face(profile, client)
    try:
        assert len(heartbeats(publish(face, client, 0.0))) == 1
        client.mav.command_long_send(
            1, 1, mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 21196, 0, 0, 0, 0, 0
        )
        assert [m.result for m in client.exchange(face, 0.3) if m.get_type() == "COMMAND_ACK"] == [
            0
        ]
        client.mav.command_long_send(
            1, 1, mavlink2.MAV_CMD_DO_SET_MODE, 0, 1, MainMode.POSCTL, 0, 0, 0, 0, 0
        )
        assert [m.result for m in client.exchange(face, 0.4) if m.get_type() == "COMMAND_ACK"] == [
            0
        ]
        assert heartbeats(publish(face, client, 0.5)) == []
        (hb,) = heartbeats(publish(face, client, 1.0))
        assert hb.base_mode & mavlink2.MAV_MODE_FLAG_SAFETY_ARMED
        assert (hb.custom_mode >> 16) & 0xFF == MainMode.POSCTL
    finally:
        face.close()


def test_ardupilot_shows_an_accepted_mode_at_once(profile: VehicleProfile, client: Client) -> None:
    face = copter_face(profile, client)
    try:
        assert len(heartbeats(publish(face, client, 0.0))) == 1
        client.mav.command_long_send(
            1, 1, mavlink2.MAV_CMD_DO_SET_MODE, 0, 1, CopterMode.STABILIZE, 0, 0, 0, 0, 0
        )
        assert [m.result for m in client.exchange(face, 0.3) if m.get_type() == "COMMAND_ACK"] == [
            0
        ]
        (hb,) = heartbeats(publish(face, client, 0.3))
        assert hb.custom_mode == CopterMode.STABILIZE
    finally:
        face.close()


def test_ardupilot_shows_its_own_failsafe_mode_at_once(
    profile: VehicleProfile, client: Client
) -> None:
    # The real ArduCopter 4.5.6, radio lost (SIM_RC_FAIL=1) in ALT_HOLD three times:
    # the heartbeat showing RTL and CRITICAL came 1.097-1.098 s later each time, off
    # its 1 Hz beat (the beats before it 0.093, 0.388 and 0.694 s after the loss).
    with armed_copter(profile, client) as (face, t):
        ap = face.autopilot
        beats = [t] * len(heartbeats(publish(face, client, t)))
        assert beats  # the arming's
        face.rc_lost = True
        t_lost, changed_at = t + 0.5, None
        while t < t_lost + 2.0:
            ap.update(t, LEVEL, LEVEL, landed=False, sticks_us=None if t >= t_lost else STICKS)
            if changed_at is None and ap.mode == CopterMode.RTL:
                changed_at = t
            msgs = publish(face, client, t)
            beats += [t] * len(heartbeats(msgs))
            if changed_at == t:
                (hb,) = heartbeats(msgs)
                assert hb.custom_mode == CopterMode.RTL
                assert hb.system_status == mavlink2.MAV_STATE_CRITICAL
            t += 0.1
        assert changed_at is not None and t_lost + 0.9 < changed_at < t_lost + 1.2
        before = max(b for b in beats if b < changed_at)
        assert changed_at - before < 0.9  # not the 1 Hz beat: sent with the change
