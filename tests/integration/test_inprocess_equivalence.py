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
from sitl.link_model import parse_link
from sitl.scenario import load_scenario

pytestmark = pytest.mark.integration

PATIENT = ("--lockstep-timeout", "3")
"""The lockstep SITL waits this long (wall clock) for each setpoint: a companion
stalled past the default 0.5 s by a loaded machine (a parallel compile) would let
the plant step without its command, and the flights would part ways for a reason
that is not the link's."""

PATIENT_COMPANION = ("--stale-imu-s", "1.0", "--rc-timeout-s", "1.0")
"""The companion's wall-clock watchdogs as patient as their bounds let them be: a
loaded machine held a lockstep mode flight's companion off the CPU for 0.5 s
(the stale-IMU and RC bounds the lab's flights use otherwise), and it handed back."""

ROOT = Path(__file__).resolve().parents[2]
RATE_HZ = 250  # the F450's IMU


def test_same_scenario_same_seed_same_flight_both_ways(tmp_path: Path) -> None:
    profile = ROOT / "vehicle_profiles" / "f450.yaml"
    # The pilot closes its loop on the vehicle's attitude and rounds its sticks to whole
    # microseconds; the link carries float32, so after long enough one stick rounds the
    # other way and the flights part (with the delay-identifying controller: at 7.3 s).
    # 6 s holds the exact comparison; the MAE bound below is the long-run check.
    duration = 6.0
    flight = fly_mavlink(profile, "paper-acro", tmp_path, duration_s=duration, sitl_args=PATIENT)
    assert flight.companion_rc == 0, flight.why()
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
        # 2.5 %: over 6 s the airborne window (truth sampled at the sample's time over
        # MAVLink, at its processing in process) moves the mean by a few samples.
        assert abs(x - y) <= 0.025 * y, (axis, x, y)


# Delay and jitter up, delay down, 5 % of the messages lost and 5 % duplicated each
# way: the two flights lose and duplicate the same messages at the same moments
# (each stream draws from the seed alone), and every command takes effect at the
# same physics step both ways: the autopilot's first IMU sample after it arrives,
# here 4 ms after its own sample (1.5 + 2.5 ms at most, the F450's sample period).
LINK = "up_delay_ms=1,up_jitter_ms=0.5,down_delay_ms=2.5,loss=0.05,duplicate=0.05"


def test_through_a_link_the_same_flight_both_ways(tmp_path: Path) -> None:
    profile = ROOT / "vehicle_profiles" / "f450.yaml"
    duration = 3.0
    link = parse_link(LINK)
    flight = fly_mavlink(
        profile, "paper-acro", tmp_path, duration_s=duration, link=link, sitl_args=PATIENT
    )
    assert flight.companion_rc == 0, flight.why()
    mav_rec = merge_logs(flight)
    sc = load_scenario("paper-acro").model_copy(update={"duration_s": duration, "link": link})
    in_rec = simulate_flight(load_profile(profile), load_controller(), sc)
    a, b = mav_rec.columns, in_rec.columns
    # The same samples lost on the way, both ways.
    assert 0.9 * duration * RATE_HZ < len(a["t_s"]) == len(b["t_s"]) < duration * RATE_HZ
    np.testing.assert_allclose(np.asarray(a["t_s"]) - a["t_s"][0], b["t_s"], atol=1e-9)
    assert np.array_equal(a["ref_rad_s"], b["ref_rad_s"])
    # (Once in many suite runs on a loaded machine the pilot's throttle parted by one
    # microsecond late in the flight; not reproduced alone or under synthetic load.
    # Where and with which lockstep counts, should it happen again.)
    parted = np.flatnonzero(np.asarray(a["thrust"]) != np.asarray(b["thrust"]))
    lockstep = {k: v for k, v in flight.sitl_summary.items() if k.startswith(("lock", "setp"))}
    assert parted.size == 0, (parted[:5], float(a["t_s"][parted[0]] - a["t_s"][0]), lockstep)
    # The gyro and the law's motors differ by the link's float32 only.
    assert np.max(np.abs(a["meas_rad_s"] - b["meas_rad_s"])) < 1e-6
    assert np.max(np.abs(a["motors"] - b["motors"])) < 1e-6
    # Each command handled 4 ms after its sample (or lost).
    age = flight.sitl_summary["setpoint_age_ms"]
    assert age["mean"] == pytest.approx(4.0, abs=1e-6)


def test_through_a_uart_link_the_same_flight_both_ways(tmp_path: Path) -> None:
    """Through `uart` the round trip (3-5 ms) ends before or after the next IMU
    sample: a command acts at the autopilot's first sample after it arrives (4 or
    8 ms after its own), at the same step both ways."""
    profile = ROOT / "vehicle_profiles" / "f450.yaml"
    duration = 3.0
    link = parse_link("uart")
    flight = fly_mavlink(
        profile, "paper-acro", tmp_path, duration_s=duration, link=link, sitl_args=PATIENT
    )
    assert flight.companion_rc == 0, flight.why()
    a = merge_logs(flight).columns
    sc = load_scenario("paper-acro").model_copy(update={"duration_s": duration, "link": link})
    b = simulate_flight(load_profile(profile), load_controller(), sc).columns
    assert len(a["t_s"]) == len(b["t_s"]) == duration * RATE_HZ
    assert np.array_equal(a["ref_rad_s"], b["ref_rad_s"])
    # float32 on the link, as in the ideal link's test; and the throttle: the SITL
    # sends RC_CHANNELS on its stream's schedule, the in-process pilot's frames leave
    # when the pilot moves, so a throttle step can reach the companion a sample apart
    # (here 1 us of stick, 0.001 of collective, in 31 samples of 750).
    assert np.max(np.abs(a["meas_rad_s"] - b["meas_rad_s"])) < 1e-5
    thrust_apart = np.abs(a["thrust"] - b["thrust"])
    assert np.count_nonzero(thrust_apart > 1e-9) <= 0.05 * len(thrust_apart)
    assert np.max(thrust_apart) <= 0.0011
    assert np.max(np.abs(a["motors"] - b["motors"])) < 0.0011
    age = flight.sitl_summary["setpoint_age_ms"]
    # Handled when it arrives: 2 x (2 +/- 0.5) ms after its sample.
    assert 3.0 - 1e-6 <= age["mean"] <= 5.0 + 1e-6 and age["max"] <= 5.0 + 1e-6, age


