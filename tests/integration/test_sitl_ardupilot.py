"""``sitl run --autopilot ardupilot`` against pymavlink's mavutil (real UDP, separate process)."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest

os.environ["MAVLINK20"] = "1"

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from sitl.flight_log import read_log
from tests.sitl.test_ardupilot import STEP_PINNED

from .conftest import SitlProcess

pytestmark = pytest.mark.integration
logger = logging.getLogger(__name__)

Starter = Callable[..., SitlProcess]
Connect = Callable[[int], mavutil.mavfile]

CUSTOM = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
GUIDED_NOGPS = 20
RATES_ONLY = mavlink.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE
STEP_REFERENCE = STEP_PINNED
"""The in-process step's regression pin (tests/sitl/test_ardupilot.py): the same
shaped step over MAVLink, lockstep, free flight (the 400 Hz loop runs up to 2.5 ms
after the setpoint arrives on the 250 Hz RAW_IMU grid)."""
STEP_TOL = 0.05  # rad/s


@pytest.fixture
def connect() -> Iterator[Connect]:
    opened: list[mavutil.mavfile] = []

    def _connect(port: int, timeout_s: float = 15.0) -> mavutil.mavfile:
        master = mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{port}", source_system=255, source_component=190, dialect="common"
        )
        opened.append(master)
        assert master.wait_heartbeat(timeout=timeout_s) is not None, "no HEARTBEAT"
        return master

    yield _connect
    for m in opened:
        m.close()


def command(
    master: mavutil.mavfile,
    cmd: int,
    *params: float,
    timeout_s: float = 3.0,
    on_imu: Callable[[Any], None] | None = None,
) -> int:
    """COMMAND_LONG -> result; ``on_imu`` answers RAW_IMU seen meanwhile (lockstep)."""
    p = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][:7]
    master.mav.command_long_send(1, 1, cmd, 0, *p)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        m = master.recv_match(type=["COMMAND_ACK", "RAW_IMU"], blocking=True, timeout=0.2)
        if m is None:
            continue
        if m.get_type() == "RAW_IMU":
            if on_imu is not None:
                on_imu(m)
        elif m.command == cmd:
            return int(m.result)
    raise AssertionError(f"no COMMAND_ACK for command {cmd}")


def read_param(master: mavutil.mavfile, name: str, timeout_s: float = 3.0) -> Any:
    master.mav.param_request_read_send(1, 1, name.encode(), -1)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        m = master.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.2)
        if m is not None and m.param_id == name:
            return m
    raise AssertionError(f"no PARAM_VALUE for {name}")


def wait_heartbeat_where(
    master: mavutil.mavfile, pred: Callable[[Any], bool], timeout_s: float = 5.0
) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        hb = master.recv_match(type="HEARTBEAT", blocking=True, timeout=0.3)
        if hb is not None and pred(hb):
            return hb
    raise AssertionError("expected HEARTBEAT never came")


def test_identity_modes_params_and_stream_limits(
    start_sitl: Starter, connect: Connect, udp_port: int
) -> None:
    start_sitl(udp_port, "--autopilot", "ardupilot")
    master = connect(udp_port)
    hb = master.recv_match(type="HEARTBEAT", blocking=True, timeout=3)
    assert hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert hb.type == mavlink.MAV_TYPE_QUADROTOR
    assert hb.base_mode & CUSTOM and hb.custom_mode == 0
    assert mavutil.mode_string_v10(hb) == "STABILIZE"

    assert command(master, mavlink.MAV_CMD_DO_SET_MODE, CUSTOM, GUIDED_NOGPS) == 0
    hb = wait_heartbeat_where(master, lambda h: h.custom_mode == GUIDED_NOGPS)
    assert mavutil.mode_string_v10(hb) == "GUIDED_NOGPS"
    assert command(master, mavlink.MAV_CMD_DO_SET_MODE, CUSTOM, 2) == 0
    hb = wait_heartbeat_where(master, lambda h: h.custom_mode == 2)
    assert mavutil.mode_string_v10(hb) == "ALT_HOLD"
    r = command(master, mavlink.MAV_CMD_DO_SET_MODE, CUSTOM, 6)  # RTL needs navigation
    assert r == mavlink.MAV_RESULT_FAILED

    # Parameters: read, set, read back.
    pv = read_param(master, "GUID_OPTIONS")
    assert pv.param_value == 0 and pv.param_type == mavlink.MAV_PARAM_TYPE_INT32
    master.mav.param_set_send(1, 1, b"GUID_OPTIONS", 8.0, mavlink.MAV_PARAM_TYPE_INT32)
    ack = master.recv_match(type="PARAM_VALUE", blocking=True, timeout=3)
    assert ack is not None and ack.param_id == "GUID_OPTIONS" and ack.param_value == 8
    assert read_param(master, "GUID_OPTIONS").param_value == 8
    assert read_param(master, "SCHED_LOOP_RATE").param_value == 400
    assert read_param(master, "GUID_TIMEOUT").param_type == mavlink.MAV_PARAM_TYPE_REAL32

    # Streams: faster than 0.8 x 400 Hz is DENIED; 300 Hz is accepted and delivered.
    interval = mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
    assert command(master, interval, 30, 1000) == mavlink.MAV_RESULT_DENIED  # 1 kHz
    assert command(master, interval, 27, 2000) == mavlink.MAV_RESULT_DENIED  # RAW_IMU 500 Hz
    assert command(master, interval, 30, 3333) == mavlink.MAV_RESULT_ACCEPTED  # 300 Hz -> 3 ms
    time.sleep(0.3)
    while master.recv_match(blocking=False) is not None:
        pass
    stamps = []
    t0 = time.monotonic()
    while time.monotonic() - t0 < 1.0:
        m = master.recv_match(type="ATTITUDE", blocking=True, timeout=0.1)
        if m is not None:
            stamps.append(m.time_boot_ms)
    sim_rate = (len(stamps) - 1) / ((stamps[-1] - stamps[0]) * 1e-3)
    assert sim_rate == pytest.approx(1000.0 / 3.0, rel=0.05)


def test_prearm_failure_refused_with_statustext(
    start_sitl: Starter, connect: Connect, udp_port: int
) -> None:
    start_sitl(udp_port, "--autopilot", "ardupilot", "--prearm-fail", "RC not calibrated")
    master = connect(udp_port)
    arm = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
    assert command(master, arm, 1) == mavlink.MAV_RESULT_FAILED
    text = master.recv_match(type="STATUSTEXT", blocking=True, timeout=3)
    assert text is not None and text.text == "PreArm: RC not calibrated"
    assert text.severity == mavlink.MAV_SEVERITY_CRITICAL
    # ARMING_CHECK = 0 skips the pre-arm checks.
    master.mav.param_set_send(1, 1, b"ARMING_CHECK", 0.0, mavlink.MAV_PARAM_TYPE_INT32)
    assert master.recv_match(type="PARAM_VALUE", blocking=True, timeout=3).param_value == 0
    assert command(master, arm, 1) == mavlink.MAV_RESULT_ACCEPTED
    wait_heartbeat_where(master, lambda h: h.base_mode & 128)


def test_guided_nogps_flies_and_roll_step_matches(
    start_sitl: Starter, connect: Connect, udp_port: int
) -> None:
    """Lockstep: take off on climb-rate thrust, hover, +1 rad/s roll step; check the log.

    No RC here: FS_OPTIONS bit 2 (4, with the default 16) keeps GUIDED_NOGPS flying
    through the radio failsafe, as a companion-only ArduPilot vehicle is set up."""
    sitl = start_sitl(
        udp_port, "--autopilot", "ardupilot", "--clock", "lockstep", "--lockstep-timeout", "2.0",
        "--param", "FS_OPTIONS=20",
    )  # fmt: skip
    master = connect(udp_port)

    def send(roll_rate: float, thrust: float) -> None:
        master.mav.set_attitude_target_send(
            0, 1, 1, RATES_ONLY, [1.0, 0.0, 0.0, 0.0], roll_rate, 0.0, 0.0, thrust
        )

    def hold(_: Any) -> None:
        send(0.0, 0.5)

    interval = mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
    assert command(master, interval, 27, 4000) == 0  # RAW_IMU 250 Hz paces the lockstep
    assert command(master, mavlink.MAV_CMD_DO_SET_MODE, CUSTOM, GUIDED_NOGPS, on_imu=hold) == 0
    assert command(master, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, on_imu=hold) == 0
    t_start_us: int | None = None
    t_step_us: int | None = None
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        m = master.recv_match(type="RAW_IMU", blocking=True, timeout=1.0)
        if m is None:
            send(0.0, 0.5)  # a lost datagram: unstick the lockstep
            continue
        t_start_us = m.time_usec if t_start_us is None else t_start_us
        t = (m.time_usec - t_start_us) * 1e-6
        if t < 1.5:
            send(0.0, 0.7)  # climb at (0.7 - 0.5) * 2 * 2.5 = 1 m/s
        elif t < 3.0:
            send(0.0, 0.5)  # hold altitude
        elif t < 3.15:
            if t_step_us is None:
                t_step_us = m.time_usec
            send(1.0, 0.5)
        elif t < 3.6:
            send(0.0, 0.5)
        else:
            break
    assert t_step_us is not None
    assert sitl.stop() == 0
    log = read_log(sitl.log_path)
    t_s, p = log["t_s"], log["rate_frd_rad_s"][:, 0]
    alt = -log["pos_ned_m"][:, 2]
    t_step = t_step_us * 1e-6
    assert alt[np.searchsorted(t_s, t_step)] > 0.8  # it flew
    assert log["armed"].any() and (log["custom_mode"] == GUIDED_NOGPS).any()
    measured = {}
    for t_ref, p_ref in STEP_REFERENCE.items():
        measured[t_ref] = float(p[np.argmin(np.abs(t_s - (t_step + t_ref)))])
        assert measured[t_ref] == pytest.approx(p_ref, abs=STEP_TOL), f"at {t_ref * 1e3:.0f} ms"
    logger.info("roll-rate step over MAVLink: %s", measured)
