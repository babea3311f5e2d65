"""The PX4 personality's parameters and firmware, over real UDP against the face:
PX4's parameter protocol (bytewise INT32, type-checked PARAM_SET, _HASH_CHECK),
the table's defaults, the parameters the autopilot follows, ``--firmware``."""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner

from companion.profile import VehicleProfile, load_profile
from sitl.autopilot import Autopilot, AutopilotConfig
from sitl.cli import cli as sitl_cli
from sitl.mavlink_link import parse_endpoint
from sitl.personality import FirmwareVersion, MavResult
from sitl.px4_face import Px4Face, px4_streams
from sitl.px4_modes import MainMode
from sitl.px4_params import (
    PARAM_INT32,
    PARAM_REAL32,
    PARAM_UINT32,
    Px4Params,
    decode_bytewise,
    encode_bytewise,
)
from sitl.runner import RunConfig, Runner
from tests.sitl.udp_client import Client

ROOT = Path(__file__).resolve().parents[2]
F450 = ROOT / "vehicle_profiles" / "f450.yaml"
LEVEL = (0.0, 0.0, 0.0)
RATES = 128  # ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE
CAP_BYTEWISE = 16
CAP_SET_ACTUATOR_TARGET = 1024
CAP_C_CAST = 131072


@pytest.fixture(scope="module")
def profile() -> VehicleProfile:
    return load_profile(F450)


def open_face(
    profile: VehicleProfile, client: Client, firmware: FirmwareVersion | None = None
) -> Px4Face:
    ap = Autopilot(profile, AutopilotConfig(), params=Px4Params(firmware or _default()))
    kw = {} if firmware is None else {"firmware": firmware}
    face = Px4Face(parse_endpoint(f"udpout:127.0.0.1:{client.port}"), ap, px4_streams(250), **kw)
    return face.open()


def _default() -> FirmwareVersion:
    return FirmwareVersion(1, 13, 3)


@pytest.fixture
def face(profile: VehicleProfile, client: Client) -> Iterator[Px4Face]:
    f = open_face(profile, client)
    yield f
    f.close()


def as_int32(wire: float) -> int:
    """A PX4 INT32 parameter from its PARAM_VALUE.param_value (its bytes)."""
    return int(struct.unpack("<i", struct.pack("<f", wire))[0])


def bits(value: int) -> float:
    """What a ground station puts in param_value for an INT32 (bytewise)."""
    return float(struct.unpack("<f", struct.pack("<i", value))[0])


def read(client: Client, face: Px4Face, name: str = "", index: int = -1) -> list[Any]:
    client.mav.param_request_read_send(1, 1, name.encode(), index)
    return client.params(face)


# ------------------------------------------------------------------- reading


def test_read_by_name_answers_value_type_count_and_index(face: Px4Face, client: Client) -> None:
    params = face.autopilot.params
    (pv,) = read(client, face, "COM_OF_LOSS_T")
    assert pv.param_id == "COM_OF_LOSS_T" and pv.param_value == pytest.approx(1.0)
    assert pv.param_type == PARAM_REAL32
    assert pv.param_count == len(params) and pv.param_index == params.index("COM_OF_LOSS_T")
    (pv,) = read(client, face, "NAV_RCL_ACT")
    assert pv.param_type == PARAM_INT32 and as_int32(pv.param_value) == 2  # PX4: Return
    assert pv.param_value != 2.0  # bytewise, not C-cast: 2's bits read as a float
    assert read(client, face, "NO_SUCH_PARAM") == []  # PX4 does not answer unknown names


def test_read_by_index_walks_the_table_in_name_order(face: Px4Face, client: Client) -> None:
    n = len(face.autopilot.params)
    names = [read(client, face, index=i)[0].param_id for i in (0, 1, n - 1)]
    assert names == sorted(names)
    (pv,) = read(client, face, index=face.autopilot.params.index("RC_MAP_ROLL"))
    assert pv.param_id == "RC_MAP_ROLL" and as_int32(pv.param_value) == 0  # PX4: unassigned
    assert read(client, face, index=n) == []


