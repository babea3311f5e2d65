"""``companion run --mode angle`` against the SITL as a separate process, over UDP.

The pilot (a stick script) takes off level, holds the roll stick half right
(17.5 deg in angle mode) for two seconds, then centres it: the vehicle must
lean to that angle and level itself again, on the SITL's attitude stream.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from sitl.flight_log import read_log
from sitl.lab.fly import fly_mavlink

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]

SCRIPT = """\
duration_s: 9
altitude_m: 5
segments:
  - {t_s: 0.0, level: true}
  - {t_s: 3.0, rate_deg_s: [360, 0, 0], ramp_s: 0.1}
  - {t_s: 5.0, rate_deg_s: [0, 0, 0], ramp_s: 0.1}
"""
HALF_STICK_DEG = 0.5 * 35.0  # 360 of 720 deg/s full scale: half the stick


def roll_deg(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q.T
    return np.degrees(np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y)))


@pytest.mark.long
def test_the_sticks_are_angles_and_centred_sticks_level(tmp_path: Path) -> None:
    sticks = tmp_path / "lean-right.yaml"
    sticks.write_text(SCRIPT, encoding="utf-8")
    scenario = tmp_path / "angle.yaml"
    scenario.write_text(
        f"name: angle\nseed: 5\npilot: {sticks}\nfree_flight: true\n", encoding="utf-8"
    )
    flight = fly_mavlink(
        ROOT / "vehicle_profiles" / "f450.yaml", str(scenario), tmp_path / "flight",
        duration_s=8.5, companion_args=("--mode", "angle"),
    )  # fmt: skip
    assert flight.companion_rc == 0, flight.why()
    kinds = [e["kind"] for e in flight.companion_events]
    assert "estimate_stream" in kinds and not any(k.startswith("failsafe") for k in kinds)
    t_eng = next(float(e["t_s"]) for e in flight.companion_events if e["kind"] == "engaged")
    log = read_log(flight.sitl_log)
    t = log["t_s"] - t_eng  # the pilot's time: it starts as the vehicle is engaged
    roll = roll_deg(log["q_wxyz"])
    assert not log.summary.get("crashed", False)
    leaning = (t > 4.0) & (t < 5.0)
    level = (t > 7.0) & (t < 8.5)
    assert leaning.sum() > 100 and level.sum() > 100
    assert abs(float(np.median(roll[leaning])) - HALF_STICK_DEG) < 3.0, roll[leaning][::50]
    assert float(np.max(np.abs(roll[level]))) < 3.0, roll[level][::50]
    assert math.isfinite(float(np.max(np.abs(roll))))
