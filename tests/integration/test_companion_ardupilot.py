"""The companion against the SITL's ArduPilot personality: refusals and a flight.

Each stack-specific refusal must end with a clear message and nothing flown.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from sitl.lab.fly import FlightProcesses, fly_mavlink, merge_logs
from sitl.lab.report import compute_metrics

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
PROFILE = ROOT / "vehicle_profiles" / "f450.yaml"


def fly(tmp_path: Path, *, sitl: tuple[str, ...] = (), comp: tuple[str, ...] = (),
        duration_s: float = 5.0) -> FlightProcesses:  # fmt: skip
    return fly_mavlink(
        PROFILE, "paper-acro", tmp_path, duration_s=duration_s, autopilot="ardupilot",
        sitl_args=("--duration", "30", *sitl), companion_args=comp,
    )  # fmt: skip


def kinds(flight: FlightProcesses) -> list[str]:
    return [str(e["kind"]) for e in flight.companion_events]


def test_actuator_output_is_refused_before_anything_is_sent(tmp_path: Path) -> None:
    flight = fly(tmp_path, comp=("--output", "actuator"))
    assert flight.companion_rc == 1
    assert "accepts no actuator setpoints" in flight.text("companion.stderr")
    assert flight.sitl_summary["setpoints_received"] == 0
    assert "engaged" not in kinds(flight)


def test_climb_rate_thrust_semantics_are_refused(tmp_path: Path) -> None:
    # fly_mavlink sets GUID_OPTIONS=8; the later --param wins.
    flight = fly(tmp_path, sitl=("--param", "GUID_OPTIONS=0"))
    assert flight.companion_rc == 1
    err = flight.text("companion.stderr")
    assert "GUID_OPTIONS = 0" in err and "climb rate" in err
    assert flight.sitl_summary["setpoints_received"] == 0


def test_prearm_failure_is_reported_with_the_autopilots_words(tmp_path: Path) -> None:
    """Waited for and tried within --arm-timeout-s, each refusal an event, then exit 1.

    The SITL's SYS_STATUS says the pre-arm checks fail (bit 28 not healthy), as
    ArduCopter's does, so the companion waits on it and tries at the end: one try."""
    flight = fly(tmp_path, sitl=("--prearm-fail", "RC not calibrated"),
                 comp=("--arm-timeout-s", "2"))  # fmt: skip
    assert flight.companion_rc == 1
    assert "arm_waiting" in kinds(flight)
    refused = [e["detail"] for e in flight.companion_events if e["kind"] == "arm_refused"]
    assert len(refused) >= 1
    assert all(d.endswith(": PreArm: RC not calibrated") for d in refused)
    failed = [e for e in flight.companion_events if e["kind"] == "engage_failed"]
    assert failed and "refused to arm" in failed[0]["detail"]
    assert failed[0]["detail"].endswith(": PreArm: RC not calibrated")
    assert "engaged" not in kinds(flight)


def test_a_denied_imu_rate_falls_back_to_the_fastest_accepted(tmp_path: Path) -> None:
    flight = fly(tmp_path, comp=("--rate-hz", "1000"))
    assert flight.companion_rc == 0, flight.text("companion.stderr")
    denied = [e["detail"] for e in flight.companion_events if e["kind"] == "imu_rate_denied"]
    stream = [e["detail"] for e in flight.companion_events if e["kind"] == "imu_stream"]
    assert denied and "400 Hz" in denied[0]  # beyond loop period / 0.8 at 400 Hz
    assert stream == ["message 30 at 333 Hz"]  # ATTITUDE, ArduPilot's fastest accepted


def test_rates_flight_engages_guided_nogps_and_hands_back_to_alt_hold(tmp_path: Path) -> None:
    # 9 s: at 9.7 s paper-acro's 720 deg/s roll outruns ArduCopter's shaped rate
    # input (ATC_ACCEL_R_MAX) and the envelope failsafe ends the flight.
    flight = fly(tmp_path, duration_s=9.0)
    assert flight.companion_rc == 0, flight.text("companion.stderr")
    ks = kinds(flight)
    assert ks.index("engaged") < ks.index("handed_back")
    assert "ALT_HOLD accepted" in flight.companion_events[ks.index("handed_back")]["detail"]
    m = compute_metrics(merge_logs(flight))
    assert not m["crashed"] and m["airborne_time_s"] > 5.0