def test_list_sends_the_hash_then_every_parameter_once(face: Px4Face, client: Client) -> None:
    client.mav.param_request_list_send(1, 1)
    got = client.params(face)
    first, rest = got[0], got[1:]
    assert first.param_id == "_HASH_CHECK" and first.param_index == 65535
    assert first.param_type == PARAM_UINT32
    assert decode_bytewise(first.param_value, PARAM_UINT32) == face.autopilot.params.hash_check()
    n = len(face.autopilot.params)
    assert len(rest) == n and {m.param_count for m in got} == {n}
    assert [m.param_index for m in rest] == list(range(n))
    names = {m.param_id for m in rest}
    for name in (
        "COM_OF_LOSS_T", "COM_OBL_RC_ACT", "COM_RC_LOSS_T", "NAV_RCL_ACT", "COM_RCL_EXCEPT",
        "COM_RC_IN_MODE", "NAV_DLL_ACT", "COM_DL_LOSS_T", "MAV_SYS_ID", "MAV_COMP_ID",
        "RC_MAP_ROLL", "RC_MAP_PITCH", "RC_MAP_YAW", "RC_MAP_THROTTLE", "RC_MAP_FLTMODE",
        "RC_MAP_OFFB_SW", "IMU_GYRO_RATEMAX", "MAV_0_RATE", "COM_OBL_ACT",
    ):  # fmt: skip
        assert name in names


def test_defaults_are_px4s() -> None:
    p = Px4Params()
    defaults = {
        "COM_OF_LOSS_T": 1.0, "COM_OBL_RC_ACT": 0, "COM_OBL_ACT": 0, "COM_RC_LOSS_T": 0.5,
        "NAV_RCL_ACT": 2, "COM_RCL_EXCEPT": 0, "COM_RC_IN_MODE": 3, "NAV_DLL_ACT": 0,
        "COM_DL_LOSS_T": 10, "MAV_SYS_ID": 1, "MAV_COMP_ID": 1, "RC_MAP_ROLL": 0,
        "RC_MAP_FLTMODE": 0, "IMU_GYRO_RATEMAX": 400, "MAV_0_RATE": 1200, "MAV_1_MODE": 2,
        "MC_ROLLRATE_K": 1.0, "MC_PITCHRATE_K": 1.0, "MC_YAWRATE_K": 1.0,
        "MC_ROLLRATE_P": 0.15, "MC_PITCHRATE_P": 0.15, "MC_YAWRATE_P": 0.2,
    }  # fmt: skip
    assert {k: p[k] for k in defaults} == pytest.approx(defaults)
    assert "COM_OBL_ACT" not in Px4Params(FirmwareVersion(1, 14, 0))  # gone in 1.14


# ------------------------------------------------------------------- setting


def test_set_int32_bytewise_and_read_back(face: Px4Face, client: Client) -> None:
    client.mav.param_set_send(1, 1, b"NAV_RCL_ACT", bits(3), PARAM_INT32)
    (ack,) = client.params(face)
    assert ack.param_id == "NAV_RCL_ACT" and as_int32(ack.param_value) == 3
    assert face.autopilot.config.rc_loss_action == 3  # the autopilot follows it
    assert as_int32(read(client, face, "NAV_RCL_ACT")[0].param_value) == 3


def test_set_real32_and_read_back(face: Px4Face, client: Client) -> None:
    client.mav.param_set_send(1, 1, b"COM_RC_LOSS_T", 0.8, PARAM_REAL32)
    (ack,) = client.params(face)
    assert ack.param_value == pytest.approx(0.8) and ack.param_type == PARAM_REAL32
    assert face.autopilot.rc_timeout_s == pytest.approx(0.8)
    assert read(client, face, "COM_RC_LOSS_T")[0].param_value == pytest.approx(0.8)


@pytest.mark.parametrize("value", [-1, 0, 1, 57600, 2**31 - 1, -(2**31)])
def test_int32_bytewise_round_trip(face: Px4Face, client: Client, value: int) -> None:
    assert decode_bytewise(encode_bytewise(value, PARAM_INT32), PARAM_INT32) == value
    client.mav.param_set_send(1, 1, b"MAV_0_RATE", bits(value), PARAM_INT32)  # stored only
    (ack,) = client.params(face)
    assert as_int32(ack.param_value) == value == face.autopilot.params["MAV_0_RATE"]


