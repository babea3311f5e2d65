"""The SITL's MAVLink 2 face: dispatch, command handling, telemetry streams.

:class:`MavlinkFace` is what both personalities' faces share: dispatch of what
its transport (:class:`sitl.mavlink_link.MavlinkLink`: UDP socket, peers,
datagram parsing, ``--mavlink`` endpoints, signing) reads, ``COMMAND_ACK`` for
every command addressed to us, message intervals and requests, and the streams
in simulation time. Each stack's face derives from it: ``sitl.px4_face`` shows the PX4-like
:class:`~sitl.autopilot.Autopilot` as PX4 SITL would, ``sitl.ardupilot_face``
the :class:`~sitl.ardupilot.ArduCopter` as ArduCopter would (arming and mode
commands, setpoints, the IMU messages and the identity differ).

Parameters (``PARAM_REQUEST_READ`` / ``PARAM_REQUEST_LIST`` / ``PARAM_SET``)
---------------------------------------------------------------------------
Both faces serve the autopilot's :class:`~sitl.personality.ParamStore`: a read by
name or index, the list and a set are answered with ``PARAM_VALUE`` (the
parameter's index in name order and the count); an unknown name or index gets
no answer, a refused value the current one. How a value rides in
``param_value`` is each face's (:meth:`MavlinkFace._param_wire`,
:meth:`MavlinkFace._param_from_set`): C-cast for ArduPilot, bytewise for PX4.

Streams (``MAV_CMD_SET_MESSAGE_INTERVAL``, ``sitl.streams``)
-----------------------------------------------------------
Each step :meth:`MavlinkFace.publish` sends, in this order: the STATUSTEXTs the
autopilot queued (ArduPilot), the messages requested once
(``MAV_CMD_REQUEST_MESSAGE``), HEARTBEAT (also at once after an accepted arm or
mode command, or a mode change of the autopilot's own, where the face's
``heartbeat_on_change`` says so, and after 1 s of wall time without one),
RC_CHANNELS, the
IMU-based streams on a new IMU sample, then LOCAL_POSITION_NED, SYS_STATUS,
EXTENDED_SYS_STATE and HOME_POSITION. Each face has its own stream table and
defaults. Through a modelled link, what was sent then goes to the socket as the
link delivers it (:meth:`~sitl.mavlink_link.MavlinkLink.flush`, at the end of
:meth:`MavlinkFace.publish`).

The estimate, not the truth (``sitl.estimator_model``)
------------------------------------------------------
ATTITUDE's roll, pitch and yaw, ATTITUDE_QUATERNION's ``q`` and
LOCAL_POSITION_NED's position and velocity are the autopilot's estimate
(:class:`VehicleSnapshot` ``est_*``, which the runner fills from its
:class:`~sitl.estimator_model.EstimatorModel`: errors, lag and rate of an EKF),
as both stacks send them: PX4's ``ATTITUDE`` / ``ATTITUDE_QUATERNION`` streams
from ``vehicle_attitude`` (EKF2's output) and LOCAL_POSITION_NED from
``vehicle_local_position``; ArduPilot's from its AHRS (EKF3). The body rates in
ATTITUDE and ATTITUDE_QUATERNION stay the gyro's (PX4 ``vehicle_angular_velocity``,
ArduPilot ``ahrs.get_gyro()``: the filtered gyro, not an estimate).

Before the first estimate: LOCAL_POSITION_NED is not sent (PX4's stream
``send()`` sends only a ``vehicle_local_position`` with ``xy_valid`` and
``v_xy_valid``, ArduPilot's only when the AHRS has a position and a velocity);
a PX4 stream that had nothing to send keeps its slot and goes out as soon as it
has (``MavlinkStream::update`` advances the schedule only when ``send()`` sent:
:attr:`MavlinkFace.holds_unsent_slots`), ArduPilot's slot passes. ATTITUDE and
ATTITUDE_QUATERNION go out with the identity (level, heading north) until the
first attitude estimate, one attitude lag (10 ms) after start: they are IMU-based
streams the lockstep clock may run on and whose body rates a client may fly on
(ArduPilot's ATTITUDE), so they must not pause; an EKF at rest before it has
aligned reports about that (ArduPilot's AHRS always sends, from DCM at first).
"""

from __future__ import annotations

import logging
import math
import os
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Generic, TypeVar

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink

