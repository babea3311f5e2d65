"""Regression checks: the shipped controller's flight figures, pinned.

These pin today's output; they do not say the figures are right (the paper's
claims are judged in scripts/reproduce_paper.py). The in-process flight is
deterministic, so a figure that moves means the flight changed: if on purpose,
measure again with the command given beside each pin and update the pin.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from companion.config import load_controller
from companion.control import AXES
from companion.profile import load_profile
from sitl.lab.report import compute_metrics
from sitl.lab.simulate import simulate_flight
from sitl.scenario import load_scenario

pytestmark = [pytest.mark.regression, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
TOLERANCE = 0.03
"""Relative: room for a numpy or platform rounding change, not for a new flight."""

# The full 60 s paper-acro, MAE roll / pitch / yaw in deg/s. Measured 2026-11-25 with
#   python scripts/reproduce_paper.py --out runs/paper    (results.md, one decimal)
PAPER_FULL = {
    "f450": (6.9, 6.4, 7.2),
    "f450_cut_props": (10.7, 9.6, 25.2),
    "tarot650": (12.8, 8.6, 11.6),
}

# The first 15 s of paper-acro on every bundled vehicle. Measured 2026-11-25 with
#   python -c 'from sitl.lab.simulate import simulate_flight; ...' (the test's own flight:
#   paper-acro with duration_s 15, mfc_default.yaml, compute_metrics(...)["mae_deg_s"])
SLICE_S = 15.0
PAPER_SLICE = {
    "f450": (11.029, 1.705, 0.913),
    "f450_cut_props": (16.142, 2.166, 3.454),
    "tarot650": (19.76, 2.457, 1.058),
    "x500": (9.275, 1.66, 0.997),
}


def _mae(profile: str, duration_s: float | None) -> dict[str, float]:
    sc = load_scenario("paper-acro")
    if duration_s is not None:
        sc = sc.model_copy(update={"duration_s": duration_s})
    m = compute_metrics(
        simulate_flight(
            load_profile(ROOT / f"vehicle_profiles/{profile}.yaml"), load_controller(), sc
        )
    )
    assert not m["crashed"]
    mae: dict[str, float] = m["mae_deg_s"]
    return mae


def _check(mae: dict[str, float], pinned: tuple[float, float, float], decimals: int) -> None:
    for axis, pin in zip(AXES, pinned, strict=True):
        got = round(mae[axis], decimals)
        assert abs(got - pin) <= TOLERANCE * pin + 0.5 * 10**-decimals, (axis, mae, pinned)


@pytest.mark.parametrize("profile", sorted(PAPER_FULL))
def test_the_paper_flights_in_full(profile: str) -> None:
    _check(_mae(profile, None), PAPER_FULL[profile], 1)


@pytest.mark.parametrize("profile", sorted(PAPER_SLICE))
def test_a_paper_acro_slice_on_every_vehicle(profile: str) -> None:
    _check(_mae(profile, SLICE_S), PAPER_SLICE[profile], 3)
