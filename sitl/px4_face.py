"""The PX4 personality's MAVLink face: identity, arming and mode commands, setpoints,
parameters, IMU.

It shows the PX4-like :class:`~sitl.autopilot.Autopilot` to a ground station or
companion exactly as PX4 SITL would: HEARTBEAT from sysid 1 / compid 1 (PX4's
``MAV_SYS_ID`` / ``MAV_COMP_ID``) with ``autopilot = MAV_AUTOPILOT_PX4`` and PX4
custom modes, ``COMMAND_ACK`` for every command addressed to it, PX4's parameter
protocol, and streams in simulation time. Dispatch, the commands both stacks
answer alike, the parameter messages and the streams' schedule are
:class:`~sitl.mavlink_face.MavlinkFace`'s; the socket and peers
:class:`~sitl.mavlink_link.MavlinkLink`'s.

Firmware (``firmware``, ``sitl run --firmware``; default 1.13.3)
-----------------------------------------------------------------
AUTOPILOT_VERSION reports ``flight_sw_version = major << 24 | minor << 16 |
patch << 8 | type`` (255 for a release). Up to 1.13 ``SET_ACTUATOR_CONTROL_TARGET``
group 0 drives the mixer and ``capabilities`` has SET_ACTUATOR_TARGET (1024);
from 1.14 (PX4 PR #20837) the message is dropped unhandled (logged once, not a
setpoint: it neither enters nor keeps OFFBOARD) and the bit is clear, while
body-rate ``SET_ATTITUDE_TARGET`` works in both. From 1.13 ``capabilities``
also has PARAM_ENCODE_BYTEWISE (16; PX4 PR #19447, April 2022).

Parameters (``sitl.px4_params``)
--------------------------------
As PX4's ``MavlinkParametersManager``: ``PARAM_VALUE`` carries an INT32's bytes
in ``param_value`` (bytewise) and a FLOAT as itself; ``PARAM_SET`` is decoded
the same way, and dropped unanswered (logged: "param types mismatch") when its
``param_type`` is not the parameter's; ``PARAM_REQUEST_LIST`` answers
``_HASH_CHECK`` first (index 65535, UINT32, not counted) and then every
parameter; ``PARAM_REQUEST_READ`` of ``_HASH_CHECK`` answers the hash alone.

Streams and their defaults (change with ``MAV_CMD_SET_MESSAGE_INTERVAL``)
-------------------------------------------------------------------------
HEARTBEAT 1 Hz, SYS_STATUS 1 Hz, EXTENDED_SYS_STATE 1 Hz, HOME_POSITION 0.2 Hz,
LOCAL_POSITION_NED 10 Hz, RC_CHANNELS 10 Hz, and the IMU-based HIGHRES_IMU,
ATTITUDE, ATTITUDE_QUATERNION at 50 Hz (never faster than the IMU). HIGHRES_IMU
carries PX4's ``sensor_combined``: the mean of the IMU samples over its
integration interval (``vehicle_imu``'s delta angle and velocity over their dt,
``IMU_INTEG_RATE`` 200 Hz: five samples of a 1 kHz IMU; a faster stream's interval
where it is asked for one), not a single sample; it is sent at the rate asked,
where PX4 sends each mean once. Interval
requests faster than 1 kHz are DENIED. The attitude and LOCAL_POSITION_NED are
the estimator's (``sitl.mavlink_face``: "The estimate, not the truth"); a
LOCAL_POSITION_NED due before the first position estimate goes out when it comes.
MANUAL_CONTROL is off until asked for; then, as PX4 v1.16 does, one frame goes
out at once (the joystick's, or with none the neutral x 0, y 0, z 500, r 0,
``enabled_extensions`` 252), and the stream goes on only while a ground
station's joystick is the stick input.
"""

from __future__ import annotations

import logging
import math
import os
from collections import deque
from collections.abc import Sequence
from typing import Any

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink

