"""The companion's angle, altitude and position modes beside ArduCopter's own on the
real ArduCopter 4.5.6 SITL: STABILIZE, ALT_HOLD and LOITER flown with the same
sticks (``sitl/lab/realstack/modes.py``), and ``--mission`` beside ArduCopter's
AUTO flying the same waypoints at the same leg speed
(``sitl/lab/realstack/missions.py``), judged by ``tests/realstack/mode_checks.py``.

The companion engages in GUIDED_NOGPS (``--output rates``, ``GUID_OPTIONS`` 8) and
reads ArduCopter's own stick limits (``ANGLE_MAX``, ``PILOT_*``, ``LOIT_*``,
``THR_DZ``...): LOITER's sticks are a lean angle up to 2/3 of ``ANGLE_MAX``, braked
after ``LOIT_BRK_DELAY``, and the companion shapes them the same way.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from sitl.lab.realstack.flights import Session
from tests.realstack.conftest import ROOT, boot
from tests.realstack.mode_checks import failures, fly_both, fly_missions, mission_failures

PROFILE = str(ROOT / "vehicle_profiles" / "arducopter_sitl_quad.yaml")
RATES = ("--output", "rates", "--profile", PROFILE)


@pytest.fixture(scope="module")
def arducopter(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Session]:
    session = boot("ardupilot", tmp_path_factory.mktemp("arducopter-modes"))
    yield session
    session.close()


@pytest.mark.parametrize("mode", ["position", "altitude", "angle"])
def test_each_mode_flies_as_arducopters_own_under_the_same_sticks(
    arducopter: Session, mode: str, figures: list[dict[str, Any]]
) -> None:
    ours, theirs, limits = fly_both(arducopter, mode, RATES, figures)
    assert "ArduCopter's LOITER" in limits
    bad = failures(mode, ours, theirs)
    assert not bad, (bad, ours, theirs, limits)


def test_the_mission_flies_as_arducopters_own_mission(
    arducopter: Session, figures: list[dict[str, Any]]
) -> None:
    ours, theirs = fly_missions(arducopter, RATES, figures)
    bad = mission_failures(ours, theirs)
    assert not bad, (bad, ours, theirs)
