"""The outer-loop report's geometry (distances to a planned path, the plan read back) and
``companion simulate --mode``'s report."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from companion.cli import cli
from companion.config import load_controller
from companion.mission import Mission, Waypoint
from companion.profile import load_profile
from sitl.lab.outer_report import mission_plan, segment_distances

ROOT = Path(__file__).resolve().parents[2]
PLAN = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])


def test_a_point_is_as_far_as_the_closest_leg() -> None:
    pts = np.array([[5.0, 0.0], [5.0, 2.0], [12.0, 5.0], [-3.0, -4.0], [11.0, 11.0]])
    d, c = segment_distances(pts, PLAN)
    assert d == pytest.approx([0.0, 2.0, 2.0, 5.0, 2.0**0.5])
    assert c[2] == pytest.approx([10.0, 5.0])  # beside the second leg
    assert c[3] == pytest.approx([0.0, 0.0])  # before the start: its end point


def test_a_single_point_plan_is_a_point() -> None:
    d, _ = segment_distances(np.array([[3.0, 4.0]]), np.array([[0.0, 0.0]]))
    assert d == pytest.approx([5.0])


def test_the_plan_starts_where_the_companion_said_it_did() -> None:
    mission = Mission(waypoints=[Waypoint(north_m=8, east_m=-2, up_m=4)])
    events = [
        {"kind": "mission_started", "detail": "1 waypoints from N 1.25 E -2.00 D -0.08 m, 5.0 s"}
    ]
    plan = mission_plan(mission, events)
    assert plan is not None
    assert plan.ravel().tolist() == pytest.approx([1.25, -2.0, -0.08, 9.25, -4.0, -4.08])
    assert mission_plan(mission, [{"kind": "engaged", "detail": ""}]) is None


@pytest.mark.long
def test_simulate_mode_flies_the_outer_loops_and_writes_their_report(tmp_path: Path) -> None:
    """``companion simulate --mode position``: the mode's scenario in process; metrics.json's
    ``outer`` is the lab's figures of that very flight, with path.png and report.md."""
    from sitl.lab.outer_flight import SCENARIOS, outer_metrics, simulate_outer_flight

    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["simulate", "--mode", "altitude", "--out", str(out),
                                   "--profile", "vehicle_profiles/x500.yaml"])  # fmt: skip
    assert res.exit_code == 0, res.output
    metrics = json.loads((out / "metrics.json").read_text(encoding="utf-8"))
    assert metrics["scenario"] == "altitude-steps" and metrics["mode"] == "altitude"
    sc = SCENARIOS["altitude-steps"]
    want = outer_metrics(
        simulate_outer_flight(load_profile(ROOT / "vehicle_profiles" / "x500.yaml",
                                           simulated=True), load_controller(), sc), sc)  # fmt: skip
    assert metrics["outer"] == json.loads(json.dumps(want))
    assert not metrics["crashed"] and metrics["outer"]["step_reach_s"]
    assert (out / "path.png").stat().st_size > 10_000
    assert "altitude-steps (altitude mode)" in (out / "report.md").read_text(encoding="utf-8")
    assert "position RMS" in res.output


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--mode", "angle", "--scenario", "square"], "square is a position-mode scenario"),
        (["--mode", "position", "--scenario", "paper-acro"], "'paper-acro': with --mode position"),
        (["--mode", "position", "--oracle"], "--oracle: not with --mode position"),
        (["--mode", "angle", "--link", "uart"], "--link: not with --mode angle"),
    ],
)
def test_simulate_mode_refuses_what_does_not_apply(
    tmp_path: Path, args: list[str], expected: str
) -> None:
    res = CliRunner().invoke(cli, ["simulate", "--out", str(tmp_path / "out"), *args])
    assert res.exit_code == 2, res.output
    assert expected in res.output
    assert not (tmp_path / "out").exists()