def test_c_cast_set_does_not_reach_px4(face: Px4Face, client: Client) -> None:
    # A REAL32 PARAM_SET of an INT32 parameter: PX4 drops it, unanswered.
    client.mav.param_set_send(1, 1, b"NAV_RCL_ACT", 3.0, PARAM_REAL32)
    assert client.params(face) == []
    # 3.0 C-cast with the right type: PX4 reads its bits, 1077936128, which is no action.
    client.mav.param_set_send(1, 1, b"NAV_RCL_ACT", 3.0, PARAM_INT32)
    (ack,) = client.params(face)
    assert as_int32(ack.param_value) == 2 and face.autopilot.config.rc_loss_action == 2


def test_unmodelled_values_are_refused_with_the_current_value(
    face: Px4Face, client: Client
) -> None:
    client.mav.param_set_send(1, 1, b"COM_OF_LOSS_T", 0.0, PARAM_REAL32)
    (ack,) = client.params(face)
    assert ack.param_value == pytest.approx(1.0)
    assert face.autopilot.config.offboard_timeout_s == pytest.approx(1.0)
    client.mav.param_set_send(1, 1, b"NO_SUCH_PARAM", 1.0, PARAM_REAL32)
    assert client.params(face) == []


# --------------------------------------------------- offboard loss (COM_OF_LOSS_T)


def offboard_loss_after(ap: Autopilot) -> float:
    """Arm in OFFBOARD on body-rate setpoints up to t = 1 s, then stop them: the
    time the offboard-loss failsafe took, s."""
    t = 0.0
    while t <= 1.0:
        ap.on_rates_target(t, (0.0, 0.0, 0.0), 0.5)
        t += 0.05
    assert ap.set_mode(1.0, MainMode.OFFBOARD) is MavResult.ACCEPTED
    assert ap.arm(1.0) is MavResult.ACCEPTED
    t = 1.0
    while ap.failsafe is None and t < 3.0:
        ap.update(t, LEVEL, LEVEL, landed=False)
        t += 0.002
    assert ap.failsafe == "offboard_loss"
    return t - 1.0


def test_com_of_loss_t_set_over_mavlink_moves_the_offboard_failsafe(
    face: Px4Face, client: Client
) -> None:
    client.mav.param_set_send(1, 1, b"COM_OF_LOSS_T", 0.3, PARAM_REAL32)
    (ack,) = client.params(face)
    assert ack.param_value == pytest.approx(0.3)
    assert offboard_loss_after(face.autopilot) == pytest.approx(0.3, abs=0.06)


def test_the_rate_loops_gain_set_over_mavlink_scales_its_p_i_and_d(
    face: Px4Face, client: Client
) -> None:
    control = face.autopilot.rate_pid.control
    before = (control.kp, control.ki, control.kd, control.kff)
    control._int = [0.1, -0.1, 0.05]
    client.mav.param_set_send(1, 1, b"MC_PITCHRATE_K", 2.5, PARAM_REAL32)
    (ack,) = client.params(face)
    assert ack.param_id == "MC_PITCHRATE_K" and ack.param_value == pytest.approx(2.5)
    for now, was in zip((control.kp, control.ki, control.kd), before[:3], strict=True):
        assert now == pytest.approx((was[0], 2.5 * was[1], was[2]))
    assert control.kff == before[3]
    assert control.integral == pytest.approx((0.1, -0.1, 0.05))  # kept, as PX4 does


def test_the_rate_loops_gain_at_boot(profile: VehicleProfile) -> None:
    cfg = RunConfig(
        mavlink=parse_endpoint("udpout:127.0.0.1:9"),
        px4_params=(("MC_ROLLRATE_K", 2.0), ("MC_YAWRATE_K", 0.5), ("MC_PITCHRATE_P", 0.3)),
    )
    control = Runner(profile, cfg).autopilot.rate_pid.control
    assert control.kp == pytest.approx((0.3, 0.3, 0.1))  # K times P
    assert control.ki == pytest.approx((0.4, 0.2, 0.05))


