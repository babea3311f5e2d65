"""The in-process flight and the lockstep MAVLink flight of one scenario and seed
are the same flight, sample for sample, except where the link itself differs.

Both run the same per-sample step (:class:`companion.step.SampleStep`) with the
same inputs (the pilot's reference, the landed state at the rate the companion
asks for it), the SITL restarts its wind, IMU and pilot streams from the
scenario's seed at arming, and the lockstep flight's timing depends on no race.
What the link changes: MAVLink carries the gyro as float32. Measured over 20 s
(paper-acro, F450): the gyro within 1e-6 rad/s on every sample, the pilot's
commands identical. The MAE differ by under 1 % only because the MAVLink
flight's "airborne" is the autopilot's landed detector, which calls the
take-off a few samples later.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from companion.config import load_controller
from companion.profile import load_profile
from sitl.lab.fly import fly_mavlink, merge_logs
from sitl.lab.report import compute_metrics
from sitl.lab.simulate import simulate_flight
from sitl.scenario import load_scenario

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
RATE_HZ = 250  # the F450's IMU


def test_same_scenario_same_seed_same_flight_both_ways(tmp_path: Path) -> None:
    profile = ROOT / "vehicle_profiles" / "f450.yaml"
    duration = 20.0
    flight = fly_mavlink(profile, "paper-acro", tmp_path, duration_s=duration)
    assert flight.companion_rc == 0, flight.text("companion.stderr")
    mav_rec = merge_logs(flight)
    sc = load_scenario("paper-acro").model_copy(update={"duration_s": duration})
    in_rec = simulate_flight(load_profile(profile), load_controller(), sc)
    mav, inproc = compute_metrics(mav_rec), compute_metrics(in_rec)
    assert not mav["crashed"] and not inproc["crashed"]
    assert mav["samples"] == inproc["samples"] == duration * RATE_HZ

    a, b = mav_rec.columns, in_rec.columns
    # Sample k of one is sample k of the other: same time since the start...
    t_a = np.asarray(a["t_s"]) - a["t_s"][0]
    np.testing.assert_allclose(t_a, b["t_s"], atol=1e-9)
    # ...the pilot asked exactly the same...
    assert np.array_equal(a["ref_rad_s"], b["ref_rad_s"])
    assert np.array_equal(a["thrust"], b["thrust"])
    # ...and the vehicle and the law differ by the link's float32 only.
    assert np.max(np.abs(a["meas_rad_s"] - b["meas_rad_s"])) < 1e-5
    assert np.max(np.abs(a["motors"] - b["motors"])) < 1e-4
    for axis in ("roll", "pitch", "yaw"):
        x, y = mav["mae_deg_s"][axis], inproc["mae_deg_s"][axis]
        assert abs(x - y) <= 0.015 * y, (axis, x, y)
