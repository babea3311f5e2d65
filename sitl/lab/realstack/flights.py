"""Flights against the real stacks: the vehicle in the air, a pilot, the companion.

A :class:`Session` is one running stack with its ground station: it gets the
vehicle into the air the stack's own way (PX4: arm and ``MAV_CMD_NAV_TAKEOFF``,
then AUTO.LOITER; ArduCopter: ALT_HOLD, arm, throttle up, then mid-stick, since
taking off in GUIDED_NOGPS with ``GUID_OPTIONS = 8`` trips an internal error in
4.5), starts ``companion run`` as a process and flies a pilot: a scripted
timeline from :mod:`sitl.pilot` seeing the vehicle through the ground station's
telemetry, with the engage switch (RC channel 5, or ``aux1`` of PX4's joystick).

The pilot's clock starts when the switch goes high; the vehicle's own estimate
(ATTITUDE, LOCAL_POSITION_NED, as the ground station receives them) is what the
virtual pilot levels and holds altitude on, as a human watching it would.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.records import read_control_log
from companion.stacks import ARDUPILOT, PX4, FlightStack
from sitl.lab import children
from sitl.lab.realstack.gcs import GroundStation, Telemetry
from sitl.lab.realstack.launch import RunningStack, start_arducopter, start_px4
from sitl.pilot.rc import RC_MID_US, RC_MIN_US
from sitl.pilot.scripted import Pilot
from sitl.pilot.virtual import PilotView

__all__ = [
    "ARDUCOPTER_PARAMS",
    "CompanionRun",
    "Session",
    "SwitchPilot",
    "new_log_dir",
    "pilot_view",
    "rate_errors",
]

ARDUCOPTER_PARAMS = {
    "GUID_OPTIONS": 8,  # SET_ATTITUDE_TARGET thrust is a normalised thrust
    "FLTMODE_CH": 6,  # channel 5 stays free for the engage switch
    "FLTMODE1": 2,  # channel 6 low (as the pilot sends it): ALT_HOLD
}
"""What the tests' ArduCopter starts with beyond its defaults (the stacks' README)."""

PX4_LOITER = (4 << 16) | (3 << 24)  # AUTO.LOITER
FAST_BOOT_SPEEDUP = 8.0
_LANDED_ON_GROUND = 1  # MAV_LANDED_STATE_ON_GROUND
SWITCH_LOW_US = 1000
SWITCH_HIGH_US = 2000
_ROOT = Path(__file__).resolve().parents[3]


def pilot_view(now: Telemetry, t0_s: float, hover_throttle: float) -> PilotView:
    """What a scripted pilot sees of the vehicle through the ground station, its
    clock from ``t0_s`` (the ground station's)."""
    pos = now.position_ned_m or (0.0, 0.0, 0.0)
    vel = now.velocity_ned_m_s or (0.0, 0.0, 0.0)
    return PilotView(
        t_s=max(0.0, now.t_s - t0_s),
        roll_rad=now.roll_rad,
        pitch_rad=now.pitch_rad,
        yaw_rad=now.yaw_rad,
        rate_frd_rad_s=now.rates_rad_s,
        altitude_m=-pos[2],
        climb_rate_m_s=-vel[2],
        hover_throttle=hover_throttle,
    )


@dataclass
class SwitchPilot:
    """The pilot's hands: centred sticks and the switch low until :meth:`engage`;
    then ``pilot`` (a scripted timeline, its clock from the switch) with the
    switch high, until :meth:`release`. ``radio_on`` False sends nothing."""

    hover_throttle: float
    pilot: Pilot | None = None
    mid_throttle_us: int = RC_MID_US
    """The throttle before engaging: mid-stick holds altitude in PX4's and
    ArduCopter's altitude modes."""
    extra_us: tuple[int, ...] = (SWITCH_LOW_US,)
    """Channels after ch5 (ArduCopter's ch6 mode switch: low = FLTMODE1)."""
    radio_on: bool = True
    switch_high: bool = False
    t_engage_s: float | None = None
    sticks_us: tuple[int, int, int, int] | None = None
    """Sticks held as they are (ch1..ch4) instead of the timeline's."""

    def engage(self, t_s: float) -> None:
        self.switch_high, self.t_engage_s = True, t_s

    def release(self) -> None:
        self.switch_high = False

    def __call__(self, now: Telemetry) -> tuple[int, ...] | None:
        if not self.radio_on:
            return None
        switch = SWITCH_HIGH_US if self.switch_high else SWITCH_LOW_US
        tail = (switch, *self.extra_us)
        if self.sticks_us is not None:
            return (*self.sticks_us, *tail)
        if self.pilot is None or self.t_engage_s is None or not self.switch_high:
            return (RC_MID_US, RC_MID_US, self.mid_throttle_us, RC_MID_US, *tail)
        s = self.pilot.sticks(pilot_view(now, self.t_engage_s, self.hover_throttle))
        return (s.roll_us, s.pitch_us, s.throttle_us, s.yaw_us, *tail)


READY_TIMEOUT_S = 20.0
"""How long :meth:`Session.start_companion` waits for the companion to stream the IMU."""
_PILOT_SEEN_S = 0.3
"""Then this long for the pilot's input (50 Hz) to reach it: the switch seen low."""


def new_log_dir(workdir: Path, name: str) -> Path:
    """``workdir/name``, made; ``name-2``, ``name-3``... where a flight already used
    it. A run is judged ready by the events in its folder: an earlier run's there
    (until the new companion moves them aside, a second or more on a loaded
    machine) would read as this one's, and the switch would go high before the
    companion saw it low."""
    log_dir, n = workdir / name, 1
    while log_dir.exists() or log_dir.with_suffix(".stderr").exists():
        n += 1
        log_dir = workdir / f"{name}-{n}"
    log_dir.mkdir(parents=True)
    return log_dir


@dataclass
class CompanionRun:
    """``companion run`` as a process, its records in ``log_dir``."""

    proc: subprocess.Popen[bytes]
    log_dir: Path
    stderr_path: Path

    def wait(self, timeout_s: float) -> int:
        try:
            return int(self.proc.wait(timeout=timeout_s))
        except subprocess.TimeoutExpired:
            self.stop()
            raise

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 10.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=timeout_s)
        return int(self.proc.returncode)

    def events(self) -> list[dict[str, Any]]:
        path = self.log_dir / "events.jsonl"
        if not path.exists():
            return []
        out = []
        for line in path.read_text(encoding="utf-8").splitlines():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                continue
        return out

    def kinds(self) -> list[str]:
        return [e["kind"] for e in self.events()]

    def details(self, kind: str) -> list[str]:
        return [e["detail"] for e in self.events() if e["kind"] == kind]

    def stderr(self) -> str:
        return self.stderr_path.read_text(encoding="utf-8", errors="replace")

    def control(self) -> dict[str, np.ndarray]:
        cols, _ = read_control_log(self.log_dir / "control.mcap")
        return cols


