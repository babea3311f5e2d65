"""The SITL's MAVLink 2 face: UDP socket, decoding, command handling, telemetry streams.

It shows the PX4-like :class:`~sitl.autopilot.Autopilot` to a ground station or
companion exactly as PX4 SITL would: HEARTBEAT from sysid 1 / compid 1 with
``autopilot = MAV_AUTOPILOT_PX4`` and PX4 custom modes, ``COMMAND_ACK`` for every
command addressed to it, and streams in simulation time.

Networking (``--mavlink``)
--------------------------
``udpout:HOST:PORT``
    Send to HOST:PORT (PX4's offboard convention: the SITL sends to 14540) from an
    ephemeral local port, and also answer whoever talks to us.
``udpin:HOST:PORT``
    Bind HOST:PORT and answer whoever talks to us.

Every sender seen is added to the peer list (bounded, most recent kept), and all
outgoing messages go to every peer.

Streams and their defaults (change with ``MAV_CMD_SET_MESSAGE_INTERVAL``)
-------------------------------------------------------------------------
HEARTBEAT 1 Hz, SYS_STATUS 1 Hz, EXTENDED_SYS_STATE 1 Hz, HOME_POSITION 0.2 Hz,
LOCAL_POSITION_NED 10 Hz, RC_CHANNELS 10 Hz, and the IMU-based HIGHRES_IMU,
ATTITUDE, ATTITUDE_QUATERNION at 50 Hz (never faster than the IMU). Interval
requests faster than 1 kHz are DENIED.
"""

from __future__ import annotations

import errno
import logging
import math
import os
import select
import socket
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink

from sitl.autopilot import (
    FORCE_DISARM_MAGIC,
    Autopilot,
    MavResult,
    MessageStreams,
    StreamSpec,
)

__all__ = ["Endpoint", "MavlinkFace", "VehicleSnapshot", "default_streams", "parse_endpoint"]

logger = logging.getLogger(__name__)

MAV_TYPE_QUADROTOR = 2
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

_MAX_PEERS = 8
_MAX_DATAGRAM_BYTES = 4096
"""A datagram longer than this is garbage (a MAVLink 2 frame is at most 280
bytes; routers pack a few per datagram): dropped unread."""
_RECV_BYTES = 2 * _MAX_DATAGRAM_BYTES  # room to see that a datagram is too long
_DEFERRED_TYPES = frozenset(
    ("COMMAND_LONG", "COMMAND_INT", "SET_MODE", "PARAM_SET", "PARAM_REQUEST_READ",
     "PARAM_REQUEST_LIST")
)  # fmt: skip
"""What ``poll(defer_commands=True)`` keeps for the start of the next step."""


def _parse_datagram(mav: Any, data: bytes) -> list[Any]:
    """The frames of one UDP datagram, parsed from a clean parser state.

    A datagram carries whole frames: a frame cut off at its end is dropped, not
    joined to the next datagram (which a parser fed datagram after datagram
    would do, losing the good frame that follows garbage). Garbage before the
    first start byte is skipped at C speed."""
    v2, v1 = data.find(b"\xfd"), data.find(b"\xfe")
    start = min(i for i in (v2, v1, len(data)) if i >= 0)
    mav.buf = bytearray()
    mav.buf_index = 0
    mav.expected_length = mavlink.HEADER_LEN_V1 + 2
    mav.have_prefix_error = False
    msgs = mav.parse_buffer(data[start:]) if start < len(data) else None
    mav.buf = bytearray()  # what is left is a frame cut short
    mav.buf_index = 0
    return list(msgs or [])


def _as_int(x: float) -> int:
    """A command parameter as an integer; NaN (MAVSDK's "unused") and inf read as 0."""
    return int(x) if math.isfinite(x) else 0


