"""Evidence for the unit reading of Table I (see companion/control/mfc.py).

Read with y in degrees, Table I's alpha = 1 deg/s^2 per us is the rad reading
with alpha = pi/180. On the F450 the true input gain is about 0.3 rad/s^2 per
us, so the deg reading over-corrects ~17x per sample and the estimator loop
chatters between the motor limits; the rad reading (alpha of the order of the
true gain, as the paper asks) does not.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from companion.config import MfcConfig, load_controller
from companion.profile import load_profile
from sitl.lab.simulate import simulate_flight
from sitl.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[2]
TABLE1 = ROOT / "companion" / "data" / "mfc_table1.yaml"


def _with_alpha(cfg: MfcConfig, alpha: float) -> MfcConfig:
    axes = cfg.axes
    new = {n: getattr(axes, n).model_copy(update={"alpha": alpha}) for n in ("roll", "pitch")}
    return cfg.model_copy(update={"axes": axes.model_copy(update=new)})


def _saturated_fraction(profile: str, alpha: float) -> float:
    cfg = load_controller(TABLE1)
    assert isinstance(cfg, MfcConfig)
    sc = load_scenario("hover-gusts").model_copy(update={"duration_s": 8.0})
    rec = simulate_flight(
        load_profile(ROOT / f"vehicle_profiles/{profile}.yaml"), _with_alpha(cfg, alpha), sc
    )
    c = rec.columns
    air = c["airborne"].astype(bool)
    assert air.sum() > 100, "the vehicle must have flown"
    return float(c["sat_axes"][air][:, :2].mean())


@pytest.mark.slow
@pytest.mark.parametrize("profile", ["f450", "tarot650"])
def test_deg_reading_chatters_at_the_motor_limits_rad_reading_does_not(profile: str) -> None:
    rad = _saturated_fraction(profile, 1.0)
    deg = _saturated_fraction(profile, math.pi / 180.0)
    # Measured: rad ~0.00-0.01, deg ~0.90 of airborne samples saturated on roll/pitch.
    assert rad < 0.05
    assert deg > 0.5
    assert np.isfinite([rad, deg]).all()
