"""One flight over MAVLink: the SITL and the companion as two processes on UDP.

:func:`fly_mavlink` starts ``sitl run`` (lockstep clock, the scenario's pilot,
seed, wind, IMU and link, the pilot's clock starting at arming) and ``companion run
--engage auto``, waits for the companion to finish its flight, stops the
SITL, and merges the two logs into a :class:`~sitl.lab.simulate.FlightRecord`:
the controller's view per sample from the companion's ``control.mcap``, the
truth (rates, altitude, on the ground or not) from the SITL's log at the same
simulation times.
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.control import AXES
from companion.records import move_earlier
from sitl.lab import children
from sitl.lab.simulate import FlightRecord
from sitl.link_model import LINK_PROFILES, LinkSpec
from sitl.runner import PILOT_END_GRACE_S as END_GRACE_S

__all__ = [
    "FLIGHT_FILES",
    "FlightProcesses",
    "fly_mavlink",
    "free_tcp_port",
    "free_udp_port",
    "free_udp_ports",
    "link_arg",
    "merge_logs",
]

EPHEMERAL_RANGE_FILE = Path("/proc/sys/net/ipv4/ip_local_port_range")
FLIGHT_FILES = ("companion", "companion.stderr", "sitl.npz", "sitl.events.jsonl", "sitl.stderr")
"""What :func:`fly_mavlink` writes into its folder (``companion`` is a folder)."""


def link_arg(spec: LinkSpec) -> str:
    """``spec`` as ``--link`` takes it (:func:`sitl.link_model.parse_link`): a
    profile's name when it is one unchanged, else every field (delays to the
    float's last digit)."""
    if LINK_PROFILES.get(spec.name) == spec:
        return spec.name
    return ",".join(
        (
            f"up_delay_ms={spec.up_delay_s * 1e3!r}",
            f"up_jitter_ms={spec.up_jitter_s * 1e3!r}",
            f"down_delay_ms={spec.down_delay_s * 1e3!r}",
            f"down_jitter_ms={spec.down_jitter_s * 1e3!r}",
            f"loss={spec.loss!r}",
            f"duplicate={spec.duplicate!r}",
            f"fifo={'true' if spec.fifo else 'false'}",
        )
    )


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that was free a moment ago (see `free_udp_ports`)."""
    return free_udp_ports(1)[0]


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (see `free_udp_ports`)."""
    return _free_ports(1, socket.SOCK_STREAM)[0]


def free_udp_ports(n: int) -> list[int]:
    """``n`` distinct UDP ports on 127.0.0.1 that were free a moment ago.

    They are drawn from below the kernel's ephemeral range, the ports it hands a
    socket that binds none (a ``udpout`` end, a client): a port of that range,
    free when chosen, can be another process's by the time ours binds it.
    """
    return _free_ports(n, socket.SOCK_DGRAM)


def _free_ports(n: int, kind: int) -> list[int]:
    lo, hi = _ephemeral_ports()
    first, end = (20000, lo) if lo > 21000 else (hi + 1, 65536)
    draw = random.SystemRandom()
    socks: list[socket.socket] = []
    try:
        for _ in range(100 * n):
            s = socket.socket(socket.AF_INET, kind)
            try:
                s.bind(("127.0.0.1", draw.randrange(first, end)))
            except OSError:
                s.close()
                continue
            socks.append(s)
            if len(socks) == n:
                return [int(s.getsockname()[1]) for s in socks]
        raise OSError(f"no {n} free ports in {first}-{end - 1}")
    finally:
        for s in socks:
            s.close()


def _ephemeral_ports() -> tuple[int, int]:
    """The kernel's ephemeral port range (Linux's default where it cannot be read)."""
    try:
        lo, hi = (int(v) for v in EPHEMERAL_RANGE_FILE.read_text().split())
    except (OSError, ValueError):
        return 32768, 60999
    return lo, hi


