"""A ground station and a pilot for the real stacks, over MAVLink (pymavlink).

:class:`GroundStation` is what a test needs beside the companion: it sets and
reads parameters, sends commands (mode, arm, take-off), records what the
autopilot says about the flight (attitude, position, mode, status, its
STATUSTEXTs), uploads a mission (the MAVLink mission protocol), and flies the
pilot's sticks: PX4 SIH has no radio, so the sticks go as ``MANUAL_CONTROL`` on
the ground station's link (joystick input, with ``aux1..6`` as the switches);
ArduCopter's SITL takes RC pulses on a UDP port.

One background thread receives and sends; the calls from the test's thread
only queue frames under a lock and wait on what the thread records.
"""

from __future__ import annotations

import contextlib
import math
import os
import socket
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil

__all__ = ["GroundStation", "MissionItem", "Sample", "SticksFn", "Telemetry"]

SticksFn = Callable[["Telemetry"], tuple[int, ...] | None]
"""The pilot: from what the ground station sees, RC channels in us (AETR, then
ch5..), or None to send nothing (a radio that is off)."""

_GCS_SYSID = 255
_GCS_COMPID = 190
_MAV_TYPE_GCS = 6
_MAV_AUTOPILOT_INVALID = 8
_PARAM_INT32 = 6
_PARAM_REAL32 = 9

_STREAMS_HZ = {
    30: 50.0,  # ATTITUDE
    32: 25.0,  # LOCAL_POSITION_NED
    1: 5.0,  # SYS_STATUS
    245: 5.0,  # EXTENDED_SYS_STATE
    83: 25.0,  # ATTITUDE_TARGET
    74: 5.0,  # VFR_HUD
}


@dataclass
class Sample:
    """One message's fields as recorded, with the ground station's clock."""

    t_s: float
    fields: dict[str, Any]


@dataclass
class Telemetry:
    """What the ground station knows of the vehicle now."""

    t_s: float = 0.0
    """Seconds since the ground station started (its clock)."""
    mode: int | None = None
    armed: bool = False
    system_status: int | None = None
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float = 0.0
    rates_rad_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    position_ned_m: tuple[float, float, float] | None = None
    velocity_ned_m_s: tuple[float, float, float] | None = None
    landed_state: int | None = None
    thrust_setpoint: float | None = None
    rc_healthy: bool | None = None


@dataclass(frozen=True)
class MissionItem:
    """One MISSION_ITEM_INT: a command at a global position (``frame`` a MAV_FRAME,
    ``MAV_FRAME_GLOBAL_RELATIVE_ALT_INT`` (6) by default: the altitude above home)."""

    command: int
    lat_deg: float
    lon_deg: float
    alt_m: float
    params: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    frame: int = 6


@dataclass
class _Pending:
    kind: str
    key: Any
    event: threading.Event = field(default_factory=threading.Event)
    result: Any = None


