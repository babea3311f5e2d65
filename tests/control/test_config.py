"""Controller files: Table I, validation errors, and building the laws from them."""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml
from click.testing import CliRunner
from pydantic import BaseModel

from companion.cli import cli as companion_cli
from companion.config import (
    DEFAULT_CONTROLLER,
    PID_DEFAULT_CONTROLLER,
    AlphaAdaptConfig,
    MfcAxisConfig,
    MfcConfig,
    PidAxisConfig,
    PidConfig,
    build_controller,
    build_stick_map,
    load_controller,
    mfc_gains,
    pid_gains,
)
from companion.control import (
    AlphaAdaptation,
    MfcAxisGains,
    MfcController,
    MfcGains,
    PidAxisGains,
    PidController,
    StickMap,
)
from companion.errors import ConfigError
from tests.control.plants import f450_mixer, f450_profile

TABLE1 = DEFAULT_CONTROLLER.parent / "mfc_table1.yaml"
CONTROLLER_FILES = sorted(DEFAULT_CONTROLLER.parent.glob("*.yaml"))
EXIT_BAD_INPUT = 2


def test_table_1_file_holds_the_papers_values() -> None:
    cfg = load_controller(TABLE1)
    assert isinstance(cfg, MfcConfig)
    assert cfg.kind == "mfc"
    roll, pitch, yaw = cfg.axes.roll, cfg.axes.pitch, cfg.axes.yaw
    assert (roll.order, roll.alpha, roll.window_s, roll.kp, roll.kd) == (2, 1.0, 0.02, 3.0, 0.096)
    assert (pitch.order, pitch.alpha, pitch.window_s, pitch.kp, pitch.kd) == (
        2,
        1.0,
        0.02,
        2.7,
        0.096,
    )
    assert (yaw.order, yaw.alpha, yaw.window_s, yaw.kp) == (1, 1.0, 0.02, 2.7)
    assert cfg.command_full_scale_us == 500.0


def test_pid_default_file_loads() -> None:
    cfg = load_controller(PID_DEFAULT_CONTROLLER)
    assert isinstance(cfg, PidConfig)
    gains = pid_gains(cfg)
    # PX4's MC_ROLLRATE_P/I/D, MC_PITCHRATE_*, MC_YAWRATE_P/I and MC_*R_INT_LIM defaults.
    assert (gains.roll.kp, gains.roll.ki, gains.roll.kd, gains.roll.i_limit) == (
        0.15, 0.2, 0.003, 0.3,
    )  # fmt: skip
    assert gains.pitch == gains.roll
    assert (gains.yaw.kp, gains.yaw.ki, gains.yaw.kd, gains.yaw.i_limit) == (0.2, 0.1, 0.0, 0.3)


def test_default_sticks() -> None:
    assert build_stick_map(load_controller()) == StickMap()


def test_build_controller_uses_the_profile_geometry() -> None:
    profile = f450_profile()
    expected = f450_mixer()
    mfc = build_controller(load_controller(TABLE1), profile)
    assert isinstance(mfc, MfcController)
    assert mfc.gains == mfc_gains(load_controller(TABLE1))
    assert isinstance(build_controller(load_controller(DEFAULT_CONTROLLER), profile), MfcController)
    pid = build_controller(load_controller(PID_DEFAULT_CONTROLLER), profile)
    assert isinstance(pid, PidController)
    for ctrl in (mfc, pid):
        assert ctrl.mixer.factors() == expected.factors()
        assert ctrl.mixer.idle == profile.limits.motor_idle == 0.05
        # And it runs.
        out = ctrl.update(0.004, (0.0, 0.0, 0.0), (0.1, 0.0, 0.0), 0.5)
        assert len(out.motors) == 4 and not out.held


# ---------------------------------------------------------------------------
# Bad files: ConfigError naming the file and the dotted key path.


def _default_raw() -> dict[str, Any]:
    raw = yaml.safe_load(DEFAULT_CONTROLLER.read_text(encoding="utf-8"))
    assert isinstance(raw, dict)
    return raw


def _set(path: str, value: Any) -> Callable[[dict[str, Any]], None]:
    def f(raw: dict[str, Any]) -> None:
        *parents, last = path.split(".")
        node = raw
        for p in parents:
            node = node[p]
        node[last] = value

    return f


