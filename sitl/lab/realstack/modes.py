"""The companion's flight modes beside the stack's own, on the real stacks.

One stick program (:data:`PROGRAM`: centred, full pitch forward, centred, a roll
step, centred) is flown twice from the stack's hold (PX4 AUTO.LOITER,
ArduCopter ALT_HOLD at mid-stick): once with ``companion run --mode M`` engaged
by the pilot's switch, once in the stack's own mode for ``M`` (PX4 STABILIZED,
ALTCTL, POSCTL; ArduCopter STABILIZE, ALT_HOLD, LOITER), switched to from the
ground station. The program's clock starts as the switch goes high or the mode
is asked for. :func:`mode_figures` then measures both from what the ground
station received (ATTITUDE, LOCAL_POSITION_NED):

* the engage transient: the largest tilt in the first 0.5 s after the mode took
  over, the altitude lost and the altitude change over the first centred part;
* under the stick: the largest tilt and horizontal speed;
* braking: how far the vehicle went on after the pitch stick was released;
* the holds: horizontal RMS about where it holds and altitude RMS about the
  engagement's altitude, over the centred parts: from the engagement, and once
  the vehicle has stopped after a stick (under 0.3 m/s).

Where the stack streams its own velocity setpoint (PX4 in its Position mode:
POSITION_TARGET_LOCAL_NED, :func:`watch_targets`), what its mode asks is measured
too: the largest speed asked under the stick, and how far the setpoint itself
runs on after the release.

In angle mode (and the stacks' STABILIZED and STABILIZE) the throttle is the
collective: the pilot holds the altitude with it (the virtual pilot's altitude
hold, trimmed at the collective that hovers: the stack's mid-stick, or the
vehicle's hover thrust for the companion, whose throttle is the collective
itself). In the other modes the throttle stays at mid-stick.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from sitl.lab.realstack.flights import SWITCH_LOW_US, CompanionRun, Session, pilot_view
from sitl.lab.realstack.gcs import Telemetry
from sitl.pilot.rc import RC_MID_US, Sticks, throttle_to_stick_us
from sitl.pilot.virtual import PilotParams, PilotView, throttle_command

__all__ = [
    "PROGRAM",
    "PROGRAMS",
    "STACK_MODES",
    "ModeFlight",
    "Phase",
    "ProgramPilot",
    "fly_companion_mode",
    "fly_stack_mode",
    "gcs_time_of_boot",
    "mode_figures",
    "settle",
    "start_mode_companion",
    "tilt_deg",
    "watch_targets",
]

STACK_MODES: dict[str, dict[str, tuple[str, float, float]]] = {
    "px4": {
        "angle": ("STABILIZED", 7.0, 0.0),
        "altitude": ("ALTCTL", 2.0, 0.0),
        "position": ("POSCTL", 3.0, 0.0),
    },
    "ardupilot": {
        "angle": ("STABILIZE", 0.0, 0.0),
        "altitude": ("ALT_HOLD", 2.0, 0.0),
        "position": ("LOITER", 5.0, 0.0),
    },
}
"""Per stack and companion mode: the stack's own mode (name, DO_SET_MODE param2, param3)."""


@dataclass(frozen=True)
class Phase:
    """A stretch of the program: roll and pitch deflections in [-1, 1] (pitch -1 is
    the stick forward, nose down), held for ``duration_s``."""

    name: str
    duration_s: float
    roll: float = 0.0
    pitch: float = 0.0

    @property
    def centred(self) -> bool:
        return self.roll == 0.0 and self.pitch == 0.0


PROGRAM: tuple[Phase, ...] = (
    Phase("engage", 2.5),
    Phase("pitch", 2.0, pitch=-1.0),
    Phase("brake", 4.5),
    Phase("roll", 1.0, roll=1.0),
    Phase("hold", 3.0),
)
"""Engage from the hold, centred; full pitch forward; centred (brake and hold); a
full roll step; centred."""

PROGRAMS: dict[str, tuple[Phase, ...]] = {
    "position": PROGRAM,
    "altitude": PROGRAM[:3],
    "angle": (*PROGRAM[:2], Phase("coast", 2.5)),
}
"""What each mode flies: the whole program in position mode; without the roll step
in altitude mode (nothing holds the position there); in angle mode no hold at all
(a level vehicle coasts on)."""

_STOPPED_M_S = 0.3
"""After a stick comes back, the hold is judged once the vehicle is this slow."""
_ENGAGE_TILT_S = 0.5


def phase_starts(program: Sequence[Phase]) -> list[float]:
    t, out = 0.0, []
    for ph in program:
        out.append(t)
        t += ph.duration_s
    return out


def _us(x: float) -> int:
    return round(RC_MID_US + 500.0 * max(-1.0, min(1.0, x)))


