"""A realtime SITL answers TIMESYNC with the clock it keeps to, the wall's, so a
client dating its samples sees how late a SITL fallen behind delivers them."""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from companion.profile import load_profile
from sitl.mavlink_link import parse_endpoint
from sitl.runner import RunConfig, Runner

ROOT = Path(__file__).resolve().parents[2]
SLOW_FROM_STEP = 100
STEP_WALL_S = 0.002
"""Each physics step (1 ms of simulation) takes this long of wall time from
``SLOW_FROM_STEP`` on: the SITL falls behind by a millisecond per step."""


def test_a_sitl_fallen_behind_the_wall_answers_timesync_with_the_walls_time() -> None:
    client = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    client.bind(("127.0.0.1", 0))
    client.settimeout(0.5)
    port = client.getsockname()[1]
    profile = load_profile(ROOT / "vehicle_profiles" / "f450.yaml")
    cfg = RunConfig(
        mavlink=parse_endpoint(f"udpout:127.0.0.1:{port}"),
        clock="realtime",
        seed=1,
        duration_s=1.0,
        initial_mode="MANUAL",
        auto_arm=False,
        log_path=None,
    )
    runner = Runner(profile, cfg, profile_name="f450")
    runner.face.streams.set_interval(mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, 4000.0, t_s=0.0)
    step = runner.quad.step

    def slow_step(motors: Any) -> None:
        if runner.quad.steps >= SLOW_FROM_STEP:
            time.sleep(STEP_WALL_S)  # a loaded machine
        step(motors)

    runner.quad.step = slow_step  # type: ignore[method-assign]
    sitl = threading.Thread(target=runner.run, daemon=True)
    mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    newest_imu_s = 0.0
    answers: list[tuple[float, float]] = []  # (the SITL's time, the newest IMU stamp)
    sitl.start()
    try:
        asked_at = 0.0
        while sitl.is_alive() and len(answers) < 5:
            try:
                data, addr = client.recvfrom(65536)
            except TimeoutError:
                continue
            for msg in mav.parse_buffer(data) or []:
                if msg.get_type() == "HIGHRES_IMU":
                    newest_imu_s = max(newest_imu_s, msg.time_usec * 1e-6)
                elif msg.get_type() == "TIMESYNC" and msg.tc1 != 0:
                    answers.append((msg.tc1 * 1e-9, newest_imu_s))
            now = time.monotonic()
            if newest_imu_s > 0.3 and now - asked_at > 0.05:
                client.sendto(mavlink.MAVLink_timesync_message(0, 1).pack(mav), addr)
                asked_at = now
    finally:
        runner.stop.set()
        sitl.join(10)
        client.close()

    assert len(answers) == 5, answers
    # Past 0.3 s of simulation, the SITL is more than 0.2 s behind the wall (one more
    # millisecond every step since 0.1 s): its answer is the wall's time, the newest
    # sample's stamp the simulation's.
    for clock_s, imu_s in answers:
        assert clock_s - imu_s > 0.15, answers