@dataclass
class FlightProcesses:
    """What a MAVLink flight left behind."""

    out_dir: Path
    companion_rc: int
    sitl_rc: int
    wall_time_s: float
    companion_events: list[dict[str, Any]] = field(default_factory=list)
    sitl_events: list[dict[str, Any]] = field(default_factory=list)
    sitl_summary: dict[str, Any] = field(default_factory=dict)

    @property
    def control_log(self) -> Path:
        return self.out_dir / "companion" / "control.mcap"

    @property
    def sitl_log(self) -> Path:
        return self.out_dir / "sitl.npz"

    def text(self, name: str) -> str:
        p = self.out_dir / name
        return p.read_text(encoding="utf-8", errors="replace") if p.exists() else ""

    def why(self, events: int = 8) -> str:
        """What a failed flight's reader needs first: the companion's exit code,
        its stderr and its last ``events`` (an engagement that gave up says why
        only there), and the SITL's summary."""
        last = "\n".join(
            f"  {e.get('t_s')} {e.get('kind')}: {e.get('detail', '')}"
            for e in self.companion_events[-events:]
        )
        return (
            f"companion exit {self.companion_rc}; stderr:\n{self.text('companion.stderr')}"
            f"its last events:\n{last}\nthe SITL's summary: {self.sitl_summary}"
        )


