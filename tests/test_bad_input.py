"""Bad input on the command lines: a clear error naming the flag or the file and
field, exit 2, before anything starts and with nothing left behind.

Each case here was found by feeding the CLIs bad values: nan through click's
float ranges (a watchdog given ``nan`` never fires), a file that is not UTF-8,
a non-finite or duplicated YAML value, a vehicle that cannot hover, an unknown
pilot in a scenario, a negative seed, an output folder that cannot be made.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import click
import pytest
from click.testing import CliRunner, Result
from pydantic import BaseModel

from companion.cli import cli as companion_cli
from companion.config import MfcConfig, PidConfig, load_controller
from companion.errors import ConfigError
from companion.failsafe import THRESHOLD_MAX
from companion.mission import Mission, load_mission
from companion.options import Finite, out_dir_problem, usable_out_dir
from companion.profile import VehicleProfile, load_profile
from sitl.cli import cli as sitl_cli
from sitl.lab.campaign_file import CampaignFile, load_campaign_file
from sitl.pilot.scripts import _ScriptModel, load_stick_script
from sitl.scenario import Scenario, load_scenario

ROOT = Path(__file__).resolve().parents[1]
F450 = ROOT / "vehicle_profiles" / "f450.yaml"
EXIT_BAD_INPUT = 2

# Every float option of `companion run` (the product): none may take nan.
RUN_FLOATS = (
    "--rate-hz", "--rates-full-scale-deg-s", "--rates-lead-s", "--stale-imu-s",
    "--link-timeout-s", "--invalid-imu-s", "--rc-timeout-s", "--envelope-time-s",
    "--envelope-error-deg-s", "--duration", "--heartbeat-timeout-s", "--arm-timeout-s",
)  # fmt: skip


def companion(*args: str) -> Result:
    return CliRunner().invoke(companion_cli, list(args))


def refused(res: Result, *words: str) -> None:
    """Exit 2, no traceback, and the message says each of ``words``."""
    assert res.exit_code == EXIT_BAD_INPUT, (res.exit_code, res.output, res.exception)
    assert "Traceback" not in res.output
    for w in words:
        assert w in res.output, res.output


@pytest.mark.parametrize("flag", RUN_FLOATS)
@pytest.mark.parametrize("value", ["nan", "inf"])
def test_run_refuses_a_non_finite_number(flag: str, value: str) -> None:
    # udpout to a closed port: if the value got through, the run would start.
    res = companion("run", "--connect", "udpout:127.0.0.1:9", "--profile", str(F450), flag, value)
    refused(res, flag)
    # A bounded range says inf is out of it; nan, and inf past an open end, are not finite.
    assert "is not a finite number" in res.output or "is not in the range" in res.output


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (("--wind-gust", "nan"), ("--wind-gust", "not a finite number")),
        (("--clock", "lockstep", "--lockstep-timeout", "nan"), ("--lockstep-timeout",)),
        (("--duration", "inf"), ("--duration", "not a finite number")),
        (("--seed", "-1"), ("--seed", "-1 is not in the range 0<=x<=4294967295")),
        (("--log", ""), ("--log", "expected a file path")),
        (("--fault", "motor-fail@1"), ("motor-fail@SECONDS:MOTOR",)),
        (("--pilot", ""), ("--pilot", "expected a maneuver name")),
        (("--autopilot", "ardupilot", "--param", "SCHED_LOOP_RATE=fast"), ("NAME=NUMBER",)),
        (("--param", "COM_OF_LOSS_T=1e308"), ("--param", "beyond a float32")),
    ],
)
def test_sitl_run_refuses(args: tuple[str, ...], words: tuple[str, ...]) -> None:
    res = CliRunner().invoke(
        sitl_cli, ["run", "--profile", str(F450), "--mavlink", "udpout:127.0.0.1:9", *args]
    )
    refused(res, *words)


def test_fly_and_run_refuse_contradicting_outputs() -> None:
    res = companion("fly", "--autopilot", "ardupilot", "--output", "actuator")
    refused(res, "--output actuator: ArduPilot accepts body rates only")
    res = companion("run", "--connect", "udpout:127.0.0.1:9", "--rates-passthrough")
    refused(res, "--rates-passthrough: needs --output rates")
    res = companion("fly", "--rates-law-axes", "yaw")
    refused(res, "--rates-law-axes needs --output rates")


def test_simulate_refuses_a_negative_seed_and_an_empty_or_impossible_out(tmp_path: Path) -> None:
    refused(companion("simulate", "--seed", "-1"), "--seed")
    refused(companion("simulate", "--out", ""), "--out", "expected a folder path")
    afile = tmp_path / "afile"
    afile.write_text("x")
    refused(companion("simulate", "--out", str(afile)), "--out", "is a file")
    refused(companion("simulate", "--out", str(afile / "sub")), "--out", "is not a folder")


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (("--gusts", "nan"), ("--gusts: expected finite sigmas",)),
        (("--gusts", "0,-1"), ("--gusts: expected finite sigmas",)),
        (("--damage", "0"), ("--damage: expected efficiencies in (0, 1]",)),
        (("--profiles", ","), ("--profiles: expected names or files",)),
        (("--controllers", ""), ("--controllers: expected names or files",)),
        (("--duration", "nan"), ("--duration", "not a finite number")),
    ],
)
def test_campaign_refuses(tmp_path: Path, args: tuple[str, ...], words: tuple[str, ...]) -> None:
    out = tmp_path / "campaign"
    refused(companion("campaign", "--out", str(out), *args), *words)
    assert not out.exists()


def _profile_with(tmp_path: Path, old: str, new: str) -> Path:
    text = F450.read_text(encoding="utf-8")
    assert old in text
    p = tmp_path / "profile.yaml"
    p.write_text(text.replace(old, new, 1), encoding="utf-8")
    return p


def test_a_profile_that_is_not_utf8_names_the_file_and_the_byte(tmp_path: Path) -> None:
    p = tmp_path / "latin1.yaml"
    p.write_bytes(F450.read_bytes().replace(b"name:", b"# caf\xe9\nname:", 1))
    refused(companion("check-config", "--profile", str(p)), str(p), "not UTF-8 text (byte 0xe9")


def test_a_non_finite_profile_value_names_the_field(tmp_path: Path) -> None:
    text = F450.read_text(encoding="utf-8")
    kf_line = next(ln for ln in text.splitlines() if "kf_n_per_rad_s2:" in ln)
    p = _profile_with(tmp_path, kf_line, "  kf_n_per_rad_s2: .inf")
    refused(
        companion("check-config", "--profile", str(p)),
        str(p), "physics.kf_n_per_rad_s2: Input should be a finite number",
    )  # fmt: skip


def test_a_profile_that_cannot_hover_is_refused_by_the_simulator_only(tmp_path: Path) -> None:
    text = F450.read_text(encoding="utf-8")
    mass_line = next(ln for ln in text.splitlines() if "mass_kg:" in ln)
    p = _profile_with(tmp_path, mass_line, "  mass_kg: 90.0")
    out = tmp_path / "out"
    res = companion("simulate", "--profile", str(p), "--out", str(out), "--no-progress")
    refused(res, str(p), "physics: cannot hover")
    assert not out.exists()
    res = CliRunner().invoke(sitl_cli, ["run", "--profile", str(p), "--duration", "1"])
    refused(res, str(p), "physics: cannot hover")
    # The companion alone never reads the physics: a real vehicle's profile may
    # carry placeholder physics.
    assert companion("check-config", "--profile", str(p)).exit_code == 0


def test_a_key_given_twice_is_refused(tmp_path: Path) -> None:
    p = _profile_with(tmp_path, "name:", "name: twice\nname:")
    refused(companion("check-config", "--profile", str(p)), str(p), "key 'name' given twice")


def test_a_scenario_with_an_unknown_pilot_is_refused_before_flying(tmp_path: Path) -> None:
    text = (ROOT / "sitl" / "scenarios" / "paper-acro.yaml").read_text(encoding="utf-8")
    pilot_line = next(ln for ln in text.splitlines() if ln.startswith("pilot:"))
    sc = tmp_path / "scenario.yaml"
    sc.write_text(text.replace(pilot_line, "pilot: no-such-pilot"), encoding="utf-8")
    out = tmp_path / "out"
    res = companion("simulate", "--scenario", str(sc), "--out", str(out), "--no-progress")
    refused(res, str(sc), "pilot: unknown 'no-such-pilot'", "paper-acro")
    assert not out.exists()


def test_an_out_dir_check_leaves_nothing_behind(tmp_path: Path) -> None:
    deep = tmp_path / "a" / "b" / "c"
    param = click.Option(["--out"])
    assert usable_out_dir(click.Context(click.Command("x")), param, str(deep)) == deep
    assert list(tmp_path.iterdir()) == []


def test_yaml_merge_keys_and_anchors_still_load(tmp_path: Path) -> None:
    from companion.schema import read_yaml

    p = tmp_path / "merge.yaml"
    p.write_text("rp: &rp {kp: 1, kd: 2}\npitch: {<<: *rp, kd: 30}\n", encoding="utf-8")
    assert read_yaml(p) == {"rp": {"kp": 1, "kd": 2}, "pitch": {"kp": 1, "kd": 30}}
    p.write_text("? [1, 2]\n: v\n", encoding="utf-8")  # PyYAML's own error, not a TypeError
    with pytest.raises(ConfigError, match="unhashable key"):
        read_yaml(p)


def test_an_out_dir_through_dotdot_or_a_broken_symlink(tmp_path: Path) -> None:
    assert out_dir_problem(str(tmp_path / "missing" / ".." / "runs")) is None
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "link").symlink_to(tmp_path / "gone")
    assert "is a broken symlink" in str(out_dir_problem(str(tmp_path / "link" / "x")))


# Every failsafe threshold of `companion run` has a bound beyond which the failsafe
# no longer protects (companion.failsafe.THRESHOLD_MAX).
THRESHOLDS = (
    "--stale-imu-s", "--invalid-imu-s", "--link-timeout-s", "--rc-timeout-s",
    "--envelope-time-s", "--envelope-error-deg-s", "--hand-back-watch-s",
)  # fmt: skip


@pytest.mark.parametrize("flag", THRESHOLDS)
def test_run_refuses_a_failsafe_threshold_beyond_its_bound(flag: str) -> None:
    value = 1.5 * THRESHOLD_MAX[flag][0]  # past the bound, within the option's own range
    res = companion(
        "run", "--connect", "udpout:127.0.0.1:9", "--profile", str(F450), flag, f"{value:g}"
    )  # fmt: skip
    refused(res, flag, f"{value:g}: beyond", "no longer protects", f"--beyond-bounds {flag}")


def test_a_bound_lifted_on_purpose_is_recorded(tmp_path: Path) -> None:
    """--beyond-bounds lets one threshold past its bound; the run says so in its events
    (here a run that finds no autopilot within the heartbeat timeout: exit 1)."""
    res = companion(
        "run", "--connect", "udpout:127.0.0.1:9", "--profile", str(F450),
        "--link-timeout-s", "60", "--beyond-bounds", "--link-timeout-s",
        "--heartbeat-timeout-s", "0.2", "--log-dir", str(tmp_path),
    )  # fmt: skip
    assert res.exit_code == 1, res.output
    events = [json.loads(line) for line in (tmp_path / "events.jsonl").read_text().splitlines()]
    lifted = [e for e in events if e["kind"] == "bounds_lifted"]
    assert len(lifted) == 1 and "--link-timeout-s 60 (bound 10)" in lifted[0]["detail"]
    # The bound lifted is that one only.
    res = companion(
        "run", "--connect", "udpout:127.0.0.1:9", "--profile", str(F450),
        "--stale-imu-s", "60", "--beyond-bounds", "--link-timeout-s",
    )  # fmt: skip
    refused(res, "--stale-imu-s 60: beyond 1")


def _numeric_options() -> list[tuple[str, click.Parameter]]:
    """Every option of every ``companion`` and ``sitl`` command that takes a number
    (a ``-v`` count aside: each ``-v`` adds one, there is no value to bound)."""
    found = []
    for prog, group in (("companion", companion_cli), ("sitl", sitl_cli)):
        ctx = click.Context(group)
        for name in group.list_commands(ctx):
            command = group.get_command(ctx, name)
            assert command is not None
            for param in command.params:
                numeric = isinstance(
                    param.type, click.types.IntParamType | click.types.FloatParamType
                )
                if numeric and not getattr(param, "count", False):
                    found.append((f"{prog} {name} {param.opts[-1]}", param))
    return found


NUMERIC_OPTIONS = _numeric_options()


def test_the_walk_finds_the_numeric_options() -> None:
    names = {name for name, _ in NUMERIC_OPTIONS}
    assert {"companion run --duration", "companion fly --duration", "sitl run --duration",
            "companion campaign --seeds", "sitl envelope --n"} <= names  # fmt: skip
    assert len(names) == len(NUMERIC_OPTIONS) > 40


@pytest.mark.parametrize(
    "param", [p for _, p in NUMERIC_OPTIONS], ids=[n for n, _ in NUMERIC_OPTIONS]
)
def test_every_numeric_option_has_two_finite_ends(param: click.Parameter) -> None:
    """A number no user needs (``--duration 1e308``) is refused by click, naming the
    option, before anything starts; a float also refuses nan (:class:`Finite`)."""
    t = param.type
    assert isinstance(t, click.IntRange | click.FloatRange), f"{t!r} has no range"
    assert t.min is not None and t.max is not None, f"{t!r}: both ends"
    assert math.isfinite(t.min) and math.isfinite(t.max) and t.min <= t.max
    if isinstance(t, click.FloatRange):
        assert isinstance(t, Finite), f"{t!r} lets nan through"


def _script_parsers() -> list[tuple[str, argparse.ArgumentParser]]:
    from sitl.lab.fuzzing.config import parser as config_fuzz_parser
    from sitl.lab.fuzzing.mavlink import _parser as fuzz_parser

    return [("fuzz.py", fuzz_parser()), ("fuzz.py config", config_fuzz_parser())]


def test_the_scripts_numbers_are_bounded(capsys: pytest.CaptureFixture[str]) -> None:
    """scripts/fuzz.py's numbers: each a bounded type, 1e308 refused naming the option."""
    checked = []
    for prog, ap in _script_parsers():
        for action in ap._actions:
            if action.type in (None, str, Path) or not action.option_strings:
                continue  # --cases, a number or 'full', is checked below
            assert action.type not in (int, float), f"{prog} {action.option_strings}: unbounded"
            flag = action.option_strings[-1]
            with pytest.raises(SystemExit) as exc:
                ap.parse_args([flag, "1e308"])
            assert exc.value.code == EXIT_BAD_INPUT
            assert f"argument {flag}" in capsys.readouterr().err
            checked.append(f"{prog} {flag}")
    assert {"fuzz.py --rate", "fuzz.py --duration", "fuzz.py config --n"} <= set(checked)
    from sitl.lab.fuzzing.mavlink import _options

    ap = _script_parsers()[0][1]
    with pytest.raises(SystemExit) as exc:
        _options(ap, ap.parse_args(["--cases", "10000000000"]))
    assert exc.value.code == EXIT_BAD_INPUT and "--cases: expected 0.." in capsys.readouterr().err


