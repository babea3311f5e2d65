"""The acceleration floor, the ideal tracker and the gyro filter of scripts/reproduce_paper.py."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from tests.file_module import load_file_module

ROOT = Path(__file__).resolve().parents[2]
DT = 0.004


rp = load_file_module(ROOT / "scripts" / "reproduce_paper.py")


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
    floor = rp.acceleration_floor_deg_s(t, ref, accel, accel)
    assert floor <= _mae_deg_s(ref, centred)
    assert floor >= 0.9 * _mae_deg_s(ref, centred)  # the grid's slack: 6.54 against 7.20
    assert _mae_deg_s(ref, _greedy(ref, accel)) > 1.8 * floor


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_no_feasible_trajectory_beats_the_floor(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, accel = 400, 150.0
    t = np.arange(n) * DT
    ref = np.repeat(rng.uniform(-12.0, 12.0, n // 40), 40)  # stick steps every 0.16 s
    floor = rp.acceleration_floor_deg_s(t, ref, accel, 0.7 * accel)
    assert 0.0 < floor <= _mae_deg_s(ref, _greedy(ref, 0.7 * accel))


def test_unbounded_acceleration_tracks_everything() -> None:
    t = np.arange(200) * DT
    ref = np.sin(t * 20.0) * 8.0
    assert rp.acceleration_floor_deg_s(t, ref, 1e6, 1e6) == 0.0


def test_ideal_tracker_holds_a_steady_stick() -> None:
    t = np.arange(300) * DT
    ref = np.full(300, 3.0)
    assert rp.ideal_tracker_deg_s(t, ref, 100.0, 100.0, 0.05) == pytest.approx(0.0, abs=1e-9)


def test_ideal_tracker_brakes_onto_a_step() -> None:
    """0 -> 10 rad/s at 100 rad/s^2 with a 50 ms motor lag: full command up, full
    command down onto the new rate, settled within the lag-free ramp plus three lags."""
    n, accel, tau = 500, 100.0, 0.05
    t = np.arange(n) * DT
    ref = np.where(np.arange(n) < 50, 0.0, 10.0)
    w = rp.ideal_tracker_rates(t, ref, accel, accel, tau)
    assert w.max() < 10.0 * 1.001  # brakes in time: no overshoot to speak of
    settled = t >= t[50] + 10.0 / accel + 3 * tau
    assert np.all(np.abs(w[settled] - 10.0) < 0.01)
    lagged = rp.ideal_tracker_deg_s(t, ref, accel, accel, tau)
    lag_free = _mae_deg_s(ref, _greedy(np.r_[ref[0], ref[:-1]], accel))  # a sample late
    assert lag_free < lagged < rp.ideal_tracker_deg_s(t, ref, accel, accel, 2 * tau)
    # without a lag it is the fastest causal ramp, one sample behind the stick
    assert rp.ideal_tracker_deg_s(t, ref, accel, accel, 1e-4) == pytest.approx(lag_free, rel=0.01)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_ideal_tracker_never_beats_the_floor(seed: int) -> None:
    """Its acceleration stays within the limits, so the floor's bound holds for it."""
    rng = np.random.default_rng(seed)
    n, accel = 400, 150.0
    t = np.arange(n) * DT
    ref = np.repeat(rng.uniform(-12.0, 12.0, n // 40), 40)
    floor = rp.acceleration_floor_deg_s(t, ref, accel, 0.7 * accel)
    assert floor <= rp.ideal_tracker_deg_s(t, ref, accel, 0.7 * accel, 0.03)


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
    np.testing.assert_allclose(rp.through_gyro_filter(rates, weight), got, rtol=0, atol=1e-12)


def test_a_filtered_ideal_lags_a_step() -> None:
    """Seen through the filter, the same ideal tracks a stick step worse."""
    n, accel, tau = 500, 100.0, 0.05
    t = np.arange(n) * DT
    ref = np.where(np.arange(n) < 50, 0.0, 10.0)
    w = rp.ideal_tracker_rates(t, ref, accel, accel, tau)
    assert _mae_deg_s(ref, rp.through_gyro_filter(w, 0.3)) > _mae_deg_s(ref, w)
