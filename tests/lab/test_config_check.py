"""``companion check-config --fly``: a config flown on reference vehicles before it flies."""

from __future__ import annotations

import json
from pathlib import Path

import yaml
from click.testing import CliRunner

from companion.cli import cli
from companion.config import DEFAULT_CONTROLLER, load_controller
from sitl.lab.config_check import EXCESS_MAX_DEG_S, check_controller, reference_vehicles


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


def test_the_shipped_controller_passes_with_its_own_figures() -> None:
    flights = check_controller(load_controller(DEFAULT_CONTROLLER))
    assert [f.passed for f in flights] == [True] * 5
    for f in flights:
        assert not f.crashed
        assert f.mae_deg_s == f.shipped_mae_deg_s  # it is the shipped one


def test_a_schema_valid_config_that_a_corner_cannot_fly_fails_with_exit_2(
    tmp_path: Path,
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


def test_without_fly_nothing_is_flown(tmp_path: Path) -> None:
    path = _clamped_alpha(tmp_path)
    result = CliRunner().invoke(cli, ["check-config", "--controller", str(path)])
    assert result.exit_code == 0, result.output
    assert "flight_check" not in json.loads(result.stdout)
