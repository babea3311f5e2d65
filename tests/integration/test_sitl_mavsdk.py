"""The SITL against MAVSDK-Python 4.x (native binding) as a ground station over real UDP.

MAVSDK listens (``udpin://0.0.0.0:PORT``), the SITL sends to that port (udpout) and
answers MAVSDK's address, as with PX4 SITL on 14540.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import AsyncIterator, Callable
from typing import Any

import pytest

# A test dependency (pyproject's test extra): missing, this module fails to
# collect, so CI fails rather than skipping the real client.
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
from mavsdk.asyncio.plugins.action import ActionAsync
from mavsdk.asyncio.plugins.offboard import (
    ActuatorControl,
    ActuatorControlGroup,
    AttitudeRate,
    OffboardAsync,
)
from mavsdk.asyncio.plugins.telemetry import FlightMode, TelemetryAsync

from sitl.flight_log import read_log

from .conftest import SitlProcess

pytestmark = pytest.mark.integration

Starter = Callable[..., SitlProcess]


async def first(gen: AsyncIterator[Any], pred: Callable[[Any], bool], timeout_s: float) -> Any:
    """First item of a MAVSDK subscription that satisfies ``pred``."""

    async def scan() -> Any:
        async for item in gen:
            if pred(item):
                return item
        raise AssertionError("subscription ended")

    try:
        return await asyncio.wait_for(scan(), timeout_s)
    finally:
        await gen.aclose()


async def test_mavsdk_discovers_flies_rates_and_actuators(
    start_sitl: Starter, udp_port: int
) -> None:
    sitl = start_sitl(udp_port, "--offboard-timeout", "1.0")
    config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(config) as drone:
        await drone.add_any_connection(f"udpin://0.0.0.0:{udp_port}")
        system = await drone.first_autopilot(15.0)
        assert system is not None, "MAVSDK did not discover the SITL"
        telemetry = TelemetryAsync(system)
        action = ActionAsync(system)
        offboard = OffboardAsync(system)

        # Telemetry: attitude (level on the ground) and IMU (gravity on -z FRD).
        att = await first(telemetry.subscribe_attitude_euler(), lambda a: True, 10.0)
        # Level, within the estimate's tilt error (0.7 deg, and 1 deg drawn per flight).
        assert abs(att.roll_deg) < 4.0 and abs(att.pitch_deg) < 4.0
        imu = await first(telemetry.subscribe_imu(), lambda i: True, 10.0)
        assert imu.acceleration_frd.down_m_s2 == pytest.approx(-9.81, abs=0.3)
        mode = await first(telemetry.subscribe_flight_mode(), lambda m: True, 10.0)
        assert mode == FlightMode.MANUAL

        # Offboard with body rates: level, a bit above hover -> climbs.
        await offboard.set_attitude_rate(AttitudeRate(0.0, 0.0, 0.0, 0.6))
        await offboard.start()
        await action.arm()
        await first(telemetry.subscribe_armed(), lambda a: a, 5.0)
        await first(telemetry.subscribe_flight_mode(), lambda m: m == FlightMode.OFFBOARD, 5.0)
        await asyncio.sleep(1.5)
        await offboard.set_attitude_rate(AttitudeRate(0.0, 0.0, 0.0, 0.45))

        # Then torques + thrust (SET_ACTUATOR_CONTROL_TARGET group 0).
        controls = [0.0, 0.0, 0.15, 0.45] + [math.nan] * 4  # yaw right
        await offboard.set_actuator_control(ActuatorControl([ActuatorControlGroup(controls)]))
        await asyncio.sleep(1.0)
        assert await offboard.is_active()
        mode = await first(telemetry.subscribe_flight_mode(), lambda m: True, 5.0)
        assert mode == FlightMode.OFFBOARD
        await offboard.stop()  # -> HOLD (AUTO LOITER)
        await first(telemetry.subscribe_flight_mode(), lambda m: m == FlightMode.HOLD, 5.0)

    assert sitl.stop() == 0
    log = read_log(sitl.log_path)
    # Climbed under the rates setpoint, and both setpoint kinds arrived.
    assert log["pos_ned_m"][:, 2].min() < -0.3
    assert log.summary["setpoints_received"] > 20
    assert log.summary["rejected_setpoints"] == 0
    # The actuator phase's yaw torque turned the nose right (FRD +r); the rates phase did not.
    assert log["rate_frd_rad_s"][:, 2].max() > 0.5
    modes = {e.get("new") for e in log.events if e["kind"] == "mode"}
    assert {"OFFBOARD", "LOITER"} <= modes
