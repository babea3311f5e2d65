"""The PX4 personality's MAVLink face: identity, arming and mode commands, setpoints, IMU.

It shows the PX4-like :class:`~sitl.autopilot.Autopilot` to a ground station or
companion exactly as PX4 SITL would: HEARTBEAT from sysid 1 / compid 1 with
``autopilot = MAV_AUTOPILOT_PX4`` and PX4 custom modes, ``COMMAND_ACK`` for every
command addressed to it, and streams in simulation time. Dispatch, the
commands both stacks answer alike and the streams' schedule are
:class:`~sitl.mavlink_face.MavlinkFace`'s; the socket and peers
:class:`~sitl.mavlink_link.MavlinkLink`'s.

Streams and their defaults (change with ``MAV_CMD_SET_MESSAGE_INTERVAL``)
-------------------------------------------------------------------------
HEARTBEAT 1 Hz, SYS_STATUS 1 Hz, EXTENDED_SYS_STATE 1 Hz, HOME_POSITION 0.2 Hz,
LOCAL_POSITION_NED 10 Hz, RC_CHANNELS 10 Hz, and the IMU-based HIGHRES_IMU,
ATTITUDE, ATTITUDE_QUATERNION at 50 Hz (never faster than the IMU). Interval
requests faster than 1 kHz are DENIED.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from typing import Any

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink

from sitl.autopilot import Autopilot
from sitl.mavlink_face import (
    ID_ATTITUDE,
    ID_ATTITUDE_QUATERNION,
    ID_HIGHRES_IMU,
    ID_LOCAL_POSITION_NED,
    STATUS_STREAMS,
    MavlinkFace,
    as_int,
)
from sitl.personality import FORCE_DISARM_MAGIC, MavResult
from sitl.px4_modes import AUTO_SUB_LAND, MainMode
from sitl.streams import MessageStreams, StreamSpec

__all__ = ["Px4Face", "px4_streams"]

logger = logging.getLogger(__name__)

MAV_AUTOPILOT_PX4 = 12
CAP_SET_ACTUATOR_TARGET = 1024
"""``MAV_PROTOCOL_CAPABILITY_SET_ACTUATOR_TARGET`` (now ``RESERVED3`` in common.xml)."""

CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
    | CAP_SET_ACTUATOR_TARGET
    | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
)
# PX4 encodes versions as major << 24 | minor << 16 | patch << 8 | type (255 = release).
# 1.13.3: the last PX4 release that honours SET_ACTUATOR_CONTROL_TARGET, which we do.
FLIGHT_SW_VERSION = (1 << 24) | (13 << 16) | (3 << 8) | 255


def px4_streams(imu_rate_hz: float) -> MessageStreams:
    """The streams and default intervals of the PX4 face."""
    return MessageStreams(
        [
            *STATUS_STREAMS,
            StreamSpec(ID_LOCAL_POSITION_NED, "LOCAL_POSITION_NED", 0.1),
            StreamSpec(ID_HIGHRES_IMU, "HIGHRES_IMU", 0.02, imu_based=True),
            StreamSpec(ID_ATTITUDE, "ATTITUDE", 0.02, imu_based=True),
            StreamSpec(ID_ATTITUDE_QUATERNION, "ATTITUDE_QUATERNION", 0.02, imu_based=True),
        ],
        imu_rate_hz=imu_rate_hz,
    )


class Px4Face(MavlinkFace[Autopilot]):
    """The MAVLink face of :class:`~sitl.autopilot.Autopilot` (sysid 1, compid 1, autopilot 12).

    On top of :class:`~sitl.mavlink_face.MavlinkFace`: PX4's heartbeat identity,
    ``MAV_CMD_COMPONENT_ARM_DISARM`` (param2 21196 forces), ``MAV_CMD_DO_SET_MODE``
    with PX4 main / sub modes, ``MAV_CMD_NAV_LAND`` (AUTO.LAND),
    ``SET_ACTUATOR_CONTROL_TARGET`` group 0 and ``SET_ATTITUDE_TARGET`` body rates
    (attitude ignored), and HIGHRES_IMU / ATTITUDE with the IMU's gyro.
    """

    mav_autopilot = MAV_AUTOPILOT_PX4
    capabilities = CAPABILITIES
    flight_sw_version = FLIGHT_SW_VERSION
    imu_streams = (ID_HIGHRES_IMU, ID_ATTITUDE, ID_ATTITUDE_QUATERNION)

    # -------------------------------------------------------------- handling

    def neutral_setpoint(self, t_s: float) -> None:
        self.autopilot.on_actuator_target(t_s, (0.0, 0.0, 0.0, 0.0))

    def _handle_actuator_target(self, msg: Any, t_s: float) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        self.setpoints_received += 1
        if msg.group_mlx != 0:
            # Auxiliary groups (MAVSDK sends group 1 alongside): nothing to drive here.
            if "group" not in self._warned:
                self._warned.add("group")
                logger.info("actuator control group %d ignored", msg.group_mlx)
            return
        self._setpoint_age(msg.time_usec * 1e-6, t_s)
        self.autopilot.on_actuator_target(t_s, list(msg.controls))

    def _handle_attitude_target(self, msg: Any, t_s: float) -> None:
        mask = msg.type_mask
        if not mask & mavlink.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE:
            self.autopilot.reject_setpoint()
            self._warn_once("att", "SET_ATTITUDE_TARGET with an attitude is not supported")
            return
        rates = (
            0.0 if mask & 1 else msg.body_roll_rate,
            0.0 if mask & 2 else msg.body_pitch_rate,
            0.0 if mask & 4 else msg.body_yaw_rate,
        )
        thrust = msg.thrust
        if mask & mavlink.ATTITUDE_TARGET_TYPEMASK_THROTTLE_IGNORE:
            thrust = self.autopilot.last_torque_thrust[3]
        self.autopilot.on_rates_target(t_s, rates, thrust)

    def _vehicle_command(self, command: int, p: Sequence[float], t_s: float) -> MavResult | None:
        ap = self.autopilot
        if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            force = as_int(p[1]) == FORCE_DISARM_MAGIC
            if p[0] >= 0.5:
                return ap.arm(t_s, force=force)
            return ap.disarm(t_s, force=force)
        if command == mavlink.MAV_CMD_DO_SET_MODE:
            if not as_int(p[0]) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                return MavResult.DENIED
            return ap.set_mode(t_s, as_int(p[1]), as_int(p[2]))
        if command == mavlink.MAV_CMD_NAV_LAND:
            return ap.set_mode(t_s, MainMode.AUTO, AUTO_SUB_LAND)
        return None
