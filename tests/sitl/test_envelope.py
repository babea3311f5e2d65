"""The vehicle envelope: consistent profiles, a stratified seeded sample, stated damage."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from companion.config import PID_DEFAULT_CONTROLLER, load_controller
from companion.profile import VehicleProfile, load_profile
from sitl.cli import cli
from sitl.envelope import (
    ENVELOPE_BOUNDS,
    EnvelopeVehicle,
    corners,
    damage_variants,
    derive,
    latin_hypercube,
    nominal_arm_m,
    peak_angular_accel_rad_s2,
    sample_envelope,
    write_profile_yaml,
)
from sitl.lab.simulate import simulate_flight
from sitl.rotors import hover_motor_command
from sitl.scenario import load_scenario
from sitl.vehicle_params import GRAVITY_M_S2, VehicleParams

PROFILE_DIR = Path(__file__).resolve().parents[2] / "vehicle_profiles"
SAMPLE = sample_envelope(30, seed=1)
CORNERS = {v.name: v for v in corners()}


def _all_profiles() -> list[VehicleProfile]:
    vehicles = SAMPLE + list(CORNERS.values())
    damaged = [p for v in [*CORNERS.values(), *SAMPLE[:5]] for p in damage_variants(v).values()]
    return [v.profile() for v in vehicles] + damaged


def _arm_m(profile: VehicleProfile) -> float:
    x, y, _ = profile.frame.motors[0].position_frd_m
    return math.hypot(x, y)


def _roll(v: EnvelopeVehicle) -> float:
    return peak_angular_accel_rad_s2(v.profile())[0]


# --- Anchors --------------------------------------------------------------------------


def test_f450_scalars_reproduce_the_f450_profile() -> None:
    f450 = load_profile(PROFILE_DIR / "f450.yaml")
    v = derive("f450", 1.5, f450.thrust_to_weight(), 0.021)
    assert v.arm_m == pytest.approx(0.225)
    got, ref = v.profile().physics, f450.physics
    np.testing.assert_allclose(got.inertia_kg_m2, ref.inertia_kg_m2, rtol=0.15)
    assert got.kf_n_per_rad_s2 == pytest.approx(ref.kf_n_per_rad_s2, rel=0.15)
    # The laws are anchored on it, so these hold far tighter than 15 %.
    np.testing.assert_allclose(got.inertia_kg_m2, ref.inertia_kg_m2, rtol=1e-9, atol=1e-15)
    for key in ("kf_n_per_rad_s2", "km_m", "motor_w_max_rad_s", "rotor_inertia_kg_m2"):
        assert getattr(got, key) == pytest.approx(getattr(ref, key), rel=1e-9), key
    assert got.motor_w_idle_rad_s == pytest.approx(ref.motor_w_idle_rad_s, rel=1e-9)
    np.testing.assert_allclose(got.drag_quadratic_n_per_m2_s2, ref.drag_quadratic_n_per_m2_s2)
    assert got.imu == ref.imu
    assert v.profile().limits == f450.limits


@pytest.mark.parametrize("name", ["x500.yaml", "tarot650.yaml"])
def test_size_law_predicts_the_other_bundled_arms(name: str) -> None:
    prof = load_profile(PROFILE_DIR / name)
    assert nominal_arm_m(prof.physics.mass_kg) == pytest.approx(_arm_m(prof), rel=0.10)


# --- Every profile is valid and round-trips ---------------------------------------------


def test_every_profile_validates_and_round_trips(tmp_path: Path) -> None:
    profiles = _all_profiles()
    assert len({p.name for p in profiles}) == len(profiles)
    for prof in profiles:
        path = tmp_path / f"{prof.name}.yaml"
        write_profile_yaml(prof, path)
        assert load_profile(path) == prof
        assert prof.frame.layout == "quad_x"
        VehicleParams.from_profile(prof)  # damaged inertia still positive definite
        assert 0.05 < hover_motor_command(prof) < 0.9


def test_thrust_to_weight_is_the_requested_one() -> None:
    for v in SAMPLE + list(CORNERS.values()):
        assert v.profile().thrust_to_weight() == pytest.approx(v.thrust_to_weight, rel=1e-9)


def test_to_dict_is_json_and_carries_the_scalars() -> None:
    v = CORNERS["mid"]
    d = json.loads(json.dumps(v.to_dict()))
    for key in ("name", "mass_kg", "arm_m", "thrust_to_weight", "motor_tau_s"):
        assert d[key] == getattr(v, key)
    assert d["peak_roll_accel_rad_s2"] == pytest.approx(_roll(v))
    assert d["ixx_kg_m2"] == v.profile().physics.inertia_kg_m2[0][0]


def test_derive_rejects_non_physical_scalars() -> None:
    with pytest.raises(ValueError, match="thrust_to_weight"):
        derive("x", 1.0, 1.0, 0.02)
    with pytest.raises(ValueError, match="mass_kg"):
        derive("x", -1.0, 2.0, 0.02, arm_m=0.2)
    with pytest.raises(ValueError, match="motor_tau_s"):
        derive("x", 1.0, 2.0, float("nan"))
    with pytest.raises(ValueError, match="name"):
        derive("", 1.0, 2.0, 0.02)


# --- The sample ---------------------------------------------------------------------------


def _unit_coordinates(vehicles: list[EnvelopeVehicle]) -> np.ndarray:
    """Each vehicle's position in [0, 1) along the four log-scaled sampled dimensions."""
    cols = []
    for key in ("mass_kg", "thrust_to_weight", "motor_tau_s", "arm_factor"):
        lo, hi = ENVELOPE_BOUNDS[key]
        x = np.array([getattr(v, key) for v in vehicles])
        cols.append(np.log(x / lo) / np.log(hi / lo))
    return np.column_stack(cols)


