"""The hand-back leaves the vehicle in a mode it can fly, against both SITL personalities.

Each flight is the SITL and the companion as separate processes over real UDP.
A vehicle with no radio (``sitl run --no-rc``) is flown from a reference file
with its own collective (``companion run --reference``), as a scripted flight
or a mission is. The SITL personalities fail safe out of manual modes without
RC and refuse hold without a position, as PX4 and ArduPilot do
(tests/sitl/test_rc_and_position.py), so the outcome is the SITL's final mode.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from companion.profile import load_profile
from sitl.ardupilot import ArduCopter, ArduCopterConfig
from sitl.lab.fly import FlightProcesses, fly_mavlink
from sitl.rotors import hover_motor_command

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
F450 = ROOT / "vehicle_profiles" / "f450.yaml"
EXIT_FAILSAFE = 3
WATCH_S = 1.5  # companion fly's --hand-back-watch-s


def kinds(events: list[dict[str, Any]]) -> list[str]:
    return [str(e["kind"]) for e in events]


def only(events: list[dict[str, Any]], kind: str) -> dict[str, Any]:
    found = [e for e in events if e["kind"] == kind]
    assert len(found) == 1, (kind, kinds(events))
    return found[0]


def sitl_modes(flight: FlightProcesses) -> list[str]:
    return [str(e["new"]) for e in flight.sitl_events if e.get("kind") == "mode"]


def hover_reference(tmp_path: Path, thrust: float) -> Path:
    """Level, a gentle climb off the ground, then the hover collective."""
    path = tmp_path / "hover.csv"
    path.write_text(
        "t_s,roll_deg_s,pitch_deg_s,yaw_deg_s,thrust\n"
        f"0,0,0,0,{1.15 * thrust:.4f}\n1.5,0,0,0,{1.15 * thrust:.4f}\n"
        f"1.6,0,0,0,{thrust:.4f}\n",
        encoding="utf-8",
    )
    return path


def fly_without_radio(
    tmp_path: Path,
    *,
    autopilot: str = "px4",
    sitl_args: tuple[str, ...] = (),
    companion_args: tuple[str, ...] = (),
    duration_s: float = 4.0,
) -> FlightProcesses:
    profile = load_profile(F450, simulated=True)
    if autopilot == "px4":
        thrust = hover_motor_command(profile)
        sitl = ("--no-rc", *sitl_args)
    else:
        cmd = hover_motor_command(profile)
        thrust = ArduCopter(profile, ArduCopterConfig(hover_motor_cmd=cmd)).hover_throttle
        # A companion-only ArduPilot vehicle keeps GUIDED_NOGPS through the radio
        # failsafe (FS_OPTIONS bit 2, with the default 16).
        sitl = ("--no-rc", "--param", "FS_OPTIONS=20", *sitl_args)
    return fly_mavlink(
        F450, "hover-gusts", tmp_path / "flight", duration_s=duration_s, autopilot=autopilot,
        sitl_args=sitl,
        companion_args=("--reference", str(hover_reference(tmp_path, thrust)), *companion_args),
    )  # fmt: skip


def assert_timely(flight: FlightProcesses, start: dict[str, Any], mode: str) -> dict[str, Any]:
    """``start`` (a failsafe, or the run's end) is followed by one hand-back to
    ``mode``, acknowledged within 1 s, then held for the watch; returns it."""
    ev = flight.companion_events
    back = only(ev, "handed_back")
    assert back["detail"].endswith(f"-> {mode} accepted"), back
    assert 0.0 <= back["wall"] - start["wall"] < 1.0, (start, back)
    held = only(ev, "safe_mode_held")
    assert held["wall"] - back["wall"] >= WATCH_S * 0.9 or "disarmed" in held["detail"], held
    assert "safe_mode_lost" not in kinds(ev)
    return back


# ------------------------------------------------------------------------------- PX4


def test_px4_without_radio_hands_back_to_hold(tmp_path: Path) -> None:
    """The case of the report: a scripted flight's end on PX4 must not ask for
    POSCTL (PX4 would refuse or fail safe out of it with no manual control)."""
    flight = fly_without_radio(tmp_path)
    assert flight.companion_rc == 0, flight.why()
    ev = flight.companion_events
    ended = ev[kinds(ev).index("handed_back") - 1]
    back = assert_timely(flight, ended, "HOLD")
    assert "no valid RC, a position estimate" in back["detail"]
    assert sitl_modes(flight)[-1] == "LOITER"
    assert "POSCTL" not in sitl_modes(flight)


def test_px4_without_radio_or_position_lands_after_a_failsafe(tmp_path: Path) -> None:
    """The gyro reads beyond its range (invalid IMU, judged in sample time) on a
    vehicle with neither: land."""
    flight = fly_without_radio(tmp_path, sitl_args=("--no-position", "--fault", "imu-range@3"))
    assert flight.companion_rc == EXIT_FAILSAFE, flight.why()
    ev = flight.companion_events
    fs = only(ev, "failsafe_invalid_imu")
    back = assert_timely(flight, fs, "LAND")
    assert "no valid RC, no position estimate" in back["detail"]
    assert sitl_modes(flight)[-1] == "LAND"


# ------------------------------------------------------------------------- ArduPilot


def test_ardupilot_without_radio_hands_back_to_loiter(tmp_path: Path) -> None:
    flight = fly_without_radio(tmp_path, autopilot="ardupilot")
    assert flight.companion_rc == 0, flight.why()
    ev = flight.companion_events
    ended = ev[kinds(ev).index("handed_back") - 1]
    assert_timely(flight, ended, "LOITER")
    assert sitl_modes(flight)[-1] == "LOITER"


def test_ardupilot_without_radio_or_position_lands(tmp_path: Path) -> None:
    flight = fly_without_radio(tmp_path, autopilot="ardupilot", sitl_args=("--no-position",))
    assert flight.companion_rc == 0, flight.why()
    ev = flight.companion_events
    ended = ev[kinds(ev).index("handed_back") - 1]
    assert_timely(flight, ended, "LAND")
    assert sitl_modes(flight)[-1] == "LAND"


def test_ardupilot_rc_loss_the_radio_failsafe_acts_and_the_companion_hands_back(
    tmp_path: Path,
) -> None:
    """With a pilot: the radio is lost mid-flight. ArduCopter keeps streaming the
    last RC_CHANNELS (as the real 4.5.6 does), so the companion learns of the loss
    from SYS_STATUS's RC receiver health, which ArduCopter clears at RC_FS_TIMEOUT
    (1 s), the moment its own radio failsafe acts (FS_THR_ENABLE 1: RTL, shown as RTL
    and flown as Land here).

    Which the companion sees first depends on timing, and both orders end safe:
    the HEARTBEAT showing RTL (the companion keeps the autopilot's failsafe mode,
    as on the real stack), or its own RC-lost failsafe 0.5 s after the receiver
    was called lost (it hands back to LOITER, a mode that needs no pilot; a
    loaded CI machine showed this order). Never a manual mode."""
    flight = fly_mavlink(
        F450, "paper-acro", tmp_path / "flight", duration_s=20.0, autopilot="ardupilot",
        sitl_args=("--fault", "rc-lost@3", "--clock", "realtime"),
        companion_args=("--hand-back-watch-s", "3"),
    )  # fmt: skip
    assert flight.companion_rc == EXIT_FAILSAFE, flight.why()
    ev = flight.companion_events
    lost = only(ev, "rc_receiver_lost")
    failsafes = [e for e in ev if str(e["kind"]).startswith("failsafe_")]
    assert len(failsafes) == 1, kinds(ev)
    fs = failsafes[0]
    back = only(ev, "handed_back")
    assert 0.0 <= back["wall"] - fs["wall"] < 1.0
    # Seen within a heartbeat or two of the receiver's loss; the HEARTBEAT showing
    # RTL goes out at once, the SYS_STATUS calling the receiver lost at its next
    # 5 Hz slot: either may come first (CI saw the HEARTBEAT 1 ms ahead).
    assert -0.25 <= fs["wall"] - lost["wall"] < 2.0, (lost, fs)
    if fs["kind"] == "failsafe_rc_lost":
        assert back["detail"].endswith("-> LOITER accepted"), back
        assert "(the failsafe is RC loss)" in back["detail"]
        assert only(ev, "safe_mode_held")["detail"].startswith("LOITER")
        assert sitl_modes(flight)[-2:] == ["RTL", "LOITER"]
    else:
        assert fs["kind"] == "failsafe_autopilot_took_over", kinds(ev)
        assert back["detail"].endswith("-> RTL kept (the autopilot's mode)"), back
        assert sitl_modes(flight)[-1] == "RTL"
    causes = [e.get("cause") for e in flight.sitl_events if e.get("kind") == "failsafe"]
    assert causes == ["radio"]
