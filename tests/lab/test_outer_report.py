"""The outer-loop report's geometry: distances to a planned path, the plan read back."""

from __future__ import annotations

import numpy as np
import pytest

from companion.mission import Mission, Waypoint
from sitl.lab.outer_report import mission_plan, segment_distances

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
