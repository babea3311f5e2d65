"""The acceleration floor, the ideal tracker, the gyro filter, the link's round trip and the
scoreboard of the paper reproduction (:mod:`sitl.lab.paper`, run by scripts/reproduce_paper.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.control import AXES
from sitl.lab.paper.analysis import (
    acceleration_floor_deg_s,
    command_acting,
    ideal_tracker_deg_s,
    ideal_tracker_rates,
    ideal_tracker_through_link_deg_s,
    mae_deg_s,
    through_gyro_filter,
)
from sitl.lab.paper.flights import OWN_PID, PAPER_VEHICLES
from sitl.lab.paper.prose import scoreboard_lines
from sitl.lab.paper.scoring import scoreboard

DT = 0.004


def _mae_deg_s(ref: np.ndarray, w: np.ndarray) -> float:
    return math.degrees(float(np.mean(np.abs(ref - w))))


def _greedy(ref: np.ndarray, accel: float) -> np.ndarray:
    """A causal tracker that moves towards the reference as fast as the bound allows."""
    w = np.zeros_like(ref)
    w[0] = ref[0]
    for k in range(1, ref.size):
        w[k] = w[k - 1] + np.clip(ref[k] - w[k - 1], -accel * DT, accel * DT)
    return w


def test_a_step_costs_half_the_causal_ramp() -> None:
    """0 -> 10 rad/s at 100 rad/s^2: the best trajectory knows the step is coming and
    ramps across it (its error is a quarter of R^2 / a, the causal ramp's a half)."""
    n, accel = 500, 100.0
    t = np.arange(n) * DT
    ref = np.where(np.arange(n) < n // 2, 0.0, 10.0)
    steps = round(10.0 / (accel * DT))  # 25 samples of ramp
    centred = np.clip((np.arange(n) - (n // 2 - steps // 2)) * accel * DT, 0.0, 10.0)
    floor = acceleration_floor_deg_s(t, ref, accel, accel)
    assert floor <= _mae_deg_s(ref, centred)
    assert floor >= 0.9 * _mae_deg_s(ref, centred)  # the grid's slack: 6.54 against 7.20
    assert _mae_deg_s(ref, _greedy(ref, accel)) > 1.8 * floor


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_no_feasible_trajectory_beats_the_floor(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, accel = 400, 150.0
    t = np.arange(n) * DT
    ref = np.repeat(rng.uniform(-12.0, 12.0, n // 40), 40)  # stick steps every 0.16 s
    floor = acceleration_floor_deg_s(t, ref, accel, 0.7 * accel)
    assert 0.0 < floor <= _mae_deg_s(ref, _greedy(ref, 0.7 * accel))


def test_unbounded_acceleration_tracks_everything() -> None:
    t = np.arange(200) * DT
    ref = np.sin(t * 20.0) * 8.0
    assert acceleration_floor_deg_s(t, ref, 1e6, 1e6) == 0.0


def test_ideal_tracker_holds_a_steady_stick() -> None:
    t = np.arange(300) * DT
    ref = np.full(300, 3.0)
    assert ideal_tracker_deg_s(t, ref, 100.0, 100.0, 0.05) == pytest.approx(0.0, abs=1e-9)


def test_ideal_tracker_brakes_onto_a_step() -> None:
    """0 -> 10 rad/s at 100 rad/s^2 with a 50 ms motor lag: full command up, full
    command down onto the new rate, settled within the lag-free ramp plus three lags."""
    n, accel, tau = 500, 100.0, 0.05
    t = np.arange(n) * DT
    ref = np.where(np.arange(n) < 50, 0.0, 10.0)
    w = ideal_tracker_rates(t, ref, accel, accel, tau)
    assert w.max() < 10.0 * 1.001  # brakes in time: no overshoot to speak of
    settled = t >= t[50] + 10.0 / accel + 3 * tau
    assert np.all(np.abs(w[settled] - 10.0) < 0.01)
    lagged = ideal_tracker_deg_s(t, ref, accel, accel, tau)
    lag_free = _mae_deg_s(ref, _greedy(np.r_[ref[0], ref[:-1]], accel))  # a sample late
    assert lag_free < lagged < ideal_tracker_deg_s(t, ref, accel, accel, 2 * tau)
    # without a lag it is the fastest causal ramp, one sample behind the stick
    assert ideal_tracker_deg_s(t, ref, accel, accel, 1e-4) == pytest.approx(lag_free, rel=0.01)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_ideal_tracker_never_beats_the_floor(seed: int) -> None:
    """Its acceleration stays within the limits, so the floor's bound holds for it."""
    rng = np.random.default_rng(seed)
    n, accel = 400, 150.0
    t = np.arange(n) * DT
    ref = np.repeat(rng.uniform(-12.0, 12.0, n // 40), 40)
    floor = acceleration_floor_deg_s(t, ref, accel, 0.7 * accel)
    assert floor <= ideal_tracker_deg_s(t, ref, accel, 0.7 * accel, 0.03)


@pytest.mark.parametrize("weight", [0.3, 1.0])
def test_gyro_filter_is_the_simulated_imus(weight: float) -> None:
    """The ideal is measured as the flights are: through sitl.imu.Imu's filter."""
    from companion.profile import ImuModel
    from sitl.imu import Imu

    rates = np.random.default_rng(7).uniform(-10.0, 10.0, 200)
    imu = Imu(
        ImuModel(rate_hz=250.0, first_stage_filter_weight=weight),
        rng=np.random.default_rng(0),
        dt_s=DT,
    )
    got = []
    for k, r in enumerate(rates.tolist()):
        sample = imu.update(k * DT, (r, 0.0, 0.0), (0.0, 0.0, -9.81))
        assert sample is not None
        got.append(sample.gyro_frd_rad_s[0])
    np.testing.assert_allclose(through_gyro_filter(rates, weight), got, rtol=0, atol=1e-12)


def test_a_filtered_ideal_lags_a_step() -> None:
    """Seen through the filter, the same ideal tracks a stick step worse."""
    n, accel, tau = 500, 100.0, 0.05
    t = np.arange(n) * DT
    ref = np.where(np.arange(n) < 50, 0.0, 10.0)
    w = ideal_tracker_rates(t, ref, accel, accel, tau)
    assert _mae_deg_s(ref, through_gyro_filter(w, 0.3)) > _mae_deg_s(ref, w)


def _flight(profile: str, mae: tuple[float, float, float], crashed: bool = False) -> dict:  # type: ignore[type-arg]
    return {"profile": profile, "crashed": crashed, "mae_deg_s": dict(zip(AXES, mae))}


def _paper_flights(mfc_crash: bool = False) -> dict:  # type: ignore[type-arg]
    flights = {}
    for p in PAPER_VEHICLES:
        flights[f"{p}_mfc"] = _flight(p, (6.0, 5.0, 8.0), crashed=mfc_crash and p == "f450")
        flights[f"{p}_oracle"] = _flight(p, (5.0, 5.0, 10.0))
        flights[f"{p}_{OWN_PID[p]}"] = _flight(p, (6.0, 4.0, 8.0))
    return flights


def test_scoreboard_ratios_and_targets() -> None:
    board = scoreboard(_paper_flights(), {p: True for p in PAPER_VEHICLES})
    assert set(board) == set(PAPER_VEHICLES)
    roll, pitch, yaw = (board["tarot650"]["axes"][a] for a in AXES)
    assert board["tarot650"]["pid_own"] == "pid_tuned"  # the Tarot's own is the Tarot-tuned
    assert roll["mfc_over_oracle"] == 1.2 and not roll["within_oracle_target"]  # > 1.15
    assert roll["mfc_over_pid_own"] == 1.0 and roll["within_pid_target"]  # equal is no worse
    assert pitch["mfc_over_oracle"] == 1.0 and pitch["within_oracle_target"]
    assert pitch["mfc_over_pid_own"] == 1.25 and not pitch["within_pid_target"]
    assert yaw["mfc_over_oracle"] == 0.8 and yaw["within_oracle_target"]
    lines = "\n".join(scoreboard_lines(board))
    assert "MFC within 1.15x of the oracle's MAE: 6 of 9 vehicle-axes" in lines
    assert "MFC no worse than the PID tuned on the vehicle: 6 of 9 vehicle-axes" in lines
    assert "not on f450 roll, f450_cut_props roll, tarot650 roll" in lines


def test_a_crash_meets_no_target_and_infeasible_is_shown() -> None:
    board = scoreboard(_paper_flights(mfc_crash=True), {"f450": False, "f450_cut_props": True,
                                                       "tarot650": True})  # fmt: skip
    assert board["f450"]["crashed"]["mfc"] and not board["f450"]["feasible"]
    assert not any(x["within_oracle_target"] for x in board["f450"]["axes"].values())
    assert "| f450 | yaw | 8.0 | 10.0 | 0.80 | 8.0 | 1.00 | no |" in scoreboard_lines(board)


def test_a_command_acts_at_the_first_sample_after_its_round_trip() -> None:
    from sitl.link_model import parse_link

    t = np.arange(50) * DT
    assert list(command_acting(t, parse_link("ideal"), 1)) == list(range(50))
    # 2 ms each way: back exactly at the next sample; 3 ms each way: two samples late.
    for delay_ms, late in ((2.0, 1), (3.0, 2)):
        acting = command_acting(t, parse_link(f"delay_ms={delay_ms}"), 1)
        assert list(acting[:late]) == [-1] * late
        assert list(acting[late:]) == list(range(50 - late))


def test_the_ideal_tracker_loses_to_the_round_trip() -> None:
    """One round trip late, a tracker that knows the plant still answers each stick
    step late: more error, growing with the delay, and none on the ideal link."""
    from sitl.link_model import parse_link

    n = 800
    t = np.arange(n) * DT
    ref = np.repeat(np.random.default_rng(4).uniform(-8.0, 8.0, n // 80), 80)
    air = np.ones(n, dtype=bool)
    lim, tau, w = (150.0, 150.0), 0.03, 0.6

    def late(link: str) -> float:
        acting = command_acting(t, parse_link(link), 1)
        return float(ideal_tracker_through_link_deg_s(t, ref, lim, tau, w, acting, air))

    now = mae_deg_s(ref, through_gyro_filter(ideal_tracker_rates(t, ref, *lim, tau), w))
    assert late("ideal") == pytest.approx(now)
    assert now < late("delay_ms=2") < late("delay_ms=6") < late("delay_ms=10")
