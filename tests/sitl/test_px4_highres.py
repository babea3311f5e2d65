"""HIGHRES_IMU carries PX4's ``sensor_combined``: the mean of the gyro and accel samples
over PX4's integration interval (``IMU_INTEG_RATE``, 200 Hz), not one sample. The
real PX4 streams it from ``sensor_combined`` (``src/modules/mavlink/streams/
HIGHRES_IMU.hpp``), which the sensors module fills with ``vehicle_imu``'s delta angle
over its dt. The face runs in this process on a real UDP socket."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink2

from companion.profile import load_profile
from sitl.autopilot import Autopilot, AutopilotConfig
from sitl.mavlink_link import parse_endpoint
from sitl.px4_face import INTEGRATION_INTERVAL_S, Px4Face, px4_streams
from tests.sitl.udp_client import Client

ROOT = Path(__file__).resolve().parents[2]
HIGHRES = mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU


def highres_per_sample(
    client: Client, imu_hz: float, gyro: list[float], stream_hz: float | None = None
) -> list[Any]:
    """A PX4 face on an ``imu_hz`` IMU, HIGHRES_IMU asked at ``stream_hz`` (default:
    the IMU's rate), fed one sample per value of ``gyro`` (roll rate; accel x the
    same): what it sent, with the index of the sample each went out with."""
    profile = load_profile(ROOT / "vehicle_profiles" / "f450.yaml")
    ap = Autopilot(profile, AutopilotConfig())
    face = Px4Face(
        parse_endpoint(f"udpout:127.0.0.1:{client.port}"), ap, px4_streams(imu_hz)
    ).open()
    try:
        client.mav.command_long_send(
            1,
            1,
            mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL,
            0,
            HIGHRES,
            1e6 / (stream_hz or imu_hz),
            0,
            0,
            0,
            0,
            0,
        )
        assert [m.result for m in client.exchange(face) if m.get_type() == "COMMAND_ACK"] == [0]
        out = []
        for k, w in enumerate(gyro):
            t = k / imu_hz
            s = face.snapshot
            s.t_s, s.imu_t_s = t, t
            s.gyro_frd_rad_s, s.accel_frd_m_s2 = (w, 0.0, 0.0), (w, 0.0, -9.81)
            face.publish(t, imu_sample=True, wall_s=t)
            out += [(k, m) for m in client.received(0.02) if m.get_type() == "HIGHRES_IMU"]
        return out
    finally:
        face.close()


def test_a_1_khz_imu_asked_at_250_hz_goes_out_as_the_mean_of_four_samples(
    client: Client,
) -> None:
    """PX4's 5 ms, shortened to the 4 ms stream; 50 Hz: the 5 ms, five samples."""
    gyro = [0.1 * k * (-1) ** k for k in range(24)]  # alternating: a point sample aliases
    for stream_hz, n in ((250.0, 4), (50.0, 5)):
        sent = highres_per_sample(client, 1000.0, gyro, stream_hz)
        assert [k for k, _ in sent] == list(range(0, len(gyro), round(1000.0 / stream_hz)))
        for k, m in sent:
            window = gyro[max(0, k - n + 1) : k + 1]
            want = math.fsum(window) / len(window)
            assert m.xgyro == pytest.approx(want, abs=1e-6), (stream_hz, k)
            assert m.xacc == pytest.approx(want, abs=1e-6), (stream_hz, k)
            assert m.time_usec == k * 1000


@pytest.mark.parametrize("imu_hz", [250.0, 1000.0])
def test_at_the_imus_own_rate_each_sample_goes_out_as_itself_to_the_bit(
    client: Client, imu_hz: float
) -> None:
    """Over MAVLink the same flight as in process: at 250 Hz PX4's 5 ms is one
    sample; a 1 kHz stream is one sample a message."""
    assert round(INTEGRATION_INTERVAL_S * 250.0) == 1
    gyro = [0.1234567 * k * (-1) ** k for k in range(6)]
    sent = highres_per_sample(client, imu_hz, gyro)
    assert [m.xgyro for _, m in sent] == [float(np.float32(w)) for w in gyro]
