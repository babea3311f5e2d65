"""The shipped default gain set (companion/data/mfc_default.yaml), and why not Table I.

See docs/research/gains.md for the search that produced the set and the full evidence
tables. Table I's yaw limit cycle (its iP on the yaw angle) is still there to
see in a calm hover, and the shipped set does not have it. The flight figures
the set reaches are pinned in tests/regression/.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from companion.config import DEFAULT_CONTROLLER, MfcConfig, load_controller
from companion.profile import load_profile
from sitl.lab.simulate import simulate_flight
from sitl.scenario import WindSpec, load_scenario

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_FILE = ROOT / "companion" / "data" / "mfc_default.yaml"
TABLE1_FILE = ROOT / "companion" / "data" / "mfc_table1.yaml"


def _default() -> MfcConfig:
    cfg = load_controller(DEFAULT_FILE)
    assert isinstance(cfg, MfcConfig)
    return cfg


def test_default_controller_points_at_the_shipped_set() -> None:
    assert Path(DEFAULT_CONTROLLER).name == "mfc_default.yaml"
    assert Path(DEFAULT_CONTROLLER).resolve() == DEFAULT_FILE.resolve()


def _calm_hover_yaw_rms(cfg: MfcConfig) -> float:
    """Yaw-rate error RMS (deg/s) of the F450 in still air after a 5 s settle."""
    paper = load_scenario("paper-acro")
    sc = load_scenario("hover-gusts").model_copy(
        update={"name": "hover-calm", "wind": WindSpec(), "imu": paper.imu, "duration_s": 15.0}
    )
    rec = simulate_flight(load_profile(ROOT / "vehicle_profiles/f450.yaml"), cfg, sc)
    c = rec.columns
    keep = c["airborne"].astype(bool) & (c["t_s"] > 5.0)
    assert keep.sum() > 500, "the vehicle must have flown"
    err = np.degrees(c["meas_rad_s"][keep, 2] - c["ref_rad_s"][keep, 2])
    return float(np.sqrt(np.mean(err**2)))


@pytest.mark.slow
def test_table1_yaw_limit_cycle_is_detectable_and_the_default_has_none() -> None:
    table1 = load_controller(TABLE1_FILE)
    assert isinstance(table1, MfcConfig)
    t1 = _calm_hover_yaw_rms(table1)
    default = _calm_hover_yaw_rms(_default())
    # Measured: Table I ~12 deg/s and growing (a ~0.3 Hz oscillation from nothing
    # but sensor noise, no wind); the default ~0.4 deg/s (the gyro noise floor).
    assert t1 > 5.0
    assert default < 1.5
    assert t1 > 5.0 * default