@dataclass
class ProgramPilot:
    """The program on the sticks (the :class:`~sitl.pilot.scripted.Pilot` protocol),
    its clock the view's; with ``hold_altitude`` the throttle holds the altitude the
    vehicle had at the program's start, trimmed at ``trim_throttle``."""

    program: tuple[Phase, ...] = PROGRAM
    hold_altitude: bool = False
    trim_throttle: float = 0.5
    duration_s: float = field(init=False)
    _target_m: float | None = None

    def __post_init__(self) -> None:
        self.duration_s = sum(ph.duration_s for ph in self.program)

    def phase_at(self, t_s: float) -> Phase:
        for start, ph in zip(phase_starts(self.program), self.program, strict=True):
            if t_s < start + ph.duration_s:
                return ph
        return self.program[-1]

    def sticks(self, view: PilotView) -> Sticks:
        ph = self.phase_at(view.t_s)
        throttle_us = RC_MID_US
        if self.hold_altitude:
            if self._target_m is None:
                self._target_m = view.altitude_m
            cos_tilt = math.cos(view.roll_rad) * math.cos(view.pitch_rad)
            thr = throttle_command(
                "hold",
                altitude_m=view.altitude_m,
                climb_rate_m_s=view.climb_rate_m_s,
                target_altitude_m=self._target_m,
                climb_target_m_s=0.0,
                hover_throttle=self.trim_throttle,
                cos_tilt=cos_tilt,
                params=PilotParams(),
            )
            throttle_us = throttle_to_stick_us(thr)
        # ch2 high is the stick back (nose up): forward (pitch -1) is below centre.
        return Sticks(_us(ph.roll), _us(ph.pitch), throttle_us, RC_MID_US)


@dataclass
class ModeFlight:
    """One flight of the program, in the ground station's clock."""

    who: str
    mode: str
    t_start_s: float
    """The program's start: the switch high, or the stack's mode asked for."""
    t_engaged_s: float
    """When the mode took over: the companion's first command flown, or the stack's ACK."""
    attitude: list[tuple[float, ...]]
    """(t, roll, pitch) rows."""
    position: list[tuple[float, ...]]
    """(t, x, y, z, vx, vy, vz) rows, NED."""
    target: list[tuple[float, ...]]
    """(t, vx, vy) rows: the stack's own velocity setpoint (POSITION_TARGET_LOCAL_NED),
    where it streams one (PX4 in its own modes)."""
    program: tuple[Phase, ...] = PROGRAM
    run: CompanionRun | None = None


def settle(session: Session, timeout_s: float = 8.0) -> None:
    """In the hold and still: both flights start from a vehicle at rest (speed under
    0.2 m/s, climb under 0.1 m/s, for a second), or after ``timeout_s``."""
    g = session.gcs
    assert g is not None
    session.ensure_airborne(15.0)
    deadline = time.monotonic() + timeout_s
    still_since: float | None = None
    while time.monotonic() < deadline:
        v = g.now.velocity_ned_m_s
        if v is not None and math.hypot(v[0], v[1]) < 0.2 and abs(v[2]) < 0.1:
            still_since = still_since or time.monotonic()
            if time.monotonic() - still_since >= 1.0:
                return
        else:
            still_since = None
        time.sleep(0.05)


def _record(
    session: Session, who: str, mode: str, t0: float, t_eng: float, program: tuple[Phase, ...]
) -> ModeFlight:
    g = session.gcs
    assert g is not None
    att = g.series("ATTITUDE", "roll", "pitch", since_s=t0 - 1.0)
    pos = g.series("LOCAL_POSITION_NED", "x", "y", "z", "vx", "vy", "vz", since_s=t0 - 1.0)
    tgt = g.series(_TARGET, "vx", "vy", since_s=t0 - 1.0)
    return ModeFlight(who, mode, t0, t_eng, att, pos, tgt, program)


_TARGET = "POSITION_TARGET_LOCAL_NED"
_TARGET_ID = 85


def watch_targets(session: Session, hz: float = 25.0) -> None:
    """Record the stack's own velocity setpoint (what its mode asks), where it
    streams one: PX4 does in its Position mode."""
    g = session.gcs
    assert g is not None
    g.record_types.add(_TARGET)
    g.send("command_long_send", g.target, 1, 511, 0, _TARGET_ID, 1e6 / hz, 0, 0, 0, 0, 0)