def _delete(path: str) -> Callable[[dict[str, Any]], None]:
    def f(raw: dict[str, Any]) -> None:
        *parents, last = path.split(".")
        node = raw
        for p in parents:
            node = node[p]
        del node[last]

    return f


@pytest.mark.parametrize(
    ("mutate", "key_path"),
    [
        pytest.param(_set("axes.roll.foo", 1.0), "axes.roll.foo", id="unknown-key"),
        pytest.param(_set("gain_scheduling", True), "gain_scheduling", id="unknown-top-key"),
        pytest.param(_delete("axes.roll.kp"), "axes.roll.kp", id="missing-key"),
        pytest.param(_delete("axes.yaw"), "axes.yaw", id="missing-axis"),
        pytest.param(_set("axes.pitch.kd", "fast"), "axes.pitch.kd", id="wrong-type"),
        pytest.param(_set("axes.yaw.order", 3), "axes.yaw.order", id="bad-order"),
        pytest.param(_delete("kind"), "kind", id="kind-missing"),
        pytest.param(_set("kind", "lqr"), "kind", id="kind-unknown"),
        pytest.param(_set("axes.roll.alpha", 0.0), "axes.roll.alpha", id="alpha-zero"),
        pytest.param(_set("axes.roll.window_s", -0.02), "axes.roll.window_s", id="negative-window"),
        pytest.param(_set("dt_max_s", -1.0), "dt_max_s", id="negative-dt"),
        pytest.param(
            _set("axes.roll.alpha_adapt.margin_min", 0.5),
            "axes.roll.alpha_adapt",
            id="margin-min-above-margin",
        ),
        pytest.param(
            _set("axes.roll.alpha_adapt.margin_min", -0.1),
            "axes.roll.alpha_adapt.margin_min",
            id="negative-margin-min",
        ),
        pytest.param(
            _set("axes.roll.actuator_tau_s", 0.0), "axes.roll", id="margin-min-without-lag"
        ),
        pytest.param(
            _set("axes.roll.lag_scaling_max", 0.8),
            "axes.roll.lag_scaling_max",
            id="lag-scaling-max-below-one",
        ),
        pytest.param(
            _set("axes.roll.lag_scaling_min", 1.5),
            "axes.roll.lag_scaling_min",
            id="lag-scaling-min-above-one",
        ),
        # Each value in its range, the combination (or the sign) dangerous in flight:
        # the fields a seeded campaign found crashing or blowing up (config fuzz).
        pytest.param(_set("axes.roll.alpha", -1.0), "axes.roll.alpha", id="alpha-negative"),
        pytest.param(_set("axes.roll.kd", True), "axes.roll.kd: expected a number", id="bool-kd"),
        pytest.param(
            _set("axes.yaw.alpha_adapt.tau_candidates_s", [0.01, True]),
            "axes.yaw.alpha_adapt.tau_candidates_s.1: expected a number",
            id="bool-in-a-list",
        ),
        pytest.param(
            _set("axes.pitch.alpha_adapt.alpha_min", 2.07), "axes.pitch", id="alpha-below-adapt"
        ),
        pytest.param(
            _set("command_full_scale_us", 0.51), "command_full_scale_us", id="full-scale-tiny"
        ),
        pytest.param(
            _set("axes.roll.output_limit_us", 0.0065),
            "axes.roll.output_limit_us",
            id="output-limit-tiny",
        ),
        pytest.param(
            _set("axes.roll.alpha_adapt.min_response_rad_s2", 470.0),
            "axes.roll.alpha_adapt.min_response_rad_s2",
            id="min-response-huge",
        ),
    ],
)
def test_bad_controller_file_names_file_and_key(
    tmp_path: Path, mutate: Callable[[dict[str, Any]], None], key_path: str
) -> None:
    raw = copy.deepcopy(_default_raw())
    mutate(raw)
    path = tmp_path / "bad_controller.yaml"
    path.write_text(yaml.safe_dump(raw), encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_controller(path)
    msg = str(info.value)
    assert str(path) in msg
    assert key_path in msg, f"{key_path!r} not named in:\n{msg}"
    assert isinstance(info.value, ValueError)


# ---------------------------------------------------------------------------
# Units: a number of the wrong unit or a quoted number is refused, naming the key.


def _write(tmp_path: Path, raw: dict[str, Any], name: str = "controller.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(raw, sort_keys=False), encoding="utf-8")
    return path


def _problem(path: Path, key_path: str) -> str:
    """The problem line ``load_controller(path)`` refuses ``key_path`` with."""
    with pytest.raises(ConfigError) as info:
        load_controller(path)
    assert info.value.path == str(path)
    lines = [p for p in info.value.problems if p.startswith(f"{key_path}:")]
    assert lines, info.value.problems
    return lines[0]


@pytest.mark.parametrize("path", CONTROLLER_FILES, ids=lambda p: p.name)
@pytest.mark.parametrize("axis", ["roll", "pitch", "yaw"])
def test_a_stick_rate_in_rad_s_is_refused_naming_the_unit(
    tmp_path: Path, path: Path, axis: str
) -> None:
    # 12.6 rad/s is the 722 deg/s meant; as deg/s, far below any flyable acro rate.
    raw = yaml.safe_load(path.read_text(encoding="utf-8"))
    raw.setdefault("sticks", {}).setdefault(axis, {})["max_deg_s"] = 12.6
    line = _problem(_write(tmp_path, raw), f"sticks.{axis}.max_deg_s")
    assert "12.6 looks like rad/s (721.9 deg/s)" in line
    assert "expected a rate at full stick in [35, 2000] deg/s" in line


@pytest.mark.parametrize(
    ("value", "words"),
    [
        (34.0, ("34 looks like rad/s",)),
        (0.0, ("expected a rate at full stick in [35, 2000] deg/s",)),
        (2001.0, ("expected a rate at full stick in [35, 2000] deg/s",)),
        ("720", ("expected a number, not text",)),
    ],
)
def test_a_stick_rate_outside_the_acro_range_is_refused(
    tmp_path: Path, value: Any, words: tuple[str, ...]
) -> None:
    raw = _default_raw()
    raw["sticks"]["pitch"]["max_deg_s"] = value
    line = _problem(_write(tmp_path, raw), "sticks.pitch.max_deg_s")
    for w in words:
        assert w in line, line


def test_the_acro_range_ends_load(tmp_path: Path) -> None:
    raw = _default_raw()
    raw["sticks"]["roll"]["max_deg_s"] = 35
    raw["sticks"]["yaw"]["max_deg_s"] = 2000.0
    sticks = load_controller(_write(tmp_path, raw)).sticks
    assert (sticks.roll.max_deg_s, sticks.yaw.max_deg_s) == (35.0, 2000.0)


@pytest.mark.parametrize(
    ("mutate", "key_path"),
    [
        pytest.param(_set("axes.roll.kp", "6.0"), "axes.roll.kp", id="gain"),
        pytest.param(_set("prefilter_hz", "30"), "prefilter_hz", id="optional"),
        pytest.param(
            _set("axes.roll.alpha_adapt.tau_candidates_s", [0.01, "0.02"]),
            "axes.roll.alpha_adapt.tau_candidates_s.1",
            id="list-element",
        ),
        pytest.param(_set("sticks.channels", [1, 2, "3", 4]), "sticks.channels.2", id="int"),
    ],
)
def test_a_quoted_number_in_a_controller_is_refused(
    tmp_path: Path, mutate: Callable[[dict[str, Any]], None], key_path: str
) -> None:
    raw = copy.deepcopy(_default_raw())
    mutate(raw)
    assert "expected a number, not text" in _problem(_write(tmp_path, raw), key_path)


@pytest.mark.parametrize(
    ("value", "words"),
    [
        (12.6, ("sticks.roll.max_deg_s: 12.6 looks like rad/s (721.9 deg/s)",)),
        ("720", ("sticks.roll.max_deg_s: expected a number, not text", "got '720'")),
    ],
    ids=["rad-s", "quoted"],
)
def test_check_config_refuses_a_bad_stick_rate(
    tmp_path: Path, value: Any, words: tuple[str, ...]
) -> None:
    raw = _default_raw()
    raw["sticks"]["roll"]["max_deg_s"] = value
    path = _write(tmp_path, raw, "sticks_in_rad_s.yaml")
    res = CliRunner().invoke(companion_cli, ["check-config", "--controller", str(path)])
    assert res.exit_code == EXIT_BAD_INPUT, (res.exit_code, res.output, res.exception)
    assert "Traceback" not in res.output
    assert str(path) in res.output
    for w in words:
        assert w in res.output, res.output


def _then(*steps: Callable[[dict[str, Any]], None]) -> Callable[[dict[str, Any]], None]:
    def f(raw: dict[str, Any]) -> None:
        for step in steps:
            step(raw)

    return f


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        pytest.param(
            _delete("axes.yaw.alpha_adapt"),
            "lag_scaled_gains needs alpha_adapt",
            id="lag-scaling-without-identification",
        ),
        pytest.param(
            _set("axes.yaw.actuator_tau_s", 0.0),
            "lag_scaled_gains needs alpha_adapt and actuator_tau_s > 0",
            id="lag-scaling-without-lag",
        ),
        pytest.param(
            _set("axes.roll.lag_scaled_gains", False),
            "lag_scaling_max and lag_scaling_min need lag_scaled_gains",
            id="lag-bounds-without-lag-scaling",
        ),
        pytest.param(
            _then(
                _set("axes.yaw.lag_scaled_gains", False),
                _set("axes.yaw.window_lag_scaled", False),
                _set("axes.yaw.lag_scaling_authority_ref", 150.0),
            ),
            "lag_scaling_authority_ref needs lag_scaled_gains or alpha_adapt.margin_min",
            id="authority-reference-reaching-nothing",
        ),
        pytest.param(
            _set("axes.yaw.lag_scaled_gains", False),
            "axes.yaw: window_lag_scaled needs lag_scaled_gains and estimator: window",
            id="window-scaling-without-lag-scaling",
        ),
        pytest.param(
            _then(
                _set("axes.yaw.lag_scaled_gains", False),
                _set("axes.yaw.window_lag_scaled", False),
                _delete("axes.yaw.alpha_adapt"),
                _set("axes.yaw.estimator", "algebraic"),
            ),
            "actuator_tau_s needs estimator: window",
            id="lag-model-without-window-means",
        ),
    ],
)
def test_settings_that_would_reach_nothing_are_refused(
    tmp_path: Path, mutate: Callable[[dict[str, Any]], None], message: str
) -> None:
    """Refused rather than ignored (or, for the lag model on the algebraic
    estimator, rather than failing at the first sample)."""
    raw = copy.deepcopy(_default_raw())
    mutate(raw)
    path = tmp_path / "unreached.yaml"
    path.write_text(yaml.safe_dump(raw), encoding="utf-8")
    with pytest.raises(ConfigError, match=message):
        load_controller(path)