def test_com_of_loss_t_and_offboard_timeout_are_the_same(profile: VehicleProfile) -> None:
    def runner(**kw: Any) -> Runner:
        cfg = RunConfig(mavlink=parse_endpoint("udpout:127.0.0.1:9"), **kw)
        return Runner(profile, cfg)

    by_flag = runner(offboard_timeout_s=0.4).autopilot
    assert by_flag.params["COM_OF_LOSS_T"] == pytest.approx(0.4)
    by_param = runner(px4_params=(("COM_OF_LOSS_T", 0.4),)).autopilot
    assert by_param.config.offboard_timeout_s == pytest.approx(0.4)
    assert offboard_loss_after(by_param) == pytest.approx(0.4, abs=0.06)  # type: ignore[arg-type]


def test_boot_params_reach_the_face_and_the_table(profile: VehicleProfile) -> None:
    cfg = RunConfig(
        mavlink=parse_endpoint("udpout:127.0.0.1:9"),
        px4_params=(
            ("MAV_SYS_ID", 7), ("IMU_GYRO_RATEMAX", 250), ("COM_RC_IN_MODE", 1),
            ("RC_MAP_FLTMODE", 5), ("NAV_RCL_ACT", 3),
        ),
    )  # fmt: skip
    r = Runner(profile, cfg)
    assert r.face.sysid == 7 and r.face.mav.srcSystem == 7 and r.face.compid == 1
    assert r.streams.imu_rate_hz == 250  # the IMU streams cannot go faster
    p = r.autopilot.params
    assert (p["COM_RC_IN_MODE"], p["RC_MAP_FLTMODE"], p["NAV_RCL_ACT"]) == (1, 5, 3)
    # The SITL airframe: the radio calibrated AETR, the gyro rate the IMU's.
    default = Runner(profile, RunConfig(mavlink=parse_endpoint("udpout:127.0.0.1:9")))
    q = default.autopilot.params
    rc = [q[f"RC_MAP_{a}"] for a in ("ROLL", "PITCH", "THROTTLE", "YAW")]
    assert rc == [1, 2, 3, 4] and q["IMU_GYRO_RATEMAX"] == profile.physics.imu.rate_hz
    assert default.streams.imu_rate_hz == profile.physics.imu.rate_hz
    with pytest.raises(ValueError, match=r"NOPE.*COM_OF_LOSS_T"):
        Runner(profile, RunConfig(mavlink=cfg.mavlink, px4_params=(("NOPE", 1.0),)))


@pytest.mark.parametrize(("action", "armed"), [(0, True), (5, False), (6, False), (3, True)])
def test_nav_rcl_act_none_terminate_disarm(
    face: Px4Face, client: Client, action: int, armed: bool
) -> None:
    """NAV_RCL_ACT 0 does nothing on RC loss; 5 (Terminate) and 6 (Disarm) stop the
    motors where the vehicle is; 3 lands."""
    client.mav.param_set_send(1, 1, b"NAV_RCL_ACT", bits(action), PARAM_INT32)
    (ack,) = client.params(face)
    assert as_int32(ack.param_value) == action
    ap = face.autopilot
    sticks = (1500, 1500, 1500, 1500)
    t = 0.0
    while t < 0.5:
        ap.update(t, LEVEL, LEVEL, sticks_us=sticks)
        t += 0.004
    assert ap.set_mode(t, MainMode.ALTCTL) is MavResult.ACCEPTED
    assert ap.arm(t, force=True) is MavResult.ACCEPTED
    while t < 1.5:  # RC silent for 1 s (COM_RC_LOSS_T 0.5 s)
        ap.update(t, LEVEL, LEVEL, landed=False)
        t += 0.004
    assert ap.armed is armed
    assert ap.failsafe == (None if action == 0 else "rc_loss")
    assert ap.mode.main == (MainMode.AUTO if action == 3 else MainMode.ALTCTL)


# ------------------------------------------------------------------ firmware