from sitl.mavlink_link import Endpoint, MavlinkLink
from sitl.personality import MavResult, ParamSpec, Personality
from sitl.streams import MessageStreams, StreamSpec

__all__ = ["ONE_SHOT", "STATUS_STREAMS", "MavlinkFace", "VehicleSnapshot", "as_int"]

logger = logging.getLogger(__name__)

MAV_TYPE_QUADROTOR = 2

HOME_LAT_DEG_E7 = 473977420  # PX4 SITL's default home (Zurich)
HOME_LON_DEG_E7 = 85455940
HOME_ALT_MM = 488_000

HIGHRES_FIELDS_GYRO_ACCEL = 0b111111  # xacc..zacc, xgyro..zgyro
SENSORS = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
)

RC_RECEIVER = mavlink.MAV_SYS_STATUS_SENSOR_RC_RECEIVER
"""SYS_STATUS bit of the RC receiver (present, enabled, healthy: the personality's
:meth:`~sitl.personality.Personality.rc_receiver`)."""
PREARM = mavlink.MAV_SYS_STATUS_PREARM_CHECK
"""SYS_STATUS bit 28: present and enabled; healthy when the pre-arm checks pass."""

ID_HEARTBEAT = mavlink.MAVLINK_MSG_ID_HEARTBEAT
ID_SYS_STATUS = mavlink.MAVLINK_MSG_ID_SYS_STATUS
ID_EXTENDED_SYS_STATE = mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE
ID_HOME_POSITION = mavlink.MAVLINK_MSG_ID_HOME_POSITION
ID_AUTOPILOT_VERSION = mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION
ID_HIGHRES_IMU = mavlink.MAVLINK_MSG_ID_HIGHRES_IMU
ID_ATTITUDE = mavlink.MAVLINK_MSG_ID_ATTITUDE
ID_ATTITUDE_QUATERNION = mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION
ID_RC_CHANNELS = mavlink.MAVLINK_MSG_ID_RC_CHANNELS
ID_LOCAL_POSITION_NED = mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED
_ESTIMATE_STREAMS = frozenset({ID_ATTITUDE_QUATERNION})
"""IMU-based streams that carry an estimate: sent ahead of the step's sample
(unless a client runs its loop on one)."""


def as_int(x: float) -> int:
    """A command parameter as an integer; NaN (MAVSDK's "unused") and inf read as 0."""
    return int(x) if math.isfinite(x) else 0


ONE_SHOT = frozenset(
    {
        ID_HEARTBEAT,
        ID_SYS_STATUS,
        ID_EXTENDED_SYS_STATE,
        ID_HOME_POSITION,
        ID_AUTOPILOT_VERSION,
        ID_LOCAL_POSITION_NED,
        ID_RC_CHANNELS,
        ID_ATTITUDE,
        ID_ATTITUDE_QUATERNION,
        ID_HIGHRES_IMU,
    }
)
"""What ``MAV_CMD_REQUEST_MESSAGE`` may ask for once (a face may add its own)."""

STATUS_STREAMS = (
    StreamSpec(ID_HEARTBEAT, "HEARTBEAT", 1.0),
    StreamSpec(ID_SYS_STATUS, "SYS_STATUS", 1.0),
    StreamSpec(ID_EXTENDED_SYS_STATE, "EXTENDED_SYS_STATE", 1.0),
    StreamSpec(ID_HOME_POSITION, "HOME_POSITION", 5.0),
    StreamSpec(ID_RC_CHANNELS, "RC_CHANNELS", 0.1),
)
"""The streams every face offers, with the same defaults; LOCAL_POSITION_NED and
the IMU-based streams are each face's own."""

_ARMING_AND_MODE_COMMANDS = (
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM,
    mavlink.MAV_CMD_DO_SET_MODE,
    mavlink.MAV_CMD_NAV_LAND,
)

_PARAM_MESSAGES = frozenset(("PARAM_REQUEST_READ", "PARAM_REQUEST_LIST", "PARAM_SET"))

P = TypeVar("P", bound=Personality[Any])