from sitl.autopilot import Autopilot, Joystick
from sitl.mavlink_face import (
    ID_ATTITUDE,
    ID_ATTITUDE_QUATERNION,
    ID_HIGHRES_IMU,
    ID_LOCAL_POSITION_NED,
    STATUS_STREAMS,
    MavlinkFace,
    Vec3,
    as_int,
)
from sitl.mavlink_link import Endpoint
from sitl.personality import FORCE_DISARM_MAGIC, FirmwareVersion, MavResult, ParamSpec
from sitl.px4_modes import AUTO_SUB_LAND, MainMode
from sitl.px4_params import (
    PARAM_INT32,
    PARAM_REAL32,
    PARAM_UINT32,
    PX4_DEFAULT_FIRMWARE,
    decode_bytewise,
    encode_bytewise,
)
from sitl.streams import MessageStreams, StreamSpec

__all__ = ["CAP_SET_ACTUATOR_TARGET", "Px4Face", "px4_capabilities", "px4_streams"]

logger = logging.getLogger(__name__)

MAV_AUTOPILOT_PX4 = 12
CAP_SET_ACTUATOR_TARGET = 1024
"""``MAV_PROTOCOL_CAPABILITY_SET_ACTUATOR_TARGET`` (now ``RESERVED3`` in common.xml)."""
HASH_PARAM = "_HASH_CHECK"
"""PX4's parameter-cache hash, sent first in a parameter list."""

_BASE_CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
    | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
)
"""What PX4's ``Mavlink::send_autopilot_capabilities`` sets and this SITL has (no
missions, FTP or position targets); PARAM_FLOAT (2) is set by PX4 too."""


def px4_capabilities(firmware: FirmwareVersion) -> int:
    """AUTOPILOT_VERSION ``capabilities`` of PX4 ``firmware``."""
    caps: int = _BASE_CAPABILITIES
    if not firmware.at_least(1, 14):
        caps |= CAP_SET_ACTUATOR_TARGET
    if firmware.at_least(1, 13):
        caps |= mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    return caps


CAPABILITIES = px4_capabilities(PX4_DEFAULT_FIRMWARE)
FLIGHT_SW_VERSION = PX4_DEFAULT_FIRMWARE.flight_sw_version


ID_MANUAL_CONTROL = mavlink.MAVLINK_MSG_ID_MANUAL_CONTROL
JOYSTICK_EXTENSIONS = 252
"""``MANUAL_CONTROL.enabled_extensions`` PX4 streams: bits 2..7, aux1..aux6."""
INTEGRATION_INTERVAL_S = 1.0 / 200.0
"""PX4's IMU integration interval: ``IMU_INTEG_RATE``, 200 Hz by default
(``src/modules/sensors/vehicle_imu/imu_parameters.c``)."""
_IMU_WINDOW_MAX = 16
"""The most IMU samples kept for one HIGHRES_IMU (5 at 1 kHz)."""

NEUTRAL_JOYSTICK = Joystick(0, 0, 500, 0, JOYSTICK_EXTENSIONS)
"""The first frame of PX4's MANUAL_CONTROL stream without a joystick: the
``manual_control_setpoint`` of no input (sticks and aux 0, throttle 0 in [-1, 1])."""


