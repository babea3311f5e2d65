"""Bounded loading: no config file can hang the companion, exhaust its memory or
flood the terminal (an alias bomb, a FIFO, a device, a huge file, a huge value).

Anything that could hang or eat memory should the guards regress runs in a
child process with a timeout and an address-space limit.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import tracemalloc
from pathlib import Path
from typing import Any

import pytest
from pydantic import ValidationError

import companion.schema as schema
from companion.config import load_controller
from companion.errors import ConfigError
from companion.profile import load_profile
from companion.reference import load_reference
from companion.schema import StrictModel, format_validation_error, load_yaml_model, read_yaml
from sitl.pilot.scripts import load_stick_script
from sitl.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
EXIT_BAD_INPUT = 2
CHILD_TIMEOUT_S = 30.0
CHILD_MEMORY_BYTES = 1 << 30


def bomb(levels: int = 10, laugh: str = "lol" * 333) -> str:
    """A "billion laughs" profile and controller (about 2.5 KB): each level a list
    of ten aliases of the one before, so ``name`` and ``kind`` hold 10**levels
    copies of ``laugh``."""
    lines = [f'laughs_0: &laughs_0 "{laugh}"']
    for i in range(1, levels + 1):
        aliases = ", ".join([f"*laughs_{i - 1}"] * 10)
        lines.append(f"laughs_{i}: &laughs_{i} [{aliases}]")
    lines += [f"name: *laughs_{levels}", f"kind: *laughs_{levels}"]
    return "\n".join(lines) + "\n"


class _Named(StrictModel):
    name: str


class _Numbers(StrictModel):
    count: float
    values: list[float]


def _limit_memory() -> None:
    """In the child: a bomb that gets through fails with MemoryError, not the host."""
    resource.setrlimit(resource.RLIMIT_AS, (CHILD_MEMORY_BYTES, CHILD_MEMORY_BYTES))


def companion(*args: str) -> subprocess.CompletedProcess[str]:
    """``companion ARGS`` in a child process, failing the test if it hangs."""
    try:
        return subprocess.run(
            [sys.executable, "-m", "companion", *args],
            capture_output=True,
            text=True,
            timeout=CHILD_TIMEOUT_S,
            preexec_fn=_limit_memory,
            cwd=ROOT,
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"companion {' '.join(args)} still busy after {CHILD_TIMEOUT_S} s")


def refused(res: subprocess.CompletedProcess[str], *words: str) -> None:
    """Exit 2, no traceback, and the message says each of ``words``."""
    assert res.returncode == EXIT_BAD_INPUT, (res.returncode, res.stderr[-2000:])
    assert "Traceback" not in res.stderr
    for w in words:
        assert w in res.stderr, res.stderr[-2000:]


@pytest.mark.parametrize("flag", ["--profile", "--controller"])
def test_check_config_refuses_an_alias_bomb_at_once(tmp_path: Path, flag: str) -> None:
    p = tmp_path / "bomb.yaml"
    p.write_text(bomb(), encoding="utf-8")
    assert 2000 < p.stat().st_size < 3000
    # Refused by the size check, in a child whose memory is limited: an expansion
    # would end it in a MemoryError, not this message.
    res = companion("check-config", flag, str(p))
    refused(res, str(p), "too large: over the limit of", "once aliases are expanded")
    assert len(res.stderr) < 1000


def test_an_alias_bomb_fails_fast_in_little_memory(tmp_path: Path) -> None:
    p = tmp_path / "bomb.yaml"
    # A million laughs: past every limit, small enough that a regression costs
    # this process seconds and tens of MB, not all of them.
    p.write_text(bomb(levels=6, laugh="lol"), encoding="utf-8")
    tracemalloc.start()
    try:
        with pytest.raises(ConfigError, match="once aliases are expanded") as info:
            load_yaml_model(p, _Named)
        peak_bytes = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert info.value.path == str(p)
    # Fast because nothing was expanded: the memory says so whatever the machine's speed.
    assert peak_bytes < 4 * 2**20  # the read buffer: 1 MiB


@pytest.mark.parametrize(
    ("text", "words"),
    [
        pytest.param("a: &a [1, *a]\n", "an alias inside the node it names", id="recursive"),
        pytest.param("a: " + "[" * 5000 + "]" * 5000, "levels of nesting", id="deep"),
        pytest.param(
            's: &s "' + "x" * 100_000 + '"\nl: [' + ", ".join(["*s"] * 20) + "]\n",
            "characters of text",
            id="long-string-aliased",
        ),
    ],
)
def test_yaml_over_a_limit_is_refused_with_its_name(tmp_path: Path, text: str, words: str) -> None:
    p = tmp_path / "big.yaml"
    p.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError, match=r"too large|recursive") as info:
        read_yaml(p)
    assert str(p) in str(info.value) and words in str(info.value)


def test_a_long_flat_file_stops_at_the_value_limit(tmp_path: Path) -> None:
    p = tmp_path / "wide.yaml"
    p.write_text("a: [" + "0, " * schema.MAX_YAML_NODES + "]\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=f"over the limit of {schema.MAX_YAML_NODES} values"):
        read_yaml(p)


@pytest.mark.parametrize(
    ("text", "words"),
    [
        pytest.param("a: 1" + "0" * 5000 + "\n", "4300 digits", id="huge-int"),
        pytest.param("a: 2024-02-30\n", "day is out of range", id="no-such-date"),
    ],
)
def test_yaml_values_python_cannot_build_are_refused(tmp_path: Path, text: str, words: str) -> None:
    p = tmp_path / "odd.yaml"
    p.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError, match="not valid YAML") as info:
        read_yaml(p)
    assert words in str(info.value)


def test_a_fifo_as_profile_is_refused_without_waiting_for_a_writer(tmp_path: Path) -> None:
    fifo = tmp_path / "profile.yaml"
    os.mkfifo(fifo)
    res = companion("check-config", "--profile", str(fifo))
    refused(res, str(fifo), "expected a regular file, got a FIFO")


def test_dev_zero_as_profile_is_refused_without_reading_it() -> None:
    res = companion("check-config", "--profile", "/dev/zero")
    refused(res, "/dev/zero", "expected a regular file, got a character device")
    assert "MemoryError" not in res.stderr


def test_a_directory_is_refused_as_such(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="expected a regular file, got a directory") as info:
        read_yaml(tmp_path)
    assert info.value.path == str(tmp_path)


def test_a_file_over_the_size_limit_is_refused(tmp_path: Path) -> None:
    limit = schema.MAX_FILE_BYTES
    p = tmp_path / "ref.csv"
    row = "1,0,0,0\n"
    p.write_text("t_s,roll_deg_s,pitch_deg_s,yaw_deg_s\n" + row * (limit // len(row)))
    assert p.stat().st_size > limit
    with pytest.raises(ConfigError, match=rf"larger than 1 MiB \({p.stat().st_size} bytes\)"):
        load_reference(p)
    with p.open("r+b") as f:
        f.truncate(limit)  # exactly at the limit: read whole
    assert len(schema.read_text(p)) == limit


def test_a_huge_value_renders_a_short_error_in_little_memory() -> None:
    # Shared references: a million numbers in a few dozen list objects, as an
    # alias bomb's lists are once PyYAML has built them.
    huge: Any = [0] * 10
    for _ in range(5):
        huge = [huge] * 10
    with pytest.raises(ValidationError) as info:
        _Named.model_validate({"name": huge})
    tracemalloc.start()
    try:
        problems = format_validation_error(info.value)
        peak_bytes = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    (problem,) = problems
    assert problem.startswith("name: Input should be a valid string, got [[[[...], [...], ")
    assert len(problem) < 150
    assert peak_bytes < 2**20


def test_many_problems_in_a_file_are_counted_not_listed(tmp_path: Path) -> None:
    p = tmp_path / "numbers.yaml"
    numbers = ", ".join(["0"] * 1000)
    words = ", ".join(["x" * 50] * 1000)
    p.write_text(f"count: [{numbers}]\nvalues: [{words}]\n", encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_yaml_model(p, _Numbers)
    problems = info.value.problems
    assert problems[0].startswith("count: Input should be a valid number, got [0, 0, 0, ")
    assert len(problems[0]) < 150
    assert problems[1].startswith("values.0: Input should be a valid number, unable to parse")
    assert len(problems) == schema.MAX_PROBLEMS + 1
    assert problems[-1] == f"... and {1001 - schema.MAX_PROBLEMS} more"
    assert len(str(info.value)) < 200 * len(problems)


TIGHTER = 5


@pytest.fixture
def tight_limits(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every limit five times tighter: the shipped files pass by a wide margin."""
    for name in ("MAX_FILE_BYTES", "MAX_YAML_NODES", "MAX_YAML_CHARS", "MAX_YAML_DEPTH"):
        monkeypatch.setattr(schema, name, getattr(schema, name) // TIGHTER)


@pytest.mark.usefixtures("tight_limits")
@pytest.mark.parametrize(
    "path", sorted((ROOT / "companion" / "data").glob("*.yaml")), ids=lambda p: p.name
)
def test_shipped_controllers_load_well_within_the_limits(path: Path) -> None:
    assert load_controller(path).kind in ("mfc", "pid")


@pytest.mark.usefixtures("tight_limits")
@pytest.mark.parametrize(
    "path", sorted((ROOT / "vehicle_profiles").glob("*.yaml")), ids=lambda p: p.name
)
def test_shipped_profiles_load_well_within_the_limits(path: Path) -> None:
    assert load_profile(path, simulated=True).name


@pytest.mark.usefixtures("tight_limits")
@pytest.mark.parametrize(
    "path", sorted((ROOT / "sitl" / "scenarios").glob("*.yaml")), ids=lambda p: p.name
)
def test_shipped_scenarios_load_well_within_the_limits(path: Path) -> None:
    assert load_scenario(path).name


@pytest.mark.usefixtures("tight_limits")
def test_the_shipped_stick_script_loads_well_within_the_limits() -> None:
    assert load_stick_script(ROOT / "sitl" / "sticks" / "example_sticks.yaml")


def test_a_boolean_is_not_a_number_in_any_config(tmp_path: Path) -> None:
    """``duration_s: yes`` would be read as 1 s: every config model refuses it."""
    from sitl.scenario import load_scenario

    path = tmp_path / "scenario.yaml"
    path.write_text("name: s\npilot: paper-acro\nduration_s: yes\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="duration_s: expected a number, not a boolean"):
        load_scenario(path)