@dataclass
class VehicleSnapshot:
    """What the streams report, refreshed by the runner each step.

    Attributes are simulation-time and state values in SI units (FRD body, NED
    world); ``gyro``/``accel`` are the latest IMU sample, ``q_wxyz`` and
    ``euler_rad`` the true attitude, ``pos_ned_m`` / ``vel_ned_m_s`` the true
    position and velocity, ``sticks_us`` the RC channels (None without RC).

    ``est_*`` are the autopilot's newest estimate, what the streams carry: the
    attitude (``est_q_wxyz``, ``est_euler_rad``, taken at ``est_att_t_s``) and the
    position and velocity (``est_pos_ned_m``, ``est_vel_ned_m_s``, taken at
    ``est_pos_t_s``); None before the first.
    """

    t_s: float = 0.0
    imu_t_s: float = 0.0
    gyro_frd_rad_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    accel_frd_m_s2: tuple[float, float, float] = (0.0, 0.0, -9.80665)
    q_wxyz: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    euler_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)
    pos_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    vel_ned_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    sticks_us: tuple[int, ...] | None = None
    est_att_t_s: float | None = None
    est_q_wxyz: tuple[float, float, float, float] | None = None
    est_euler_rad: tuple[float, float, float] | None = None
    est_pos_t_s: float | None = None
    est_pos_ned_m: tuple[float, float, float] | None = None
    est_vel_ned_m_s: tuple[float, float, float] | None = None


Vec3 = tuple[float, float, float]
_IDENTITY_Q = (1.0, 0.0, 0.0, 0.0)
_LEVEL_EULER = (0.0, 0.0, 0.0)