def px4_streams(imu_rate_hz: float) -> MessageStreams:
    """The streams and default intervals of the PX4 face."""
    return MessageStreams(
        [
            *STATUS_STREAMS,
            StreamSpec(ID_MANUAL_CONTROL, "MANUAL_CONTROL", 0.0),
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
    ``SET_ACTUATOR_CONTROL_TARGET`` group 0 (PX4 <= 1.13) and ``SET_ATTITUDE_TARGET``
    body rates (attitude ignored), bytewise parameters, and HIGHRES_IMU / ATTITUDE
    with the IMU's gyro.

    Parameters
    ----------
    endpoint, autopilot, streams, sysid, compid
        As :class:`~sitl.mavlink_face.MavlinkFace`.
    firmware
        The PX4 version shown (see the module's docstring).
    """

    mav_autopilot = MAV_AUTOPILOT_PX4
    capabilities = CAPABILITIES
    flight_sw_version = FLIGHT_SW_VERSION
    imu_streams = (ID_HIGHRES_IMU, ID_ATTITUDE, ID_ATTITUDE_QUATERNION)
    extra_streams = (ID_MANUAL_CONTROL,)
    heartbeat_on_change = False  # PX4's HEARTBEAT is a 1 Hz stream like any other

    def __init__(
        self,
        endpoint: Endpoint,
        autopilot: Autopilot,
        streams: MessageStreams,
        *,
        sysid: int = 1,
        compid: int = 1,
        firmware: FirmwareVersion = PX4_DEFAULT_FIRMWARE,
    ) -> None:
        super().__init__(endpoint, autopilot, streams, sysid=sysid, compid=compid)
        self.firmware = firmware
        self.flight_sw_version = firmware.flight_sw_version
        self.capabilities = px4_capabilities(firmware)
        self.actuator_targets = not firmware.at_least(1, 14)
        """``SET_ACTUATOR_CONTROL_TARGET`` is handled (PX4 <= 1.13)."""
        if not self.actuator_targets:
            self.lockstep_setpoints = frozenset(("SET_ATTITUDE_TARGET",))
        self._manual_control_first = False
        """The MANUAL_CONTROL stream was just turned on: its first frame is due."""
        self._imu_recent: deque[tuple[Vec3, Vec3]] = deque(maxlen=_IMU_WINDOW_MAX)
        """The latest IMU samples (accel, gyro), newest last."""

    # ---------------------------------------------------------------- streams

    def publish(self, t_s: float, *, imu_sample: bool, wall_s: float) -> bool:
        if imu_sample:
            s = self.snapshot
            self._imu_recent.append((s.accel_frd_m_s2, s.gyro_frd_rad_s))
        return super().publish(t_s, imu_sample=imu_sample, wall_s=wall_s)

    def _highres_accel_gyro(self) -> tuple[Vec3, Vec3]:
        """The mean of the IMU samples of PX4's integration interval, as PX4's
        ``sensor_combined`` is: :data:`INTEGRATION_INTERVAL_S`, or the stream's
        interval where shorter (a companion that gets a faster stream from PX4 has
        raised ``IMU_INTEG_RATE`` to get it), to the nearest whole sample. One
        sample goes out as itself, to the bit. NaN gyro after an ``imu-nan`` fault."""
        recent = self._imu_recent
        interval_s = self.streams.interval_s(ID_HIGHRES_IMU)
        if interval_s <= 0.0:  # the stream off: a one-off request
            interval_s = INTEGRATION_INTERVAL_S
        span_s = min(interval_s, INTEGRATION_INTERVAL_S)
        n = min(len(recent), max(1, round(span_s * self.streams.imu_rate_hz)))
        if n <= 1:
            return super()._highres_accel_gyro()
        window = list(recent)[-n:]
        a = [math.fsum(r[0][i] for r in window) / n for i in range(3)]
        g = [math.fsum(r[1][i] for r in window) / n for i in range(3)]
        gyro = self._gyro() if self.imu_nan else (g[0], g[1], g[2])
        return (a[0], a[1], a[2]), gyro

    # -------------------------------------------------------------- handling

    def neutral_setpoint(self, t_s: float) -> None:
        if self.actuator_targets:
            self.autopilot.on_actuator_target(t_s, (0.0, 0.0, 0.0, 0.0))
        else:
            self.autopilot.on_rates_target(t_s, (0.0, 0.0, 0.0), 0.0)

    def _handle_actuator_target(self, msg: Any, t_s: float) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        if not self.actuator_targets:
            self._warn_once(
                "act",
                "SET_ACTUATOR_CONTROL_TARGET dropped: PX4 %s does not handle it (>= 1.14)",
                self.firmware,
            )
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

    def _handle_other(self, mtype: str, msg: Any, t_s: float) -> None:
        """``MANUAL_CONTROL`` from any ground station (any sysid) addressed to us:
        PX4's stick input when ``COM_RC_IN_MODE`` takes a joystick."""
        if mtype != "MANUAL_CONTROL" or msg.target not in (0, self.sysid):
            return
        ext = int(getattr(msg, "enabled_extensions", 0) or 0)
        aux = tuple(int(getattr(msg, f"aux{i}", 0) or 0) for i in range(1, 7))
        self.autopilot.on_manual_control(
            t_s,
            Joystick(msg.x, msg.y, msg.z, msg.r, ext, aux),  # type: ignore[arg-type]
        )

    def _send_one(self, msg_id: int) -> None:
        if msg_id != ID_MANUAL_CONTROL:
            super()._send_one(msg_id)
            return
        # PX4 streams the manual_control_setpoint it flies on: only while a joystick
        # is its stick input (nothing once it stops), from its own sysid. A new
        # stream's first frame is the last setpoint published, joystick or not: with
        # none, the neutral one (throttle 0 in PX4's [-1, 1] is z 500).
        j = self.autopilot.joystick(self.snapshot.t_s)
        first, self._manual_control_first = self._manual_control_first, False
        if j is None and first:
            j = NEUTRAL_JOYSTICK
        if j is not None:
            self.mav.manual_control_send(
                self.sysid, j.x, j.y, j.z, j.r, 0, 0, JOYSTICK_EXTENSIONS, 0, 0, *j.aux
            )

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

    def _external_control_mode(self, mode: float) -> bool:
        return as_int(mode) == MainMode.OFFBOARD

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
        if command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL and as_int(p[0]) == ID_MANUAL_CONTROL:
            return self._manual_control_interval(float(p[1]), t_s)
        return None

    def _manual_control_interval(self, interval_us: float, t_s: float) -> MavResult:
        """The MANUAL_CONTROL stream asked for: a stream that was off starts with one
        frame at once (PX4 v1.16 answered so, a ground station's joystick there or not),
        then streams while a joystick is the stick input."""
        was_on = self.streams.interval_s(ID_MANUAL_CONTROL) > 0.0
        result = self.streams.set_interval(ID_MANUAL_CONTROL, interval_us, t_s=t_s)
        if result == MavResult.ACCEPTED and not was_on:
            self._manual_control_first = self.streams.interval_s(ID_MANUAL_CONTROL) > 0.0
        return result

    # ------------------------------------------------------------ parameters

    def _param_wire(self, spec: ParamSpec, value: float) -> float:
        """Bytewise: an INT32's bytes read as a float32, a FLOAT as itself."""
        return encode_bytewise(value, spec.param_type)

    def _param_from_set(self, spec: ParamSpec, wire_value: float, wire_type: int) -> float | None:
        """Decoded bytewise; None (dropped, no answer) when ``wire_type`` is not the
        parameter's, as PX4 does ("param types mismatch")."""
        if wire_type != spec.param_type or wire_type not in (PARAM_INT32, PARAM_REAL32):
            self._warn_once(
                f"param-type:{spec.name}",
                "param types mismatch param: %s (PARAM_SET type %d, parameter type %d)",
                spec.name,
                wire_type,
                spec.param_type,
            )
            return None
        return decode_bytewise(wire_value, wire_type)

    def _handle_param(self, mtype: str, msg: Any) -> None:
        if mtype == "PARAM_REQUEST_READ" and msg.param_index < 0 and msg.param_id == HASH_PARAM:
            self._send_hash()
        elif mtype == "PARAM_SET" and msg.param_id == HASH_PARAM:
            return  # "stop sending the list": it went out whole already
        else:
            super()._handle_param(mtype, msg)

    def _param_list(self) -> None:
        self._send_hash()
        super()._param_list()

    def _send_hash(self) -> None:
        params = self.autopilot.params
        wire = encode_bytewise(params.hash_check(), PARAM_UINT32)
        self.mav.param_value_send(HASH_PARAM.encode(), wire, PARAM_UINT32, len(params), 65535)