class GroundStation:
    """A ground station on ``url`` (pymavlink form) for the autopilot ``sysid``.

    ``rc_port``: ArduCopter's RC input (UDP, localhost); without it the sticks
    go as ``MANUAL_CONTROL`` (PX4). ``sysid``: the autopilot's system id (PX4
    instance ``I`` is ``1 + I``); None learns it from the first autopilot heartbeat.
    """

    def __init__(
        self,
        url: str,
        *,
        stack: str,
        rc_port: int | None = None,
        sysid: int | None = None,
        connect_timeout_s: float = 30.0,
    ) -> None:
        self.stack = stack
        self.sysid = sysid
        self.rc_port = rc_port
        self._t0 = time.monotonic()
        self._conn = self._connect(url, connect_timeout_s)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.now = Telemetry()
        self.texts: list[tuple[float, str]] = []
        self.heartbeats: list[tuple[float, int, bool, int]] = []
        """(t, custom_mode, armed, system_status) at each change."""
        self.records: dict[str, list[Sample]] = {}
        self.record_types = {"ATTITUDE", "LOCAL_POSITION_NED", "EXTENDED_SYS_STATE", "SYS_STATUS"}
        self._pending: list[_Pending] = []
        self._pilot: SticksFn | None = None
        self.pilot_error: Exception | None = None
        self._upload: tuple[MissionItem, ...] = ()
        self._pilot_period_s = 0.02
        self._rc_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM) if rc_port else None
        self._thread = threading.Thread(target=self._loop, name="gcs", daemon=True)
        self._thread.start()

    # ---------------------------------------------------------------- set-up
    def _connect(self, url: str, timeout_s: float) -> Any:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                return mavutil.mavlink_connection(
                    url,
                    source_system=_GCS_SYSID,
                    source_component=_GCS_COMPID,
                    autoreconnect=True,
                    retries=1,
                )
            except (OSError, ConnectionError):
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.5)

    def clock(self) -> float:
        return time.monotonic() - self._t0

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        with contextlib.suppress(Exception):  # a socket the stack already closed
            self._conn.close()
        if self._rc_sock is not None:
            self._rc_sock.close()

    @property
    def target(self) -> int:
        if self.sysid is None:
            raise RuntimeError(f"no heartbeat from the {self.stack} SITL yet")
        return self.sysid

    def wait_heartbeat(self, timeout_s: float = 30.0) -> None:
        if not self.wait(lambda t: t.mode is not None, timeout_s):
            raise TimeoutError(f"no heartbeat from the {self.stack} SITL in {timeout_s:g} s")
        for msg_id, hz in _STREAMS_HZ.items():
            self.send("command_long_send", self.target, 1, 511, 0, msg_id, 1e6 / hz, 0, 0, 0, 0, 0)

    def wait(self, cond: Callable[[Telemetry], bool], timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if cond(self.now):
                return True
            time.sleep(0.02)
        return bool(cond(self.now))

    def wait_text(self, text: str, timeout_s: float, *, since_s: float = 0.0) -> str | None:
        """The first STATUSTEXT since ``since_s`` containing ``text``, waited for."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for t, said in list(self.texts):
                if t >= since_s and text in said:
                    return said
            time.sleep(0.05)
        return None

    # ----------------------------------------------------------------- sending
    def send(self, method: str, *args: Any) -> None:
        with self._lock:
            getattr(self._conn.mav, method)(*args)

    def set_pilot(self, pilot: SticksFn | None) -> None:
        """Fly these sticks from now on (50 Hz); None: send nothing (the radio off)."""
        self._pilot = pilot

    def _send_sticks(self, ch: tuple[int, ...]) -> None:
        if self._rc_sock is not None:
            chans = [int(c) for c in ch[:16]] + [1500] * (16 - min(len(ch), 16))
            self._rc_sock.sendto(struct.pack("<16H", *chans), ("127.0.0.1", self.rc_port))
            return
        roll, pitch, thr, yaw = ch[0], ch[1], ch[2], ch[3]
        aux = [(int(c) - 1500) * 2 for c in ch[4:10]] + [0] * (6 - len(ch[4:10]))
        self.send(
            "manual_control_send",
            self.target,
            -(pitch - 1500) * 2,  # x: stick forward (nose down) positive; ch2 high is back
            (roll - 1500) * 2,
            max(0, min(1000, thr - 1000)),
            (yaw - 1500) * 2,
            0,
            0,
            0b11111100,  # aux1..aux6 present
            0,
            0,
            *aux,
        )

    def command(self, cmd: int, *params: float, timeout_s: float = 3.0) -> int | None:
        """COMMAND_LONG to the autopilot; its MAV_RESULT (None: no answer)."""
        p = [*params, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][:7]
        for _ in range(3):
            pend = self._expect("ack", cmd)
            self.send("command_long_send", self.target, 1, cmd, 0, *p)
            if pend.event.wait(timeout_s / 3):
                return int(pend.result)
        return None

    def set_mode(self, param2: float, param3: float = 0.0) -> int | None:
        return self.command(176, 1, param2, param3)

    def arm(self, *, force: bool = False) -> int | None:
        return self.command(400, 1, 21196 if force else 0)

    def disarm(self, *, force: bool = False) -> int | None:
        return self.command(400, 0, 21196 if force else 0)

    def param_get(self, name: str, timeout_s: float = 3.0) -> tuple[float, int] | None:
        """(value, type) of a parameter, decoded (PX4's integers are bytewise)."""
        for _ in range(3):
            pend = self._expect("param", name)
            self.send("param_request_read_send", self.target, 1, name.encode(), -1)
            if pend.event.wait(timeout_s / 3):
                return pend.result  # type: ignore[no-any-return]
        return None

    def param_set(self, name: str, value: float, timeout_s: float = 3.0) -> float:
        """Set a parameter and return the value the autopilot confirms.

        Raises
        ------
        RuntimeError
            When the autopilot does not know it or does not confirm it.
        """
        got = self.param_get(name)
        if got is None:
            raise RuntimeError(f"{self.stack} has no parameter {name}")
        ptype = got[1]
        wire = value
        if self.stack == "px4" and ptype == _PARAM_INT32:
            wire = struct.unpack("<f", struct.pack("<i", int(value)))[0]
        for _ in range(3):
            pend = self._expect("param", name)
            self.send("param_set_send", self.target, 1, name.encode(), wire, ptype)
            if pend.event.wait(timeout_s / 3):
                confirmed = float(pend.result[0])
                if math.isclose(confirmed, value, rel_tol=1e-5, abs_tol=1e-6):
                    return confirmed
        raise RuntimeError(f"{self.stack} did not confirm {name} = {value:g}")

    def upload_mission(self, items: Sequence[MissionItem], timeout_s: float = 10.0) -> int | None:
        """Replace the autopilot's mission with ``items`` (the mission protocol:
        MISSION_COUNT, then each MISSION_ITEM_INT it asks for with MISSION_REQUEST_INT
        or MISSION_REQUEST); the MISSION_ACK's type (0: accepted; None: no answer)."""
        with self._lock:
            self._upload = tuple(items)
        try:
            for _ in range(2):
                pend = self._expect("mission_ack", 0)
                self.send("mission_count_send", self.target, 1, len(items), 0)
                if pend.event.wait(timeout_s / 2):
                    return int(pend.result)
            return None
        finally:
            with self._lock:
                self._upload = ()

    def _send_mission_item(self, seq: int) -> None:
        with self._lock:
            items = self._upload
        if not 0 <= seq < len(items):
            return
        it = items[seq]
        self.send(
            "mission_item_int_send", self.target, 1, seq, it.frame, it.command,
            0, 1, *it.params, round(it.lat_deg * 1e7), round(it.lon_deg * 1e7), it.alt_m, 0,
        )  # fmt: skip

    def _expect(self, kind: str, key: Any) -> _Pending:
        pend = _Pending(kind, key)
        with self._lock:
            self._pending.append(pend)
        return pend

    # ----------------------------------------------------------------- the thread
    def _loop(self) -> None:
        next_hb = 0.0
        next_stick = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_hb:
                next_hb = now + 1.0
                self.send("heartbeat_send", _MAV_TYPE_GCS, _MAV_AUTOPILOT_INVALID, 0, 0, 0)
            if now >= next_stick:
                next_stick = now + self._pilot_period_s
                pilot = self._pilot
                if pilot is not None and (self._rc_sock is not None or self.sysid is not None):
                    self.now.t_s = self.clock()
                    try:
                        ch = pilot(self.now)
                        if ch is not None:
                            self._send_sticks(ch)
                    except Exception as exc:  # the test reads it: the pilot stops
                        self.pilot_error = exc
                        self._pilot = None
            try:
                msg = self._conn.recv_match(blocking=True, timeout=0.005)
            except (OSError, ConnectionError):
                time.sleep(0.05)
                continue
            while msg is not None:
                self._on_message(msg)
                try:
                    msg = self._conn.recv_match(blocking=False)
                except (OSError, ConnectionError):
                    msg = None

    def _on_message(self, msg: Any) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA" or msg.get_srcComponent() != 1:
            return
        if self.sysid is None:
            if mtype != "HEARTBEAT" or msg.autopilot == _MAV_AUTOPILOT_INVALID:
                return
            self.sysid = msg.get_srcSystem()
        if msg.get_srcSystem() != self.sysid:
            return
        t = self.clock()
        now = self.now
        if mtype in self.record_types:
            self.records.setdefault(mtype, []).append(Sample(t, msg.to_dict()))
        if mtype == "HEARTBEAT":
            armed = bool(msg.base_mode & 128)
            key = (int(msg.custom_mode), armed, int(msg.system_status))
            if (now.mode, now.armed, now.system_status) != key:
                self.heartbeats.append((t, *key))
            now.mode, now.armed, now.system_status = key
        elif mtype == "ATTITUDE":
            now.roll_rad, now.pitch_rad, now.yaw_rad = msg.roll, msg.pitch, msg.yaw
            now.rates_rad_s = (msg.rollspeed, msg.pitchspeed, msg.yawspeed)
        elif mtype == "LOCAL_POSITION_NED":
            now.position_ned_m = (msg.x, msg.y, msg.z)
            now.velocity_ned_m_s = (msg.vx, msg.vy, msg.vz)
        elif mtype == "EXTENDED_SYS_STATE":
            now.landed_state = int(msg.landed_state)
        elif mtype == "ATTITUDE_TARGET":
            now.thrust_setpoint = float(msg.thrust)
        elif mtype == "SYS_STATUS":
            rc = 1 << 16
            now.rc_healthy = bool(msg.onboard_control_sensors_health & rc)
        elif mtype == "HOME_POSITION":
            self._resolve("message", mtype, msg.altitude * 1e-3)
        elif mtype == "GLOBAL_POSITION_INT":
            got = (msg.lat * 1e-7, msg.lon * 1e-7, msg.relative_alt * 1e-3)
            self._resolve("message", mtype, got)
        elif mtype in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
            if getattr(msg, "mission_type", 0) == 0:
                self._send_mission_item(int(msg.seq))
        elif mtype == "MISSION_ACK":
            if getattr(msg, "mission_type", 0) == 0:
                self._resolve("mission_ack", 0, int(msg.type))
        elif mtype == "STATUSTEXT":
            text = msg.text if isinstance(msg.text, str) else msg.text.decode(errors="replace")
            self.texts.append((t, text.rstrip("\x00")))
        elif mtype == "COMMAND_ACK":
            self._resolve("ack", int(msg.command), int(msg.result))
        elif mtype == "PARAM_VALUE":
            name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode()
            name = name.rstrip("\x00")
            value = float(msg.param_value)
            if self.stack == "px4" and msg.param_type == _PARAM_INT32:
                value = float(struct.unpack("<i", struct.pack("<f", msg.param_value))[0])
            self._resolve("param", name, (value, int(msg.param_type)))

    def _resolve(self, kind: str, key: Any, result: Any) -> None:
        with self._lock:
            for pend in self._pending:
                if pend.kind == kind and pend.key == key and not pend.event.is_set():
                    pend.result = result
                    pend.event.set()
            self._pending = [p for p in self._pending if not p.event.is_set()]

    def home_altitude_m(self, timeout_s: float = 3.0) -> float:
        """The home position's altitude (AMSL, m), asked for (MAV_CMD_REQUEST_MESSAGE)."""
        return float(self._request_message(242, "HOME_POSITION", timeout_s))

    def global_position(self, timeout_s: float = 3.0) -> tuple[float, float, float]:
        """(latitude deg, longitude deg, altitude above home m) of the vehicle now
        (GLOBAL_POSITION_INT, asked for with MAV_CMD_REQUEST_MESSAGE)."""
        lat, lon, up = self._request_message(33, "GLOBAL_POSITION_INT", timeout_s)
        return float(lat), float(lon), float(up)

    def _request_message(self, msg_id: int, name: str, timeout_s: float) -> Any:
        """What :meth:`_on_message` makes of the next ``name``, asked for every 0.5 s."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            pend = self._expect("message", name)
            self.send("command_long_send", self.target, 1, 512, 0, msg_id, 0, 0, 0, 0, 0, 0)
            if pend.event.wait(min(0.5, max(0.0, deadline - time.monotonic()))):
                return pend.result
        raise TimeoutError(f"no {name} from the {self.stack} SITL")

    # ------------------------------------------------------------------ readings
    def series(self, mtype: str, *names: str, since_s: float = 0.0) -> list[tuple[float, ...]]:
        """Recorded fields of ``mtype`` since ``since_s``: rows of (t, *names)."""
        rows = self.records.get(mtype, [])
        return [(s.t_s, *(s.fields[n] for n in names)) for s in list(rows) if s.t_s >= since_s]

    def texts_since(self, since_s: float) -> list[str]:
        return [text for t, text in list(self.texts) if t >= since_s]