class MavlinkFace(MavlinkLink, ABC, Generic[P]):
    """MAVLink endpoint of a simulated autopilot: what the PX4 and ArduPilot faces share.

    Parameters
    ----------
    endpoint
        Where to send / listen, see :func:`sitl.mavlink_link.parse_endpoint`.
    autopilot
        The autopilot commands and setpoints go to.
    streams
        Stream table (each face's ``*_streams`` function).
    sysid, compid
        Our MAVLink ids (both stacks: 1, 1).

    Notes
    -----
    Nothing touches the network in the constructor: call :meth:`open` (or use the
    object as a context manager); the socket and peers are
    :class:`~sitl.mavlink_link.MavlinkLink`'s.

    A stack's face sets :attr:`mav_autopilot`, :attr:`capabilities`,
    :attr:`flight_sw_version`, :attr:`imu_streams` (and :attr:`one_shot` to add
    requests, :attr:`highres_temperature_c`), and implements
    :meth:`_vehicle_command`, :meth:`_handle_actuator_target` and
    :meth:`_handle_attitude_target`; it may say which body rates its IMU
    messages carry (:meth:`_body_rates`), extend :meth:`_send_one` with
    messages of its own, and say how parameter values ride on the wire
    (:meth:`_param_wire`, :meth:`_param_from_set`, :meth:`_param_list`).
    """

    mav_autopilot: ClassVar[int]
    """HEARTBEAT ``autopilot`` (``MAV_AUTOPILOT_*``)."""
    capabilities: int
    """AUTOPILOT_VERSION ``capabilities`` (a face may set its own per firmware)."""
    flight_sw_version: int
    """AUTOPILOT_VERSION ``flight_sw_version`` (see :class:`~sitl.personality.FirmwareVersion`)."""
    imu_streams: ClassVar[tuple[int, ...]]
    """The IMU-based streams, in the order they go out; the lockstep clock waits
    after the fastest (ties: the first)."""
    one_shot: ClassVar[frozenset[int]] = ONE_SHOT
    """What ``MAV_CMD_REQUEST_MESSAGE`` may ask for."""
    highres_temperature_c: ClassVar[float] = 0.0
    """HIGHRES_IMU ``temperature``."""
    holds_unsent_slots: ClassVar[bool] = True
    """A stream due with nothing to send (LOCAL_POSITION_NED without a valid
    estimate) keeps its slot and goes out as soon as it has something, as PX4's
    ``MavlinkStream::update`` does; False: the slot passes (ArduPilot)."""
    extra_streams: ClassVar[tuple[int, ...]] = ()
    """A face's own streams beyond the shared ones, sent after RC_CHANNELS when due."""
    heartbeat_on_change: ClassVar[bool] = True
    """HEARTBEAT also at once after an accepted arm or mode command, and when the
    autopilot changes mode itself (a failsafe's RTL: ArduCopter 4.5.6 sends it with
    the change, off its 1 Hz beat); False: only at its 1 Hz beat, the new state
    shown up to a second later (PX4)."""
    lockstep_setpoints: frozenset[str] = frozenset(
        ("SET_ACTUATOR_CONTROL_TARGET", "SET_ATTITUDE_TARGET")
    )
    """The setpoints (addressed to us) the lockstep clock waits for: those counted
    in :attr:`setpoints_received`."""

    def __init__(
        self,
        endpoint: Endpoint,
        autopilot: P,
        streams: MessageStreams,
        *,
        sysid: int = 1,
        compid: int = 1,
    ) -> None:
        super().__init__(endpoint, sysid=sysid, compid=compid)
        self.autopilot = autopilot
        self.streams = streams
        self.snapshot = VehicleSnapshot()
        self.setpoints_received = 0
        self.imu_messages_sent = 0
        # Fault injection (sitl.runner --fault), besides the link's ``muted``: IMU
        # streams can be stopped or their gyro replaced by NaN; the RC receiver can
        # lose its signal.
        self._heartbeat_now = False
        self.imu_stopped = False
        self.imu_nan = False
        self.rc_lost = False
        self.rc_fitted = True
        """The vehicle has an RC receiver: False (PX4 flown by a ground station's
        joystick, as PX4 SIH) sends no RC_CHANNELS at all."""
        self.rc_lost_freezes = False
        """A receiver that lost its signal keeps reporting its last channels (ArduPilot:
        RC_CHANNELS go on with the last values, RSSI unchanged), rather than none."""
        self._rc_last_sent: tuple[list[int], int, int] | None = None
        self.messages_received = 0
        self.timesync_clock: Callable[[], float] | None = None
        """The autopilot's clock a TIMESYNC is answered with, s; None: the simulation
        time of the step that handles it. A realtime run sets the wall-paced clock
        (the time the simulation keeps to), so a client's sample ages include what
        a SITL fallen behind the wall delivers late, as a slow autopilot's would."""
        self.commands_received = 0
        """COMMAND_LONG and COMMAND_INT addressed to this autopilot."""
        self.params_sent = 0
        self._pending: set[int] = set()
        self._last_heartbeat_wall_s = -math.inf
        self._heartbeat_mode: int | None = None
        """The mode the last HEARTBEAT showed."""
        # How old the sample a setpoint answers is when the setpoint is handled (its
        # time field against the simulation time): what the link added, s.
        self.setpoint_age_n = 0
        self.setpoint_age_sum_s = 0.0
        self.setpoint_age_max_s = 0.0

    @property
    def setpoints_arrived(self) -> int:
        """Setpoints read from the socket that the lockstep clock counts: all but
        the answers to samples older than the ones it waits for
        (:meth:`~sitl.mavlink_link.MavlinkLink.expect_answers`)."""
        return self._setpoints_arrived

    def _setpoint_stamp(self, msg: Any) -> tuple[int, float] | None:
        if msg.get_type() == "SET_ACTUATOR_CONTROL_TARGET":
            return int(msg.time_usec), 1e-6
        if msg.get_type() == "SET_ATTITUDE_TARGET":
            return int(msg.time_boot_ms), 1e-3
        return None

    def setpoint_age_ms(self) -> dict[str, float]:
        """How long after its sample's time each setpoint was handled: mean and max, ms."""
        n = self.setpoint_age_n
        return {
            "n": n,
            "mean": self.setpoint_age_sum_s / n * 1e3 if n else 0.0,
            "max": self.setpoint_age_max_s * 1e3,
        }

    def _is_setpoint(self, msg: Any) -> bool:
        return msg.get_type() in self.lockstep_setpoints and self._for_us(
            msg.target_system, msg.target_component
        )

    def _setpoint_age(self, sample_t_s: float, t_s: float) -> None:
        age = t_s - sample_t_s
        if 0.0 <= age <= 1.0:  # a stamp on another clock (or a wrapped one) says nothing
            self.setpoint_age_n += 1
            self.setpoint_age_sum_s += age
            if age > self.setpoint_age_max_s:
                self.setpoint_age_max_s = age

    # -------------------------------------------------------------- handling

    def _for_us(self, target_system: int, target_component: int | None) -> bool:
        if target_system not in (0, self.sysid):
            return False
        return target_component is None or target_component in (0, self.compid)

    def _handle(self, msg: Any, t_s: float) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            self.bad_packets += 1
            return
        self.messages_received += 1
        if mtype == "SET_ACTUATOR_CONTROL_TARGET":
            self._handle_actuator_target(msg, t_s)
        elif mtype == "SET_ATTITUDE_TARGET":
            if not self._for_us(msg.target_system, msg.target_component):
                return
            self.setpoints_received += 1
            self._setpoint_age(msg.time_boot_ms * 1e-3, t_s)
            self._handle_attitude_target(msg, t_s)
        elif mtype == "COMMAND_LONG":
            if self._for_us(msg.target_system, msg.target_component):
                self.commands_received += 1
                params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6)
                self._handle_command(msg, msg.command, params, t_s)
        elif mtype == "COMMAND_INT":
            if self._for_us(msg.target_system, msg.target_component):
                self.commands_received += 1
                params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y)
                self._handle_command(msg, msg.command, params, t_s)
        elif mtype == "TIMESYNC" and msg.tc1 == 0:
            now = t_s if self.timesync_clock is None else self.timesync_clock()
            self.mav.timesync_send(round(now * 1e9), msg.ts1)
        elif mtype in _PARAM_MESSAGES:
            if self._for_us(msg.target_system, msg.target_component):
                self._handle_param(mtype, msg)
        else:
            self._handle_other(mtype, msg, t_s)

    @property
    def leaving_external_control(self) -> bool:
        """A command kept for the next step (:meth:`poll` with ``defer_commands``),
        or on its way through a modelled link (which cannot deliver it while the
        clock waits), takes the vehicle out of the companion's hands: a land, or a mode other
        than the one its setpoints fly in. The lockstep clock stops waiting
        for a setpoint then: the client handing back answers no more samples."""
        pending = (*self._deferred, *(m for _, _, m in self._inbox))  # kept, or on its way
        return any(self._ends_external_control(m) for m in pending)

    def _ends_external_control(self, msg: Any) -> bool:
        if msg.get_type() not in ("COMMAND_LONG", "COMMAND_INT"):
            return False
        if not self._for_us(msg.target_system, msg.target_component):
            return False
        if msg.command == mavlink.MAV_CMD_NAV_LAND:
            return True
        if msg.command == mavlink.MAV_CMD_DO_SET_MODE:
            try:
                return not self._external_control_mode(msg.param2)
            except (ValueError, OverflowError):
                return False  # refused when it is handled (int(nan))
        return False

    @abstractmethod
    def _external_control_mode(self, mode: float) -> bool:
        """``MAV_CMD_DO_SET_MODE``'s param2 names a mode the companion's setpoints fly."""

    @abstractmethod
    def neutral_setpoint(self, t_s: float) -> None:
        """Give the autopilot a setpoint of zero rates or torques and zero thrust
        (motors at idle): through a modelled link, what it flies at the flight's
        start until the first answer arrives, rather than a setpoint from before."""

    def reset_setpoint_age(self) -> None:
        """Start :meth:`setpoint_age_ms` again (at the flight's start)."""
        self.setpoint_age_n = 0
        self.setpoint_age_sum_s = 0.0
        self.setpoint_age_max_s = 0.0

    @abstractmethod
    def _handle_actuator_target(self, msg: Any, t_s: float) -> None:
        """``SET_ACTUATOR_CONTROL_TARGET`` (counted in :attr:`messages_received`)."""

    @abstractmethod
    def _handle_attitude_target(self, msg: Any, t_s: float) -> None:
        """``SET_ATTITUDE_TARGET`` addressed to us (counted in :attr:`setpoints_received`)."""

    def _handle_other(self, mtype: str, msg: Any, t_s: float) -> None:
        """Any other message (counted in :attr:`messages_received`): ignored here."""

    # ------------------------------------------------------------ parameters

    def _handle_param(self, mtype: str, msg: Any) -> None:
        """``PARAM_REQUEST_READ`` (by index when ``param_index`` >= 0, else by name),
        ``PARAM_REQUEST_LIST``, ``PARAM_SET``, addressed to us."""
        params = self.autopilot.params
        if mtype == "PARAM_REQUEST_READ":
            if msg.param_index >= 0:
                self._send_param_index(msg.param_index)
            elif msg.param_id in params:
                self._send_param_index(params.index(msg.param_id))
            # Unknown names get no answer (neither stack answers them).
        elif mtype == "PARAM_REQUEST_LIST":
            self._param_list()
        else:
            self._param_set(msg.param_id, msg.param_value, msg.param_type)

    def _param_list(self) -> None:
        """Answer ``PARAM_REQUEST_LIST``: every parameter, in index order."""
        for i in range(len(self.autopilot.params)):
            self._send_param_index(i)

    def _param_set(self, param_id: str, wire_value: float, wire_type: int) -> None:
        params = self.autopilot.params
        spec = params.spec(param_id)
        if spec is None:
            self._warn_once(f"param:{param_id}", "PARAM_SET of unknown parameter %s", param_id)
            return
        value = self._param_from_set(spec, wire_value, wire_type)
        if value is None:
            return
        try:
            params.set(param_id, value)
        except ValueError as exc:
            logger.warning("PARAM_SET %s: %s", param_id, exc)
        self._send_param_index(params.index(param_id))

    def _param_wire(self, spec: ParamSpec, value: float) -> float:
        """``PARAM_VALUE.param_value`` for ``value``: C-cast (the value as a float)."""
        return value

    def _param_from_set(self, spec: ParamSpec, wire_value: float, wire_type: int) -> float | None:
        """The value a ``PARAM_SET`` asks for (C-cast: the float, whatever its
        ``param_type``), or None to drop the message unanswered."""
        return float(wire_value)

    def _send_param_index(self, index: int) -> None:
        params = self.autopilot.params
        spec = params.by_index(index)
        if spec is None:
            return
        wire = self._param_wire(spec, params[spec.name])
        self.mav.param_value_send(spec.name.encode(), wire, spec.param_type, len(params), index)
        self.params_sent += 1

    # -------------------------------------------------------------- commands

    def _handle_command(self, msg: Any, command: int, p: Sequence[float], t_s: float) -> None:
        try:
            result = self._command_result(command, p, t_s)
        except (ValueError, OverflowError) as exc:  # e.g. int(nan) in a parameter
            logger.warning("command %d with bad parameters %s: %s", command, p, exc)
            result = MavResult.DENIED
        self._ack(msg, command, result)
        accepted = result == MavResult.ACCEPTED and command in _ARMING_AND_MODE_COMMANDS
        if accepted and self.heartbeat_on_change:
            self._heartbeat_now = True

    def _ack(self, msg: Any, command: int, result: MavResult) -> None:
        self.mav.command_ack_send(
            command, int(result), 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
        )

    def _command_result(self, command: int, p: Sequence[float], t_s: float) -> MavResult:
        result = self._vehicle_command(command, p, t_s)
        if result is not None:
            return result
        if command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self.streams.set_interval(as_int(p[0]), float(p[1]), t_s=t_s)
        if command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            return self._request(as_int(p[0]))
        if command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            return self._request(ID_AUTOPILOT_VERSION)
        if command == mavlink.MAV_CMD_GET_HOME_POSITION:
            return self._request(ID_HOME_POSITION)
        logger.debug("unsupported command %d", command)
        return MavResult.UNSUPPORTED

    @abstractmethod
    def _vehicle_command(self, command: int, p: Sequence[float], t_s: float) -> MavResult | None:
        """The stack's arming and mode commands (ARM_DISARM, DO_SET_MODE, NAV_LAND).

        Returns the result, or None for a command the face handles itself.
        """

    def _request(self, msg_id: int) -> MavResult:
        if msg_id not in self.one_shot:
            return MavResult.DENIED
        self._pending.add(msg_id)
        return MavResult.ACCEPTED

    # -------------------------------------------------------------- streams

    def publish(self, t_s: float, *, imu_sample: bool, wall_s: float) -> bool:
        """Send what is due at simulation time ``t_s``.

        Parameters
        ----------
        t_s
            Simulation time, s.
        imu_sample
            A new IMU sample is in the snapshot (IMU-based streams are only due then).
        wall_s
            Wall clock (monotonic), s: a heartbeat also goes out after 1 s of wall
            time without one, so a slow lockstep client keeps the link.

        Returns
        -------
        bool
            True when the fastest IMU-based stream (:attr:`imu_streams`: the one
            the client runs its loop on) went out: the lockstep clock waits after it.
            Through a modelled link: when the link delivered one or more samples
            of that stream newer than any before (their arrival times in
            :attr:`samples_delivered`), the client's next answers.
        """
        linked = self.link_model is not None
        self._t_s = t_s
        self._send_status_texts()
        st = self.streams
        pending = self._pending
        if pending:
            self._pending = set()
            for msg_id in pending:
                self._send_one(msg_id)
        if (
            self._heartbeat_now
            or (self.heartbeat_on_change and self.autopilot.custom_mode != self._heartbeat_mode)
            or st.due(ID_HEARTBEAT, t_s)
            or wall_s - self._last_heartbeat_wall_s > 1.0
        ):
            self._heartbeat_now = False
            self._send_heartbeat(wall_s)
        # RC before IMU: a client that maps sticks when RC arrives then uses this
        # step's sticks for this step's IMU sample, as the in-process loop does.
        if self.rc_fitted and st.due(ID_RC_CHANNELS, t_s):
            self._send_one(ID_RC_CHANNELS)
        for msg_id in self.extra_streams:
            if st.due(msg_id, t_s):
                self._send_one(msg_id)
        # The estimates go out ahead of the IMU sample they come with: a client
        # flies that sample on them, and at a flight's start (arming, with
        # pilot_from_arm) on the estimator's first output, whenever that was.
        self._send_due(ID_LOCAL_POSITION_NED, t_s)
        imu_sent = False
        if imu_sample and not self.imu_stopped:
            # Lockstep follows the fastest body-rate stream: the one the client runs on.
            clock = st.lockstep_stream(self.imu_streams)
            ahead = tuple(m for m in self.imu_streams if m in _ESTIMATE_STREAMS and m != clock)
            for msg_id in (*ahead, *(m for m in self.imu_streams if m not in ahead)):
                if st.due(msg_id, t_s):
                    if linked and msg_id == clock:
                        # Tag its frame with the sample's time: flush tells a new one.
                        self._clock_t_s = self.snapshot.imu_t_s
                        self._send_one(msg_id)
                        self._clock_t_s = None
                    else:
                        self._send_one(msg_id)
                        if msg_id == clock:
                            self.given_to_client(self.snapshot.imu_t_s)
                    imu_sent = imu_sent or msg_id == clock
        for msg_id in (ID_SYS_STATUS, ID_EXTENDED_SYS_STATE, ID_HOME_POSITION):
            self._send_due(msg_id, t_s)
        if linked:
            return self.flush(t_s) > 0
        return imu_sent

    def keep_alive(self, wall_s: float) -> None:
        """A heartbeat if none went out for 1 s of wall time (on the ideal link):
        a lockstep SITL waiting for a slow client's setpoint still beats, as the
        autopilot it imitates would, so the client's link watchdog does not take
        the client's own slowness for a lost autopilot."""
        if self.link_model is None and wall_s - self._last_heartbeat_wall_s > 1.0:
            self._send_heartbeat(wall_s)

    def _send_due(self, msg_id: int, t_s: float) -> None:
        """Send ``msg_id`` if its stream is due (and, where slots are held, it has data)."""
        if self.holds_unsent_slots and not self._has_data(msg_id):
            return
        if self.streams.due(msg_id, t_s):
            self._send_one(msg_id)

    def _send_status_texts(self) -> None:
        """Send the STATUSTEXTs the autopilot queued."""
        for severity, text in self.autopilot.drain_statustexts():
            self.mav.statustext_send(severity, text.encode(), 0, 0)

    def _send_heartbeat(self, wall_s: float) -> None:
        ap = self.autopilot
        self.mav.heartbeat_send(
            MAV_TYPE_QUADROTOR, self.mav_autopilot, ap.base_mode, ap.custom_mode, ap.system_status
        )
        self._last_heartbeat_wall_s = wall_s
        self._heartbeat_mode = ap.custom_mode

    def _body_rates(self) -> tuple[float, float, float]:
        """The body rates HIGHRES_IMU and ATTITUDE carry: the IMU's gyro here."""
        return self.snapshot.gyro_frd_rad_s

    def _has_data(self, msg_id: int) -> bool:
        """Whether ``msg_id`` has something to send: LOCAL_POSITION_NED only while
        the position estimate is valid and there is one (both stacks)."""
        if msg_id == ID_LOCAL_POSITION_NED:
            return self.autopilot.position_valid and self.snapshot.est_pos_ned_m is not None
        return True

    def _highres_accel_gyro(self) -> tuple[Vec3, Vec3]:
        """What HIGHRES_IMU carries: the latest sample's accel and :meth:`_gyro`."""
        return self.snapshot.accel_frd_m_s2, self._gyro()

    def _gyro(self) -> tuple[float, float, float]:
        """The IMU messages' gyro: :meth:`_body_rates`, NaN after an ``imu-nan`` fault."""
        if self.imu_nan:
            return (math.nan, math.nan, math.nan)
        return self._body_rates()

    def _send_one(self, msg_id: int) -> None:
        """Send one message now."""
        s = self.snapshot
        mav = self.mav
        ap = self.autopilot
        if msg_id == ID_HIGHRES_IMU:
            a, g = self._highres_accel_gyro()
            mav.highres_imu_send(
                round(s.imu_t_s * 1e6),
                a[0], a[1], a[2], g[0], g[1], g[2],
                0.0, 0.0, 0.0, 0.0, 0.0, 0.0, self.highres_temperature_c,
                HIGHRES_FIELDS_GYRO_ACCEL,
            )  # fmt: skip
            self.imu_messages_sent += 1
        elif msg_id == ID_ATTITUDE:
            # The estimate's angles (identity before the first: module docstring),
            # the gyro's rates; stamped with the IMU sample it goes out with.
            e = s.est_euler_rad if s.est_euler_rad is not None else _LEVEL_EULER
            g = self._body_rates()
            mav.attitude_send(round(s.imu_t_s * 1e3), e[0], e[1], e[2], g[0], g[1], g[2])
        elif msg_id == ID_ATTITUDE_QUATERNION:
            q = s.est_q_wxyz if s.est_q_wxyz is not None else _IDENTITY_Q
            g = s.gyro_frd_rad_s
            mav.attitude_quaternion_send(
                round(s.imu_t_s * 1e3), q[0], q[1], q[2], q[3], g[0], g[1], g[2]
            )
        elif msg_id == ID_RC_CHANNELS:
            if self.rc_lost and self.rc_lost_freezes and self._rc_last_sent is not None:
                # The receiver's last frame, again (ArduPilot keeps its last values).
                chans, n, rssi = self._rc_last_sent
            else:
                # No sticks, or a receiver without signal: no channel (chancount 0),
                # every one UINT16_MAX ("unused"), RSSI 0.
                chans = [] if self.rc_lost else list(s.sticks_us or ())[:18]
                n = len(chans)
                chans += [65535] * (18 - n)
                rssi = 254 if n else 0
                if n:
                    self._rc_last_sent = (chans, n, rssi)
            mav.rc_channels_send(round(s.t_s * 1e3), n, *chans, rssi)
        elif msg_id == ID_LOCAL_POSITION_NED:
            # PX4 and ArduPilot send it only while their position estimate is valid.
            x, v = s.est_pos_ned_m, s.est_vel_ned_m_s
            if ap.position_valid and x is not None and v is not None:
                mav.local_position_ned_send(round(s.t_s * 1e3), x[0], x[1], x[2], v[0], v[1], v[2])
        elif msg_id == ID_SYS_STATUS:
            present, enabled, health = SENSORS | PREARM, SENSORS | PREARM, SENSORS
            if ap.prearm_ok(s.t_s):
                health |= PREARM
            rc = ap.rc_receiver(s.t_s)
            present |= RC_RECEIVER if rc[0] else 0
            enabled |= RC_RECEIVER if rc[1] else 0
            health |= RC_RECEIVER if rc[2] else 0
            mav.sys_status_send(present, enabled, health, 0, 16800, -1, 100, 0, 0, 0, 0, 0, 0)
        elif msg_id == ID_EXTENDED_SYS_STATE:
            mav.extended_sys_state_send(mavlink.MAV_VTOL_STATE_UNDEFINED, ap.landed_state)
        elif msg_id == ID_HOME_POSITION:
            mav.home_position_send(
                HOME_LAT_DEG_E7, HOME_LON_DEG_E7, HOME_ALT_MM,
                0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0,
                round(s.t_s * 1e6),
            )  # fmt: skip
        elif msg_id == ID_AUTOPILOT_VERSION:
            mav.autopilot_version_send(
                self.capabilities, self.flight_sw_version, 0, 0, 0,
                [0] * 8, [0] * 8, [0] * 8, 0, 0, 1,
            )  # fmt: skip
        elif msg_id == ID_HEARTBEAT:
            self._send_heartbeat(self._last_heartbeat_wall_s)
