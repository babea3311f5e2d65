"""A companion killed mid-flight: what the autopilot does alone, and what it costs.

:func:`fly_killed` flies a scenario as :func:`sitl.lab.fly.fly_mavlink` does (the
SITL in lockstep, ``companion run --engage auto``), with a :class:`KillRelay`
between the two: a UDP relay that reads the SITL's IMU stream and sends the
companion ``SIGKILL`` at the first sample that meets a :class:`KillAt` (a time
since arming, and optionally a body rate reached), before that sample reaches
it. The companion's last setpoint is the one it sent for the sample before: the
autopilot holds it until its own offboard-loss timeout (PX4 ``COM_OF_LOSS_T``),
then flies its fallback (``COM_OBL_RC_ACT``: Land here). The SITL flies on to
the end of its ``--duration``, and :func:`kill_figures` reads from its
true-state log what followed: the largest body rate, the altitude lost before
the vehicle was back under control, and whether it was, or crashed.

Under control means level within :data:`LEVEL_TILT_DEG`, turning slower than
:data:`STILL_RATE_DEG_S` and sinking slower than :data:`SINK_M_S` (the SITL's
AUTO.LAND descends at 0.7 m/s), all held for :data:`RECOVERED_HOLD_S`. The
altitude lost is the altitude at the kill less the lowest altitude before then.
"""

from __future__ import annotations

import contextlib
import math
import os
import selectors
import signal
import socket
import threading
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

from sitl.flight_log import read_log
from sitl.lab.fly import FlightProcesses, fly_mavlink

__all__ = [
    "LEVEL_TILT_DEG",
    "RATE_WINDOW_S",
    "RECOVERED_HOLD_S",
    "SINK_M_S",
    "STILL_RATE_DEG_S",
    "KillAt",
    "KillFigures",
    "KillRelay",
    "KilledFlight",
    "figures_row",
    "fly_killed",
    "kill_figures",
    "outcome",
]

LEVEL_TILT_DEG = 15.0
STILL_RATE_DEG_S = 30.0
SINK_M_S = 1.5
RECOVERED_HOLD_S = 0.5
RATE_WINDOW_S = 3.0
"""A kill waiting for a body rate waits at most this long after its time."""
_MAV_CMD_COMPONENT_ARM_DISARM = 400


@dataclass(frozen=True)
class KillAt:
    """When to kill: the first IMU sample at least ``after_s`` after the companion's
    arm command whose gyro on ``axis`` (0 roll, 1 pitch, 2 yaw) is at least
    ``rate_deg_s`` in magnitude (``rate_deg_s`` 0: the first sample after
    ``after_s``; a rate waited for at most :data:`RATE_WINDOW_S`)."""

    after_s: float
    rate_deg_s: float = 0.0
    axis: int = 0


class KillRelay:
    """A UDP relay between the SITL and the companion that kills the companion.

    The SITL sends to :attr:`port`; the relay forwards to the companion's port and
    back. Before forwarding an IMU sample (``HIGHRES_IMU``) that meets ``when``, it
    sends the companion (:attr:`pid`, set once it runs) ``SIGKILL`` and forwards
    nothing to it any more; what the companion had sent before still reaches the
    SITL. :attr:`killed_imu_t_s` is the sample's time (the SITL's clock),
    :attr:`armed_imu_t_s` the last sample's before the arm command went through.
    """

    def __init__(self, when: KillAt) -> None:
        self.when = when
        self.pid: int | None = None
        self.armed_imu_t_s: float | None = None
        self.killed_imu_t_s: float | None = None
        self.killed_gyro_rad_s: tuple[float, float, float] | None = None
        self._last_imu_t_s: float | None = None
        self._to_sitl: tuple[str, int] | None = None
        self._to_companion: tuple[str, int] | None = None
        self._sitl_side = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sitl_side.bind(("127.0.0.1", 0))
        self._companion_side = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._companion_side.bind(("127.0.0.1", 0))
        self._from_sitl = mavlink2.MAVLink(None)
        self._from_companion = mavlink2.MAVLink(None)
        for mav in (self._from_sitl, self._from_companion):
            mav.robust_parsing = True
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="kill-relay", daemon=True)

    @property
    def port(self) -> int:
        return int(self._sitl_side.getsockname()[1])

    def start(self, companion_port: int) -> int:
        """Forward to ``companion_port``; returns the port the SITL should send to."""
        self._to_companion = ("127.0.0.1", companion_port)
        self._thread.start()
        return self.port

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self._sitl_side.close()
        self._companion_side.close()

    def _loop(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self._sitl_side, selectors.EVENT_READ, "sitl")
        sel.register(self._companion_side, selectors.EVENT_READ, "companion")
        try:
            while not self._stop.is_set():
                for key, _ in sel.select(timeout=0.1):
                    sock: socket.socket = key.fileobj  # type: ignore[assignment]
                    try:
                        data, addr = sock.recvfrom(65536)
                    except OSError:
                        continue  # ECONNREFUSED from a companion that is gone
                    if key.data == "sitl":
                        self._to_sitl = addr
                        self._from_the_sitl(data)
                    else:
                        self._from_the_companion(data)
        finally:
            sel.close()

    def _from_the_sitl(self, data: bytes) -> None:
        if self.killed_imu_t_s is not None:
            return
        for msg in self._parse(self._from_sitl, data):
            if msg.get_msgId() != mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU:
                continue
            t_s = msg.time_usec * 1e-6
            self._last_imu_t_s = t_s
            gyro = (float(msg.xgyro), float(msg.ygyro), float(msg.zgyro))
            if self._due(t_s, gyro):
                self._kill(t_s, gyro)
                return
        if self._to_companion is not None:
            self._send(self._companion_side, data, self._to_companion)

    def _from_the_companion(self, data: bytes) -> None:
        if self.armed_imu_t_s is None:
            for msg in self._parse(self._from_companion, data):
                if (
                    msg.get_msgId() == mavlink2.MAVLINK_MSG_ID_COMMAND_LONG
                    and msg.command == _MAV_CMD_COMPONENT_ARM_DISARM
                    and msg.param1 == 1.0
                ):
                    self.armed_imu_t_s = self._last_imu_t_s
        if self._to_sitl is not None:
            self._send(self._sitl_side, data, self._to_sitl)

    def _due(self, t_s: float, gyro: tuple[float, float, float]) -> bool:
        w = self.when
        if self.pid is None or self.armed_imu_t_s is None:
            return False
        if t_s - self.armed_imu_t_s < w.after_s - 1e-9:
            return False
        return abs(math.degrees(gyro[w.axis])) >= w.rate_deg_s

    def _kill(self, t_s: float, gyro: tuple[float, float, float]) -> None:
        assert self.pid is not None
        os.kill(self.pid, signal.SIGKILL)
        self.killed_imu_t_s = t_s
        self.killed_gyro_rad_s = gyro

    @staticmethod
    def _parse(mav: Any, data: bytes) -> list[Any]:
        try:
            return list(mav.parse_buffer(data) or [])
        except Exception:  # a frame this relay cannot read is still forwarded
            return []

    @staticmethod
    def _send(sock: socket.socket, data: bytes, addr: tuple[str, int]) -> None:
        with contextlib.suppress(OSError):  # the other end is not listening (any more)
            sock.sendto(data, addr)