def test_run_and_fly_refuse_a_duration_of_1e308_and_start_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Found by an outside campaign: ``run --duration 1e308`` raised an OverflowError
    once started, and ``fly`` left a traceback in companion.stderr."""

    def no_process(*args: object, **kwargs: object) -> None:
        raise AssertionError(f"a process was started: {args}")

    monkeypatch.setattr(subprocess, "Popen", no_process)
    logs, out = tmp_path / "logs", tmp_path / "fly"
    res = companion(
        "run", "--connect", "udpout:127.0.0.1:9", "--profile", str(F450),
        "--log-dir", str(logs), "--duration", "1e308",
    )  # fmt: skip
    refused(res, "--duration", "1e+308 is not in the range")
    res = companion("fly", "--duration", "1e308", "--out", str(out), "--no-progress")
    refused(res, "--duration", "1e+308 is not in the range")
    assert list(tmp_path.iterdir()) == []  # neither the log folder nor the output folder


# ------------------------------------------ numbers in files: numbers, in a plausible range

UNIT = re.compile(r"_(kg|m|m2|s|s2|hz|us|us2|rad|n)$")
"""A field name ending in a unit: ``mass_kg``, ``t_s``, ``rate_hz``, ``kf_n_per_rad_s2``,
``aux_us``, ``error_limit_rad``, ``imbalance_n``..."""

UNIT_IN_DOC = {
    "AlphaAdaptConfig.alpha_max",
    "AlphaAdaptConfig.alpha_min",
    "MfcAxisConfig.alpha",
    "MfcAxisConfig.lag_scaling_authority_ref",
}
"""Fields whose unit is in their description, not their name ((rad/s^m) per us)."""

CONFIG_MODELS: tuple[type[BaseModel], ...] = (
    MfcConfig, PidConfig, VehicleProfile, Scenario, Mission, CampaignFile, _ScriptModel,
)  # fmt: skip
"""The top of every kind of file: controller, profile, scenario, mission, campaign,
stick script (the models under them are walked from these)."""


def _number_schemas(schema: dict[str, Any]) -> Iterator[dict[str, Any]]:
    """The JSON schemas of the numbers in a field: itself, an optional's, a tuple's or
    a list's elements (a nested model is walked as a model of its own)."""
    if schema.get("type") in ("number", "integer"):
        yield schema
        return
    for sub in [*schema.get("anyOf", ()), *schema.get("prefixItems", ())]:
        yield from _number_schemas(sub)
    if isinstance(schema.get("items"), dict):
        yield from _number_schemas(schema["items"])


