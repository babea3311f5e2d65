"""``companion check-config --fly``: a config flown on reference vehicles before it flies."""

from __future__ import annotations

import json
from datetime import datetime, timedelta, timezone
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner

from companion.cli import cli
from companion.config import DEFAULT_CONTROLLER, load_controller
from companion.fly_check import RECORD_NAME, STATE_DIR_ENV, file_sha256
from sitl.lab.config_check import EXCESS_MAX_DEG_S, check_controller, reference_vehicles


@pytest.fixture
def state(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The fly-check record's folder (companion.fly_check), this test's own."""
    folder = tmp_path / "state"
    monkeypatch.setenv(STATE_DIR_ENV, str(folder))
    return folder


def _run(controller: Path, log_dir: Path) -> int:
    """``companion run`` with ``controller`` against no autopilot: 2 when refused, 1 when
    it started and found none."""
    args = ["run", "--connect", "udpout:127.0.0.1:9", "--controller", str(controller),
            "--heartbeat-timeout-s", "0.2", "--log-dir", str(log_dir)]  # fmt: skip
    return CliRunner().invoke(cli, args).exit_code


def _clamped_alpha(tmp_path: Path) -> Path:
    """Valid by the schema, dangerous in flight: roll and pitch alpha pinned at 0.03,
    so a vehicle with far more authority (the envelope's tiny-fast corner) is
    commanded 100x too hard. The paper's vehicles fly it."""
    raw = yaml.safe_load(DEFAULT_CONTROLLER.read_text(encoding="utf-8"))
    for axis in ("roll", "pitch"):
        raw["axes"][axis] = {**raw["axes"]["roll"], "alpha": 0.03}
        raw["axes"][axis]["alpha_adapt"] = {**raw["axes"]["roll"]["alpha_adapt"], "alpha_max": 0.03}
    path = tmp_path / "clamped.yaml"
    path.write_text(yaml.safe_dump(raw), encoding="utf-8")
    load_controller(path)  # the schema takes it
    return path


def test_the_reference_vehicles_are_the_papers_three_and_two_corners() -> None:
    names = [v.name for v in reference_vehicles()]
    assert len(names) == 5 and names[-2:] == ["tiny-fast", "heavy-weak"]


@pytest.mark.long
def test_the_shipped_controller_passes_with_its_own_figures() -> None:
    flights = check_controller(load_controller(DEFAULT_CONTROLLER))
    assert [f.passed for f in flights] == [True] * 5
    for f in flights:
        assert not f.crashed
        assert f.mae_deg_s == f.shipped_mae_deg_s  # it is the shipped one


@pytest.mark.long
def test_a_schema_valid_config_that_a_corner_cannot_fly_fails_with_exit_2(
    tmp_path: Path, state: Path
) -> None:
    path = _clamped_alpha(tmp_path)
    result = CliRunner().invoke(cli, ["check-config", "--controller", str(path), "--fly"])
    assert result.exit_code == 2, result.output
    doc = json.loads(result.stdout)
    verdicts = {f["vehicle"]: f["passed"] for f in doc["flight_check"]}
    assert verdicts["tiny-fast"] is False
    assert verdicts["DJI F450"] is True  # the paper's vehicles fly it: only the corner tells
    assert f"error: {path}: flown in the simulator, it fails:" in result.stderr
    assert "tiny-fast: roll error" in result.stderr
    tiny = next(f for f in doc["flight_check"] if f["vehicle"] == "tiny-fast")
    assert tiny["mae_deg_s"]["roll"] > tiny["shipped_mae_deg_s"]["roll"] + EXCESS_MAX_DEG_S
    # Remembered: companion run refuses it, saying it failed and why.
    entry = json.loads((state / RECORD_NAME).read_text())["checks"][file_sha256(path)]
    assert entry["verdict"] == "failed" and entry["problems"][0].startswith("tiny-fast: roll")
    refused = CliRunner().invoke(cli, ["run", "--connect", "udpout:127.0.0.1:9",
                                       "--controller", str(path)])  # fmt: skip
    assert refused.exit_code == 2
    assert f"{path}: failed the fly check on" in refused.stderr
    assert "tiny-fast: roll error" in refused.stderr


@pytest.mark.long
@pytest.mark.slow
def test_a_pass_is_recorded_and_run_flies_that_file_only_as_it_was(
    tmp_path: Path, state: Path
) -> None:
    """A harmless copy of the shipped file (another hash) passes a real check; the pass
    is recorded with the hash, the path, the date and the verdict; companion run then
    flies it and says so; changed afterwards, it is refused again."""
    path = tmp_path / "my_gains.yaml"
    path.write_bytes(DEFAULT_CONTROLLER.read_bytes() + b"# my copy of the shipped gains\n")
    assert _run(path, tmp_path / "before") == 2  # not checked yet
    result = CliRunner().invoke(cli, ["check-config", "--controller", str(path), "--fly"])
    assert result.exit_code == 0, result.output
    assert f"{path}: passed the fly check" in result.stderr
    assert f"recorded in {state / RECORD_NAME}: companion run flies it" in result.stderr
    digest = file_sha256(path)
    entry = json.loads((state / RECORD_NAME).read_text())["checks"][digest]
    assert (entry["verdict"], entry["path"], entry["problems"]) == (
        "passed", str(path.resolve()), [],
    )  # fmt: skip
    when = datetime.fromisoformat(entry["date"].replace("Z", "+00:00"))
    assert abs(datetime.now(timezone.utc) - when) < timedelta(minutes=5)
    logs = tmp_path / "logs"
    assert _run(path, logs) == 1  # started: no autopilot answered
    lines = (logs / "events.jsonl").read_text(encoding="utf-8").splitlines()
    passed = [e for e in map(json.loads, lines) if e["kind"] == "fly_check_passed"]
    assert len(passed) == 1 and f"sha256 {digest[:16]}" in passed[0]["detail"]
    path.write_bytes(path.read_bytes() + b"# tuned after the check\n")
    assert _run(path, tmp_path / "after") == 2


def test_without_fly_nothing_is_flown(tmp_path: Path) -> None:
    path = _clamped_alpha(tmp_path)
    result = CliRunner().invoke(cli, ["check-config", "--controller", str(path)])
    assert result.exit_code == 0, result.output
    assert "flight_check" not in json.loads(result.stdout)