def rate_errors(cols: dict[str, np.ndarray], *, skip_s: float = 0.5) -> dict[str, float]:
    """MAE of the rate tracking (deg/s) per axis over the engaged, airborne samples,
    the first ``skip_s`` after engaging left out (the hand-over)."""
    engaged = cols["engaged"] > 0.5
    air = cols["on_ground"] < 0.5
    t = cols["t_s"]
    if not engaged.any():
        return {"roll": math.nan, "pitch": math.nan, "yaw": math.nan, "n": 0}
    t0 = t[engaged][0]
    keep = engaged & air & (t >= t0 + skip_s)
    out: dict[str, float] = {"n": int(keep.sum())}
    for a in ("roll", "pitch", "yaw"):
        e = np.degrees(cols[f"meas_{a}_rad_s"][keep] - cols[f"ref_{a}_rad_s"][keep])
        e = e[np.isfinite(e)]
        out[a] = round(float(np.mean(np.abs(e))), 2) if e.size else math.nan
    return out


class Session:
    """One real stack, running, with a ground station and a pilot on it."""

    def __init__(
        self,
        stack: str,
        workdir: Path,
        *,
        params: dict[str, float] | None = None,
        fast_boot: bool = True,
    ):
        self.name = stack
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.companion_port: int | None = None
        self.stack: RunningStack
        if stack == "px4":
            self.stack = start_px4(self.workdir)
        else:
            from sitl.lab.fly import free_udp_port

            self.companion_port = free_udp_port()
            # Booted 8x faster than real time until its EKF uses GPS (about 45 s of sim
            # time), then at real time (connect()): SIM_SPEEDUP is a parameter.
            boot = {"SIM_SPEEDUP": FAST_BOOT_SPEEDUP} if fast_boot else {}
            merged = {**ARDUCOPTER_PARAMS, **boot, **(params or {})}
            self.stack = start_arducopter(
                self.workdir, params=merged, companion_port=self.companion_port
            )
        self.gcs: GroundStation | None = None
        self.hover_throttle = 0.5
        self.pilot = SwitchPilot(hover_throttle=self.hover_throttle)
        self._runs = 0
        self._bound: dict[str, CompanionRun] = {}
        """The last companion started on each connection URL (one may bind it)."""

    # ---------------------------------------------------------------- start-up
    def connect(self, timeout_s: float = 60.0, *, wait_ready: bool = True) -> GroundStation:
        """The ground station on the stack, the pilot's input flowing; with
        ``wait_ready``, once the stack is ready (PX4 "Ready for takeoff", ArduCopter's
        EKF using GPS, then at real time)."""
        st = self.stack
        if self.name == "px4" and wait_ready and not st.wait_log("Ready for takeoff", timeout_s):
            raise RuntimeError(f"PX4 did not get ready in {timeout_s:g} s:\n{st.log()[-2000:]}")
        self.gcs = g = GroundStation(st.gcs_url, stack=self.name, rc_port=st.rc_port)
        g.wait_heartbeat(timeout_s)
        g.set_pilot(self.pilot)
        if self.name == "ardupilot" and wait_ready:
            if g.wait_text("is using GPS", timeout_s) is None:
                raise RuntimeError(f"ArduCopter's EKF did not use GPS in {timeout_s:g} s")
            got = g.param_get("SIM_SPEEDUP")
            if got is not None and got[0] != 1.0:
                g.param_set("SIM_SPEEDUP", 1.0)
        return g

    @property
    def stack_dialect(self) -> FlightStack:
        """The companion's view of this stack (its modes' names and numbers)."""
        return PX4 if self.name == "px4" else ARDUPILOT

    @property
    def hold_mode(self) -> tuple[float, float]:
        """DO_SET_MODE param2, param3 of the mode the tests hold in (PX4 AUTO.LOITER,
        ArduCopter ALT_HOLD, mid stick)."""
        return (4.0, 3.0) if self.name == "px4" else (2.0, 0.0)

    def hold(self, timeout_s: float = 10.0) -> None:
        """Sticks centred, the switch low, and the stack in its hold mode."""
        g = self.gcs
        assert g is not None
        p = self.pilot
        p.release()
        p.pilot, p.sticks_us, p.radio_on = None, None, True
        p.mid_throttle_us = RC_MID_US
        p2, p3 = self.hold_mode
        want = PX4_LOITER if self.name == "px4" else int(p2)
        deadline = time.monotonic() + timeout_s
        self._retry_until(lambda: g.set_mode(p2, p3) == 0, deadline, "hold mode")
        g.wait(lambda t: t.mode == want, max(0.0, deadline - time.monotonic()))

    def land(self, timeout_s: float = 60.0) -> None:
        """Down and disarmed, the stack's own way (its land mode, then its auto-disarm)."""
        g = self.gcs
        assert g is not None
        deadline = time.monotonic() + timeout_s
        if g.now.armed:
            land = (4.0, 6.0) if self.name == "px4" else (9.0, 0.0)
            self._retry_until(lambda: g.set_mode(*land) == 0, deadline, "land mode")
            if not g.wait(lambda t: not t.armed, max(1.0, deadline - time.monotonic())):
                raise RuntimeError(f"{self.name}: not landed and disarmed in {timeout_s:g} s")

    def airborne(self, min_m: float = 5.0) -> bool:
        g = self.gcs
        pos = g.now.position_ned_m if g is not None else None
        return bool(g is not None and g.now.armed and pos is not None and -pos[2] >= min_m)

    def ensure_airborne(self, altitude_m: float = 15.0, timeout_s: float = 90.0) -> None:
        """In the air (taking off again after a landing) and holding, the sticks centred."""
        g = self.gcs
        assert g is not None
        deadline = time.monotonic() + timeout_s
        on_ground = g.now.landed_state == _LANDED_ON_GROUND
        if g.now.armed and on_ground:
            # Landed: its own auto-disarm follows within seconds; else disarm it.
            if not g.wait(lambda t: not t.armed, 5.0):
                self._retry_until(lambda: g.disarm() == 0, deadline, "disarm")
            g.wait(lambda t: not t.armed, 5.0)
        if not g.now.armed:
            time.sleep(1.0)  # PX4 refuses to arm again at once after a landing
            self.take_off(altitude_m, max(10.0, deadline - time.monotonic()))
        self.hold()
        self.climb_to(altitude_m)

    def climb_to(self, altitude_m: float, timeout_s: float = 30.0) -> None:
        """Back near ``altitude_m`` in the hold mode (PX4: a reposition; ArduCopter: the
        throttle stick)."""
        g = self.gcs
        assert g is not None
        pos = g.now.position_ned_m
        if pos is None or abs(-pos[2] - altitude_m) < 2.0:
            return
        deadline = time.monotonic() + timeout_s
        if self.name == "px4":
            # MAV_CMD_DO_REPOSITION to here at altitude_m (relative: home is the ground)
            home = g.home_altitude_m()
            g.command(192, -1, 0, 0, math.nan, math.nan, math.nan, home + altitude_m)
        else:
            self.pilot.mid_throttle_us = 1800 if -pos[2] < altitude_m else 1200
        while time.monotonic() < deadline:
            pos = g.now.position_ned_m
            if pos is not None and abs(-pos[2] - altitude_m) < 1.5:
                break
            time.sleep(0.1)
        self.pilot.mid_throttle_us = RC_MID_US
        time.sleep(1.0)

    def lose_pilot(self) -> None:
        """The pilot's input lost: PX4's joystick stops; ArduCopter's radio fails
        (``SIM_RC_FAIL=1``: no pulses, as a receiver that lost its transmitter)."""
        if self.name == "px4":
            self.pilot.radio_on = False
        else:
            assert self.gcs is not None
            self.gcs.param_set("SIM_RC_FAIL", 1.0)

    def restore_pilot(self) -> None:
        """The pilot's input back, sticks centred and the switch low."""
        self.pilot.release()
        self.pilot.radio_on = True
        if self.name != "px4":
            assert self.gcs is not None
            self.gcs.param_set("SIM_RC_FAIL", 0.0)

    def fly(
        self,
        *args: str,
        pilot: Pilot | None = None,
        sticks_us: tuple[int, int, int, int] | None = None,
        duration_s: float,
        name: str | None = None,
        settle_s: float = 4.0,
        start_s: float = 1.0,
    ) -> CompanionRun:
        """``companion run --engage rc-switch *args`` from the hold: the switch low for
        ``start_s``, then high with ``pilot`` (or the sticks held at ``sticks_us``)
        for ``duration_s``, then low; ``settle_s`` of its hand-back; then stopped.

        The switch is high for ``duration_s`` on the pilot's clock, whenever the
        companion's engagement shows in the autopilot's heartbeat (once a second):
        every flight of one pilot is the same length."""
        g = self.gcs
        assert g is not None
        run = self.start_companion("--engage", "rc-switch", *args, name=name)
        time.sleep(start_s)
        p = self.pilot
        p.pilot, p.sticks_us = pilot, sticks_us
        switched = time.monotonic()
        p.engage(g.clock())
        self.wait_engaged(run, 5.0)
        time.sleep(max(0.0, switched + duration_s - time.monotonic()))
        p.release()
        time.sleep(settle_s)
        run.stop()
        p.pilot, p.sticks_us = None, None
        return run

    def take_off(self, altitude_m: float = 15.0, timeout_s: float = 90.0) -> None:
        """Into the air and holding, the stack's own way; learns the hover throttle."""
        g = self.gcs
        assert g is not None
        deadline = time.monotonic() + timeout_s
        if self.name == "px4":
            g.param_set("MIS_TAKEOFF_ALT", altitude_m)
            self._retry_until(lambda: g.arm() == 0, deadline, "arm")
            self._retry_until(
                lambda: g.command(22, 0, 0, 0, math.nan, math.nan, math.nan, math.nan) == 0,
                deadline,
                "take off",
            )
            self._wait_altitude(altitude_m - 0.5, deadline)
            g.wait(lambda t: t.mode == PX4_LOITER, 10.0)
            time.sleep(2.0)
            self.hover_throttle = self._mean_thrust(2.0)
        else:
            self._retry_until(lambda: g.set_mode(2) == 0, deadline, "ALT_HOLD")
            self.pilot.mid_throttle_us = RC_MIN_US
            self._retry_until(lambda: g.arm() == 0, deadline, "arm")
            self.pilot.mid_throttle_us = 1800
            self._wait_altitude(altitude_m - 1.0, deadline)
            self.pilot.mid_throttle_us = RC_MID_US
            time.sleep(3.0)
            got = g.param_get("MOT_THST_HOVER")
            self.hover_throttle = got[0] if got else 0.39
        self.pilot.hover_throttle = self.hover_throttle

    def _retry_until(self, attempt: Any, deadline: float, what: str) -> None:
        while not attempt():
            if time.monotonic() > deadline:
                g = self.gcs
                said = g.texts[-5:] if g else []
                raise RuntimeError(f"{self.name}: {what} failed; it said {said}")
            time.sleep(1.0)

    def _wait_altitude(self, up_m: float, deadline: float) -> None:
        g = self.gcs
        assert g is not None
        while time.monotonic() < deadline:
            pos = g.now.position_ned_m
            if pos is not None and -pos[2] >= up_m:
                return
            time.sleep(0.1)
        raise RuntimeError(f"{self.name}: did not reach {up_m:g} m; it said {g.texts[-5:]}")

    def _mean_thrust(self, over_s: float) -> float:
        g = self.gcs
        assert g is not None
        vals = []
        end = time.monotonic() + over_s
        while time.monotonic() < end:
            if g.now.thrust_setpoint is not None:
                vals.append(g.now.thrust_setpoint)
            time.sleep(0.05)
        return float(np.mean(vals)) if vals else 0.5

    # ---------------------------------------------------------------- companion
    def start_companion(
        self, *args: str, name: str | None = None, connect_url: str | None = None
    ) -> CompanionRun:
        """``companion run --connect <the stack> --log-dir <a new folder> *args``
        (``connect_url``: another way to the stack, e.g. through a relay), returned
        once it streams the IMU and has had the pilot's input a moment
        (:data:`READY_TIMEOUT_S` at most): a switch flipped high before it saw it low
        would not engage it (the companion's rule), and a loaded machine starts it
        in well over a second."""
        url = connect_url or self.stack.companion_url
        left = self._bound.pop(url, None)
        if left is not None:
            # A flight that failed may leave its companion holding the port: the next
            # one could not bind it (one UDP port, one companion).
            left.stop()
        self._runs += 1
        log_dir = new_log_dir(self.workdir, name or f"companion-{self._runs}")
        stderr_path = log_dir.with_suffix(".stderr")
        cmd = [sys.executable, "-m", "companion", "-v", "run", "--connect",
               url, "--log-dir", str(log_dir), *args]  # fmt: skip
        env = dict(os.environ, MAVLINK20="1", PYTHONUNBUFFERED="1")
        with stderr_path.open("wb") as err:
            proc = children.start(cmd, cwd=_ROOT, env=env, stdout=subprocess.DEVNULL, stderr=err)
        run = self._bound[url] = CompanionRun(proc, log_dir, stderr_path)
        deadline = time.monotonic() + READY_TIMEOUT_S
        while time.monotonic() < deadline and proc.poll() is None:
            if "imu_stream" in run.kinds():
                time.sleep(_PILOT_SEEN_S)
                break
            time.sleep(0.05)
        return run

    def wait_engaged(self, run: CompanionRun, timeout_s: float = 10.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if "engaged" in run.kinds():
                return True
            if run.proc.poll() is not None:
                return False
            time.sleep(0.1)
        return False

    def close(self) -> None:
        if self.gcs is not None:
            self.gcs.close()
        self.stack.stop()
