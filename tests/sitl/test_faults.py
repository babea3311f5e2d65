"""``--fault``: what each spelling means, the error a bad one gets, and the event it logs."""

from __future__ import annotations

from pathlib import Path

import pytest

from companion.profile import load_profile
from sitl.faults import FAULT_KINDS, Fault, parse_fault
from sitl.flight_log import read_log
from sitl.lab.fly import free_udp_port
from sitl.mavlink_link import parse_endpoint
from sitl.runner import RunConfig, Runner

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(
    ("text", "fault"),
    [
        ("imu-stop@6", Fault("imu-stop", 6.0)),
        ("rc-lost@2.5", Fault("rc-lost", 2.5)),
        ("motor-fail@6:3", Fault("motor-fail", 6.0, 3)),
        ("heartbeat-stop@0", Fault("heartbeat-stop", 0.0)),
    ],
)
def test_a_fault_is_kind_time_and_motor(text: str, fault: Fault) -> None:
    assert parse_fault(text) == fault


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("rc-gone@3", "KIND is one of"),
        ("rc-lost@-1", "SECONDS >= 0"),
        ("rc-lost@nan", "SECONDS >= 0"),
        ("rc-lost@x", "expected KIND@SECONDS[:MOTOR]"),
        ("motor-fail@6:a", "expected KIND@SECONDS[:MOTOR]"),
        ("rc-lost", "expected KIND@SECONDS[:MOTOR]"),
        ("motor-fail@6", "expected motor-fail@SECONDS:MOTOR"),
        ("motor-fail@6:", "expected KIND@SECONDS[:MOTOR]"),
        ("imu-stop@6:2", "other kinds KIND@SECONDS"),
    ],
)
def test_a_bad_fault_names_itself_and_what_was_expected(text: str, expected: str) -> None:
    with pytest.raises(ValueError, match=r"fault '.*'") as err:
        parse_fault(text)
    assert expected in str(err.value)
    assert repr(text) in str(err.value)


def test_every_kind_is_listed_in_the_error() -> None:
    with pytest.raises(ValueError) as err:
        parse_fault("nope@1")
    assert all(k in str(err.value) for k in FAULT_KINDS)


def test_a_motor_the_vehicle_lacks_is_refused_before_the_run() -> None:
    profile = load_profile(ROOT / "vehicle_profiles" / "f450.yaml")
    config = RunConfig(
        mavlink=parse_endpoint("udpout:127.0.0.1:9"), faults=(Fault("motor-fail", 1.0, 4),)
    )
    with pytest.raises(ValueError, match=r"motor-fail@1:4: MOTOR is 0\.\.3 on f450"):
        Runner(profile, config, profile_name="f450")
    # The last motor is fine.
    ok = RunConfig(mavlink=config.mavlink, faults=(Fault("motor-fail", 1.0, 3),))
    Runner(profile, ok, profile_name="f450").face.close()


def test_every_fault_is_logged_as_a_fault_event(tmp_path: Path) -> None:
    profile = load_profile(ROOT / "vehicle_profiles" / "f450.yaml")
    faults = tuple(Fault(k, 0.05, 2 if k == "motor-fail" else 0) for k in FAULT_KINDS)
    config = RunConfig(
        mavlink=parse_endpoint(f"udpout:127.0.0.1:{free_udp_port()}"),
        clock="lockstep",
        duration_s=0.1,
        log_path=tmp_path / "sitl.npz",
        faults=faults,
    )
    Runner(profile, config, profile_name="f450").run()
    logged = read_log(tmp_path / "sitl.npz").events
    # The fault events, whatever "kind" they carry (a fault's own kind must not replace it).
    events = [e for e in logged if e.get("kind") in ("fault", *FAULT_KINDS)]
    assert [e["kind"] for e in events] == ["fault"] * len(FAULT_KINDS)
    assert [(e["fault"], e["arg"]) for e in events] == [(f.kind, f.arg) for f in faults]
    assert all(e["t_s"] == pytest.approx(0.05) for e in events)