def default_streams(imu_rate_hz: float) -> MessageStreams:
    """The streams and default intervals this SITL offers."""
    return MessageStreams(
        [
            StreamSpec(ID_HEARTBEAT, "HEARTBEAT", 1.0),
            StreamSpec(ID_SYS_STATUS, "SYS_STATUS", 1.0),
            StreamSpec(ID_EXTENDED_SYS_STATE, "EXTENDED_SYS_STATE", 1.0),
            StreamSpec(ID_HOME_POSITION, "HOME_POSITION", 5.0),
            StreamSpec(ID_LOCAL_POSITION_NED, "LOCAL_POSITION_NED", 0.1),
            StreamSpec(ID_RC_CHANNELS, "RC_CHANNELS", 0.1),
            StreamSpec(ID_HIGHRES_IMU, "HIGHRES_IMU", 0.02, imu_based=True),
            StreamSpec(ID_ATTITUDE, "ATTITUDE", 0.02, imu_based=True),
            StreamSpec(ID_ATTITUDE_QUATERNION, "ATTITUDE_QUATERNION", 0.02, imu_based=True),
        ],
        imu_rate_hz=imu_rate_hz,
    )


_ONE_SHOT = {
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


@dataclass(frozen=True)
class Endpoint:
    """A parsed ``--mavlink`` address."""

    kind: Literal["udpout", "udpin"]
    host: str
    port: int

    def __str__(self) -> str:
        return f"{self.kind}:{self.host}:{self.port}"


def parse_endpoint(url: str) -> Endpoint:
    """Parse ``udpout:HOST:PORT`` or ``udpin:HOST:PORT``.

    Raises
    ------
    ValueError
        On any other form, naming what was expected.
    """
    parts = url.strip().split(":")
    if len(parts) != 3 or parts[0] not in ("udpout", "udpin"):
        raise ValueError(f"expected udpout:HOST:PORT or udpin:HOST:PORT, got {url!r}")
    kind, host, port_s = parts
    try:
        port = int(port_s)
    except ValueError:
        raise ValueError(f"expected an integer port in {url!r}") from None
    if not 0 < port < 65536 or not host:
        raise ValueError(f"expected a host and a port in 1..65535, got {url!r}")
    return Endpoint(kind, host, port)  # type: ignore[arg-type]


@dataclass
class VehicleSnapshot:
    """What the streams report, refreshed by the runner each step.

    Attributes are simulation-time and state values in SI units (FRD body, NED
    world); ``gyro``/``accel`` are the latest IMU sample, ``q_wxyz`` and
    ``euler_rad`` the attitude, ``sticks_us`` the RC channels (None without RC).
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


class _Sink:
    """File-like object pymavlink writes packed messages to: one sendto per peer."""

    def __init__(self, face: MavlinkFace) -> None:
        self._face = face

    def write(self, buf: bytes) -> None:
        self._face._send_bytes(buf)


def enable_signing(mav: Any, key: bytes, *, link_id: int = 0) -> None:
    """Sign what ``mav`` sends and accept only validly signed frames (MAVLink 2).

    Once ``secret_key`` is set, pymavlink drops unsigned frames
    (``allow_unsigned_callback`` is left unset) and asks ``mav.check_signature``
    about each signed one. pymavlink's own ``check_signature`` stores a frame's
    timestamp for its stream *before* verifying the signature, so a single forged
    frame with a far-future timestamp would block the real sender's stream for
    good. It is replaced here by :class:`companion.link.signing.SignatureChecker`
    (the companion's checker): the signature is verified first, and only a valid
    frame moves its stream's timestamp, and ours, forward. Frames with a bad
    signature, replays and new streams more than a minute behind our clock are
    dropped.
    """
    from companion.link.signing import SignatureChecker, signing_timestamp_now

    if len(key) != 32:
        raise ValueError("a MAVLink signing key is 32 bytes")
    signing = mav.signing
    signing.secret_key = key
    signing.link_id = link_id
    signing.timestamp = signing_timestamp_now()
    signing.sign_outgoing = True
    checker = SignatureChecker(key)

    def check_signature(msgbuf: bytearray, src_system: int, src_component: int) -> bool:
        # src_system/src_component are the frame's header bytes, which the checker reads itself.
        verdict, timestamp = checker.check(msgbuf, signing.timestamp)
        if verdict != SignatureChecker.OK:
            return False
        if timestamp > signing.timestamp:  # spec: follow the newest valid timestamp
            signing.timestamp = timestamp
        return True

    # pymavlink's decode() calls self.check_signature: an instance attribute wins.
    mav.check_signature = check_signature


class MavlinkFace:
    """MAVLink endpoint of the simulated autopilot.

    Parameters
    ----------
    endpoint
        Where to send / listen, see :func:`parse_endpoint`.
    autopilot
        The autopilot commands and setpoints go to.
    streams
        Stream table (``default_streams``).
    sysid, compid
        Our MAVLink ids (PX4: 1, 1).

    Notes
    -----
    Nothing touches the network in the constructor: call :meth:`open` (or use the
    object as a context manager).
    """

    def __init__(
        self,
        endpoint: Endpoint,
        autopilot: Autopilot,
        streams: MessageStreams,
        *,
        sysid: int = 1,
        compid: int = 1,
    ) -> None:
        self.endpoint = endpoint
        self.autopilot = autopilot
        self.streams = streams
        self.sysid = sysid
        self.compid = compid
        self.mav = mavlink.MAVLink(_Sink(self), srcSystem=sysid, srcComponent=compid)
        self.mav.robust_parsing = True
        self.snapshot = VehicleSnapshot()
        self.sock: socket.socket | None = None
        self.peers: list[tuple[str, int]] = []
        self.setpoints_received = 0
        self.imu_messages_sent = 0
        # Fault injection (sitl.runner --fault): a muted face neither sends nor
        # reads; IMU streams can be stopped or their gyro replaced by NaN; the RC
        # receiver can lose its signal.
        self.muted = False
        self._heartbeat_now = False
        self.imu_stopped = False
        self.imu_nan = False
        self.rc_lost = False
        self.messages_sent = 0
        self.messages_received = 0
        self.bad_packets = 0
        self.send_errors = 0
        self._pending: set[int] = set()
        self._deferred: list[Any] = []
        self._last_heartbeat_wall_s = -math.inf
        self._warned: set[str] = set()

    # -------------------------------------------------------------- lifecycle

    def open(self) -> MavlinkFace:
        """Create and bind the UDP socket.

        Raises
        ------
        OSError
            If the address cannot be bound.
        """
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if self.endpoint.kind == "udpin":
            sock.bind((self.endpoint.host, self.endpoint.port))
        else:
            sock.bind(("0.0.0.0", 0))
            self.peers.append((socket.gethostbyname(self.endpoint.host), self.endpoint.port))
        sock.setblocking(False)
        self.sock = sock
        logger.info("MAVLink %s (local %s)", self.endpoint, sock.getsockname())
        return self

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None

    def __enter__(self) -> MavlinkFace:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ I/O

    def _send_bytes(self, buf: bytes) -> None:
        sock = self.sock
        if sock is None or self.muted:
            return
        for peer in self.peers:
            try:
                sock.sendto(buf, peer)
            except OSError as exc:
                self.send_errors += 1
                if exc.errno not in (errno.ECONNREFUSED, errno.EAGAIN):
                    self._warn_once("send", "send to %s failed: %s", peer, exc)
        self.messages_sent += 1

    def _warn_once(self, key: str, fmt: str, *args: Any) -> None:
        if key not in self._warned:
            self._warned.add(key)
            logger.warning(fmt, *args)

    def wait_readable(self, timeout_s: float) -> bool:
        """Block until a datagram is waiting or ``timeout_s`` (wall) passes."""
        if self.sock is None:
            return False
        r, _, _ = select.select([self.sock], [], [], max(0.0, timeout_s))
        return bool(r)

    def poll(self, t_s: float, *, defer_commands: bool = False) -> int:
        """Read and handle every waiting datagram; return how many were read.

        Parameters
        ----------
        t_s
            Current simulation time, stamped on setpoints and commands.
        defer_commands
            Keep commands (arm, mode, parameters) for the next poll without it
            (the lockstep clock's wait for a setpoint uses it): a command then
            takes effect at the start of a step, whichever moment of the wait it
            arrived in, so a lockstep flight does not depend on wall-clock timing.
        """
        sock = self.sock
        if sock is None:
            return 0
        if not defer_commands and self._deferred:
            deferred, self._deferred = self._deferred, []
            for msg in deferred:
                self._handle(msg, t_s)
        n = 0
        while True:
            try:
                data, addr = sock.recvfrom(_RECV_BYTES)
            except (BlockingIOError, InterruptedError):
                return n
            except OSError as exc:  # e.g. ECONNREFUSED reported by an ICMP error
                self._warn_once("recv", "receive failed: %s", exc)
                return n
            n += 1
            if self.muted:
                continue  # a dropped link loses what arrives too
            if len(data) > _MAX_DATAGRAM_BYTES:
                self.bad_packets += 1
                continue
            self._add_peer(addr)
            try:
                msgs = _parse_datagram(self.mav, data)
            except mavlink.MAVError as exc:
                self.bad_packets += 1
                self._warn_once("parse", "bad MAVLink data from %s: %s", addr, exc)
                continue
            for msg in msgs:
                if defer_commands and msg.get_type() in _DEFERRED_TYPES:
                    self._deferred.append(msg)
                else:
                    self._handle(msg, t_s)

    def _add_peer(self, addr: tuple[str, int]) -> None:
        if addr in self.peers:
            return
        logger.info("new MAVLink peer %s:%d", *addr)
        self.peers.append(addr)
        if len(self.peers) > _MAX_PEERS:
            # Keep the configured udpout target (first), drop the oldest other peer.
            del self.peers[1 if self.endpoint.kind == "udpout" else 0]

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
            if not self._for_us(msg.target_system, msg.target_component):
                return
            self.setpoints_received += 1
            if msg.group_mlx != 0:
                # Auxiliary groups (MAVSDK sends group 1 alongside): nothing to drive here.
                if "group" not in self._warned:
                    self._warned.add("group")
                    logger.info("actuator control group %d ignored", msg.group_mlx)
                return
            self.autopilot.on_actuator_target(t_s, list(msg.controls))
        elif mtype == "SET_ATTITUDE_TARGET":
            if not self._for_us(msg.target_system, msg.target_component):
                return
            self.setpoints_received += 1
            self._handle_attitude_target(msg, t_s)
        elif mtype == "COMMAND_LONG":
            if self._for_us(msg.target_system, msg.target_component):
                params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6)
                self._handle_command(msg, msg.command, params, t_s)
        elif mtype == "COMMAND_INT":
            if self._for_us(msg.target_system, msg.target_component):
                params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.x, msg.y)
                self._handle_command(msg, msg.command, params, t_s)
        elif mtype == "TIMESYNC" and msg.tc1 == 0:
            self.mav.timesync_send(round(t_s * 1e9), msg.ts1)

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

    def _handle_command(self, msg: Any, command: int, p: Sequence[float], t_s: float) -> None:
        try:
            result = self._command_result(command, p, t_s)
        except (ValueError, OverflowError) as exc:  # e.g. int(nan) in a parameter
            logger.warning("command %d with bad parameters %s: %s", command, p, exc)
            result = MavResult.DENIED
        self.mav.command_ack_send(
            command, int(result), 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
        )
        if result == MavResult.ACCEPTED and command in (
            mavlink.MAV_CMD_COMPONENT_ARM_DISARM,
            mavlink.MAV_CMD_DO_SET_MODE,
            mavlink.MAV_CMD_NAV_LAND,
        ):
            # Announce the new state at once rather than at the next 1 Hz beat, so
            # a client sees arming and mode changes at the step they happened.
            self._heartbeat_now = True

    def _command_result(self, command: int, p: Sequence[float], t_s: float) -> MavResult:
        ap = self.autopilot
        if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            force = _as_int(p[1]) == FORCE_DISARM_MAGIC
            if p[0] >= 0.5:
                return ap.arm(t_s, force=force)
            return ap.disarm(t_s, force=force)
        if command == mavlink.MAV_CMD_DO_SET_MODE:
            if not _as_int(p[0]) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                return MavResult.DENIED
            return ap.set_mode(t_s, _as_int(p[1]), _as_int(p[2]))
        if command == mavlink.MAV_CMD_NAV_LAND:
            return ap.set_mode(t_s, 4, 6)
        if command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self.streams.set_interval(_as_int(p[0]), float(p[1]), t_s=t_s)
        if command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            return self._request(_as_int(p[0]))
        if command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            return self._request(ID_AUTOPILOT_VERSION)
        if command == mavlink.MAV_CMD_GET_HOME_POSITION:
            return self._request(ID_HOME_POSITION)
        logger.debug("unsupported command %d", command)
        return MavResult.UNSUPPORTED

    def _request(self, msg_id: int) -> MavResult:
        if msg_id not in _ONE_SHOT:
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
            True when a HIGHRES_IMU went out (the lockstep clock waits after it).
        """
        st = self.streams
        pending = self._pending
        if pending:
            self._pending = set()
            for msg_id in pending:
                self._send_one(msg_id)
        if (
            self._heartbeat_now
            or st.due(ID_HEARTBEAT, t_s)
            or wall_s - self._last_heartbeat_wall_s > 1.0
        ):
            self._heartbeat_now = False
            self._send_heartbeat(wall_s)
        # RC before IMU: a client that maps sticks when RC arrives then uses this
        # step's sticks for this step's IMU sample, as the in-process loop does.
        if st.due(ID_RC_CHANNELS, t_s):
            self._send_one(ID_RC_CHANNELS)
        imu_sent = False
        if imu_sample and not self.imu_stopped:
            # Lockstep follows the fastest body-rate stream: the one the client runs on.
            clock = st.lockstep_stream((ID_HIGHRES_IMU, ID_ATTITUDE, ID_ATTITUDE_QUATERNION))
            for msg_id in (ID_HIGHRES_IMU, ID_ATTITUDE, ID_ATTITUDE_QUATERNION):
                if st.due(msg_id, t_s):
                    self._send_one(msg_id)
                    imu_sent = imu_sent or msg_id == clock
        for msg_id in (
            ID_LOCAL_POSITION_NED,
            ID_SYS_STATUS,
            ID_EXTENDED_SYS_STATE,
            ID_HOME_POSITION,
        ):
            if st.due(msg_id, t_s):
                self._send_one(msg_id)
        return imu_sent

    def _send_heartbeat(self, wall_s: float) -> None:
        ap = self.autopilot
        self.mav.heartbeat_send(
            MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4, ap.base_mode, ap.custom_mode, ap.system_status
        )
        self._last_heartbeat_wall_s = wall_s

    def _send_one(self, msg_id: int) -> None:
        s = self.snapshot
        mav = self.mav
        ap = self.autopilot
        if msg_id == ID_HIGHRES_IMU:
            a, g = s.accel_frd_m_s2, s.gyro_frd_rad_s
            if self.imu_nan:
                g = (math.nan, math.nan, math.nan)
            mav.highres_imu_send(
                round(s.imu_t_s * 1e6),
                a[0], a[1], a[2], g[0], g[1], g[2],
                0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                HIGHRES_FIELDS_GYRO_ACCEL,
            )  # fmt: skip
            self.imu_messages_sent += 1
        elif msg_id == ID_ATTITUDE:
            e, g = s.euler_rad, s.gyro_frd_rad_s
            mav.attitude_send(round(s.imu_t_s * 1e3), e[0], e[1], e[2], g[0], g[1], g[2])
        elif msg_id == ID_ATTITUDE_QUATERNION:
            q, g = s.q_wxyz, s.gyro_frd_rad_s
            mav.attitude_quaternion_send(
                round(s.imu_t_s * 1e3), q[0], q[1], q[2], q[3], g[0], g[1], g[2]
            )
        elif msg_id == ID_RC_CHANNELS:
            # No sticks, or a receiver without signal: no channel (chancount 0),
            # every one UINT16_MAX ("unused"), RSSI 0.
            chans = [] if self.rc_lost else list(s.sticks_us or ())[:18]
            n = len(chans)
            chans += [65535] * (18 - n)
            mav.rc_channels_send(round(s.t_s * 1e3), n, *chans, 254 if n else 0)
        elif msg_id == ID_LOCAL_POSITION_NED:
            # PX4 and ArduPilot send it only while their position estimate is valid.
            if self.autopilot.position_valid:
                x, v = s.pos_ned_m, s.vel_ned_m_s
                mav.local_position_ned_send(round(s.t_s * 1e3), x[0], x[1], x[2], v[0], v[1], v[2])
        elif msg_id == ID_SYS_STATUS:
            mav.sys_status_send(SENSORS, SENSORS, SENSORS, 0, 16800, -1, 100, 0, 0, 0, 0, 0, 0)
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
                CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0,
                [0] * 8, [0] * 8, [0] * 8, 0, 0, 1,
            )  # fmt: skip
        elif msg_id == ID_HEARTBEAT:
            self._send_heartbeat(self._last_heartbeat_wall_s)