def _unit_fields() -> dict[str, list[dict[str, Any]]]:
    """``Model.field`` of every numeric field with a unit, and its numbers' schemas."""
    out: dict[str, list[dict[str, Any]]] = {}
    for root in CONFIG_MODELS:
        js = root.model_json_schema()
        for model in [js, *js.get("$defs", {}).values()]:
            for name, schema in model.get("properties", {}).items():
                key = f"{model['title']}.{name}"
                numbers = list(_number_schemas(schema))
                if numbers and (UNIT.search(name) or key in UNIT_IN_DOC):
                    out[key] = numbers
    return out


UNIT_FIELDS = _unit_fields()


def test_the_walk_finds_the_fields_with_units() -> None:
    assert len(UNIT_FIELDS) > 80
    for key in ("Physics.mass_kg", "AxisRatesConfig.max_deg_s", "Waypoint.speed_m_s",
                "CampaignFile.gust_sigma_m_s", "_SegmentModel.aux_us", "LinkSpec.up_delay_s",
                "Limits.rate_max_deg_s", "MfcAxisConfig.alpha"):  # fmt: skip
        assert key in UNIT_FIELDS, key


@pytest.mark.parametrize("key", sorted(UNIT_FIELDS))
def test_every_number_with_a_unit_has_both_bounds(key: str) -> None:
    for schema in UNIT_FIELDS[key]:
        assert "minimum" in schema or "exclusiveMinimum" in schema, (key, schema)
        assert "maximum" in schema or "exclusiveMaximum" in schema, (key, schema)


