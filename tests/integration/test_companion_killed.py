"""The companion killed mid-manoeuvre, against the SITL as a separate process.

``kill -9`` of the companion at the first sample 9.35 s into paper-acro, as the
F450 starts its first roll flip (about 300-400 deg/s and accelerating): nothing is
handed back, and the autopilot holds the companion's last setpoint until its
offboard-loss timeout (``COM_OF_LOSS_T``), then lands (``COM_OBL_RC_ACT`` 4).
:mod:`sitl.lab.killed` kills it through a relay, at an exact sample.

* Actuator output with PX4's default 1 s: the torque held spins the vehicle up
  to thousands of deg/s, beyond what the autopilot's LAND recovers from 13 m.
* Body rates, or actuator output, with 0.3 s (docs/failsafes.md, "The companion
  dies"): the vehicle is back level and still within 2 s; with body rates the
  largest rate is the one held (the autopilot's own rate loop keeps it).
"""

from __future__ import annotations

import signal
from pathlib import Path

import pytest

from sitl.lab.killed import KillAt, KilledFlight, KillFigures, fly_killed

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
F450 = ROOT / "vehicle_profiles" / "f450.yaml"
KILL = KillAt(9.35)
FLIP_RATE_DEG_S = 720.0
"""paper-acro's first roll flip, at full stick."""


def killed(tmp_path: Path, output: str, loss_s: float) -> tuple[KilledFlight, KillFigures]:
    k = fly_killed(
        F450, "paper-acro", tmp_path, KILL, output=output, offboard_timeout_s=loss_s, fly_on_s=4.0
    )
    assert k.flight.companion_rc == -signal.SIGKILL, k.flight.why()
    assert k.figures is not None, k.notes
    f = k.figures
    assert f.t_kill_s == pytest.approx(KILL.after_s, abs=0.005), f
    assert 200.0 < f.rate_at_kill_deg_s[0] < FLIP_RATE_DEG_S, f  # mid-roll
    # Nothing was handed back: the autopilot's own timeout, then its LAND.
    assert f.failsafe_mode == "LAND", f
    assert f.failsafe_after_s == pytest.approx(loss_s, abs=0.01), f
    return k, f


@pytest.mark.long
def test_a_torque_held_1_s_from_a_kill_mid_roll_runs_away(tmp_path: Path) -> None:
    _, f = killed(tmp_path, "actuator", 1.0)
    assert f.max_rate_deg_s > 3000.0, f.row()
    assert f.crashed, f.row()


@pytest.mark.parametrize(
    # rates: a long check (scripts/test --long); the default run flies actuator.
    "output",
    [pytest.param("rates", marks=pytest.mark.long), "actuator"],
)
def test_with_com_of_loss_t_0_3_s_a_kill_mid_roll_is_recovered(tmp_path: Path, output: str) -> None:
    _, f = killed(tmp_path, output, 0.3)
    assert f.outcome == "recovered", f.row()
    assert f.recovered_after_s is not None and f.recovered_after_s < 2.0, f.row()
    assert f.altitude_lost_m < 3.0, f.row()
    if output == "rates":
        # The autopilot's rate loop holds the last rate asked: no runaway.
        assert f.max_rate_deg_s < 1.25 * FLIP_RATE_DEG_S, f.row()