def test_sample_respects_the_bounds_and_names() -> None:
    assert [v.name for v in SAMPLE] == [f"env-{i:02d}" for i in range(30)]
    for v in SAMPLE:
        for key, (lo, hi) in ENVELOPE_BOUNDS.items():
            value = getattr(v, key)
            assert lo <= value <= hi, (v.name, key, value)
    for v in CORNERS.values():
        for key, (lo, hi) in ENVELOPE_BOUNDS.items():
            value = getattr(v, key)
            assert lo * (1 - 1e-12) <= value <= hi * (1 + 1e-12), (v.name, key, value)


@pytest.mark.parametrize("n", [1, 7, 30])
def test_sample_is_a_latin_hypercube(n: int) -> None:
    u = _unit_coordinates(sample_envelope(n, seed=3))
    assert u.shape == (n, 4)
    for j in range(4):
        assert sorted(np.floor(u[:, j] * n).astype(int).tolist()) == list(range(n)), j


def test_latin_hypercube_takes_a_generator() -> None:
    u = latin_hypercube(12, 3, np.random.default_rng(0))
    assert ((u >= 0.0) & (u < 1.0)).all()
    for j in range(3):
        assert sorted(np.floor(u[:, j] * 12).astype(int).tolist()) == list(range(12))
    np.testing.assert_array_equal(u, latin_hypercube(12, 3, np.random.default_rng(0)))
    with pytest.raises(ValueError):
        latin_hypercube(0, 3, np.random.default_rng(0))


def test_same_seed_same_vehicles_other_seed_others() -> None:
    assert sample_envelope(30, seed=1) == SAMPLE
    other = sample_envelope(30, seed=2)
    assert [v.name for v in other] == [v.name for v in SAMPLE]
    assert all(a != b for a, b in zip(other, SAMPLE, strict=True))


def test_names_widen_past_100() -> None:
    names = [v.name for v in sample_envelope(101, seed=0)]
    assert names[0] == "env-000" and names[-1] == "env-100"


# --- Figure of merit ------------------------------------------------------------------------


def test_peak_angular_accel_matches_the_quad_x_formula() -> None:
    for v in CORNERS.values():
        ph = v.profile().physics
        w_lo = ph.motor_w_idle_rad_s + 0.05 * (ph.motor_w_max_rad_s - ph.motor_w_idle_rad_s)
        dw2 = ph.motor_w_max_rad_s**2 - w_lo**2
        lever = v.arm_m / math.sqrt(2.0)
        ixx, iyy, izz = (ph.inertia_kg_m2[i][i] for i in range(3))
        roll, pitch, yaw = peak_angular_accel_rad_s2(v.profile())
        assert roll == pytest.approx(2 * ph.kf_n_per_rad_s2 * dw2 * lever / ixx, rel=1e-9)
        assert pitch == pytest.approx(2 * ph.kf_n_per_rad_s2 * dw2 * lever / iyy, rel=1e-9)
        assert yaw == pytest.approx(2 * ph.km_m * ph.kf_n_per_rad_s2 * dw2 / izz, rel=1e-9)
        # The approximation of the module docstring: (T/W) g / (2 sqrt 2 c_x L).
        approx = v.thrust_to_weight * GRAVITY_M_S2 * v.mass_kg * v.arm_m / (2 * math.sqrt(2) * ixx)
        assert roll == pytest.approx(approx, rel=0.05)


def test_corners_span_more_than_15x_and_bracket_the_sample() -> None:
    fastest, slowest = _roll(CORNERS["tiny-fast"]), _roll(CORNERS["heavy-weak"])
    corner_rolls = [_roll(v) for v in CORNERS.values()]
    assert max(corner_rolls) == fastest and min(corner_rolls) == slowest
    assert fastest / slowest >= 15.0  # measured 38.8x
    sample_rolls = [_roll(v) for v in SAMPLE]
    assert slowest <= min(sample_rolls) and max(sample_rolls) <= fastest
    # Over the sample alone the span depends on the seed: a 4-D hypercube of 30
    # rarely lands one point in the small, short-arm, T/W-10 corner. Seed 1
    # gives 24x; over seeds 0-199 the median is 13.9x (5th percentile 8.9x).
    assert max(sample_rolls) / min(sample_rolls) >= 15.0
    assert (max(sample_rolls + corner_rolls) / min(sample_rolls + corner_rolls)) >= 15.0


