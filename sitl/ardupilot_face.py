"""The ArduPilot personality's MAVLink face: identity, commands, parameters, streams.

It shows the ArduCopter-like :class:`~sitl.ardupilot.ArduCopter` as ArduCopter
4.x would (``docs/research/ardupilot.md``): HEARTBEAT with ``autopilot =
MAV_AUTOPILOT_ARDUPILOTMEGA`` and Copter mode numbers, ``SET_MODE`` and
``MAV_CMD_DO_SET_MODE``, parameters, ``STATUSTEXT``, ArduPilot's IMU messages
and its message-interval rules. Dispatch, the commands both stacks answer
alike, the parameter protocol and the streams' schedule are
:class:`~sitl.mavlink_face.MavlinkFace`'s; the socket and peers
:class:`~sitl.mavlink_link.MavlinkLink`'s.

Parameters (``sitl.ardupilot_params``) travel C-cast, as ArduPilot's
``GCS_MAVLINK`` sends them (``cast_to_float``: an integer parameter's value as a
float) and reads ``PARAM_SET`` (the float, whatever its ``param_type``);
AUTOPILOT_VERSION advertises ``MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST``.
``flight_sw_version`` is ArduCopter 4.7.0-dev unless ``firmware`` says otherwise
(``major << 24 | minor << 16 | patch << 8 | FIRMWARE_VERSION_TYPE``, as
``GCS_MAVLINK::send_autopilot_version`` packs ``AP_FWVersion``).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from typing import Any

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink

from sitl.ardupilot import ArduCopter
from sitl.ardupilot_modes import GUIDED, CopterMode
from sitl.mavlink_face import (
    ID_ATTITUDE,
    ID_ATTITUDE_QUATERNION,
    ID_HIGHRES_IMU,
    ID_LOCAL_POSITION_NED,
    ONE_SHOT,
    STATUS_STREAMS,
    MavlinkFace,
    as_int,
)
from sitl.mavlink_link import Endpoint
from sitl.personality import FORCE_DISARM_MAGIC, FirmwareVersion, MavResult
from sitl.streams import MessageStreams, StreamSpec

__all__ = [
    "ARDUPILOT_DEFAULT_FIRMWARE",
    "FORCE_ARM_MAGIC",
    "MAV_AUTOPILOT_ARDUPILOTMEGA",
    "ArduPilotFace",
    "ArduStreams",
    "ardupilot_streams",
    "max_stream_rate_hz",
]

logger = logging.getLogger(__name__)

MAV_AUTOPILOT_ARDUPILOTMEGA = 3
FORCE_ARM_MAGIC = 2989
"""``MAV_CMD_COMPONENT_ARM_DISARM`` param2 that skips the arming checks (ArduPilot)."""

ID_RAW_IMU = mavlink.MAVLINK_MSG_ID_RAW_IMU
ID_SCALED_IMU = mavlink.MAVLINK_MSG_ID_SCALED_IMU
ID_STATUSTEXT = mavlink.MAVLINK_MSG_ID_STATUSTEXT

GRAVITY_M_S2 = 9.80665


def max_stream_rate_hz(loop_rate_hz: float) -> float:
    """Fastest stream ArduPilot accepts: 0.8 x loop rate, in whole ms (333 Hz at 400)."""
    loop_period_us = 1e6 / loop_rate_hz
    return 1000.0 / max(1, int(loop_period_us / 800.0))


class ArduStreams(MessageStreams):
    """Message intervals with ArduPilot's rules (``GCS_MAVLINK::set_message_interval``).

    The interval is kept in whole milliseconds (``interval_us / 1000``, below 1 ms
    -> 1 ms); one faster than 0.8 x the main-loop rate
    (``interval_ms * 800 < loop_period_us``, ``cap_message_interval``) is
    DENIED (what a real ArduCopter 4.7.0-dev answered:
    ``docs/research/ardupilot.md#observed-4-7-dev``); an unknown message or
    a reset-to-default of one without a default is FAILED.
    """

    def __init__(self, specs: Sequence[StreamSpec], *, loop_rate_hz: float) -> None:
        super().__init__(specs, imu_rate_hz=loop_rate_hz, max_rate_hz=loop_rate_hz)
        self.loop_rate_hz = loop_rate_hz

    def set_interval(self, msg_id: int, interval_us: float, *, t_s: float = 0.0) -> MavResult:
        st = self._streams.get(msg_id)
        if st is None or not math.isfinite(interval_us):
            return MavResult.FAILED
        us = int(interval_us)
        if us == -1:
            st.interval_s = 0.0
            return MavResult.ACCEPTED
        if us == 0:
            if st.spec.default_interval_s <= 0.0:
                return MavResult.FAILED
            st.interval_s = st.spec.default_interval_s
            st.next_due_s = t_s
            return MavResult.ACCEPTED
        if us < 0:
            return MavResult.FAILED
        interval_ms = 1 if us < 1000 else min(us // 1000, 60000)
        loop_period_us = 1e6 / self.loop_rate_hz
        if interval_ms * 800 < loop_period_us and int(loop_period_us / 800.0) > interval_ms:
            return MavResult.DENIED
        st.interval_s = interval_ms * 1e-3
        st.next_due_s = t_s
        return MavResult.ACCEPTED


def ardupilot_streams(loop_rate_hz: float = 400.0) -> ArduStreams:
    """Streams of the ArduPilot face and their defaults (0: off until requested).

    ArduPilot's defaults come from its ``SRn_*`` parameters; these are chosen
    for the SITL (assumed, not ArduPilot's).
    """
    return ArduStreams(
        [
            *STATUS_STREAMS,
            StreamSpec(ID_LOCAL_POSITION_NED, "LOCAL_POSITION_NED", 0.25),
            StreamSpec(ID_ATTITUDE, "ATTITUDE", 0.1, imu_based=True),
            StreamSpec(ID_RAW_IMU, "RAW_IMU", 0.1, imu_based=True),
            StreamSpec(ID_SCALED_IMU, "SCALED_IMU", 0.0, imu_based=True),
            StreamSpec(ID_HIGHRES_IMU, "HIGHRES_IMU", 0.0, imu_based=True),
            StreamSpec(ID_ATTITUDE_QUATERNION, "ATTITUDE_QUATERNION", 0.0, imu_based=True),
        ],
        loop_rate_hz=loop_rate_hz,
    )


ARDUPILOT_CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
    | mavlink.MAV_PROTOCOL_CAPABILITY_FLIGHT_TERMINATION
    | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
)
"""ArduCopter's (``GCS_MAVLINK_Copter::capabilities``) less terrain and the
position targets. PARAM_FLOAT (2, deprecated) is what ArduPilot sets for its
parameter protocol; PARAM_ENCODE_C_CAST (131072), the bit that now names its
encoding, entered ArduPilot's MAVLink definitions in July 2025
(ArduPilot/mavlink #414): real ArduPilot releases before that do not set it,
so a client should also take PARAM_FLOAT without BYTEWISE, or autopilot 3, as
C-cast."""

ARDUPILOT_DEFAULT_FIRMWARE = FirmwareVersion(4, 7, 0, 0)
"""ArduCopter 4.7.0-dev (``FIRMWARE_VERSION_TYPE_DEV``): the version of the real ArduCopter
SITL whose answers this personality copies (``docs/research/ardupilot.md#observed-4-7-dev``)."""
ARDUPILOT_SW_VERSION = ARDUPILOT_DEFAULT_FIRMWARE.flight_sw_version

_ONE_SHOT = ONE_SHOT | {ID_RAW_IMU, ID_SCALED_IMU}


def _i16(x: float) -> int:
    return int(max(-32768, min(32767, round(x)))) if math.isfinite(x) else 0


class ArduPilotFace(MavlinkFace[ArduCopter]):
    """The MAVLink face of :class:`~sitl.ardupilot.ArduCopter` (sysid 1, compid 1, autopilot 3).

    On top of :class:`~sitl.mavlink_face.MavlinkFace` (sockets, peers, streams,
    parameters): ArduPilot heartbeat and modes, ``SET_MODE``, C-cast parameter
    values, ``STATUSTEXT``, ``RAW_IMU`` / ``SCALED_IMU`` / ``HIGHRES_IMU``, and
    ``SET_ATTITUDE_TARGET`` with ArduCopter's rules. ``SET_ACTUATOR_CONTROL_TARGET``
    is ignored, as ArduPilot does.

    IMU units: RAW_IMU and SCALED_IMU carry the INS-filtered gyro in mrad/s and
    the accelerometer in mG as int16 (ArduPilot's ``send_raw_imu`` scaling, the
    same in both); HIGHRES_IMU in rad/s and m/s^2 (floats). ATTITUDE rates are
    the filtered gyro too (ArduPilot sends the AHRS gyro).

    The lockstep clock waits after the fastest body-rate stream (HIGHRES_IMU,
    RAW_IMU, SCALED_IMU, ATTITUDE or ATTITUDE_QUATERNION: whichever the client
    asked to be fast) in GUIDED / GUIDED_NOGPS.
    """

    mav_autopilot = MAV_AUTOPILOT_ARDUPILOTMEGA
    capabilities = ARDUPILOT_CAPABILITIES
    flight_sw_version = ARDUPILOT_SW_VERSION
    imu_streams = (ID_HIGHRES_IMU, ID_RAW_IMU, ID_SCALED_IMU, ID_ATTITUDE, ID_ATTITUDE_QUATERNION)
    one_shot = _ONE_SHOT
    highres_temperature_c = 45.0
    # SET_ACTUATOR_CONTROL_TARGET is ignored, as ArduPilot does: not waited for.
    lockstep_setpoints = frozenset(("SET_ATTITUDE_TARGET",))
    # A message due with nothing to send (LOCAL_POSITION_NED before the AHRS has a
    # position) counts as sent: GCS_MAVLINK::try_send_message returns true after
    # send_local_position() returned without sending.
    holds_unsent_slots = False

    def __init__(
        self,
        endpoint: Endpoint,
        autopilot: ArduCopter,
        streams: ArduStreams,
        *,
        sysid: int = 1,
        compid: int = 1,
        firmware: FirmwareVersion = ARDUPILOT_DEFAULT_FIRMWARE,
    ) -> None:
        super().__init__(endpoint, autopilot, streams, sysid=sysid, compid=compid)
        self.firmware = firmware
        self.flight_sw_version = firmware.flight_sw_version

    # -------------------------------------------------------------- handling

    def neutral_setpoint(self, t_s: float) -> None:
        self.autopilot.on_attitude_target(
            t_s, mavlink.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE, (0.0, 0.0, 0.0), 0.0
        )

    def _handle_actuator_target(self, msg: Any, t_s: float) -> None:
        self.autopilot.on_actuator_target(t_s, ())
        self._warn_once("act", "SET_ACTUATOR_CONTROL_TARGET ignored (ArduPilot)")

    def _handle_other(self, mtype: str, msg: Any, t_s: float) -> None:
        if mtype != "SET_MODE" or not self._for_us(msg.target_system, None):
            return
        result = self._set_mode_common(msg.base_mode, msg.custom_mode, t_s)
        self._ack(msg, mavlink.MAVLINK_MSG_ID_SET_MODE, result)
        if result == MavResult.ACCEPTED:
            self._heartbeat_now = True

    def _handle_attitude_target(self, msg: Any, t_s: float) -> None:
        rates = (msg.body_roll_rate, msg.body_pitch_rate, msg.body_yaw_rate)
        self.autopilot.on_attitude_target(t_s, msg.type_mask, rates, msg.thrust)

    def _set_mode_common(self, base_mode: int, custom_mode: int, t_s: float) -> MavResult:
        if not base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return MavResult.UNSUPPORTED
        return self.autopilot.set_mode(t_s, custom_mode)

    def _external_control_mode(self, mode: float) -> bool:
        return as_int(mode) in GUIDED

    def _ends_external_control(self, msg: Any) -> bool:
        if msg.get_type() == "SET_MODE":
            return self._for_us(msg.target_system, None) and msg.custom_mode not in GUIDED
        return super()._ends_external_control(msg)

    def _vehicle_command(self, command: int, p: Sequence[float], t_s: float) -> MavResult | None:
        ap = self.autopilot
        if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            if p[0] == 1.0:
                return ap.arm(t_s, force=as_int(p[1]) == FORCE_ARM_MAGIC)
            if p[0] == 0.0:
                return ap.disarm(t_s, force=as_int(p[1]) == FORCE_DISARM_MAGIC)
            return MavResult.UNSUPPORTED
        if command == mavlink.MAV_CMD_DO_SET_MODE:
            return self._set_mode_common(as_int(p[0]), as_int(p[1]), t_s)
        if command == mavlink.MAV_CMD_NAV_LAND:
            return ap.set_mode(t_s, CopterMode.LAND)
        return None

    # -------------------------------------------------------------- streams

    def _body_rates(self) -> tuple[float, float, float]:
        return self.autopilot.gyro_filtered_rad_s

    def _send_one(self, msg_id: int) -> None:
        if msg_id in (ID_RAW_IMU, ID_SCALED_IMU):
            s = self.snapshot
            a, g = s.accel_frd_m_s2, self._gyro()
            acc_mg = [_i16(v * 1000.0 / GRAVITY_M_S2) for v in a]
            gyro_mrad = [_i16(v * 1000.0) for v in g]
            if msg_id == ID_RAW_IMU:
                self.mav.raw_imu_send(round(s.imu_t_s * 1e6), *acc_mg, *gyro_mrad, 0, 0, 0, 0, 4500)
            else:
                self.mav.scaled_imu_send(round(s.imu_t_s * 1e3), *acc_mg, *gyro_mrad, 0, 0, 0, 4500)
            self.imu_messages_sent += 1
        else:
            super()._send_one(msg_id)
