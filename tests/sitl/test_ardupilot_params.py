"""The ArduPilot personality's parameters over real UDP against the face: C-cast
values (an integer parameter's number as a float), the capability bit that says
so, the firmware version, and the parameters a preflight reads."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from companion.profile import VehicleProfile, load_profile
from sitl.ardupilot import ArduCopter, ArduCopterConfig
from sitl.ardupilot_face import ArduPilotFace, ardupilot_streams
from sitl.mavlink_link import parse_endpoint
from sitl.personality import FirmwareVersion
from sitl.runner import RunConfig, Runner
from tests.sitl.udp_client import Client

ROOT = Path(__file__).resolve().parents[2]
INT8, INT16, INT32, REAL32 = 2, 4, 6, 9  # MAV_PARAM_TYPE
CAP_PARAM_FLOAT = 2
CAP_BYTEWISE = 16
CAP_C_CAST = 131072


@pytest.fixture(scope="module")
def profile() -> VehicleProfile:
    return load_profile(ROOT / "vehicle_profiles" / "f450.yaml")


def open_face(
    profile: VehicleProfile, client: Client, firmware: FirmwareVersion | None = None
) -> ArduPilotFace:
    ap = ArduCopter(profile, ArduCopterConfig())
    kw = {} if firmware is None else {"firmware": firmware}
    endpoint = parse_endpoint(f"udpout:127.0.0.1:{client.port}")
    return ArduPilotFace(endpoint, ap, ardupilot_streams(400.0), **kw).open()


@pytest.fixture
def face(profile: VehicleProfile, client: Client) -> Iterator[ArduPilotFace]:
    f = open_face(profile, client)
    yield f
    f.close()


def read(client: Client, face: ArduPilotFace, name: str) -> Any:
    client.mav.param_request_read_send(1, 1, name.encode(), -1)
    (pv,) = client.params(face)
    return pv


def test_integers_travel_c_cast(face: ArduPilotFace, client: Client) -> None:
    pv = read(client, face, "RCMAP_YAW")
    assert pv.param_type == INT8 and pv.param_value == 4.0  # the number, not its bits
    client.mav.param_set_send(1, 1, b"GUID_OPTIONS", 8.0, INT32)
    (ack,) = client.params(face)
    assert ack.param_id == "GUID_OPTIONS" and ack.param_value == 8.0
    assert face.autopilot.guided_thrust_is_thrust
    assert read(client, face, "GUID_OPTIONS").param_value == 8.0
    # ArduPilot takes the float whatever the PARAM_SET's type says, and rounds it.
    client.mav.param_set_send(1, 1, b"GUID_OPTIONS", 0.4, REAL32)
    (ack,) = client.params(face)
    assert ack.param_value == 0.0 and ack.param_type == INT32


def test_list_has_every_parameter_and_no_hash(face: ArduPilotFace, client: Client) -> None:
    client.mav.param_request_list_send(1, 1)
    got = client.params(face)
    n = len(face.autopilot.params)
    assert len(got) == n and [m.param_index for m in got] == list(range(n))
    names = {m.param_id for m in got}
    assert {m.param_count for m in got} == {n} and "_HASH_CHECK" not in names
    assert {"RCMAP_ROLL", "FLTMODE_CH", "MAV_SYSID", "FS_GCS_ENABLE"} <= names


@pytest.mark.parametrize(
    ("name", "ptype", "value"),
    [
        ("RCMAP_ROLL", INT8, 1),
        ("RCMAP_PITCH", INT8, 2),
        ("RCMAP_THROTTLE", INT8, 3),
        ("RCMAP_YAW", INT8, 4),
        ("FLTMODE_CH", INT8, 5),
        ("MAV_SYSID", INT16, 1),
        ("FS_GCS_ENABLE", INT8, 0),
        ("FS_GCS_TIMEOUT", REAL32, 5.0),
    ],
)
def test_new_preflight_parameters_and_their_defaults(
    face: ArduPilotFace, client: Client, name: str, ptype: int, value: float
) -> None:
    pv = read(client, face, name)
    assert pv.param_type == ptype and pv.param_value == pytest.approx(value)


@pytest.mark.parametrize(
    ("firmware", "sw_version"),
    [(None, 0x04070000), (FirmwareVersion(4, 5, 7), 0x040507FF)],
)
def test_autopilot_version_says_c_cast_and_the_firmware(
    profile: VehicleProfile, client: Client, firmware: FirmwareVersion | None, sw_version: int
) -> None:
    face = open_face(profile, client, firmware)
    try:
        ver = client.autopilot_version(face)
        assert ver.capabilities & CAP_C_CAST and ver.capabilities & CAP_PARAM_FLOAT
        assert not ver.capabilities & CAP_BYTEWISE
        assert ver.flight_sw_version == sw_version
    finally:
        face.close()


def test_boot_params_and_firmware_reach_the_face(profile: VehicleProfile) -> None:
    cfg = RunConfig(
        mavlink=parse_endpoint("udpout:127.0.0.1:9"),
        autopilot="ardupilot",
        ardupilot_params=(("MAV_SYSID", 3), ("RCMAP_ROLL", 2)),
        firmware=FirmwareVersion(4, 6, 2),
    )
    r = Runner(profile, cfg)
    assert r.face.sysid == 3 and r.face.mav.srcSystem == 3
    assert r.autopilot.params["RCMAP_ROLL"] == 2
    assert r.autopilot.params["FLTMODE_CH"] == 6  # the SITL airframe: ch5 engages the companion
    assert r.face.flight_sw_version == 0x040602FF