# --- Damage -----------------------------------------------------------------------------------


def _flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(d, dict):
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    return {prefix.rstrip("."): d}


@pytest.mark.parametrize("vehicle", [*CORNERS.values(), SAMPLE[7]], ids=lambda v: v.name)
def test_damage_variants_change_exactly_what_they_say(vehicle: EnvelopeVehicle) -> None:
    base = vehicle.profile()
    variants = damage_variants(vehicle)
    assert set(variants) == {"motor60", "imbalance", "cg10"}
    flat_base = _flatten(base.model_dump(mode="json"))
    for key, prof in variants.items():
        assert prof.name == f"{vehicle.name}+{key}"
        flat = _flatten(prof.model_dump(mode="json"))
        changed = {k for k in flat if flat[k] != flat_base[k]}
        assert changed <= {"name"} | {k for k in flat if k.startswith("physics.damage.")}

    dmg = variants["motor60"].physics.damage
    assert len(dmg.motors) == 1 and dmg.cg_offset_frd_m == (0.0, 0.0, 0.0)
    m = dmg.motors[0]
    assert (m.motor, m.thrust_efficiency, m.torque_efficiency, m.imbalance_n) == (0, 0.6, 0.6, 0)
    assert m.fail_at_s is None

    dmg = variants["imbalance"].physics.damage
    assert len(dmg.motors) == 1 and dmg.cg_offset_frd_m == (0.0, 0.0, 0.0)
    m = dmg.motors[0]
    assert (m.motor, m.thrust_efficiency, m.torque_efficiency) == (0, 1.0, 1.0)
    assert m.imbalance_n == pytest.approx(0.3 * vehicle.max_motor_thrust_n)
    assert m.imbalance_n == pytest.approx(
        0.3 * base.physics.kf_n_per_rad_s2 * base.physics.motor_w_max_rad_s**2
    )

    dmg = variants["cg10"].physics.damage
    assert dmg.motors == []
    cg = np.array(dmg.cg_offset_frd_m)
    assert np.linalg.norm(cg) == pytest.approx(0.1 * vehicle.arm_m)
    np.testing.assert_allclose(cg, 0.1 * np.array((*base.frame.motors[0].position_frd_m[:2], 0.0)))


def test_damage_lowers_the_two_way_authority() -> None:
    v = CORNERS["mid"]
    intact = peak_angular_accel_rad_s2(v.profile())
    variants = damage_variants(v)
    weak = peak_angular_accel_rad_s2(variants["motor60"])
    assert all(w < i for w, i in zip(weak, intact, strict=True))
    assert peak_angular_accel_rad_s2(variants["imbalance"]) == pytest.approx(intact)
    # Motor 0 is front right: the CG moved towards it shortens its lever.
    cg = peak_angular_accel_rad_s2(variants["cg10"])
    assert cg[0] < intact[0] and cg[1] < intact[1]


# --- Closed loop ------------------------------------------------------------------------------


_HEAVY_WEAK_DAMAGED = list(damage_variants(CORNERS["heavy-weak"]).values())


@pytest.mark.parametrize(
    "profile",
    [v.profile() for v in CORNERS.values()] + _HEAVY_WEAK_DAMAGED,
    ids=lambda p: p.name,
)
def test_px4_default_pid_hovers_every_corner(profile: VehicleProfile) -> None:
    scenario = load_scenario("hover-gusts").model_copy(update={"duration_s": 6.0})
    rec = simulate_flight(profile, load_controller(PID_DEFAULT_CONTROLLER), scenario)
    assert not rec.meta["crashed"]
    cols = rec.columns
    assert cols["altitude_m"][-1] > 8.0  # climbed to the pilot's 10 m hold
    assert np.degrees(np.abs(cols["euler_rad"][:, :2])).max() < 20.0


# --- CLI --------------------------------------------------------------------------------------


def test_cli_writes_profiles_and_figures(tmp_path: Path) -> None:
    out = tmp_path / "env"
    args = ["envelope", "--n", "3", "--seed", "1", "--out", str(out), "--corners"]
    result = CliRunner().invoke(cli, args, catch_exceptions=False)
    assert result.exit_code == 0, result.output
    figures = json.loads((out / "envelope.json").read_text(encoding="utf-8"))
    names = [f["name"] for f in figures]
    assert names == ["env-00", "env-01", "env-02", *CORNERS]
    for fig in figures:
        prof = load_profile(out / f"{fig['name']}.yaml")
        assert prof.physics.mass_kg == fig["mass_kg"]
    assert load_profile(out / "env-00.yaml") == sample_envelope(3, seed=1)[0].profile()


def test_cli_refuses_an_empty_envelope(tmp_path: Path) -> None:
    result = CliRunner().invoke(cli, ["envelope", "--n", "0", "--out", str(tmp_path)])
    assert result.exit_code == 2