def _read_jsonl(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    out = []
    for line in path.read_text(encoding="utf-8").splitlines():
        line = line.strip()
        if line:
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                continue  # a line cut by a killed writer
    return out


def fly_mavlink(
    profile_path: str | Path,
    scenario: str,
    out_dir: str | Path,
    *,
    controller_path: str | Path | None = None,
    output: str = "actuator",
    duration_s: float | None = None,
    seed: int | None = None,
    sitl_args: Sequence[str] = (),
    companion_args: Sequence[str] = (),
    controller_profile_path: str | Path | None = None,
    autopilot: str = "px4",
    link: LinkSpec | None = None,
    timeout_s: float | None = None,
    progress: Callable[[float], None] | None = None,
    on_started: Callable[[subprocess.Popen[bytes], subprocess.Popen[bytes]], None] | None = None,
    relay: Callable[[int], int] | None = None,
    sitl_flies_on: bool = False,
) -> FlightProcesses:
    """Fly ``scenario`` with the SITL and the companion as separate processes.

    Parameters
    ----------
    profile_path
        The vehicle the SITL simulates.
    scenario
        Scenario name or file (pilot, seed, wind, IMU).
    out_dir
        Where ``sitl.npz``, its events, ``companion/`` (tlog, control.mcap,
        events) and both processes' stderr go (:data:`FLIGHT_FILES`; an earlier
        flight's are moved into ``earlier-<UTC time>/`` in it first).
    controller_path, output
        Passed to ``companion run``.
    duration_s
        Engaged flight time; default: the scenario's (or its pilot's) duration.
    controller_profile_path
        The profile the companion is given (default: ``profile_path``).
    autopilot
        The SITL's personality, ``px4`` or ``ardupilot`` (ArduPilot takes body
        rates only, so ``output`` becomes ``rates``; its GUID_OPTIONS is set to 8
        so the thrust is a normalised collective).
    link
        The companion link the SITL models (``sitl run --link``); default: the
        scenario's.
    on_started
        Called with (sitl, companion) processes once both are running (tests
        use it to send signals).
    relay
        Called with the companion's UDP port before anything starts; returns the
        port the SITL sends to instead (a relay there, started by the caller,
        forwards to the companion's).
    sitl_flies_on
        When the companion ends, let the SITL fly on to the end of its own
        ``--duration`` (in ``sitl_args``; counted from arming) or a crash, within
        ``timeout_s``, instead of stopping it: what the autopilot does alone after
        a companion that died.
    timeout_s
        Wall-clock limit for the companion; default 30 s + 4x the flight.

    Raises
    ------
    ValueError
        If an earlier flight's files in ``out_dir`` cannot be moved aside.
    """
    from sitl.pilot import make_pilot
    from sitl.scenario import load_scenario

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    move_earlier(out, FLIGHT_FILES, what=str(out))  # an earlier flight's, kept
    sc = load_scenario(scenario)
    if duration_s is None:
        duration_s = sc.duration_s or make_pilot(sc.pilot, rng=np.random.default_rng(0)).duration_s
    if timeout_s is None:
        # A lockstep flight runs several times faster than real time: 4x the flight
        # (plus start-up) is generous, and a hang does not stall a test run for long.
        timeout_s = 30.0 + 4.0 * duration_s
    port = free_udp_port()
    sitl_port = port if relay is None else relay(port)
    py = sys.executable
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    if autopilot == "ardupilot":
        output = "rates"
    sitl_cmd = [
        py, "-m", "sitl", "run",
        "--profile", str(profile_path),
        "--mavlink", f"udpout:127.0.0.1:{sitl_port}",
        "--scenario", str(scenario),
        "--clock", "lockstep",
        "--pilot-from-arm", "--no-auto-arm",
        *(["--mode", "manual"] if autopilot == "px4" else
          ["--autopilot", "ardupilot", "--mode", "stabilize", "--param", "GUID_OPTIONS=8"]),
        "--log", str(out / "sitl.npz"),
        "--link", link_arg(sc.link if link is None else link),
        *(["--seed", str(seed)] if seed is not None else []),
        # From arming, the companion's flight from its engagement and its hand-back
        # (a scenario's own duration_s would stop the SITL under an engaged companion).
        *([] if "--duration" in sitl_args else ["--duration", f"{duration_s + END_GRACE_S:g}"]),
        *sitl_args,
    ]  # fmt: skip
    comp_cmd = [
        py, "-m", "companion", "run",
        "--connect", f"udpin:127.0.0.1:{port}",
        "--profile", str(controller_profile_path or profile_path),
        "--engage", "auto",
        "--output", output,
        "--rate-hz", str(int(sc.imu.rate_hz or 1000)),
        "--duration", str(duration_s),
        "--log-dir", str(out / "companion"),
        # Wall-clock watchdog: a lockstep SITL on a loaded machine can stall
        # longer than a real IMU ever would; 0.5 s still catches a stopped stream.
        "--stale-imu-s", "0.5",
        # The SITL ends a moment after the flight: watching the hand-back longer
        # than its 1 Hz heartbeat and 0.5-1 s failsafes need only delays the report.
        "--hand-back-watch-s", "1.5",
        *(["--controller", str(controller_path)] if controller_path else []),
        # A lab flight is itself a simulator flight: a controller file that has not
        # passed check-config --fly flies here, and its events say so.
        "--skip-fly-check",
        *companion_args,
    ]  # fmt: skip
    t0 = time.monotonic()
    with (out / "companion.stderr").open("wb") as c_err, (out / "sitl.stderr").open("wb") as s_err:
        comp = children.start(comp_cmd, stdout=subprocess.DEVNULL, stderr=c_err, env=env)
        sitl = children.start(sitl_cmd, stdout=subprocess.DEVNULL, stderr=s_err, env=env)
        if on_started is not None:
            on_started(sitl, comp)
        try:
            while comp.poll() is None:
                if time.monotonic() - t0 > timeout_s:
                    comp.kill()
                    break
                if progress is not None:
                    progress(_progress(out / "companion" / "events.jsonl", duration_s))
                time.sleep(0.2)
            comp_rc = comp.wait()
            if sitl_flies_on:
                left_s = timeout_s - (time.monotonic() - t0)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    sitl.wait(timeout=max(0.0, left_s))
        finally:
            # The companion is done (its hand-back watched): what the SITL would fly
            # of the pilot's timeline after that is nobody's flight. Stop it now; it
            # writes its log whole whenever the signal lands.
            if sitl.poll() is None:
                sitl.send_signal(signal.SIGINT)
                try:
                    sitl.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    sitl.kill()
                    sitl.wait()
            if comp.poll() is None:
                comp.kill()
                comp.wait()
    sitl_events = _read_jsonl(out / "sitl.events.jsonl")
    summary: dict[str, Any] = next(
        (e for e in reversed(sitl_events) if e.get("kind") == "summary"), {}
    )
    if progress is not None:
        progress(1.0)
    return FlightProcesses(
        out_dir=out,
        companion_rc=comp_rc,
        sitl_rc=int(sitl.returncode),
        wall_time_s=time.monotonic() - t0,
        companion_events=_read_jsonl(out / "companion" / "events.jsonl"),
        sitl_events=sitl_events,
        sitl_summary=summary,
    )


def _progress(events_path: Path, duration_s: float) -> float:
    """A rough fraction done, from the companion's last logged sample time."""
    from companion.records import last_sample_time

    events = _read_jsonl(events_path)
    t_eng = next((e["t_s"] for e in events if e.get("kind") == "engaged"), None)
    if t_eng is None:
        return 0.0
    t = last_sample_time(events_path.parent / "control.mcap")
    if t is None:
        return 0.0
    return max(0.0, min(1.0, (t - float(t_eng)) / duration_s))


def merge_logs(flight: FlightProcesses, *, meta: dict[str, Any] | None = None) -> FlightRecord:
    """The controller's log and the SITL's truth as one :class:`FlightRecord`.

    Samples are those logged while engaged; the truth is the SITL state at
    the physics step of each sample's timestamp.
    """
    from companion.records import read_control_log
    from sitl.flight_log import read_log

    cols, cmeta = read_control_log(flight.control_log)
    eng = cols["engaged"] > 0.5
    t = cols["t_s"][eng]
    log = read_log(flight.sitl_log)
    st = log["t_s"]
    idx = np.clip(np.searchsorted(st, t - 1e-7), 0, len(st) - 1)
    pos = log["pos_ned_m"][idx]
    true_rate = log["rate_frd_rad_s"][idx]
    q = log["q_wxyz"][idx]
    n_motors = sum(1 for k in cols if k.startswith("motor_"))

    def stack(prefix: str, suffix: str = "") -> np.ndarray:
        return np.stack([cols[f"{prefix}{a}{suffix}"][eng] for a in AXES], axis=1)

    # On the ground = at z ~ 0 and not climbing (the SITL holds a landed vehicle at 0).
    airborne = pos[:, 2] < -0.05
    w, x, y, z = q.T
    euler = np.stack(
        [
            np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)),
            np.arcsin(np.clip(2 * (w * y - z * x), -1, 1)),
            np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)),
        ],
        axis=1,
    )
    columns = {
        "t_s": t,
        "ref_rad_s": stack("ref_", "_rad_s"),
        "meas_rad_s": stack("meas_", "_rad_s"),
        "true_rad_s": true_rate,
        "thrust": cols["thrust"][eng],
        "torque": stack("torque_"),
        "u": stack("u_"),
        "f_hat": stack("f_hat_"),
        "motors": np.stack([cols[f"motor_{i + 1}"][eng] for i in range(n_motors)], axis=1),
        "sat_axes": stack("sat_") > 0.5,
        "held": cols["held"][eng] > 0.5,
        "euler_rad": euler,
        "altitude_m": -pos[:, 2],
        "airborne": airborne,
        "latency_us": cols["latency_us"][eng],
    }
    summary = flight.sitl_summary
    crashed = summary.get("status") == "crashed"
    crash_t = next((e["t_s"] for e in flight.sitl_events if e.get("status") == "crashed"), None)
    failsafes = [
        e for e in flight.companion_events if str(e.get("kind", "")).startswith("failsafe")
    ]
    info: dict[str, Any] = {
        "profile": cmeta.get("profile", ""),
        "controller": cmeta.get("controller", ""),
        "sim_time_s": float(t[-1] - t[0]) if len(t) else 0.0,
        "wall_time_s": flight.wall_time_s,
        "crashed": crashed,
        "crashed_at_s": crash_t,
        "failsafe_events": [
            {"t_s": e.get("t_s"), "kind": e.get("kind"), "detail": e.get("detail")}
            for e in failsafes
        ],
        "companion_exit_code": flight.companion_rc,
        "sitl_realtime_factor": summary.get("realtime_factor"),
        "nonfinite_events": int(np.sum(columns["held"])),
        **(
            {"rates_law_axes": cmeta.get("rates_law_axes", "")}
            if cmeta.get("output") == "rates"
            else {}
        ),  # the axes the law corrected (--rates-law-axes auto: as chosen)
        **(meta or {}),
    }
    return FlightRecord(columns, info)