def fly_stack_mode(session: Session, mode: str, program: tuple[Phase, ...] = PROGRAM) -> ModeFlight:
    """The program in the stack's own mode for ``mode``, from its hold; back to the
    hold after."""
    g = session.gcs
    assert g is not None
    settle(session)
    name, p2, p3 = STACK_MODES[session.name][mode]
    want = (int(p2) << 16) | (int(p3) << 24) if session.name == "px4" else int(p2)
    try:
        for _ in range(3):
            pilot = ProgramPilot(program, hold_altitude=mode == "angle", trim_throttle=0.5)
            # The mode first, on the session's centred sticks: a stick that moves while
            # PX4 still holds is the pilot taking over (COM_RC_OVERRIDE: Position mode).
            # An ACK is matched by its command alone (a late one for the hold's switch
            # would do): the stack's heartbeat must show the mode (PX4's: once a second).
            res = g.set_mode(p2, p3)
            if res == 0 and g.wait(lambda t: t.mode == want, 1.5):
                # The program on the sticks from now, the engage switch low (a companion
                # started for the next flight waits), then the session's own pilot again.
                t0 = t_eng = g.clock()
                g.set_pilot(_SwitchLow(pilot, t0, session.hover_throttle, session.pilot.extra_us))
                break
            session.hold()
        else:
            raise RuntimeError(f"{session.name} did not fly {name}: {g.texts[-3:]}")
        time.sleep(max(0.0, pilot.duration_s - (g.clock() - t0)))
    finally:
        g.set_pilot(session.pilot)
    flight = _record(session, "stack", mode, t0, t_eng, program)
    session.hold()
    return flight


@dataclass
class _SwitchLow:
    """A ground station's pilot (``SticksFn``): the program from ``t0_s`` on the
    sticks, the engage switch low, the channels after it as ``extra_us``."""

    pilot: ProgramPilot
    t0_s: float
    hover_throttle: float
    extra_us: tuple[int, ...]

    def __call__(self, now: Telemetry) -> tuple[int, ...]:
        st = self.pilot.sticks(pilot_view(now, self.t0_s, self.hover_throttle))
        return (st.roll_us, st.pitch_us, st.throttle_us, st.yaw_us, SWITCH_LOW_US, *self.extra_us)


def start_mode_companion(
    session: Session, mode: str, *args: str, ready_timeout_s: float = 15.0
) -> CompanionRun:
    """``companion run --engage rc-switch --mode mode *args``, started and waited for
    until it flies on its estimates (it can start while the stack flies its own mode:
    until the switch goes high it sends no setpoint)."""
    n = len(list(session.workdir.glob(f"companion-{mode}-*.stderr")))
    run = session.start_companion(
        "--engage", "rc-switch", "--mode", mode, *args, name=f"companion-{mode}-{n}"
    )
    deadline = time.monotonic() + ready_timeout_s
    streams = 1 if mode == "angle" else 2  # ATTITUDE_QUATERNION, LOCAL_POSITION_NED
    while run.kinds().count("estimate_stream") < streams:
        if run.proc.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"companion not ready: {run.events()[-5:]}\n{run.stderr()[-2000:]}")
        time.sleep(0.1)
    return run


def fly_companion_mode(
    session: Session,
    run: CompanionRun,
    mode: str,
    program: tuple[Phase, ...] = PROGRAM,
) -> ModeFlight:
    """The program with the companion ``run`` (:func:`start_mode_companion`), engaged
    by the pilot's switch from the stack's hold; the switch low at its end (the
    companion hands back), the run stopped, then the hold."""
    g = session.gcs
    assert g is not None
    settle(session)
    sw = session.pilot
    sw.pilot = ProgramPilot(
        program, hold_altitude=mode == "angle", trim_throttle=session.hover_throttle
    )
    t0 = g.clock()
    sw.engage(t0)
    if not session.wait_engaged(run, 5.0):
        sw.release()
        run.stop()
        raise RuntimeError(f"companion did not engage: {run.events()[-5:]}")
    time.sleep(max(0.0, sum(ph.duration_s for ph in program) - (g.clock() - t0)))
    sw.release()
    t_end = g.clock()
    time.sleep(1.0)
    run.stop()
    sw.pilot = None
    cols = run.control()
    flown = cols["engaged"] > 0.5
    t_eng = t0
    if flown.any():
        t_eng = gcs_time_of_boot(session, float(cols["t_s"][flown][0]))
    flight = _record(session, "companion", mode, t0, t_eng, program)
    flight.run = run
    flight.position = [r for r in flight.position if r[0] <= t_end]
    flight.attitude = [r for r in flight.attitude if r[0] <= t_end]
    session.hold()
    return flight


def gcs_time_of_boot(session: Session, boot_s: float) -> float:
    """The ground station's clock when the autopilot's boot time (the companion's
    IMU time) was ``boot_s``: interpolated between the ATTITUDE messages around it
    (``time_boot_ms``, and when each arrived). Local, since the two clocks drift
    apart when the autopilot runs behind real time on a loaded machine: an offset
    taken over the last minute put the engagement up to 2 s before the switch."""
    g = session.gcs
    assert g is not None
    rows = list(g.records.get("ATTITUDE", []))  # the reader thread appends meanwhile
    boot = np.array([r.fields["time_boot_ms"] * 1e-3 for r in rows])
    arrived = np.array([r.t_s for r in rows])
    return float(np.interp(boot_s, boot, arrived))


