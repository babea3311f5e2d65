"""Profiles that cannot hurt: wrong units and inconsistent physics are refused by
magnitude, naming the field and the likely mistake; doubts are warnings.

Each mistake below (wrong units, inconsistent physics) is written to a real
YAML file and loaded; the shipped profiles and every vehicle the envelope
generator makes (corners, a seeded sample, damage variants) still load clean.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml
from click.testing import CliRunner

from companion.cli import cli as companion_cli
from companion.errors import ConfigError
from companion.profile import (
    GYRO_RANGE_MIN_DEG_S,
    INERTIA_RANGE_PER_M_ARM2,
    INERTIA_TYPICAL_PER_M_ARM2,
    KF_RANGE_N_PER_RAD_S2,
    RATE_LIMIT_MAX_DEG_S,
    RATE_LIMIT_MIN_DEG_S,
    VehicleProfile,
    load_profile,
    profile_warnings,
)
from sitl.envelope import (
    AIR_DENSITY_KG_M3,
    corners,
    damage_variants,
    sample_envelope,
    write_profile_yaml,
)
from sitl.lab.envelope_setup import envelope_cases

ROOT = Path(__file__).resolve().parents[1]
PROFILE_DIR = ROOT / "vehicle_profiles"
PROFILE_FILES = sorted(PROFILE_DIR.glob("*.yaml"))
F450 = PROFILE_DIR / "f450.yaml"
EXIT_BAD_INPUT = 2

Data = dict[str, Any]


def f450_data() -> Data:
    data = yaml.safe_load(F450.read_text(encoding="utf-8"))
    assert isinstance(data, dict)
    return data


def write(tmp_path: Path, data: Data, name: str = "vehicle.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def refused(path: Path, key_path: str, *words: str) -> str:
    """``load_profile(path)`` raises a ConfigError naming the file, with a problem
    line starting at ``key_path`` that says each of ``words``; returns that line."""
    with pytest.raises(ConfigError) as info:
        load_profile(path)
    assert info.value.path == str(path)
    assert str(path) in str(info.value)
    lines = [p for p in info.value.problems if p.startswith(f"{key_path}:")]
    assert lines, info.value.problems
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


def set_physics(**kv: Any) -> Callable[[Data], None]:
    return lambda d: d["physics"].update(kv)


def set_positions(*xyz: tuple[float, float, float]) -> Callable[[Data], None]:
    def mutate(d: Data) -> None:
        for m, p in zip(d["frame"]["motors"], xyz, strict=True):
            m["position_frd_m"] = list(p)

    return mutate


def scale_positions(factor: float) -> Callable[[Data], None]:
    def mutate(d: Data) -> None:
        for m in d["frame"]["motors"]:
            m["position_frd_m"] = [factor * x for x in m["position_frd_m"]]

    return mutate


def _hexa(d: Data) -> None:
    # Six motors (a hexacopter's) still labelled quad_x.
    r = 0.225
    d["frame"]["motors"] = [
        {
            "position_frd_m": [r * math.cos(math.radians(a)), r * math.sin(math.radians(a)), 0.0],
            "spin": "cw" if i % 2 else "ccw",
        }
        for i, a in enumerate(range(0, 360, 60))
    ]


def _adjacent_spins(d: Data) -> None:
    # PX4 quad-X order: 0 front-right, 1 rear-left, 2 front-left, 3 rear-right.
    # Both front motors CCW: yaw and pitch share one column of the mixer.
    for m, spin in zip(d["frame"]["motors"], ["ccw", "cw", "ccw", "cw"], strict=True):
        m["spin"] = spin


def _rates_in_rad_s(d: Data) -> None:
    d["limits"]["rate_max_deg_s"] = [round(math.radians(x), 3) for x in (1080, 1080, 720)]


def _gyro_range_in_rad_s(d: Data) -> None:
    d["physics"]["imu"]["gyro_range_deg_s"] = round(math.radians(2000.0), 2)


def _inertia_times(k: float) -> Callable[[Data], None]:
    def mutate(d: Data) -> None:
        d["physics"]["inertia_kg_m2"] = [
            [k * x for x in row] for row in d["physics"]["inertia_kg_m2"]
        ]

    return mutate


PLUS = ((0.225, 0.0, 0.0), (0.0, 0.225, 0.0), (-0.225, 0.0, 0.0), (0.0, -0.225, 0.0))

MISTAKES: list[tuple[str, Callable[[Data], None], str, tuple[str, ...]]] = [
    # The required cases, each named by the check: rates and gyro range in rad/s,
    # positions in mm, an absurd kf, a quad-X with six motors.
    ("rates-in-rad-s", _rates_in_rad_s, "limits.rate_max_deg_s", ("18.85 looks like rad/s",)),
    ("gyro-range-in-rad-s", _gyro_range_in_rad_s, "physics.imu.gyro_range_deg_s", ("rad/s",)),
    ("positions-in-mm", scale_positions(1000.0), "frame.motors.0.position_frd_m", ("millimetres",)),
    ("kf-1e9", set_physics(kf_n_per_rad_s2=1e9), "physics.kf_n_per_rad_s2", ("no propeller",)),
    ("quad-x-with-6-motors", _hexa, "frame.layout", ("6 motors", "quad_x has 4")),
    # Other units by magnitude.
    ("positions-in-cm", scale_positions(100.0), "frame.motors.3.position_frd_m", ("centimetres",)),
    ("kf-per-rpm2", set_physics(kf_n_per_rad_s2=1e-11), "physics.kf_n_per_rad_s2", ("rpm^2",)),
    ("mass-in-grams", set_physics(mass_kg=1500), "physics.mass_kg", ("grams", "1.5 kg")),
    ("km-in-mm", set_physics(km_m=16.6), "physics.km_m", ("millimetres",)),
    ("w-max-in-rpm", set_physics(motor_w_max_rad_s=30000.0), "physics.motor_w_max_rad_s", ("rpm",)),
    (
        "w-max-in-rev-s",
        set_physics(motor_w_max_rad_s=25.0),
        "physics.motor_w_max_rad_s",
        ("rev/s",),
    ),
    # Consistency across fields.
    (
        "thrust-to-weight-of-rpm",  # the F450's 7162 rpm: in range alone, 91x the thrust
        set_physics(motor_w_max_rad_s=7162.0),
        "physics",
        ("thrust-to-weight 234", "motor_w_max_rad_s", "kf_n_per_rad_s2", "mass_kg"),
    ),
    ("inertia-in-g-m2", _inertia_times(1000.0), "physics.inertia_kg_m2", ("Ixx", "g m^2")),
    ("inertia-point-mass", _inertia_times(1e-3), "physics.inertia_kg_m2", ("Ixx", "0.0025 to 4")),
    ("quad-x-as-plus", set_positions(*PLUS), "frame.layout", ("not a quad_x", "quadrant")),
    ("quad-x-adjacent-spins", _adjacent_spins, "frame.layout", ("spin the same way",)),
]


@pytest.mark.parametrize(
    ("mutate", "key_path", "words"),
    [m[1:] for m in MISTAKES],
    ids=[m[0] for m in MISTAKES],
)
def test_a_mistake_is_refused_naming_the_field(
    tmp_path: Path, mutate: Callable[[Data], None], key_path: str, words: tuple[str, ...]
) -> None:
    data = f450_data()
    mutate(data)
    refused(write(tmp_path, data), key_path, *words)


@pytest.mark.parametrize(
    ("line", "key_path"),
    [
        ("  mass_kg: 1.5 ", "physics.mass_kg"),
        ("    latency_s: 0.0", "physics.imu.latency_s"),
        ("  motor_idle: 0.05", "limits.motor_idle"),
    ],
    ids=["mass", "imu-latency", "motor-idle"],
)
@pytest.mark.parametrize("boolean", ["true", "yes", "on", "false"])
def test_a_boolean_is_not_a_number(tmp_path: Path, line: str, key_path: str, boolean: str) -> None:
    # YAML reads true, yes and on as True; pydantic would then read True as 1.0.
    text = F450.read_text(encoding="utf-8")
    assert line in text
    path = tmp_path / "vehicle.yaml"
    key = line.split(":")[0]
    path.write_text(text.replace(line, f"{key}: {boolean} ", 1), encoding="utf-8")
    refused(path, key_path, "not a boolean")


def test_a_boolean_in_a_vector_or_an_index_is_refused(tmp_path: Path) -> None:
    data = f450_data()
    data["limits"]["rate_max_deg_s"] = [1080.0, True, 720.0]
    refused(write(tmp_path, data), "limits.rate_max_deg_s.1", "not a boolean")
    data = f450_data()
    data["physics"]["damage"] = {"motors": [{"motor": True, "thrust_efficiency": 0.5}]}
    refused(write(tmp_path, data), "physics.damage.motors.0.motor", "not a boolean")


@pytest.mark.parametrize(
    ("line", "quoted", "key_path"),
    [
        ("  mass_kg: 1.5 ", '  mass_kg: "1.5" ', "physics.mass_kg"),
        ("  kf_n_per_rad_s2: 1.68e-5", "  kf_n_per_rad_s2: '1.68e-5'", "physics.kf_n_per_rad_s2"),
        (
            "rate_max_deg_s: [1080.0, 1080.0, 720.0]",
            'rate_max_deg_s: [1080.0, "1080", 720.0]',
            "limits.rate_max_deg_s.1",
        ),
        (
            "    - {position_frd_m: [0.159,",
            "    - {position_frd_m: ['0.159',",
            "frame.motors.0.position_frd_m.0",
        ),
    ],
    ids=["mass", "kf", "vector-element", "motor-position"],
)
def test_a_quoted_number_is_not_a_number(
    tmp_path: Path, line: str, quoted: str, key_path: str
) -> None:
    # YAML reads a quoted number as text; pydantic would then read "1.5" as 1.5.
    text = F450.read_text(encoding="utf-8")
    assert line in text
    path = tmp_path / "vehicle.yaml"
    path.write_text(text.replace(line, quoted, 1), encoding="utf-8")
    refused(path, key_path, "expected a number, not text", "write 1.5")


def test_check_config_refuses_a_quoted_mass(tmp_path: Path) -> None:
    text = F450.read_text(encoding="utf-8")
    path = tmp_path / "vehicle.yaml"
    path.write_text(text.replace("  mass_kg: 1.5 ", '  mass_kg: "1.5" ', 1), encoding="utf-8")
    res = CliRunner().invoke(companion_cli, ["check-config", "--profile", str(path)])
    assert res.exit_code == EXIT_BAD_INPUT, (res.exit_code, res.output, res.exception)
    assert "Traceback" not in res.output
    assert str(path) in res.output
    assert "physics.mass_kg: expected a number, not text" in res.output
    assert "got '1.5'" in res.output


def test_ints_and_yaml_1_2_exponents_pass_as_floats(tmp_path: Path) -> None:
    text = F450.read_text(encoding="utf-8")
    # mass_kg: 2 is an int; 168e-7 (no dot) is a number in YAML 1.2, text to YAML 1.1.
    text = text.replace("mass_kg: 1.5 ", "mass_kg: 2 ", 1)
    text = text.replace("kf_n_per_rad_s2: 1.68e-5", "kf_n_per_rad_s2: 168e-7", 1)
    path = tmp_path / "vehicle.yaml"
    path.write_text(text, encoding="utf-8")
    prof = load_profile(path, simulated=True)
    assert prof.physics.mass_kg == 2.0 and isinstance(prof.physics.mass_kg, float)
    assert prof.physics.kf_n_per_rad_s2 == pytest.approx(1.68e-5)


def test_every_rate_limit_written_in_rad_s_is_below_the_floor() -> None:
    # The bound is what makes a rad/s value an error: the largest allowed limit,
    # written in rad/s, is still below it; so is the widest gyro's range.
    assert math.radians(RATE_LIMIT_MAX_DEG_S) < RATE_LIMIT_MIN_DEG_S
    assert math.radians(4000.0) < GYRO_RANGE_MIN_DEG_S


def test_the_kf_bounds_hold_every_prop_from_1_6_to_60_inches() -> None:
    # kf = C_T rho pi r^4, C_T 0.01-0.03 (the F450's 0.0168 between).
    lo, hi = KF_RANGE_N_PER_RAD_S2
    for c_t in (0.01, 0.03):
        for r in (0.02, 0.75):
            assert lo < c_t * AIR_DENSITY_KG_M3 * math.pi * r**4 < hi


def test_a_refusal_lists_every_problem_of_the_file(tmp_path: Path) -> None:
    data = f450_data()
    _rates_in_rad_s(data)
    data["physics"]["mass_kg"] = True
    with pytest.raises(ConfigError) as info:
        load_profile(write(tmp_path, data))
    keys = {p.split(":")[0] for p in info.value.problems}
    assert {"limits.rate_max_deg_s", "physics.mass_kg"} <= keys


# ----------------------------------------------------------------- what still loads


SIMULATORS_OWN = {"arducopter_sitl_quad.yaml"}
"""Profiles that copy a simulator's own vehicle, numbers and all: ArduPilot SITL's
quad computes its inertia for the motors at half the distance it places them
(SIM_Frame.cpp), 0.06 m L^2, inside the warning band but not comfortably."""


@pytest.mark.parametrize("path", PROFILE_FILES, ids=lambda p: p.name)
def test_shipped_profiles_load_clean(path: Path) -> None:
    prof = load_profile(path, simulated=True)
    assert profile_warnings(prof) == []
    if path.name in SIMULATORS_OWN:
        return
    lo, hi = INERTIA_TYPICAL_PER_M_ARM2
    m_l2 = prof.physics.mass_kg * prof.mean_arm_m() ** 2
    for i in range(3):  # comfortably inside: the warning band, not just the error one
        assert 2 * lo < prof.physics.inertia_kg_m2[i][i] / m_l2 < hi / 2


def envelope_vehicles() -> list[VehicleProfile]:
    """Every corner and a seeded sample, intact and with each damage variant."""
    vehicles = [*corners(), *sample_envelope(40, seed=7)]
    out = []
    for v in vehicles:
        out.append(v.profile())
        out.extend(damage_variants(v).values())
    return out


def test_every_envelope_vehicle_is_valid_and_unsurprising() -> None:
    profiles = envelope_vehicles()
    assert len(profiles) == 4 * 45
    lo, hi = INERTIA_RANGE_PER_M_ARM2
    for prof in profiles:
        assert profile_warnings(prof) == [], prof.name
        m_l2 = prof.physics.mass_kg * prof.mean_arm_m() ** 2
        for i in range(3):  # tenfold inside the error bounds
            assert 10 * lo < prof.physics.inertia_kg_m2[i][i] / m_l2 < hi / 5


def test_the_campaign_cases_build() -> None:
    cases = envelope_cases(n=30, seed=1)
    assert len(cases) == 35 + 3 * 8


def test_envelope_corners_round_trip_through_yaml(tmp_path: Path) -> None:
    for v in corners():
        path = tmp_path / f"{v.name}.yaml"
        write_profile_yaml(v.profile(), path)
        assert load_profile(path, simulated=True) == v.profile()


def test_other_layouts_load(tmp_path: Path) -> None:
    data = f450_data()
    set_positions(*PLUS)(data)
    data["frame"]["layout"] = "quad_plus"
    for m, spin in zip(data["frame"]["motors"], ["cw", "ccw", "cw", "ccw"], strict=True):
        m["spin"] = spin  # front and back CW, right and left CCW
    assert load_profile(write(tmp_path, data)).frame.layout == "quad_plus"
    data = f450_data()
    _hexa(data)
    data["frame"]["layout"] = "custom"
    assert load_profile(write(tmp_path, data)).n_motors == 6
    # A quad_plus with X geometry contradicts its name.
    data = f450_data()
    data["frame"]["layout"] = "quad_plus"
    refused(write(tmp_path, data), "frame.layout", "not a quad_plus", "half-axis")


# ------------------------------------------------------------------------ warnings


def warned(data: Data, tmp_path: Path, *words: str) -> None:
    """``data`` loads, and one warning says each of ``words``."""
    warnings = profile_warnings(load_profile(write(tmp_path, data)))
    assert any(all(w in line for w in words) for line in warnings), warnings


def test_a_vehicle_that_cannot_hover_is_a_warning_and_an_error_only_to_the_simulator(
    tmp_path: Path,
) -> None:
    # Placeholder physics (tests/test_bad_input.py's 90 kg F450): the companion
    # never reads them, so they load; check-config can say why the SITL would not.
    data = f450_data()
    data["physics"]["mass_kg"] = 90.0
    warned(data, tmp_path, "physics: cannot hover")
    warned(data, tmp_path, "physics.inertia_kg_m2", "Ixx")
    with pytest.raises(ConfigError, match="cannot hover"):
        load_profile(write(tmp_path, data), simulated=True)


@pytest.mark.parametrize(
    ("mutate", "words"),
    [
        (set_physics(motor_w_max_rad_s=550.0), ("physics: thrust-to-weight 1.38", "steer")),
        (set_physics(motor_w_max_rad_s=2000.0), ("physics: thrust-to-weight 18.3", "racing")),
        (_inertia_times(0.1), ("physics.inertia_kg_m2", "Ixx is 0.0278 m L^2")),
        (set_physics(km_m=1e-9), ("physics.km_m", "yaw")),
        (
            lambda d: d["physics"]["imu"].update(gyro_range_deg_s=500.0),
            ("limits.rate_max_deg_s", "1080 deg/s", "gyro_range_deg_s"),
        ),
    ],
    ids=["low-thrust-to-weight", "high-thrust-to-weight", "light-inertia", "no-km", "gyro-range"],
)
def test_doubts_are_warnings(
    tmp_path: Path, mutate: Callable[[Data], None], words: tuple[str, ...]
) -> None:
    data = f450_data()
    mutate(data)
    warned(data, tmp_path, *words)


# ------------------------------------------------------------------ the command line


def test_check_config_refuses_a_profile_in_the_wrong_units(tmp_path: Path) -> None:
    data = f450_data()
    _rates_in_rad_s(data)
    path = write(tmp_path, data, "bad_vehicle.yaml")
    res = CliRunner().invoke(companion_cli, ["check-config", "--profile", str(path)])
    assert res.exit_code == EXIT_BAD_INPUT, (res.exit_code, res.output, res.exception)
    assert "Traceback" not in res.output
    assert str(path) in res.output
    assert "limits.rate_max_deg_s: 18.85 looks like rad/s (1080 deg/s)" in res.output


def test_check_config_prints_the_profiles_doubts_and_still_passes(tmp_path: Path) -> None:
    data = f450_data()
    set_physics(km_m=1e-9)(data)
    path = write(tmp_path, data)
    result = CliRunner().invoke(companion_cli, ["check-config", "--profile", str(path)])
    assert result.exit_code == 0, result.output
    assert f"warning: {path}: physics.km_m" in result.stderr
