"""Malformed MAVLink against the companion and the SITL in flight (``scripts/fuzz.py``).

One short seeded run (a clean flight, then about 3000 cases of every default
kind over four 3 s flights on the real-time clock; about 40 s of wall time) as a
subprocess, the way a user runs it; its JSON report is the witness. The harness
and the kinds are described in :mod:`sitl.lab.fuzzing.mavlink`. Its tracking
ratios are real-time figures: marked ``alone``, so ``scripts/test --long`` flies
them after the other long checks, not beside them.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sitl.lab.fuzzing.mavlink import (
    DEFAULT_KINDS,
    IMU_PERIOD_US,
    KINDS,
    StreamState,
    generate_cases,
    late_commands,
)

ROOT = Path(__file__).resolve().parents[2]
CASES = 3000
SHORT_RUN = ("--json", "--seed", "1", "--cases", str(CASES), "--rate", "2000", "--duration", "3")


@pytest.fixture(scope="module")
def short_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[int, dict[str, Any]]:
    """The exit code and the report of ``scripts/fuzz.py`` with :data:`SHORT_RUN`."""
    out = tmp_path_factory.mktemp("fuzz")
    proc = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "fuzz.py"), *SHORT_RUN, "--out", str(out)],
        cwd=ROOT, capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert proc.returncode in (0, 1) and proc.stdout.startswith("{"), proc.stderr[-3000:]
    return proc.returncode, json.loads(proc.stdout)


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.long
@pytest.mark.alone
def test_every_kind_is_sent_and_counted(short_run: tuple[int, dict[str, Any]]) -> None:
    _, report = short_run
    assert report["clean"]["failsafes"] == [] and report["clean"]["crashes"] == []
    assert report["clean"]["budget"]["sample_ratio"] > 0.98
    sent = report["cases_sent"]
    assert set(sent) == set(DEFAULT_KINDS), sent
    # What a failsafe cut off is counted, not lost.
    assert sum(sent.values()) + report["cases_undelivered"] == CASES
    for flight in report["flights"]:
        assert flight["commands"]["setpoints"] > 0, flight["name"]


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.long
@pytest.mark.alone
def test_no_crash_and_no_nonfinite_command(short_run: tuple[int, dict[str, Any]]) -> None:
    """Neither process dies or logs a traceback, the vehicle does not crash, and every
    setpoint on the wire is finite and in range, whatever arrived."""
    _, report = short_run
    crashes = [(f["name"], c) for f in report["flights"] for c in f["crashes"]]
    assert report["crashes"] == 0, crashes
    assert report["vehicle_crashes"] == 0, report["failures"]
    bad = [(f["name"], f["commands"]["examples"]) for f in report["flights"]]
    assert report["nonfinite_commands"] == 0, bad


@pytest.mark.integration
@pytest.mark.slow
@pytest.mark.long
@pytest.mark.alone
def test_garbage_without_a_valid_imu_sample_costs_no_failsafe_and_no_tracking(
    short_run: tuple[int, dict[str, Any]],
) -> None:
    """The targets in full (the script's exit code): for garbage that carries no
    valid IMU sample, no failsafe and an MAE within 1.2x of the clean flight."""
    rc, report = short_run
    assert report["targets_met"] and rc == 0, report["failures"]


def test_the_same_seed_makes_the_same_cases() -> None:
    st = StreamState(imu_time_usec=5_000_000, gyro_rad_s=(0.5, -0.1, 0.2))
    for kind in KINDS:
        a = generate_cases(7, kind, 40, st)
        assert a == generate_cases(7, kind, 40, st), kind
        assert a != generate_cases(8, kind, 40, st), kind
        assert {c.path for c in a} <= set(KINDS[kind].paths)


def _sitl_log(path: Path, delays_steps: list[int]) -> Path:
    """A SITL log at 1 kHz with IMU samples every 4 steps, each answered by a new
    motor command ``delays_steps[i]`` steps after its sample."""
    n = 4 * len(delays_steps) + 800
    t = np.arange(n) * 1e-3
    imu_idx = np.arange(0, 4 * len(delays_steps), 4) + 200
    cmd = np.zeros((n, 4))
    level = 0.0
    for i, d in zip(imu_idx, delays_steps, strict=True):
        level += 0.01
        cmd[i + d :] = level
    np.savez(path, t_s=t, motor_cmd=cmd, imu_t_s=t[imu_idx])
    return path


def test_late_commands_counts_answers_past_the_next_sample(tmp_path: Path) -> None:
    assert IMU_PERIOD_US == 4000
    on_time = _sitl_log(tmp_path / "a.npz", [4] * 300)
    assert late_commands(on_time) == 0
    delays = [4] * 300
    for i in (100, 150, 200):
        delays[i] = 7  # the answer lands 3 ms after the next sample
    assert late_commands(_sitl_log(tmp_path / "b.npz", delays)) == 3
    assert late_commands(tmp_path / "missing.npz") is None
