"""The companion killed mid-manoeuvre on a real stack, and what the stack did alone.

:func:`fly_and_kill` starts ``companion run --engage rc-switch`` on a
:class:`~sitl.lab.realstack.flights.Session` already in the air, engages it with a
scripted pilot and sends the companion ``SIGKILL`` at the first moment the ground
station's ``ATTITUDE`` shows a body rate reached on an axis (after a given time
since engaging): mid-roll. The pilot's sticks are centred at the kill (the
autopilot's fallback is what is measured, not the pilot's script flying on), the
switch left high. The stack flies on alone for ``fly_on_s``; :class:`RealKill`
holds what its telemetry showed: the largest body rate, the altitude lost before
the vehicle was back under control (:mod:`sitl.lab.killed`'s rule), the modes it
went through, and when the held setpoint ended (its ``ATTITUDE_TARGET``).
"""

from __future__ import annotations

import math
import os
import signal
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from sitl.lab.killed import (
    LEVEL_TILT_DEG,
    RECOVERED_HOLD_S,
    SINK_M_S,
    STILL_RATE_DEG_S,
    figures_row,
    outcome,
)
from sitl.lab.realstack.flights import CompanionRun, Session
from sitl.pilot.maneuvers import acro_random_timeline
from sitl.pilot.rc import RC_MID_US
from sitl.pilot.scripted import Pilot, ScriptedPilot
from sitl.pilot.virtual import PilotParams
from sitl.px4_modes import mode_name, unpack_custom_mode

__all__ = ["GROUND_M", "RealKill", "acro_pilot", "fly_and_kill"]

_IN_FLIGHT_S = 0.05
"""A telemetry message this soon after the kill may have left before it."""
GROUND_M = 0.5
"""An altitude below this before the vehicle was back under control: it hit the
ground (the stack's own physics stops it there; a real vehicle crashed)."""


@dataclass(frozen=True)
class RealKill:
    """What the stack's telemetry showed after the kill (deg, deg/s, m, s from the
    kill; ``t_kill_s`` since engaging)."""

    t_kill_s: float
    rate_at_kill_deg_s: tuple[float, float, float]
    tilt_at_kill_deg: float
    altitude_at_kill_m: float
    setpoint_held_s: float | None
    """Until PX4's ``ATTITUDE_TARGET`` stream, silent while it holds the companion's
    last setpoint, showed a setpoint of its own."""
    failsafe_text_s: float | None
    """PX4's ``Failsafe activated`` STATUSTEXT."""
    modes: tuple[tuple[float, str], ...]
    """(s after the kill, mode) at each heartbeat that showed a new mode."""
    max_rate_deg_s: float
    max_tilt_deg: float
    altitude_lost_m: float
    recovered_after_s: float | None
    crashed: bool
    texts: tuple[str, ...]

    @property
    def outcome(self) -> str:
        return outcome(self.crashed, self.recovered_after_s)

    def row(self) -> dict[str, Any]:
        """The figures as one flat dict (rounded), with the outcome."""
        return figures_row(self)


def acro_pilot(seed: int, altitude_m: float) -> ScriptedPilot:
    """``acro-random`` (:func:`~sitl.pilot.maneuvers.acro_random_timeline`) of
    ``seed``, its altitude held at ``altitude_m`` (the library's holds 10 m)."""
    segments, duration_s = acro_random_timeline(np.random.default_rng(seed))
    return ScriptedPilot(
        segments, duration_s, params=PilotParams(altitude_m=altitude_m), name="acro-random"
    )


def fly_and_kill(
    session: Session,
    *args: str,
    pilot: Pilot,
    after_s: float,
    rate_deg_s: float,
    axis: int = 0,
    within_s: float = 10.0,
    fly_on_s: float = 8.0,
    start_s: float = 1.0,
    name: str | None = None,
) -> tuple[CompanionRun, RealKill]:
    """Engage ``companion run --engage rc-switch *args`` with ``pilot`` and kill it
    at the first ``ATTITUDE`` at least ``after_s`` after engaging whose rate on
    ``axis`` reaches ``rate_deg_s`` (within ``within_s`` more); then ``fly_on_s``
    of the stack alone.

    Raises
    ------
    RuntimeError
        If the companion did not engage, ended before the kill, or the rate was
        never reached.
    """
    g = session.gcs
    assert g is not None
    g.record_types.add("ATTITUDE_TARGET")
    run = session.start_companion("--engage", "rc-switch", *args, name=name)
    time.sleep(start_s)
    p = session.pilot
    p.pilot, p.sticks_us = pilot, None
    p.engage(g.clock())
    assert p.t_engage_s is not None
    t_engage = p.t_engage_s
    if not session.wait_engaged(run, 5.0):
        run.stop()
        raise RuntimeError(f"the companion did not engage: {run.kinds()}\n{run.stderr()[-2000:]}")
    deadline = t_engage + after_s + within_s
    t_kill: float | None = None
    while g.clock() < deadline:
        if run.proc.poll() is not None:
            raise RuntimeError(f"the companion ended before the kill: {run.events()}")
        if g.clock() - t_engage >= after_s:
            rate = math.degrees(g.now.rates_rad_s[axis])
            if abs(rate) >= rate_deg_s:
                os.kill(run.proc.pid, signal.SIGKILL)
                t_kill = g.clock()
                break
        time.sleep(0.002)
    if t_kill is None:
        run.stop()
        raise RuntimeError(f"no {'rpy'[axis]} rate of {rate_deg_s:g} deg/s within {within_s} s")
    run.proc.wait(timeout=5.0)
    p.sticks_us = (RC_MID_US, RC_MID_US, RC_MID_US, RC_MID_US)  # the pilot lets go
    time.sleep(fly_on_s)
    return run, _figures(session, t_kill - t_engage, t_kill)


