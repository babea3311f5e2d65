"""The SITL against pymavlink's mavutil acting as a ground station (real UDP, separate process)."""

from __future__ import annotations

import itertools
import logging
import os
import time
from collections.abc import Callable, Iterator

import pytest

os.environ["MAVLINK20"] = "1"

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from sitl.flight_log import read_log

from .conftest import SitlProcess

pytestmark = pytest.mark.integration
logger = logging.getLogger(__name__)

Starter = Callable[..., SitlProcess]
Connect = Callable[[int], mavutil.mavfile]


@pytest.fixture
def connect() -> Iterator[Callable[[int], mavutil.mavfile]]:
    """Factory: a mavutil ground station on ``udpin:127.0.0.1:port`` that saw a HEARTBEAT."""
    opened: list[mavutil.mavfile] = []

    def _connect(port: int, timeout_s: float = 15.0) -> mavutil.mavfile:
        master = mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{port}", source_system=255, source_component=190, dialect="common"
        )
        opened.append(master)
        hb = master.wait_heartbeat(timeout=timeout_s)
        assert hb is not None, "no HEARTBEAT from the SITL"
        return master

    yield _connect
    for m in opened:
        m.close()


def command(
    master: mavutil.mavfile,
    cmd: int,
    *params: float,
    timeout_s: float = 3.0,
    stepping: bool = False,
) -> int:
    """COMMAND_LONG; its MAV_RESULT. ``stepping``: a lockstep SITL in OFFBOARD handles a
    command at its next step, which waits for a setpoint: send one until the answer."""
    p = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][:7]
    master.mav.command_long_send(1, 1, cmd, 0, *p)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if stepping:
            send_actuators(master, 0.0)
        ack = master.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.2)
        if ack is not None and ack.command == cmd:
            return int(ack.result)
    raise AssertionError(f"no COMMAND_ACK for command {cmd}")


def wait_heartbeat_where(
    master: mavutil.mavfile, pred: Callable[[object], bool], timeout_s: float = 5.0
) -> object:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        hb = master.recv_match(type="HEARTBEAT", blocking=True, timeout=0.3)
        if hb is not None and pred(hb):
            return hb
    raise AssertionError("expected HEARTBEAT never came")


def send_actuators(master: mavutil.mavfile, thrust: float) -> None:
    master.mav.set_actuator_control_target_send(
        0, 0, 1, 1, [0.0, 0.0, 0.0, thrust, 0.0, 0.0, 0.0, 0.0]
    )


def test_heartbeat_identity_and_mode(start_sitl: Starter, connect: Connect, udp_port: int) -> None:
    start_sitl(udp_port)
    master = connect(udp_port)
    hb = master.recv_match(type="HEARTBEAT", blocking=True, timeout=3)
    assert hb is not None
    assert hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4
    assert hb.type == mavlink.MAV_TYPE_QUADROTOR
    assert hb.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert mavutil.mode_string_v10(hb) == "MANUAL"
    assert master.flightmode == "MANUAL"
    assert hb.system_status == mavlink.MAV_STATE_STANDBY
    # AUTOPILOT_VERSION on request, with the capabilities clients look for.
    assert command(master, mavlink.MAV_CMD_REQUEST_MESSAGE, 148) == mavlink.MAV_RESULT_ACCEPTED
    ver = master.recv_match(type="AUTOPILOT_VERSION", blocking=True, timeout=3)
    assert ver is not None
    assert ver.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    assert ver.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
    assert ver.capabilities & 1024  # SET_ACTUATOR_TARGET
    # Unknown commands are answered, not ignored.
    assert command(master, 31000) == mavlink.MAV_RESULT_UNSUPPORTED


def test_message_interval_rate_within_10_percent(
    start_sitl: Starter, connect: Connect, udp_port: int
) -> None:
    start_sitl(udp_port)
    master = connect(udp_port)
    r = command(master, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 30, 10_000)  # ATTITUDE 100 Hz
    assert r == mavlink.MAV_RESULT_ACCEPTED
    # Faster than the 1 kHz IMU: denied.
    r = command(master, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 105, 500)
    assert r == mavlink.MAV_RESULT_DENIED
    time.sleep(0.3)  # let the new rate settle, then count over 2 s of wall time
    while master.recv_match(blocking=False) is not None:
        pass
    t0 = time.monotonic()
    stamps = []
    while time.monotonic() - t0 < 2.0:
        m = master.recv_match(type="ATTITUDE", blocking=True, timeout=0.1)
        if m is not None:
            stamps.append(m.time_boot_ms)
    wall = time.monotonic() - t0
    assert len(stamps) / wall == pytest.approx(100.0, rel=0.1)
    sim_rate = (len(stamps) - 1) / ((stamps[-1] - stamps[0]) * 1e-3)
    assert sim_rate == pytest.approx(100.0, rel=0.1)
    # Disable it: the stream stops.
    assert command(master, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 30, -1) == 0
    time.sleep(0.2)
    while master.recv_match(blocking=False) is not None:
        pass
    assert master.recv_match(type="ATTITUDE", blocking=True, timeout=0.5) is None