SHIPPED: dict[str, Callable[[Path], object]] = {
    "vehicle_profiles": lambda p: load_profile(p, simulated=True),
    "companion/data": load_controller,
    "sitl/scenarios": load_scenario,
    "sitl/sticks": load_stick_script,
    "campaigns": load_campaign_file,
}
SHIPPED_FILES = [p for folder in SHIPPED for p in sorted((ROOT / folder).glob("*.yaml"))]


def test_every_folder_of_shipped_files_has_some() -> None:
    for folder in SHIPPED:
        assert any(p.parent == ROOT / folder for p in SHIPPED_FILES), folder


@pytest.mark.parametrize("path", SHIPPED_FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_shipped_file_loads(path: Path) -> None:
    SHIPPED[str(path.parent.relative_to(ROOT))](path)


MISSION = "speed_m_s: 2.0\nwaypoints:\n  - {north_m: 10, east_m: 0, up_m: 5, hold_s: 2}\n"


@pytest.mark.parametrize(
    ("source", "old", "new", "load", "key_path"),
    [
        ("sitl/scenarios/paper-acro.yaml", "physics_dt_s: 0.001", 'physics_dt_s: "0.001"',
         load_scenario, "physics_dt_s"),
        ("sitl/scenarios/paper-acro.yaml", "steady_ned_m_s: [2.0,", "steady_ned_m_s: ['2.0',",
         load_scenario, "wind.steady_ned_m_s.0"),
        ("sitl/sticks/example_sticks.yaml", "duration_s: 30", 'duration_s: "30"',
         load_stick_script, "duration_s"),
        ("campaigns/seeds-1000.yaml", "duration_s: 20", "duration_s: '20'",
         load_campaign_file, "duration_s"),
        ("campaigns/seeds-1000.yaml", "count: 1000}", "count: '1000'}",
         load_campaign_file, "seeds.range.count"),
        (None, "up_m: 5", "up_m: '5'", load_mission, "waypoints.0.up_m"),
    ],
    ids=["scenario", "scenario-vector", "stick-script", "campaign", "campaign-seeds", "mission"],
)  # fmt: skip
def test_a_quoted_number_is_refused_in_every_kind_of_file(
    tmp_path: Path,
    source: str | None,
    old: str,
    new: str,
    load: Callable[[Path], object],
    key_path: str,
) -> None:
    text = MISSION if source is None else (ROOT / source).read_text(encoding="utf-8")
    assert old in text
    path = tmp_path / "file.yaml"
    path.write_text(text.replace(old, new, 1), encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load(path)
    assert info.value.path == str(path)
    lines = [p for p in info.value.problems if p.startswith(f"{key_path}:")]
    assert lines, info.value.problems
    assert "expected a number, not text" in lines[0]


@pytest.mark.parametrize(
    ("text", "key_path", "words"),
    [
        ("rate_full_scale_deg_s: [720, 12.6, 360]", "rate_full_scale_deg_s",
         ("12.6 looks like rad/s (721.9 deg/s)", "[35, 2000] deg/s")),
        ("aux_us: [1000, 20000]", "aux_us.1", ("less than or equal to 2000",)),
    ],
    ids=["rates-in-rad-s", "aux-out-of-range"],
)  # fmt: skip
def test_a_stick_script_out_of_range_names_the_key(
    tmp_path: Path, text: str, key_path: str, words: tuple[str, ...]
) -> None:
    path = tmp_path / "sticks.yaml"
    path.write_text(f"duration_s: 5\n{text}\nsegments:\n  - {{t_s: 0, level: true}}\n")
    with pytest.raises(ConfigError) as info:
        load_stick_script(path)
    lines = [p for p in info.value.problems if p.startswith(f"{key_path}:")]
    assert lines, info.value.problems
    for w in words:
        assert w in lines[0], lines[0]


@pytest.mark.parametrize(
    ("value", "words"),
    [
        ("0", ("1..65535",)),
        ("70000", ("1..65535",)),
        ("-1", ("1..65535",)),
        ("nan", ("not an integer",)),
        ("eight", ("not an integer",)),
        (":8765", ("the host is empty",)),
        ("", ("not an integer",)),
    ],
)
@pytest.mark.parametrize("command", ["run", "fly"])
def test_run_and_fly_refuse_a_live_address(
    tmp_path: Path, command: str, value: str, words: tuple[str, ...]
) -> None:
    args = (
        ["--connect", "udpin:127.0.0.1:0"] if command == "run" else ["--out", str(tmp_path / "o")]
    )
    refused(companion(command, *args, "--live", value), "--live", *words)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("command", ["run", "fly"])
def test_live_without_its_extra_names_the_extra_and_starts_nothing(
    tmp_path: Path, command: str
) -> None:
    """An install without the foxglove-sdk package (sys.modules: its import fails)."""
    args = (
        ["--connect", "udpin:127.0.0.1:0"] if command == "run" else ["--out", str(tmp_path / "o")]
    )
    code = (
        "import sys; sys.modules['foxglove'] = None\n"
        "from companion.cli import main; sys.argv = ['companion', *sys.argv[1:]]; main()"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, command, *args, "--live", "8765"],
        cwd=ROOT, capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert proc.returncode == EXIT_BAD_INPUT, proc.stderr
    assert "pip install 'mfc-companion[live]'" in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "o").exists()