@dataclass(frozen=True)
class KillFigures:
    """What followed a kill, from the SITL's true state (angles and rates in deg).

    ``t_kill_s`` counts from the pilot's start (arming); every other time from the
    kill. ``altitude_lost_m`` is the altitude at the kill less the lowest before
    recovery (before the crash, or the end of the log, without one).
    """

    t_kill_s: float
    rate_at_kill_deg_s: tuple[float, float, float]
    tilt_at_kill_deg: float
    altitude_at_kill_m: float
    failsafe_after_s: float | None
    failsafe_mode: str | None
    max_rate_deg_s: float
    max_tilt_deg: float
    altitude_lost_m: float
    recovered_after_s: float | None
    crashed: bool
    crashed_after_s: float | None

    @property
    def outcome(self) -> str:
        return outcome(self.crashed, self.recovered_after_s)

    def row(self) -> dict[str, Any]:
        """The figures as one flat dict (rounded), with the outcome."""
        return figures_row(self)


def outcome(crashed: bool, recovered_after_s: float | None) -> str:
    """``crashed``, ``recovered`` or ``not recovered`` (by the end of the log)."""
    if crashed:
        return "crashed"
    return "recovered" if recovered_after_s is not None else "not recovered"


def _rounded(value: Any) -> Any:
    if isinstance(value, float):
        return round(value, 3)
    if isinstance(value, (list, tuple)):
        return [_rounded(v) for v in value]
    return value


def figures_row(figures: Any) -> dict[str, Any]:
    """A dataclass of figures with an ``outcome`` as one JSON-ready dict, floats
    rounded to 3 decimals."""
    return {**{k: _rounded(v) for k, v in asdict(figures).items()}, "outcome": figures.outcome}


def _tilt_deg(q_wxyz: np.ndarray) -> np.ndarray:
    """Angle between the body's down axis and the world's, deg."""
    x, y = q_wxyz[:, 1], q_wxyz[:, 2]
    cos_tilt = np.clip(1.0 - 2.0 * (x * x + y * y), -1.0, 1.0)
    return np.asarray(np.degrees(np.arccos(cos_tilt)))


