"""Rate steps flown through the companion's pass-through, on a real stack or the bundled SITL.

The same measurement on both sides, so the bundled SITL's personalities can be
checked against the real PX4 v1.16 SIH and ArduCopter 4.5.6 on the same vehicle:
``companion run --output rates --rates-passthrough --engage rc-switch`` forwards the
pilot's rate steps (``sitl.pilot`` maneuvers ``step-roll`` / ``step-pitch`` /
``step-yaw``: doublets of 90, 180, 360 deg/s on roll and pitch, 90, 180, 270 on
yaw) to the autopilot's rate loop, and ``control.mcap`` records what it sent
(``sent_<axis>_rad_s``) and the gyro it saw (``meas_<axis>_rad_s``).
:func:`step_metrics` reads each step up from rest: the measured rate 40, 80 and
120 ms after the step as a fraction of the step, and the time to reach 90 %.

* :func:`fly_real`: a real stack (:class:`~sitl.lab.realstack.flights.Session`:
  into the air the stack's own way, the pilot's switch, the companion as a process).
  Real time; minutes of CPU.
* :func:`fly_bundled`: the bundled SITL with the matching profile and personality,
  as processes on real UDP (``sitl.lab.fly.fly_mavlink``, lockstep).

Run as ``python -m sitl.lab.realstack.ratestep STACK AXIS OUT_DIR`` (STACK ``px4`` or
``ardupilot``, ``--bundled`` for the SITL side): prints the metrics as JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["PROFILES", "fly_bundled", "fly_real", "step_metrics"]

_ROOT = Path(__file__).resolve().parents[3]
PROFILES = {
    "px4": _ROOT / "vehicle_profiles" / "px4_sih_quadx.yaml",
    "ardupilot": _ROOT / "vehicle_profiles" / "arducopter_sitl_quad.yaml",
}
"""The real stacks' own vehicles (PX4 SIH's quadrotor, ArduPilot SITL's quad)."""
AT_S = (0.04, 0.08, 0.12, 0.25, 0.5)
"""When the measured rate is read after a step, s (the last two for yaw's slow rise)."""
STEP_MIN_RAD_S = math.radians(45.0)
REST_RAD_S = math.radians(5.0)
_NO_ENVELOPE = ("--envelope-error-deg-s", "2000")
"""The companion's envelope failsafe out of the way: a 360 deg/s step behind
ArduCopter's input shaping lags by more than its 300 deg/s average for 0.5 s, and
the measurement is of the autopilot's loop, which pass-through leaves alone."""


def step_metrics(cols: dict[str, np.ndarray], axis: str) -> dict[str, Any]:
    """Each step of the sent rate up from rest (|before| < 5 deg/s, a rise > 45 deg/s):
    the first half of each of the maneuver's doublets.

    Returns ``steps`` (per step: size in deg/s, the measured rate at :data:`AT_S`
    as a fraction of it, rise time to 90 % in ms, NaN if not reached while the step
    is held), and their means ``frac`` and ``rise_90_ms``.
    """
    t = np.asarray(cols["t_s"], dtype=float)
    sent = np.asarray(cols[f"sent_{axis}_rad_s"], dtype=float)
    meas = np.asarray(cols[f"meas_{axis}_rad_s"], dtype=float)
    ok = np.isfinite(sent) & np.isfinite(meas)
    t, sent, meas = t[ok], sent[ok], meas[ok]
    steps = []
    for k in range(1, len(t)):
        jump = sent[k] - sent[k - 1]
        # Up from rest to a doublet's first half (the level segments' own rates are
        # the pilot levelling, not a step).
        if jump < STEP_MIN_RAD_S or abs(sent[k - 1]) > REST_RAD_S:
            continue
        t0 = t[k - 1]  # sent with the sample before: the step left then
        before = (t >= t0 - 0.05) & (t <= t0)
        base = float(np.mean(meas[before])) if before.any() else float(meas[k - 1])
        size = float(sent[k])
        hold = (t >= t0) & (t <= t0 + 1.0) & (np.abs(sent - size) < 1e-6 + 0.02 * abs(size))
        hold &= np.cumsum(~hold) == np.cumsum(~hold)[k - 1]  # this step's run only
        frac = [float((np.interp(t0 + a, t, meas) - base) / size) for a in AT_S]
        reached = np.nonzero(hold & ((meas - base) / size >= 0.9))[0]
        rise = float((t[reached[0]] - t0) * 1e3) if reached.size else math.nan
        steps.append(
            {"t_s": round(float(t0), 3), "size_deg_s": round(math.degrees(size), 1),
             "frac": [round(f, 3) for f in frac], "rise_90_ms": round(rise, 1)}
        )  # fmt: skip
    fr = np.array([s["frac"] for s in steps]) if steps else np.full((0, len(AT_S)), math.nan)
    rises = np.array([s["rise_90_ms"] for s in steps], dtype=float)
    return {
        "axis": axis,
        "steps": steps,
        "at_s": list(AT_S),
        "frac": [round(float(v), 3) for v in np.nanmean(fr, axis=0)] if steps else [],
        "rise_90_ms": round(float(np.nanmean(rises)), 1) if np.isfinite(rises).any() else None,
    }


