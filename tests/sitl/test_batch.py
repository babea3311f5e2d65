"""The vectorised batch plant against the scalar one."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from companion.profile import VehicleProfile, load_profile
from sitl.batch import BatchQuadrotor
from sitl.frames import euler_to_quat
from sitl.physics import Quadrotor
from sitl.vehicle_params import GRAVITY_M_S2
from sitl.wind import Wind, WindConfig

PROFILES = Path(__file__).resolve().parents[2] / "vehicle_profiles"


def hover_speed(profile: VehicleProfile) -> float:
    ph = profile.physics
    return math.sqrt(ph.mass_kg * GRAVITY_M_S2 / (profile.n_motors * ph.kf_n_per_rad_s2))


def commands(k: int, dt: float) -> list[float]:
    """Deterministic, uneven, time-varying commands (exercise every term)."""
    t = k * dt
    return [
        0.70 + 0.10 * math.sin(2 * math.pi * 1.0 * t),
        0.72 + 0.08 * math.sin(2 * math.pi * 1.7 * t + 1.0),
        0.68 + 0.10 * math.cos(2 * math.pi * 0.8 * t),
        0.75 if t < 0.5 else 0.60,
    ]


@pytest.mark.parametrize("name", ["f450_cut_props.yaml", "tarot650.yaml", "x500.yaml"])
def test_one_batch_vehicle_matches_the_scalar_plant(name: str) -> None:
    prof = load_profile(PROFILES / name)
    data = prof.model_dump()
    # A failure during the run, to check fail_at_s in both.
    data["physics"]["damage"]["motors"] = [
        *data["physics"]["damage"]["motors"],
        {"motor": 3, "fail_at_s": 0.6, "efficiency_after_fail": 0.5},
    ]
    prof = VehicleProfile.model_validate(data)
    w0 = hover_speed(prof)
    start = dict(
        pos_ned_m=(1.0, 2.0, -100.0),
        vel_ned_m_s=(1.0, -0.5, 0.2),
        q_wxyz=euler_to_quat(0.1, -0.05, 0.7),
        rate_frd_rad_s=(0.2, -0.1, 0.3),
        motor_w_rad_s=[w0] * 4,
        rotor_phase_rad=[0.0, 1.0, 2.0, 3.0],
    )
    wind = (2.0, -1.0, 0.0)
    scalar = Quadrotor(
        prof,
        rng=np.random.default_rng(0),
        wind=Wind(WindConfig(steady_ned_m_s=wind), rng=np.random.default_rng(0)),
    )
    scalar.set_state(**start)
    batch = BatchQuadrotor(prof, 3, dt_s=scalar.dt_s, wind_ned_m_s=wind)
    batch.set_state(**start)
    for k in range(1000):
        cmd = commands(k, scalar.dt_s)
        scalar.step(cmd)
        batch.step(np.array([cmd] * 3))
    s = scalar.state
    assert not s.landed and not s.crashed
    i = 1
    np.testing.assert_allclose(batch.pos_ned_m[i], s.pos_ned_m, rtol=0, atol=1e-9)
    np.testing.assert_allclose(batch.vel_ned_m_s[i], s.vel_ned_m_s, rtol=0, atol=1e-9)
    np.testing.assert_allclose(batch.q_wxyz[i], s.q_wxyz, rtol=0, atol=1e-10)
    np.testing.assert_allclose(batch.rate_frd_rad_s[i], s.rate_frd_rad_s, rtol=0, atol=1e-9)
    np.testing.assert_allclose(batch.motor_w_rad_s[i], s.motor_w_rad_s, rtol=1e-12)
    np.testing.assert_allclose(
        batch.specific_force_frd_m_s2[i], s.specific_force_frd_m_s2, rtol=0, atol=1e-8
    )
    np.testing.assert_allclose(batch.t_s, s.t_s, rtol=1e-12)
    # And it did move: the comparison is not between two vehicles at rest.
    assert np.linalg.norm(np.subtract(s.pos_ned_m, start["pos_ned_m"])) > 0.5


def test_per_vehicle_profiles() -> None:
    base = load_profile(PROFILES / "f450.yaml")
    heavier = VehicleProfile.model_validate(
        {**base.model_dump(), "physics": {**base.model_dump()["physics"], "mass_kg": 2.0}}
    )
    batch = BatchQuadrotor([base, heavier])
    w = hover_speed(base)
    ph = base.physics
    cmd = (w - ph.motor_w_idle_rad_s) / (ph.motor_w_max_rad_s - ph.motor_w_idle_rad_s)
    batch.set_state(pos_ned_m=(0.0, 0.0, -10.0), motor_w_rad_s=w)
    batch.step(np.full((2, 4), cmd))
    # Same thrust, more mass: specific force m0 g / m (rtol: the heavier one starts
    # sinking within the step, and drag on that speed adds ~1e-5).
    np.testing.assert_allclose(
        batch.specific_force_frd_m_s2[:, 2], [-GRAVITY_M_S2, -GRAVITY_M_S2 * 1.5 / 2.0], rtol=1e-4
    )
    assert batch.vel_ned_m_s[0, 2] == 0.0 and batch.vel_ned_m_s[1, 2] > 0.0


def test_non_finite_commands_stop_motors() -> None:
    prof = load_profile(PROFILES / "f450.yaml")
    batch = BatchQuadrotor(prof, 2)
    for _ in range(300):
        batch.step(np.array([[np.nan, np.inf, -1.0, 3.0]] * 2))
    np.testing.assert_allclose(batch.motor_w_rad_s[:, :3], 0.0)
    np.testing.assert_allclose(batch.motor_w_rad_s[:, 3], prof.physics.motor_w_max_rad_s, rtol=1e-5)


def test_rejects_mixed_motor_counts_and_bad_sizes() -> None:
    prof = load_profile(PROFILES / "f450.yaml")
    with pytest.raises(ValueError):
        BatchQuadrotor(prof)
    with pytest.raises(ValueError):
        BatchQuadrotor([prof, prof], 3)
    with pytest.raises(ValueError):
        BatchQuadrotor([])
