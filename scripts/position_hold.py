#!/usr/bin/env python3
"""Position hold in gusty wind over MAVLink: ``companion run --mode position`` against
the SITL, one flight per autopilot personality, printed as JSON.

PX4's personality takes the companion's actuator output, ArduPilot's its body
rates (the autopilot's own rate loop under the companion's). The pilot centres
the roll, pitch and yaw sticks and holds 5 m on the throttle; the wind blows 3 m/s
north with 2 m/s gusts. Scored from 8 s after lift-off to the companion's end
(its ``--duration``, engaged time; after it the SITL's own mode flies), on the true
position from the SITL's log, against where the vehicle lifted off (the hold is
taken there): ``rms_m`` (horizontal), ``max_m``, ``mean_offset_m`` (the steady
part), and with both personalities ``rates_over_actuator`` (the target:
<= 1.5).

Usage::

    python scripts/position_hold.py [--profile vehicle_profiles/f450.yaml] [--duration 30]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sitl.flight_log import read_log  # noqa: E402
from sitl.lab.fly import fly_mavlink  # noqa: E402

SETTLE_S = 8.0


def hold_flight(profile: Path, autopilot: str, duration_s: float, out: Path) -> dict[str, object]:
    out.mkdir(parents=True, exist_ok=True)
    sticks = out / "centred.yaml"
    sticks.write_text(
        f"duration_s: {duration_s + 4}\naltitude_m: 5\nsegments:\n"
        "  - {t_s: 0.0, rate_deg_s: [0, 0, 0]}\n",
        encoding="utf-8",
    )
    scenario = out / "position-hold.yaml"
    scenario.write_text(
        f"name: position-hold\nseed: 11\npilot: {sticks}\nfree_flight: true\n"
        "wind:\n  steady_ned_m_s: [3.0, 0.0, 0.0]\n  gust_sigma_m_s: 2.0\n"
        "  gust_length_m: 30.0\n",
        encoding="utf-8",
    )
    flight = fly_mavlink(
        profile, str(scenario), out / autopilot, duration_s=duration_s, autopilot=autopilot,
        companion_args=("--mode", "position"),
    )  # fmt: skip
    log = read_log(flight.sitl_log)
    pos, t = log["pos_ned_m"], log["t_s"]
    airborne = pos[:, 2] < -0.5
    failsafes = [e["kind"] for e in flight.companion_events if e["kind"].startswith("failsafe")]
    if not airborne.any():
        return {"companion_rc": flight.companion_rc, "failsafes": failsafes, "lifted_off": False}
    i0 = int(np.argmax(airborne))
    # Until the companion's run ended (its --duration): after it hands back, the
    # SITL's own position mode flies, and no longer in lockstep.
    end = next(float(e["t_s"]) for e in flight.companion_events if e["kind"] == "duration")
    late = (t > t[i0] + SETTLE_S) & (t <= end)
    h = pos[late, :2] - pos[i0, :2]
    d = np.hypot(h[:, 0], h[:, 1])
    return {
        "companion_rc": flight.companion_rc,
        "failsafes": failsafes,
        "output": "actuator" if autopilot == "px4" else "rates",
        "scored_s": round(float(t[late][-1] - t[late][0]), 2) if late.any() else 0.0,
        "rms_m": round(float(np.sqrt(np.mean(d * d))), 3),
        "max_m": round(float(d.max()), 3),
        "mean_offset_m": round(float(np.hypot(*h.mean(axis=0))), 3),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--profile", type=Path, default=ROOT / "vehicle_profiles" / "f450.yaml")
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--autopilot", action="append", choices=["px4", "ardupilot"])
    args = ap.parse_args(argv)
    autopilots = args.autopilot or ["px4", "ardupilot"]
    result: dict[str, object] = {"profile": args.profile.stem, "duration_s": args.duration}
    with tempfile.TemporaryDirectory() as tmp:
        for name in autopilots:
            result[name] = hold_flight(args.profile, name, args.duration, Path(tmp) / name)
    px4, ardu = result.get("px4"), result.get("ardupilot")
    if isinstance(px4, dict) and isinstance(ardu, dict) and "rms_m" in px4 and "rms_m" in ardu:
        result["rates_over_actuator"] = round(float(ardu["rms_m"]) / float(px4["rms_m"]), 2)
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
