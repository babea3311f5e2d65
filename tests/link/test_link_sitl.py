"""MavlinkLink against the bundled SITL running as a separate process over real UDP."""

from __future__ import annotations

import asyncio
import time
from typing import Any

import pytest

from companion.link.mavlink import MavlinkLink, mavlink2
from companion.link.transport import open_transport

from ..integration.conftest import free_udp_port, start_sitl  # noqa: F401  (fixture)

pytestmark = pytest.mark.integration


async def test_link_against_sitl(start_sitl: Any) -> None:  # noqa: F811
    port = free_udp_port()
    seen: dict[str, int] = {}

    def on_message(msg: Any) -> None:
        t = msg.get_type()
        seen[t] = seen.get(t, 0) + 1

    link = MavlinkLink(open_transport(f"udpin:127.0.0.1:{port}"), on_message=on_message)
    async with link:  # listen before the SITL starts sending
        sitl = start_sitl(port, "--clock", "realtime", duration_s=5.0)
        t_wait = time.monotonic()
        hb = await link.wait_heartbeat(15.0)
        waited_s = time.monotonic() - t_wait
        assert link.target == (1, 1)
        assert hb.autopilot == mavlink2.MAV_AUTOPILOT_PX4
        result = await link.request_message_interval(
            mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU, 4000, timeout_s=1.0
        )
        assert result == mavlink2.MAV_RESULT_ACCEPTED
        before = seen.get("HIGHRES_IMU", 0)
        await asyncio.sleep(1.0)
        imu_per_s = seen.get("HIGHRES_IMU", 0) - before
        assert sitl.proc.poll() is None, sitl.stderr()
    assert seen.get("HEARTBEAT", 0) >= 1
    assert imu_per_s > 150, f"HIGHRES_IMU at {imu_per_s}/s after asking for 250 Hz"
    assert link.counters["foreign_ignored"] == 0
    assert link.counters["bad_data"] == 0
    # Only what we sent before the SITL first spoke (our heartbeats, one a second)
    # had nowhere to go.
    assert link.transport.counters["dropped_no_peer"] <= 1 + int(waited_s)
    assert link.transport.counters["chunks_out"] >= 2