def kill_figures(sitl_log: str | Path, killed_t_s: float) -> KillFigures:
    """The figures of a kill at ``killed_t_s`` (the SITL's clock) from its log."""
    from sitl.px4_modes import mode_name, unpack_custom_mode

    log = read_log(sitl_log)
    t = log["t_s"]
    start = next((float(e["t_s"]) for e in log.events if e.get("kind") == "pilot_start"), 0.0)
    k0 = int(np.searchsorted(t, killed_t_s - 1e-9))
    after = slice(k0, len(t))
    rate = np.degrees(log["rate_frd_rad_s"])
    rate_norm = np.linalg.norm(rate, axis=1)
    tilt = _tilt_deg(log["q_wxyz"])
    alt = -log["pos_ned_m"][:, 2]
    sink = log["vel_ned_m_s"][:, 2]
    mode = log["custom_mode"].astype(np.int64)
    changed = np.nonzero(mode[after] != mode[k0])[0]
    fs_i = k0 + int(changed[0]) if changed.size else None
    crash_t = next(
        (float(e["t_s"]) for e in log.events if e.get("status") == "crashed"),
        None,
    )
    end = len(t) if crash_t is None else int(np.searchsorted(t, crash_t - 1e-9)) + 1
    calm = (tilt < LEVEL_TILT_DEG) & (rate_norm < STILL_RATE_DEG_S) & (sink < SINK_M_S)
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.001
    hold = max(1, round(RECOVERED_HOLD_S / dt))
    rec_i: int | None = None
    run = 0
    # Recovery is judged after the failsafe took over: before it the held setpoint flies.
    first = fs_i if fs_i is not None else k0
    for i in range(first, end):
        run = run + 1 if calm[i] else 0
        if run >= hold:
            rec_i = i - hold + 1
            break
    low_end = rec_i + 1 if rec_i is not None else end
    lowest = float(np.min(alt[k0:low_end])) if low_end > k0 else float(alt[k0])
    return KillFigures(
        t_kill_s=float(t[k0] - start),
        rate_at_kill_deg_s=(float(rate[k0, 0]), float(rate[k0, 1]), float(rate[k0, 2])),
        tilt_at_kill_deg=float(tilt[k0]),
        altitude_at_kill_m=float(alt[k0]),
        failsafe_after_s=None if fs_i is None else float(t[fs_i] - t[k0]),
        failsafe_mode=None if fs_i is None else mode_name(*unpack_custom_mode(int(mode[fs_i]))),
        max_rate_deg_s=float(np.max(rate_norm[k0:end])),
        max_tilt_deg=float(np.max(tilt[k0:low_end])),
        altitude_lost_m=float(alt[k0]) - lowest,
        recovered_after_s=None if rec_i is None else float(t[rec_i] - t[k0]),
        crashed=crash_t is not None and crash_t >= float(t[k0]),
        crashed_after_s=None if crash_t is None else crash_t - float(t[k0]),
    )


@dataclass
class KilledFlight:
    """A flight whose companion was killed: the processes, the kill and its figures."""

    flight: FlightProcesses
    when: KillAt
    killed_imu_t_s: float | None
    figures: KillFigures | None
    notes: list[str] = field(default_factory=list)


def fly_killed(
    profile_path: str | Path,
    scenario: str,
    out_dir: str | Path,
    when: KillAt,
    *,
    output: str = "actuator",
    offboard_timeout_s: float = 1.0,
    offboard_loss_action: int = 4,
    fly_on_s: float = 8.0,
    lockstep_timeout_s: float = 2.0,
    sitl_args: Sequence[str] = (),
    companion_args: Sequence[str] = (),
    timeout_s: float | None = None,
) -> KilledFlight:
    """Fly ``scenario``, kill the companion at ``when``, and let the SITL fly on
    ``fly_on_s`` more (simulated) seconds on its own.

    Parameters
    ----------
    offboard_timeout_s
        PX4 ``COM_OF_LOSS_T`` of the SITL.
    offboard_loss_action
        PX4 ``COM_OBL_RC_ACT`` of the SITL; 4, Land: a fallback flown from the
        sticks (0, Position mode, PX4's default) would fly the scenario's scripted
        pilot on, who goes on with the programme where a pilot would take over.
    lockstep_timeout_s
        ``sitl run --lockstep-timeout``: a companion slower than this on a loaded
        machine lets the SITL run on without its setpoints, and a short
        ``COM_OF_LOSS_T`` then fails safe before the kill (the kill then waits
        this long once, for the setpoint that never comes).
    sitl_args, companion_args
        More options for ``sitl run`` and ``companion run``.
    """
    relay = KillRelay(when)
    # A kill that waits for a rate waits at most RATE_WINDOW_S for it.
    duration = when.after_s + fly_on_s + (RATE_WINDOW_S if when.rate_deg_s > 0.0 else 0.0)

    def started(sitl: Any, comp: Any) -> None:
        relay.pid = comp.pid

    try:
        flight = fly_mavlink(
            profile_path,
            scenario,
            out_dir,
            output=output,
            sitl_args=(
                *("--offboard-timeout", f"{offboard_timeout_s:g}"),
                *("--param", f"COM_OBL_RC_ACT={offboard_loss_action}"),
                *("--duration", f"{duration:g}"),
                *("--lockstep-timeout", f"{lockstep_timeout_s:g}"),
                *sitl_args,
            ),
            companion_args=companion_args,
            timeout_s=timeout_s,
            on_started=started,
            relay=relay.start,
            sitl_flies_on=True,
        )
    finally:
        relay.close()
    notes: list[str] = []
    figures = None
    if relay.killed_imu_t_s is None:
        notes.append("the kill condition was never met")
    elif flight.sitl_log.exists():
        figures = kill_figures(flight.sitl_log, relay.killed_imu_t_s)
    else:
        notes.append("the SITL wrote no log")
    return KilledFlight(flight, when, relay.killed_imu_t_s, figures, notes)
