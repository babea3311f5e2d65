"""Every vehicle profile loads and is physically plausible; bad ones are rejected."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from companion.errors import ConfigError
from companion.profile import load_profile
from sitl.rotors import hover_motor_command
from sitl.vehicle_params import VehicleParams

PROFILE_DIR = Path(__file__).resolve().parents[2] / "vehicle_profiles"
PROFILE_FILES = sorted(PROFILE_DIR.glob("*.yaml"))


def test_the_expected_profiles_exist() -> None:
    names = {p.name for p in PROFILE_FILES}
    assert {"f450.yaml", "f450_cut_props.yaml", "tarot650.yaml", "x500.yaml"} <= names


@pytest.mark.parametrize("path", PROFILE_FILES, ids=lambda p: p.name)
def test_profile_loads_and_is_flyable(path: Path) -> None:
    prof = load_profile(path)
    assert 1.8 <= prof.thrust_to_weight() <= 3.0
    P = VehicleParams.from_profile(prof)  # damaged inertia still positive definite
    eff_tw = prof.thrust_to_weight() * min(P.thrust_coeff) / prof.physics.kf_n_per_rad_s2
    assert eff_tw > 1.3
    assert 0.2 < hover_motor_command(prof) < 0.85  # room left to manoeuvre


QUAD_X_FILES = [p for p in PROFILE_FILES if load_profile(p).frame.layout == "quad_x"]


def test_every_bundled_profile_is_a_quad_x() -> None:
    # The next test checks the PX4 quad-X order on these; a new layout needs its own.
    assert QUAD_X_FILES == PROFILE_FILES


@pytest.mark.parametrize("path", QUAD_X_FILES, ids=lambda p: p.name)
def test_px4_quad_x_motor_order(path: Path) -> None:
    prof = load_profile(path)
    # 1 front-right CCW, 2 rear-left CCW, 3 front-left CW, 4 rear-right CW.
    expected = [((1, 1), "ccw"), ((-1, -1), "ccw"), ((1, -1), "cw"), ((-1, 1), "cw")]
    for motor, ((sx, sy), spin) in zip(prof.frame.motors, expected, strict=True):
        x, y, _ = motor.position_frd_m
        assert np.sign(x) == sx and np.sign(y) == sy and motor.spin == spin


@pytest.mark.parametrize("path", PROFILE_FILES, ids=lambda p: p.name)
def test_every_physics_number_says_where_it_comes_from(path: Path) -> None:
    # A number directly under physics: must carry a comment: its source or "estimate".
    section = ""
    for line in path.read_text().splitlines():
        top = re.match(r"^([a-z_]+):", line)
        if top:
            section = top.group(1)
        elif section == "physics" and re.match(r"^  [a-z_]+: *[-0-9.\[]", line):
            assert "#" in line, f"{path.name}: no source comment on {line.strip()!r}"


def test_cut_props_are_weaker_and_unbalanced() -> None:
    cut = load_profile(PROFILE_DIR / "f450_cut_props.yaml")
    damage = cut.physics.damage.motors
    assert sorted(d.motor for d in damage) == [0, 1, 2, 3]
    for d in damage:
        assert 0.6 <= d.thrust_efficiency <= 0.7
        assert d.torque_efficiency < d.thrust_efficiency
        assert d.imbalance_n > 0.0


def test_tarot_has_a_lateral_cg_offset_and_inertia_change() -> None:
    tarot = load_profile(PROFILE_DIR / "tarot650.yaml")
    d = tarot.physics.damage
    assert 0.01 <= abs(d.cg_offset_frd_m[1]) <= 0.05
    assert np.any(np.array(d.inertia_delta_kg_m2) != 0.0)
    assert 2.5 <= tarot.physics.mass_kg <= 3.5


# ------------------------------------------------------------------- bad profiles


def good_data() -> dict[str, Any]:
    data = yaml.safe_load((PROFILE_DIR / "f450.yaml").read_text())
    assert isinstance(data, dict)
    return data


def _unknown_key(d: dict[str, Any]) -> None:
    d["physics"]["mass_kgs"] = 1.0


def _missing_key(d: dict[str, Any]) -> None:
    del d["physics"]["kf_n_per_rad_s2"]


def _negative_mass(d: dict[str, Any]) -> None:
    d["physics"]["mass_kg"] = -1.5


def _singular_inertia(d: dict[str, Any]) -> None:
    d["physics"]["inertia_kg_m2"] = [[0.02, 0.0, 0.0], [0.0, 0.02, 0.0], [0.0, 0.0, 0.0]]


def _zero_motors(d: dict[str, Any]) -> None:
    d["frame"]["motors"] = []


def _wrong_type(d: dict[str, Any]) -> None:
    d["physics"]["motor_tau_up_s"] = "fast"


def _bad_damage_index(d: dict[str, Any]) -> None:
    d["physics"]["damage"] = {"motors": [{"motor": 7, "thrust_efficiency": 0.5}]}


@pytest.mark.parametrize(
    ("mutate", "key_path"),
    [
        (_unknown_key, "physics.mass_kgs"),
        (_missing_key, "physics.kf_n_per_rad_s2"),
        (_negative_mass, "physics.mass_kg"),
        (_singular_inertia, "physics.inertia_kg_m2"),
        (_zero_motors, "frame.motors"),
        (_wrong_type, "physics.motor_tau_up_s"),
        (_bad_damage_index, "physics.damage.motors"),
    ],
    ids=lambda v: getattr(v, "__name__", v),
)
def test_bad_profile_names_file_and_key(tmp_path: Path, mutate: Any, key_path: str) -> None:
    data = good_data()
    mutate(data)
    path = tmp_path / "bad_vehicle.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as info:
        load_profile(path)
    msg = str(info.value)
    assert "bad_vehicle.yaml" in msg
    assert key_path in msg


def test_good_data_round_trips(tmp_path: Path) -> None:
    # Guards the test above: the unmodified data must load.
    path = tmp_path / "good.yaml"
    path.write_text(yaml.safe_dump(good_data()))
    assert load_profile(path).n_motors == 4
