"""``companion preflight`` against the SITL as a separate process, each personality:
set up well, it passes (exit 0); set up badly, each check fails or warns on its
own line with its fix (exit 1). Nothing moves: the vehicle stays disarmed and no
setpoint reaches the SITL."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from tests.integration.conftest import ROOT, SitlProcess

pytestmark = pytest.mark.integration

SWITCH_FLIP = """\
duration_s: 60
aux_us: [1000]
segments:
  - {t_s: 0.0, level: true}
  - {t_s: 1.2, level: true, aux_us: [2000]}
  - {t_s: 1.8, level: true, aux_us: [1000]}
"""
"""The pilot flips the engage switch (ch5) once, early, while preflight watches."""


def preflight(
    port: int, tmp_path: Path, *args: str, start: Callable[[], SitlProcess]
) -> tuple[int, dict[str, Any], str]:
    """Start preflight listening on ``port``, then the SITL; the JSON it printed."""
    env = dict(os.environ, MAVLINK20="1", PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "companion", "preflight", "--json",
           "--connect", f"udpin:127.0.0.1:{port}", *args]  # fmt: skip
    proc = subprocess.Popen(
        cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    sitl = start()
    try:
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    sitl_rc = sitl.stop()
    assert sitl_rc == 0, sitl.stderr()
    events = sitl.log_path.with_suffix(".events.jsonl")
    kinds = [json.loads(x)["kind"] for x in events.read_text().splitlines() if x.strip()]
    assert not [k for k in kinds if "arm" in k or "setpoint" in k or "offboard" in k], kinds
    return proc.returncode, json.loads(out), err.decode()


def lines(doc: dict[str, Any]) -> dict[str, tuple[str, str, str]]:
    return {c["name"]: (c["status"], c["detail"], c["fix"]) for c in doc["checks"]}


@pytest.fixture
def key(tmp_path: Path) -> Path:
    path = tmp_path / "key"
    path.write_text("preflight test passphrase\n")
    path.chmod(0o600)
    return path


@pytest.fixture
def sticks(tmp_path: Path) -> Path:
    path = tmp_path / "switch.yaml"
    path.write_text(SWITCH_FLIP)
    return path


GOOD = {
    "px4": ("--offboard-timeout", "0.3"),
    "ardupilot": ("--param", "GUID_OPTIONS=8", "--param", "GUID_TIMEOUT=1"),
}
OUTPUT = {"px4": "actuator", "ardupilot": "rates"}


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_a_well_set_autopilot_passes(
    autopilot: str,
    udp_port: int,
    tmp_path: Path,
    start_sitl: Callable[..., SitlProcess],
    key: Path,
    sticks: Path,
) -> None:
    rc, doc, err = preflight(
        udp_port, tmp_path, "--output", OUTPUT[autopilot], "--signing-key", str(key),
        "--watch-s", "3",
        start=lambda: start_sitl(
            udp_port, "--autopilot", autopilot, "--pilot", str(sticks), "--no-auto-arm",
            "--signing-key", str(key), *GOOD[autopilot],
        ),
    )  # fmt: skip
    got = lines(doc)
    not_passed = {n: v for n, v in got.items() if v[0] != "pass"}
    assert rc == 0, (not_passed, err[-2000:])
    assert doc["ok"] is True and doc["stack"] == autopilot
    # What is measured on this machine may warn on a loaded one (a gap in the
    # SITL's stream, the round trip's jitter, the law's p99; the dev install runs
    # the pure-Python core, which warns anyway); everything read must pass.
    assert set(not_passed) <= {"control core", "IMU rate", "round trip"}, not_passed
    assert got["engage switch"][0] == "pass"
    assert got["signing"][0] == "pass"
    assert 200 <= doc["imu_rate_hz"] <= 300
    # The SITL is paced by the wall clock: its IMU time stamps keep real time.
    assert 0.9 <= doc["autopilot_clock_ratio"] <= 1.1, doc


def test_a_badly_set_px4_fails_each_check_with_its_fix(
    udp_port: int, tmp_path: Path, start_sitl: Callable[..., SitlProcess]
) -> None:
    bad = (
        "--firmware", "1.14.0",
        "--param", "COM_OF_LOSS_T=5", "--param", "COM_OBL_RC_ACT=6",
        "--param", "COM_RC_LOSS_T=3", "--param", "NAV_RCL_ACT=0",
        "--param", "COM_RCL_EXCEPT=4", "--param", "COM_RC_IN_MODE=4",
        "--param", "RC_MAP_PITCH=3", "--param", "RC_MAP_THROTTLE=2",
        "--param", "IMU_GYRO_RATEMAX=200",
        "--no-rc", "--no-position", "--link", "delay_ms=15",
    )  # fmt: skip
    rc, doc, err = preflight(
        udp_port, tmp_path, "--rate-hz", "1000", "--watch-s", "2",
        start=lambda: start_sitl(udp_port, "--autopilot", "px4", "--no-auto-arm", *bad),
    )  # fmt: skip
    got = lines(doc)
    assert rc == 1, (got, err)
    expected = {
        "output": ("fail", "--output rates"),
        "COM_OF_LOSS_T": ("fail", "COM_OF_LOSS_T to 0.3"),
        "COM_OBL_RC_ACT": ("fail", "Position mode"),
        "COM_RC_LOSS_T": ("warn", "at most 1"),
        "NAV_RCL_ACT": ("fail", "2 (Return)"),
        "COM_RCL_EXCEPT": ("warn", "COM_RCL_EXCEPT = 0"),
        "COM_RC_IN_MODE": ("fail", "RC only"),
        "RC map": ("fail", "sticks.channels"),
        "IMU_GYRO_RATEMAX": ("warn", "--rate-hz 200"),
        "IMU rate": ("fail", "lower --rate-hz"),
        "round trip": ("warn", "faster link"),
        "RC": ("fail", "bind"),
        "signing": ("warn", "signing on both sides"),
        "position": ("warn", "GPS"),
    }
    for name, (status, fix) in expected.items():
        assert got[name][0] == status and fix in got[name][2], (name, got[name])
    assert got["landed state"][0] == "pass"


def test_a_badly_set_ardupilot_fails_each_check_with_its_fix(
    udp_port: int, tmp_path: Path, start_sitl: Callable[..., SitlProcess]
) -> None:
    bad = (
        "--param", "GUID_OPTIONS=0", "--param", "GUID_TIMEOUT=3",
        "--param", "MAV_GCS_SYSID=1", "--param", "FS_THR_ENABLE=0",
        "--param", "FS_OPTIONS=20", "--param", "RC_FS_TIMEOUT=5",
        "--param", "SCHED_LOOP_RATE=200", "--param", "FLTMODE_CH=5",
        "--param", "RCMAP_ROLL=4", "--param", "RCMAP_YAW=1",
    )  # fmt: skip
    rc, doc, err = preflight(
        udp_port, tmp_path, "--output", "actuator", "--watch-s", "2",
        start=lambda: start_sitl(
            udp_port, "--autopilot", "ardupilot", "--pilot", "paper-acro", "--no-auto-arm", *bad
        ),
    )  # fmt: skip
    got = lines(doc)
    assert rc == 1, (got, err)
    expected = {
        "output": ("fail", "--output rates"),
        "GUID_TIMEOUT": ("warn", "GUID_TIMEOUT to 1"),
        "MAV_GCS_SYSID": ("warn", "255"),
        "FS_THR_ENABLE": ("fail", "1 (RTL)"),
        "FS_OPTIONS": ("warn", "FS_OPTIONS = 16"),
        "RC_FS_TIMEOUT": ("warn", "at most 1"),
        "SCHED_LOOP_RATE": ("warn", "--rate-hz 160"),
        "FLTMODE_CH": ("fail", "--engage-channel"),
        "RC map": ("fail", "RCMAP_ROLL"),
        "engage switch": ("fail", "--engage-channel"),
    }
    for name, (status, fix) in expected.items():
        assert got[name][0] == status and fix in got[name][2], (name, got[name])
    # GUID_OPTIONS matters for body rates only: with actuator output the output line fails.
    assert got["GUID_OPTIONS"][0] == "pass"


def test_a_signing_autopilot_and_a_companion_without_its_key(
    udp_port: int, tmp_path: Path, start_sitl: Callable[..., SitlProcess], key: Path
) -> None:
    rc, doc, err = preflight(
        udp_port, tmp_path, "--watch-s", "1",
        start=lambda: start_sitl(udp_port, "--no-auto-arm", "--signing-key", str(key)),
    )  # fmt: skip
    got = lines(doc)
    assert rc == 1, (got, err)
    assert got["signing"][0] == "fail" and "--signing-key" in got["signing"][2]


def test_no_autopilot_is_a_failed_link_line(tmp_path: Path, udp_port: int) -> None:
    out = subprocess.run(
        [sys.executable, "-m", "companion", "preflight", "--connect",
         f"udpin:127.0.0.1:{udp_port}", "--heartbeat-timeout-s", "0.5"],
        cwd=ROOT, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert out.returncode == 1, out.stderr
    assert out.stdout.startswith("FAIL  link")
    assert "no HEARTBEAT" in out.stdout and "fix: check the --connect URL" in out.stdout
