"""IMU and wind models: rates, statistics, saturation, latency, filter."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.profile import ImuModel
from sitl.imu import Imu, ImuSample
from sitl.wind import Wind, WindConfig

DT = 0.001


def run_imu(
    imu: Imu, n_steps: int, rate=(0.0, 0.0, 0.0), force=(0.0, 0.0, -9.8)
) -> list[ImuSample]:
    out = []
    for k in range(1, n_steps + 1):
        s = imu.update(k * DT, rate, force)
        if s is not None:
            out.append(s)
    return out


# ----------------------------------------------------------------------------- IMU


def test_sample_rate_follows_model() -> None:
    imu = Imu(ImuModel(rate_hz=250.0), rng=np.random.default_rng(0), dt_s=DT)
    samples = run_imu(imu, 1000)
    assert len(samples) == 250
    np.testing.assert_allclose(np.diff([s.time_s for s in samples]), 0.004, atol=1e-12)


def test_noiseless_passthrough() -> None:
    imu = Imu(ImuModel(), rng=np.random.default_rng(0), dt_s=DT)
    s = imu.update(0.001, (0.1, -0.2, 0.3), (1.0, 2.0, -9.0))
    assert s == ImuSample(0.001, (0.1, -0.2, 0.3), (1.0, 2.0, -9.0))


def test_white_noise_sigma() -> None:
    density = 0.01  # rad/s/sqrt(Hz)
    model = ImuModel(rate_hz=1000.0, gyro_noise_density_rad_s_sqrt_hz=density)
    imu = Imu(model, rng=np.random.default_rng(1), dt_s=DT)
    g = np.array([s.gyro_frd_rad_s for s in run_imu(imu, 20000, rate=(1.0, 0.0, -1.0))])
    sigma = density * math.sqrt(1000.0)
    # 20000 samples: the std estimate is good to ~0.5 %; 3 % fails any wrong scaling.
    np.testing.assert_allclose(g.std(axis=0), [sigma] * 3, rtol=0.03)
    np.testing.assert_allclose(g.mean(axis=0), [1.0, 0.0, -1.0], atol=4 * sigma / math.sqrt(2e4))
    # White: consecutive samples uncorrelated.
    r1 = np.corrcoef(g[:-1, 0], g[1:, 0])[0, 1]
    assert abs(r1) < 0.03


def test_bias_random_walk_variance() -> None:
    n_b = 0.01  # rad/s^2/sqrt(Hz)
    model = ImuModel(rate_hz=500.0, gyro_bias_random_walk_rad_s2_sqrt_hz=n_b)
    rng = np.random.default_rng(2)
    T = 1.0
    biases = []
    for _ in range(100):
        imu = Imu(model, rng=rng, dt_s=DT)
        run_imu(imu, round(T / DT))
        biases.extend(imu.bias_frd_rad_s)
    # var(b(T)) = N_b^2 T; 300 draws, so the variance estimate is good to ~8 %.
    np.testing.assert_allclose(np.var(biases), n_b**2 * T, rtol=0.3)


def test_saturation_at_full_scale() -> None:
    model = ImuModel(gyro_range_deg_s=2000.0, gyro_noise_density_rad_s_sqrt_hz=1e-3)
    imu = Imu(model, rng=np.random.default_rng(3), dt_s=DT)
    s = imu.update(0.001, (100.0, -100.0, 1.0), (0.0, 0.0, 0.0))
    assert s is not None
    lim = math.radians(2000.0)
    assert s.gyro_frd_rad_s[0] == lim and s.gyro_frd_rad_s[1] == -lim
    assert abs(s.gyro_frd_rad_s[2] - 1.0) < 5 * 1e-3 * math.sqrt(1000.0)  # 5 sigma


def test_latency_delays_delivery_not_timestamp() -> None:
    latency = 0.005
    imu = Imu(ImuModel(latency_s=latency), rng=np.random.default_rng(4), dt_s=DT)
    delivered = []
    for k in range(1, 101):
        t = k * DT
        # Encode the measurement time in the rate so we can tell which state we got.
        s = imu.update(t, (t, 0.0, 0.0), (0.0, 0.0, -9.8))
        if s is not None:
            delivered.append((t, s))
    t_first = delivered[0][0]
    np.testing.assert_allclose(t_first, DT + latency, atol=1e-12)
    for t, s in delivered:
        np.testing.assert_allclose(s.time_s, t - latency, atol=1e-12)
        np.testing.assert_allclose(s.gyro_frd_rad_s[0], s.time_s, atol=1e-12)
    assert len(delivered) == 100 - round(latency / DT)


def test_first_stage_filter_step_response() -> None:
    w = 0.3
    imu = Imu(ImuModel(first_stage_filter_weight=w), rng=np.random.default_rng(5), dt_s=DT)
    imu.update(DT, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    out = [imu.update((k + 2) * DT, (1.0, -2.0, 0.0), (0.0, 0.0, 0.0)) for k in range(20)]
    y = np.array([s.gyro_frd_rad_s for s in out if s is not None])
    k = np.arange(1, 21)
    # y_k = w u + (1 - w) y_{k-1}, y_0 = 0  ->  y_k = u (1 - (1 - w)^k)
    np.testing.assert_allclose(y[:, 0], 1.0 - (1.0 - w) ** k, rtol=1e-12)
    np.testing.assert_allclose(y[:, 1], -2.0 * (1.0 - (1.0 - w) ** k), rtol=1e-12)


def test_filter_reduces_noise_as_predicted() -> None:
    w = 0.25
    model = ImuModel(gyro_noise_density_rad_s_sqrt_hz=0.01, first_stage_filter_weight=w)
    imu = Imu(model, rng=np.random.default_rng(6), dt_s=DT)
    g = np.array([s.gyro_frd_rad_s for s in run_imu(imu, 20000)])[100:]
    # First-order IIR on white noise: var_out = var_in * w / (2 - w).
    sigma = 0.01 * math.sqrt(1000.0)
    np.testing.assert_allclose(g.std(axis=0), [sigma * math.sqrt(w / (2 - w))] * 3, rtol=0.05)


def test_rejects_bad_step() -> None:
    with pytest.raises(ValueError):
        Imu(ImuModel(), rng=np.random.default_rng(0), dt_s=0.0)


def test_imu_same_seed_same_samples() -> None:
    model = ImuModel(
        gyro_noise_density_rad_s_sqrt_hz=1e-3, gyro_bias_random_walk_rad_s2_sqrt_hz=1e-3
    )
    a = run_imu(Imu(model, rng=np.random.default_rng(9), dt_s=DT), 500)
    b = run_imu(Imu(model, rng=np.random.default_rng(9), dt_s=DT), 500)
    c = run_imu(Imu(model, rng=np.random.default_rng(10), dt_s=DT), 500)
    assert a == b
    assert a != c


# ---------------------------------------------------------------------------- wind


def test_steady_wind_is_returned_exactly() -> None:
    wind = Wind(WindConfig(steady_ned_m_s=(3.0, -4.0, 0.5)), rng=np.random.default_rng(0))
    for k in range(100):
        assert wind.velocity_ned(k * 0.01, 0.01, 5.0) == (3.0, -4.0, 0.5)


def test_gust_statistics() -> None:
    sigma, L, V, dt = 2.0, 50.0, 10.0, 0.02
    wind = Wind(
        WindConfig(steady_ned_m_s=(5.0, 0.0, 0.0), gust_sigma_m_s=sigma, gust_length_m=L),
        rng=np.random.default_rng(11),
    )
    n = 100_000  # 2000 s, 400 correlation times L / V = 5 s
    u = np.array([wind.velocity_ned(k * dt, dt, V) for k in range(n)])
    np.testing.assert_allclose(u.mean(axis=0), [5.0, 0.0, 0.0], atol=0.35)
    np.testing.assert_allclose(u.std(axis=0), [sigma] * 3, rtol=0.15)
    # Autocorrelation at one correlation time is exp(-1).
    lag = round(L / V / dt)
    for i in range(3):
        x = u[:, i] - u[:, i].mean()
        rho = float(np.dot(x[:-lag], x[lag:]) / np.dot(x, x))
        np.testing.assert_allclose(rho, math.exp(-1.0), atol=0.12)
    # Independent axes.
    assert abs(np.corrcoef(u[:, 0], u[:, 1])[0, 1]) < 0.15


def test_gust_bandwidth_scales_with_airspeed() -> None:
    def lag1(v: float) -> float:
        wind = Wind(WindConfig(gust_sigma_m_s=1.0), rng=np.random.default_rng(12))
        u = np.array([wind.velocity_ned(0.0, 0.01, v)[0] for _ in range(20000)])
        return float(np.corrcoef(u[:-1], u[1:])[0, 1])

    # a = exp(-V dt / L): faster flight, less correlated gusts step to step.
    np.testing.assert_allclose(lag1(20.0), math.exp(-20.0 * 0.01 / 50.0), atol=2e-3)
    assert lag1(20.0) < lag1(2.0)


def test_wind_config_rejects_nonsense() -> None:
    with pytest.raises(ValueError, match="gust_sigma_m_s"):
        WindConfig(gust_sigma_m_s=-1.0)
    with pytest.raises(ValueError, match="gust_length_m"):
        WindConfig(gust_length_m=0.0)
    with pytest.raises(ValueError, match="steady_ned_m_s"):
        WindConfig(steady_ned_m_s=(0.0, float("nan"), 0.0))


def test_wind_same_seed_same_gusts() -> None:
    cfg = WindConfig(gust_sigma_m_s=1.0)
    a = Wind(cfg, rng=np.random.default_rng(3))
    b = Wind(cfg, rng=np.random.default_rng(3))
    c = Wind(cfg, rng=np.random.default_rng(4))
    ua = [a.velocity_ned(0.0, 0.01, 3.0) for _ in range(100)]
    assert ua == [b.velocity_ned(0.0, 0.01, 3.0) for _ in range(100)]
    assert ua != [c.velocity_ned(0.0, 0.01, 3.0) for _ in range(100)]