def _step_pilot(axis: str) -> Any:
    from sitl.pilot import make_pilot

    return make_pilot(f"step-{axis}", rng=np.random.default_rng(0), free_flight=True)


def fly_real(stack: str, axis: str, workdir: Path, *, altitude_m: float = 15.0) -> dict[str, Any]:
    """Fly the step maneuver through the companion's pass-through on the real ``stack``."""
    from sitl.lab.realstack.flights import Session

    session = Session(stack, workdir)
    try:
        gcs = session.connect(timeout_s=120.0)
        session.take_off(altitude_m=altitude_m, timeout_s=150.0)
        run = session.start_companion(
            "--profile", str(PROFILES[stack]), "--output", "rates", "--rates-passthrough",
            "--engage", "rc-switch", "--stale-imu-s", "0.5", *_NO_ENVELOPE, name=f"steps-{axis}",
        )  # fmt: skip
        time.sleep(6.0)  # the companion's start-up: connected, streams asked for
        pilot = _step_pilot(axis)
        session.pilot.pilot = pilot
        session.pilot.engage(gcs.now.t_s)
        if not session.wait_engaged(run, timeout_s=15.0):
            raise RuntimeError(f"{stack}: the companion did not engage: {run.kinds()}")
        time.sleep(pilot.duration_s + 1.0)
        session.pilot.release()
        time.sleep(1.0)
        run.stop()
        out = step_metrics(run.control(), axis)
        out["stack"] = stack
        out["companion_events"] = run.kinds()
        return out
    finally:
        session.close()


def fly_bundled(stack: str, axis: str, workdir: Path) -> dict[str, Any]:
    """The same maneuver through the same pass-through on the bundled SITL (lockstep),
    the matching profile and personality."""
    from sitl.lab.fly import fly_mavlink

    workdir.mkdir(parents=True, exist_ok=True)
    scenario = workdir / f"steps-{axis}.yaml"
    scenario.write_text(
        f"name: steps-{axis}\ndescription: rate steps through the pass-through\n"
        f"seed: 1\npilot: step-{axis}\nfree_flight: true\nphysics_dt_s: 0.001\n"
        "rc_rate_hz: 50.0\n",
        encoding="utf-8",
    )
    flight = fly_mavlink(
        PROFILES[stack], str(scenario), workdir / f"bundled-{stack}-{axis}", output="rates",
        companion_args=("--rates-passthrough", *_NO_ENVELOPE), autopilot=stack,
    )  # fmt: skip
    if flight.companion_rc != 0:
        raise RuntimeError(flight.text("companion.stderr")[-2000:])
    from companion.records import read_control_log

    cols, _ = read_control_log(flight.control_log)
    out = step_metrics(cols, axis)
    out["stack"] = f"bundled {stack}"
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stack", choices=("px4", "ardupilot"))
    ap.add_argument("axis", choices=("roll", "pitch", "yaw"))
    ap.add_argument("out", type=Path)
    ap.add_argument("--bundled", action="store_true", help="the bundled SITL instead")
    a = ap.parse_args(argv)
    fn = fly_bundled if a.bundled else fly_real
    res = fn(a.stack, a.axis, a.out)
    json.dump(res, sys.stdout, indent=1)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