def tilt_deg(roll: float, pitch: float) -> float:
    c = max(-1.0, min(1.0, math.cos(roll) * math.cos(pitch)))
    return math.degrees(math.acos(c))


def mode_figures(flight: ModeFlight) -> dict[str, Any]:
    """The figures of one flight (module docstring), rounded; NaN where a window
    holds no sample."""
    program = flight.program
    t0, te = flight.t_start_s, flight.t_engaged_s
    att = np.asarray(flight.attitude, dtype=float).reshape(-1, 3)
    pos = np.asarray(flight.position, dtype=float).reshape(-1, 7)
    ta, tilt = att[:, 0], np.array([tilt_deg(r, p) for _, r, p in att])
    tp = pos[:, 0]
    up = -pos[:, 3]
    speed = np.hypot(pos[:, 4], pos[:, 5])
    starts = phase_starts(program)

    def window(t: np.ndarray, a: float, b: float) -> np.ndarray:
        return (t >= a) & (t <= b)

    def at(t_s: float, col: int) -> float:
        return float(np.interp(t_s, tp, pos[:, col]))

    up0 = -at(te, 3)
    first_end = t0 + starts[1]
    w = window(tp, te, first_end)
    d_up = up[w] - up0
    out: dict[str, Any] = {
        "who": flight.who,
        "mode": flight.mode,
        "engage_after_s": round(te - t0, 2),
        "engage_tilt_deg": _max(tilt[window(ta, te, te + _ENGAGE_TILT_S)]),
        "engage_sag_m": _max(-d_up),
        "engage_alt_change_m": _max(np.abs(d_up)),
    }
    k = next(i for i, ph in enumerate(program) if ph.name == "pitch")
    a, b = t0 + starts[k], t0 + starts[k] + program[k].duration_s
    out["stick_tilt_deg"] = _max(tilt[window(ta, a, b + 0.3)])
    out["stick_speed_m_s"] = _max(speed[window(tp, a, b + 0.3)])
    tgt = np.asarray(flight.target, dtype=float).reshape(-1, 3)
    asked = np.hypot(tgt[:, 1], tgt[:, 2])[window(tgt[:, 0], a, b + 0.3)]
    out["asked_speed_m_s"] = _max(asked[np.isfinite(asked)])
    after = window(tgt[:, 0], b, t0 + starts[k + 1] + program[k + 1].duration_s)
    v_after = np.hypot(tgt[after, 1], tgt[after, 2])
    ok = np.isfinite(v_after)
    out["asked_braking_m"] = (
        round(float(np.trapezoid(v_after[ok], tgt[after, 0][ok])), 3) if ok.sum() > 1 else math.nan
    )
    release = (at(b, 1), at(b, 2))
    brake = window(tp, b, t0 + starts[k + 1] + program[k + 1].duration_s)
    out["braking_m"] = _max(np.hypot(pos[brake, 1] - release[0], pos[brake, 2] - release[1]))
    # The holds: the first from the engagement (about where it engaged), the others
    # once stopped (about where they settled); the altitude about the engagement's.
    holds: list[tuple[np.ndarray, tuple[float, float] | None]] = [
        (window(tp, te, first_end), (at(te, 1), at(te, 2)))
    ]
    for i, ph in enumerate(program):
        if i > 0 and ph.centred:
            a, b = t0 + starts[i], t0 + starts[i] + ph.duration_s
            stopped = np.nonzero(window(tp, a, b) & (speed < _STOPPED_M_S))[0]
            holds.append((window(tp, tp[stopped[0]] if stopped.size else b, b), None))
    sq_h: list[np.ndarray] = []
    sq_z: list[np.ndarray] = []
    per_hold = []
    for mask, ref in holds:
        if not mask.any():
            per_hold.append(math.nan)
            continue
        n, e = pos[mask, 1], pos[mask, 2]
        rn, re = ref if ref is not None else (float(n.mean()), float(e.mean()))
        d2 = (n - rn) ** 2 + (e - re) ** 2
        sq_h.append(d2)
        sq_z.append((up[mask] - up0) ** 2)
        per_hold.append(round(float(np.sqrt(d2.mean())), 3))
    out["hold_rms_m"] = _rms(sq_h)
    out["alt_rms_m"] = _rms(sq_z)
    out["hold_rms_each_m"] = per_hold
    return out


def _max(x: np.ndarray) -> float:
    return round(float(np.max(x)), 3) if x.size else math.nan


def _rms(squares: list[np.ndarray]) -> float:
    if not squares:
        return math.nan
    return round(float(np.sqrt(np.concatenate(squares).mean())), 3)