@pytest.mark.parametrize(
    "text", ["kind: mfc\naxes: [1, 2\n", "- just\n- a list\n", ""], ids=["yaml", "list", "empty"]
)
def test_unparseable_controller_file(tmp_path: Path, text: str) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError, match=r"c\.yaml"):
        load_controller(path)


def test_missing_controller_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"nope\.yaml"):
        load_controller(tmp_path / "nope.yaml")


def test_config_objects_are_frozen() -> None:
    cfg = load_controller()
    with pytest.raises(Exception):  # noqa: B017 - pydantic's frozen error type
        cfg.kind = "pid"  # type: ignore[misc]


@pytest.mark.parametrize(
    ("law", "model", "built"),
    [
        (MfcGains, MfcConfig, {"roll", "pitch", "yaw"}),
        (MfcAxisGains, MfcAxisConfig, set()),
        (AlphaAdaptation, AlphaAdaptConfig, set()),
        (PidAxisGains, PidAxisConfig, set()),
    ],
    ids=lambda x: getattr(x, "__name__", ""),
)
def test_each_law_setting_is_defined_once_in_the_schema(
    law: type, model: type[BaseModel], built: set[str]
) -> None:
    """A law's settings are the schema's fields under the same names (the builder
    renames nothing), and the schema alone holds their defaults: a gain added to one
    and not the other, or given a second default in the law, fails here."""
    names = {f.name for f in dataclasses.fields(law)}
    assert names - built == set(model.model_fields) - {"kind", "sticks", "axes"}
    defaulted = [
        f.name
        for f in dataclasses.fields(law)
        if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING
    ]
    assert defaulted == []