def _figures(session: Session, t_since_engage_s: float, t_kill: float) -> RealKill:
    g = session.gcs
    assert g is not None
    att = g.series(
        "ATTITUDE", "roll", "pitch", "rollspeed", "pitchspeed", "yawspeed", since_s=t_kill - 1.0
    )
    pos = g.series("LOCAL_POSITION_NED", "z", "vz", since_s=t_kill - 1.0)
    tgt = g.series("ATTITUDE_TARGET", "thrust", since_s=t_kill - 1.0)
    if not att or not pos:
        raise RuntimeError("no ATTITUDE or LOCAL_POSITION_NED recorded around the kill")
    t_att = np.array([r[0] for r in att])
    ang = np.array([r[1:3] for r in att])
    rates = np.degrees(np.array([r[3:6] for r in att]))
    norm = np.linalg.norm(rates, axis=1)
    tilt = np.degrees(np.arccos(np.clip(np.cos(ang[:, 0]) * np.cos(ang[:, 1]), -1.0, 1.0)))
    k0 = int(np.searchsorted(t_att, t_kill))
    k0 = min(k0, len(t_att) - 1)
    # PX4 streams ATTITUDE_TARGET as its setpoints change: none while it holds the
    # companion's last one (one may still be on its way at the kill).
    later = [r[0] for r in tgt if r[0] > t_kill + _IN_FLIGHT_S]
    held_s = later[0] - t_kill if later else None
    said = [(t - t_kill, text) for t, text in list(g.texts) if t >= t_kill]
    failsafe_s = next((t for t, text in said if "ailsafe" in text), None)
    modes: list[tuple[float, str]] = []
    last_mode: int | None = None
    for t, mode, _armed, _status in list(g.heartbeats):
        if t >= t_kill and mode != last_mode:
            modes.append((t - t_kill, mode_name(*unpack_custom_mode(mode))))
        last_mode = mode
    # Recovery is judged once the autopilot flew on its own: the first sign of it.
    signs = [s for s in (held_s, failsafe_s, modes[0][0] if modes else None) if s is not None]
    t_own = t_kill + (min(signs) if signs else 0.0)
    pz = np.array([r[0] for r in pos])
    alt = -np.array([r[1] for r in pos])
    sink = np.array([r[2] for r in pos])
    sink_at = np.interp(t_att, pz, sink)
    calm = (tilt < LEVEL_TILT_DEG) & (norm < STILL_RATE_DEG_S) & (sink_at < SINK_M_S)
    rec_t: float | None = None
    start: float | None = None
    for i in range(k0, len(t_att)):
        if t_att[i] < t_own or not calm[i]:
            start = None
            continue
        start = t_att[i] if start is None else start
        if t_att[i] - start >= RECOVERED_HOLD_S:
            rec_t = start
            break
    alt0 = float(np.interp(t_kill, pz, alt))
    low_end = rec_t if rec_t is not None else t_att[-1]
    window = alt[(pz >= t_kill) & (pz <= low_end)]
    lowest = float(np.min(window)) if window.size else alt0
    return RealKill(
        t_kill_s=t_since_engage_s,
        rate_at_kill_deg_s=(float(rates[k0, 0]), float(rates[k0, 1]), float(rates[k0, 2])),
        tilt_at_kill_deg=float(tilt[k0]),
        altitude_at_kill_m=alt0,
        setpoint_held_s=held_s,
        failsafe_text_s=failsafe_s,
        modes=tuple(modes),
        max_rate_deg_s=float(np.max(norm[k0:])),
        max_tilt_deg=float(np.max(tilt[k0:])),
        altitude_lost_m=alt0 - lowest,
        recovered_after_s=None if rec_t is None else rec_t - t_kill,
        crashed=lowest < GROUND_M,
        texts=tuple(text for _t, text in said),
    )
