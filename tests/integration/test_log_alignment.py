"""The companion's control log lines up with the autopilot's own log on one time axis.

Each control-log message is stamped with its IMU sample's time on the autopilot's
clock (companion.records.control_log). The bundled SITL keeps every IMU sample it
took in its log (``imu_t_s``, ``imu_gyro_rad_s``), as PX4 keeps ``sensor_combined``
in its ULog: read with the reference reader (``mcap``), every sample the companion
logged is one of the autopilot's, at the same time to the microsecond, with the same
gyro reading (to MAVLink's float32). The real PX4's ULog: tests/realstack/test_px4.py.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from sitl.flight_log import read_log
from sitl.lab.fly import fly_mavlink

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
F450 = ROOT / "vehicle_profiles" / "f450.yaml"
AXES = ("roll", "pitch", "yaw")


def test_every_logged_sample_is_the_autopilots_at_the_same_time(tmp_path: Path) -> None:
    flight = fly_mavlink(F450, "paper-acro", tmp_path / "flight", duration_s=6.0)
    assert flight.companion_rc == 0, flight.why()
    sitl = read_log(flight.sitl_log)
    imu_us = np.round(sitl["imu_t_s"] * 1e6).astype(np.int64)
    at = {int(t): i for i, t in enumerate(imu_us)}
    gyro = sitl["imu_gyro_rad_s"].astype(np.float32)
    n = 0
    with flight.control_log.open("rb") as f:
        for _schema, _channel, msg in make_reader(f).iter_messages(topics=["/rates"]):
            assert msg.log_time % 1000 == 0, msg.log_time  # whole microseconds
            i = at.get(msg.log_time // 1000)
            assert i is not None, f"{msg.log_time} ns is no IMU sample of the autopilot's"
            got = json.loads(msg.data)
            want = gyro[i]
            for k, axis in enumerate(AXES):
                assert np.float32(got[f"meas_{axis}_rad_s"]) == want[k], (msg.log_time, axis)
            n += 1
    period_s = float(np.median(np.diff(sitl["imu_t_s"])))
    assert n > 0.9 * 3.0 / period_s, n  # the samples of at least 3 s of flight
