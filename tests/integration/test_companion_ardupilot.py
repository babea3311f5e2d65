"""The companion against the SITL's ArduPilot personality: refusals and a flight.

Each stack-specific refusal must end with a clear message and nothing flown.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from sitl.flight_log import read_log
from sitl.lab.fly import FlightProcesses, fly_mavlink, merge_logs
from sitl.lab.report import compute_metrics
from tests.integration import test_failsafe_cases as _cases
from tests.integration.conftest import SitlProcess, free_udp_port
from tests.integration.test_failsafe_cases import CompanionProcess

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
PROFILE = ROOT / "vehicle_profiles" / "f450.yaml"

start_companion = _cases.start_companion
"""The fixture that runs ``companion run`` (tests/integration/test_failsafe_cases.py)."""


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
    assert flight.companion_rc == 0, flight.why()
    denied = [e["detail"] for e in flight.companion_events if e["kind"] == "imu_rate_denied"]
    stream = [e["detail"] for e in flight.companion_events if e["kind"] == "imu_stream"]
    assert denied and "400 Hz" in denied[0]  # beyond loop period / 0.8 at 400 Hz
    assert stream == ["message 30 at 333 Hz"]  # ATTITUDE, ArduPilot's fastest accepted


def test_rates_flight_engages_guided_nogps_and_hands_back_to_alt_hold(tmp_path: Path) -> None:
    # 9 s: at 9.7 s paper-acro's 720 deg/s roll outruns ArduCopter's shaped rate
    # input (ATC_ACCEL_R_MAX) and the envelope failsafe ends the flight.
    flight = fly(tmp_path, duration_s=9.0)
    assert flight.companion_rc == 0, flight.why()
    ks = kinds(flight)
    assert ks.index("engaged") < ks.index("handed_back")
    # Taking off in GUIDED_NOGPS with GUID_OPTIONS 8, ArduCopter 4.5 reports an
    # internal error once (its land detector) and flies on: so does the companion.
    says = [e["detail"] for e in flight.companion_events if e["kind"] == "autopilot_says"]
    assert says.count("Internal Errors 0x100000") == 1, says
    assert "ALT_HOLD accepted" in flight.companion_events[ks.index("handed_back")]["detail"]
    m = compute_metrics(merge_logs(flight))
    assert not m["crashed"] and m["airborne_time_s"] > 5.0


def test_arming_with_the_throttle_up_is_refused_in_the_autopilots_words(
    start_sitl: Callable[..., SitlProcess],
    start_companion: Callable[..., CompanionProcess],
) -> None:
    """ArduCopter 4.5.6 refuses to arm in GUIDED_NOGPS while the radio's throttle is
    above idle ("Arm: Throttle (RC3) is not neutral"; armed at RC3_MIN). The SITL's
    pilot holds the throttle up from boot (its timeline not waiting for arming): an
    ``--engage auto`` run tries within ``--arm-timeout-s``, quoting each refusal, then
    exits 1, the vehicle never armed."""
    port = free_udp_port()
    comp = start_companion(
        port, "--engage", "auto", "--output", "rates", "--arm-timeout-s", "3",
        "--rate-hz", "250", "--stale-imu-s", "0.5",
    )  # fmt: skip
    sitl = start_sitl(
        port, "--autopilot", "ardupilot", "--mode", "stabilize", "--param", "GUID_OPTIONS=8",
        "--pilot", "hover", "--no-auto-arm", "--clock", "realtime", duration_s=30.0,
    )  # fmt: skip
    try:
        rc = comp.proc.wait(timeout=40)
    finally:
        sitl.stop()
    ev = comp.events()
    assert rc == 1, ([e["kind"] for e in ev], comp.stderr()[-2000:])
    refused = [e["detail"] for e in ev if e["kind"] == "arm_refused"]
    assert len(refused) >= 2, refused  # tried again within the timeout
    assert all(d.endswith(": Arm: Throttle (RC3) is not neutral") for d in refused), refused
    failed = [e["detail"] for e in ev if e["kind"] == "engage_failed"]
    assert failed and failed[0].endswith("Arm: Throttle (RC3) is not neutral"), failed
    log = read_log(sitl.log_path)
    assert not log["armed"].any()
    assert [e["new"] for e in log.events if e.get("kind") == "mode"] == ["GUIDED_NOGPS"]
