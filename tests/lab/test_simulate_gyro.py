"""The gyro as PX4 sends it to a companion, in the lab's loop
(``sitl.lab.simulate``: ``GyroMeans`` and ``simulate_flight(gyro_hz=...)``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from companion.config import load_controller
from companion.profile import load_profile
from sitl.lab.simulate import GyroMeans, simulate_flight
from sitl.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[2]


def test_every_nth_sample_goes_out_as_the_mean_of_the_last_n() -> None:
    means = GyroMeans(4)
    got = [means.add((0.1 * k, -0.2 * k, 1.0)) for k in range(1, 10)]
    assert [g is not None for g in got] == [False, False, False, True] * 2 + [False]
    assert got[3] == pytest.approx((0.25, -0.5, 1.0))
    assert got[7] == pytest.approx((0.65, -1.3, 1.0))


def test_one_sample_a_mean_is_the_sample_to_the_bit() -> None:
    means = GyroMeans(1)
    g = (-0.0, 1e-300, 0.1 + 0.2)
    assert means.add(g) is g


def test_a_mean_of_no_samples_is_refused() -> None:
    with pytest.raises(ValueError, match="at least 1"):
        GyroMeans(0)


def test_a_flight_on_every_samples_rate_is_the_default_flight_bit_for_bit() -> None:
    profile = load_profile(ROOT / "vehicle_profiles" / "f450.yaml")
    sc = load_scenario(ROOT / "sitl" / "scenarios" / "hover-gusts.yaml")
    sc = sc.model_copy(update={"duration_s": 2.0})
    a = simulate_flight(profile, load_controller(), sc)
    b = simulate_flight(profile, load_controller(), sc, gyro_hz=sc.imu_model(profile).rate_hz)
    for k in a.columns:
        assert np.array_equal(a.columns[k], b.columns[k], equal_nan=True), k
    c = simulate_flight(profile, load_controller(), sc, gyro_hz=250.0)
    assert c.meta["gyro_hz"] == 250.0 and c.meta["imu_rate_hz"] == a.meta["imu_rate_hz"]
    np.testing.assert_allclose(np.diff(c.columns["t_s"]), 0.004, atol=1e-9)