def test_arm_disarm_offboard_and_failsafe(
    start_sitl: Starter, connect: Connect, udp_port: int
) -> None:
    sitl = start_sitl(udp_port, "--offboard-timeout", "0.5")
    master = connect(udp_port)
    assert command(master, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    wait_heartbeat_where(master, lambda hb: hb.base_mode & 128)
    assert command(master, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0) == 0
    wait_heartbeat_where(master, lambda hb: not hb.base_mode & 128)

    flags = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    r = command(master, mavlink.MAV_CMD_DO_SET_MODE, flags, 6, 0)
    assert r == mavlink.MAV_RESULT_TEMPORARILY_REJECTED  # no setpoints yet

    # Stream setpoints at 20 Hz, then switch to OFFBOARD and arm.
    for _ in range(10):
        send_actuators(master, 0.2)
        time.sleep(0.05)
    assert command(master, mavlink.MAV_CMD_DO_SET_MODE, flags, 6, 0) == 0
    send_actuators(master, 0.2)
    assert command(master, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    hb = wait_heartbeat_where(master, lambda hb: hb.base_mode & 128)
    assert mavutil.mode_string_v10(hb) == "OFFBOARD"
    for _ in range(10):
        send_actuators(master, 0.2)
        time.sleep(0.05)
    # Stop the setpoints: after 0.5 s it fails safe to LAND and, on the ground, disarms.
    hb = wait_heartbeat_where(master, lambda hb: mavutil.mode_string_v10(hb) == "LAND")
    wait_heartbeat_where(master, lambda hb: not hb.base_mode & 128)
    assert sitl.stop() == 0
    log = read_log(sitl.log_path)
    kinds = [e["kind"] for e in log.events]
    assert "failsafe" in kinds and "disarmed" in kinds
    assert log.summary["status"] == "stopped"
    assert log["armed"].any()
    assert (log["custom_mode"] == 6 << 16).any()


def test_lockstep_waits_for_the_client(
    start_sitl: Starter, connect: Connect, udp_port: int
) -> None:
    """In lockstep + OFFBOARD the simulation advances only as the client answers IMU samples."""
    sitl = start_sitl(udp_port, "--clock", "lockstep", "--lockstep-timeout", "2.0")
    master = connect(udp_port)
    r = command(master, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 105, 4000)  # 250 Hz
    assert r == 0
    flags = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    send_actuators(master, 0.0)
    assert command(master, mavlink.MAV_CMD_DO_SET_MODE, flags, 6, 0) == 0
    send_actuators(master, 0.0)
    assert command(master, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0
    # Answer each HIGHRES_IMU with one setpoint; record simulation time.
    stamps = []
    t0 = time.monotonic()
    while len(stamps) < 1000 and time.monotonic() - t0 < 20.0:
        m = master.recv_match(type="HIGHRES_IMU", blocking=True, timeout=1.0)
        if m is None:
            send_actuators(master, 0.4)  # unstick after a lost datagram
            continue
        stamps.append(m.time_usec)
        send_actuators(master, 0.4)
    wall = time.monotonic() - t0
    assert len(stamps) == 1000
    steps = [b - a for a, b in itertools.pairwise(stamps)]
    assert min(steps) == 4000 and sorted(steps)[len(steps) // 2] == 4000
    logger.info(
        "lockstep: %.0f IMU round trips/s = %.0f physics steps/s",
        len(stamps) / wall,
        4 * len(stamps) / wall,
    )
    # Stall the client (less than the lockstep timeout): simulation time must not run on.
    last = stamps[-1]
    time.sleep(0.5)
    pending = []
    while (m := master.recv_match(type="HIGHRES_IMU", blocking=False)) is not None:
        pending.append(m.time_usec)
    assert all(t <= last + 4000 for t in pending)
    assert sitl.stop() == 0
    summary = read_log(sitl.log_path).summary
    assert summary["lockstep_waits"] >= 1000
    assert summary["clock"] == "lockstep"


def test_a_lockstep_wait_still_beats(start_sitl: Starter, connect: Connect, udp_port: int) -> None:
    """A client held off the CPU leaves the lockstep SITL waiting for its setpoint:
    the autopilot's heartbeat goes on (1 Hz of wall time), simulation time does
    not, so the client's link watchdog does not take its own stall for a lost
    autopilot (a loaded machine's lab flight failed safe so, "no heartbeat for
    3.5 s")."""
    sitl = start_sitl(udp_port, "--clock", "lockstep", "--lockstep-timeout", "5.0")
    master = connect(udp_port)
    assert command(master, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 105, 4000) == 0
    flags = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    send_actuators(master, 0.0)
    assert command(master, mavlink.MAV_CMD_DO_SET_MODE, flags, 6, 0) == 0
    assert command(master, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, stepping=True) == 0
    send_actuators(master, 0.0)
    # Drain what came, then answer nothing for 3 s (inside the lockstep timeout).
    while master.recv_match(blocking=True, timeout=0.2) is not None:
        pass
    beats, samples = [], []
    t0 = time.monotonic()
    while time.monotonic() - t0 < 3.0:
        m = master.recv_match(type=["HEARTBEAT", "HIGHRES_IMU"], blocking=True, timeout=0.2)
        if m is None:
            continue
        (beats if m.get_type() == "HEARTBEAT" else samples).append(time.monotonic() - t0)
    assert sitl.stop() == 0
    assert len(samples) <= 1  # waiting: no new sample
    assert len(beats) >= 2, beats  # but beating, about once a second
    assert max(b - a for a, b in itertools.pairwise([0.0, *beats, 3.0])) < 1.6, beats


def test_bad_profile_exits_2(tmp_path: object, udp_port: int) -> None:
    import subprocess
    import sys
    from pathlib import Path

    bad = Path(str(tmp_path)) / "bad.yaml"
    bad.write_text("name: x\nframe: {motors: []}\nphysics: {mass_kg: -1}\n")
    proc = subprocess.run(
        [sys.executable, "-m", "sitl", "run", "--profile", str(bad), "--duration", "1",
         "--mavlink", f"udpout:127.0.0.1:{udp_port}"],
        capture_output=True, timeout=30, text=True,
    )  # fmt: skip
    assert proc.returncode == 2
    assert "bad.yaml" in proc.stderr and "mass_kg" in proc.stderr