@pytest.mark.parametrize(
    ("firmware", "actuator"),
    [(None, True), (FirmwareVersion(1, 14, 0), False), (FirmwareVersion(1, 15, 2), False)],
)
def test_firmware_version_and_actuator_targets(
    profile: VehicleProfile, client: Client, firmware: FirmwareVersion | None, actuator: bool
) -> None:
    face = open_face(profile, client, firmware)
    try:
        ver = client.autopilot_version(face)
        fw = firmware or _default()
        assert ver.flight_sw_version == fw.major << 24 | fw.minor << 16 | fw.patch << 8 | 255
        assert bool(ver.capabilities & CAP_SET_ACTUATOR_TARGET) is actuator
        assert ver.capabilities & CAP_BYTEWISE and not ver.capabilities & CAP_C_CAST
        assert ver.capabilities & 64  # SET_ATTITUDE_TARGET in every version
        ap = face.autopilot
        client.mav.set_actuator_control_target_send(0, 0, 1, 1, [0.1, 0.0, 0.0, 0.5] + [0.0] * 4)
        client.exchange(face)
        assert ap.accepted_setpoints == (1 if actuator else 0)
        assert face.setpoints_received == (1 if actuator else 0)
        client.mav.set_attitude_target_send(0, 1, 1, RATES, [1, 0, 0, 0], 0.2, 0.0, 0.0, 0.5)
        client.exchange(face)
        assert ap.accepted_setpoints == (2 if actuator else 1)  # body rates: always
    finally:
        face.close()


def test_firmware_1_14_offboard_needs_rates_not_actuator_targets(
    profile: VehicleProfile, client: Client
) -> None:
    face = open_face(profile, client, FirmwareVersion(1, 14, 0))
    try:
        for i in range(3):
            client.mav.set_actuator_control_target_send(i, 0, 1, 1, [0.0, 0.0, 0.0, 0.5] + [0] * 4)
            client.exchange(face, t_s=0.1 * i)
        assert face.autopilot.set_mode(0.3, MainMode.OFFBOARD) is MavResult.TEMPORARILY_REJECTED
    finally:
        face.close()


def test_firmware_parse_and_encoding() -> None:
    assert FirmwareVersion.parse("1.13.3").flight_sw_version == 0x010D03FF
    assert FirmwareVersion.parse("v1.14.0-rc1") == FirmwareVersion(1, 14, 0, 192)
    assert FirmwareVersion.parse("4.7.0-dev").flight_sw_version == 0x04070000
    assert str(FirmwareVersion.parse("1.15.4-beta2")) == "1.15.4-beta"
    for bad in ("1.14", "1.14.x", "1.256.0", "", "1.14.0-foo"):
        with pytest.raises(ValueError, match=r"MAJOR\.MINOR\.PATCH"):
            FirmwareVersion.parse(bad)


# ----------------------------------------------------------------------- CLI


def sitl_run(*args: str) -> Any:
    return CliRunner().invoke(
        sitl_cli, ["run", "--profile", str(F450), "--mavlink", "udpout:127.0.0.1:9", *args]
    )


@pytest.mark.parametrize("bad", ["1.14", "one.two.three", "1.14.0-foo", "300.0.0"])
def test_bad_firmware_is_refused_naming_the_option(bad: str) -> None:
    res = sitl_run("--firmware", bad)
    assert res.exit_code == 2, res.output
    assert "--firmware" in res.output and "MAJOR.MINOR.PATCH" in res.output
    assert "Traceback" not in res.output


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (("--param", "NOPE=1"), ("--param", "NOPE", "COM_OF_LOSS_T", "IMU_GYRO_RATEMAX")),
        (("--firmware", "1.14.0", "--param", "COM_OBL_ACT=1"), ("--param", "COM_OBL_ACT")),
        (("--autopilot", "ardupilot", "--param", "NOPE=1"), ("--param", "NOPE", "RCMAP_ROLL")),
        (("--param", "MAV_SYS_ID=0"), ("MAV_SYS_ID", "1..254")),
    ],
)
def test_bad_params_are_refused_before_the_run(
    args: tuple[str, ...], words: tuple[str, ...]
) -> None:
    res = sitl_run(*args)
    assert res.exit_code == 2, res.output
    for w in words:
        assert w in res.output, res.output
    assert "Traceback" not in res.output