# A flight mode's flight: the pilot works the throttle towards 3 m (its own altitude
# hold) and, once up, the roll stick; the outer loops fly on the SITL's estimates.
MODE_STICKS = """\
duration_s: 8
altitude_m: 3
segments:
  - {t_s: 0.0, rate_deg_s: [0, 0, 0]}
  - {t_s: 4.0, rate_deg_s: [40, 0, 0]}
  - {t_s: 4.5, rate_deg_s: [0, -30, 20]}
  - {t_s: 5.0, rate_deg_s: [0, 0, 0]}
"""
MODE_SCENARIO = """\
name: mode-equivalence
seed: 7
pilot: {pilot}
free_flight: true
wind:
  steady_ned_m_s: [2.0, 0.0, 0.0]
  gust_sigma_m_s: 1.0
  gust_length_m: 30.0
"""
MISSION = """\
speed_m_s: 2.0
waypoints:
  - {north_m: 0, east_m: 0, up_m: 2}
  - {north_m: 3, east_m: 0, up_m: 2}
"""


@pytest.mark.long
@pytest.mark.parametrize("mode", ["angle", "altitude", "position", "mission"])
def test_each_flight_mode_is_the_same_flight_both_ways(tmp_path: Path, mode: str) -> None:
    """The flight modes sample for sample, on the SITL's estimates: they cross the
    link as float32 (as the gyro does), ahead of the IMU sample they come with."""
    from companion.mission import load_mission

    profile = ROOT / "vehicle_profiles" / "f450.yaml"
    sticks = tmp_path / "sticks.yaml"
    sticks.write_text(MODE_STICKS, encoding="utf-8")
    scenario = tmp_path / "scenario.yaml"
    scenario.write_text(MODE_SCENARIO.format(pilot=sticks), encoding="utf-8")
    mission = None
    args: tuple[str, ...] = ("--mode", mode)
    if mode == "mission":
        path = tmp_path / "mission.yaml"
        path.write_text(MISSION, encoding="utf-8")
        mission = load_mission(path)
        args = ("--mode", "position", "--mission", str(path))
    duration = 6.0
    flight = fly_mavlink(
        profile, str(scenario), tmp_path / "flight", duration_s=duration,
        sitl_args=PATIENT, companion_args=(*args, *PATIENT_COMPANION),
    )  # fmt: skip
    assert flight.companion_rc == 0, flight.why()
    assert not [e for e in flight.companion_events if e["kind"].startswith("failsafe")]
    a = merge_logs(flight).columns
    sc = load_scenario(str(scenario)).model_copy(update={"duration_s": duration})
    in_rec = simulate_flight(
        load_profile(profile), load_controller(), sc,
        mode="position" if mode == "mission" else mode, mission=mission,
    )  # fmt: skip
    b = in_rec.columns
    assert len(a["t_s"]) == len(b["t_s"]) == duration * in_rec.meta["imu_rate_hz"]
    np.testing.assert_allclose(np.asarray(a["t_s"]) - a["t_s"][0], b["t_s"], atol=1e-9)
    assert max(np.max(a["altitude_m"]), np.max(b["altitude_m"])) > 1.0  # it flew
    apart = {
        key: np.abs(np.asarray(a[key]) - np.asarray(b[key])).reshape(len(b["t_s"]), -1).max(axis=1)
        for key in ("ref_rad_s", "thrust", "meas_rad_s", "motors")
    }
    if mode != "angle":
        # The mode's rate reference and collective, the gyro and the motors apart by
        # the link's float32 only (measured: under 2e-7 each, 6 s).
        for key, d in apart.items():
            assert np.max(d) < 1e-6, (key, float(np.max(d)))
        return
    # In angle mode the collective is the pilot's throttle, and the pilot closes its
    # loop on the altitude, which the float32 link moves by 2e-5 m: one stick
    # microsecond rounds the other way now and then (measured: 40 samples of 6000,
    # from 4.14 s, 0.001 of collective; with both cores busy, once 220: why load
    # moves it is not established, the pilot input's wall-clock freshness is the
    # first suspect). Everything else as above.
    thrust = apart["thrust"]
    assert np.count_nonzero(thrust > 1e-9) <= 0.1 * len(thrust) and np.max(thrust) <= 0.0011
    assert np.max(apart["motors"]) <= 0.0011
    assert np.max(apart["ref_rad_s"]) < 1e-5 and np.max(apart["meas_rad_s"]) < 1e-4
