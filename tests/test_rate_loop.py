"""companion.rate_loop: which axes ``--rates-law-axes auto`` corrects, from PX4's gains."""

from __future__ import annotations

import math

import pytest

from companion.rate_loop import PX4_RATE_GAINS, STIFF

DEFAULTS = {"MC_ROLLRATE_K": 1.0, "MC_ROLLRATE_P": 0.15, "MC_PITCHRATE_K": 1.0,
            "MC_PITCHRATE_P": 0.15}  # fmt: skip


@pytest.mark.parametrize(
    ("changed", "axes"),
    [
        ({}, (True, True, True)),
        ({"MC_ROLLRATE_K": STIFF}, (False, True, True)),  # from the threshold on
        ({"MC_ROLLRATE_K": 0.99 * STIFF}, (True, True, True)),
        ({"MC_PITCHRATE_P": 0.15 * STIFF}, (True, False, True)),  # through P alike
        ({"MC_PITCHRATE_K": 1.25, "MC_PITCHRATE_P": 0.18}, (True, False, True)),  # K x P
        ({"MC_ROLLRATE_K": 3.0, "MC_ROLLRATE_P": 0.05}, (True, True, True)),  # K x P = 1
        ({"MC_ROLLRATE_K": 0.5}, (True, True, True)),  # softer: the law's
    ],
)
def test_an_axis_from_the_threshold_on_is_left_to_the_pilot_yaw_never(
    changed: dict[str, float], axes: tuple[bool, bool, bool]
) -> None:
    assert PX4_RATE_GAINS.law_axes({**DEFAULTS, **changed}) == axes


def test_only_finite_positive_gains_are_usable() -> None:
    got: dict[str, float | None] = {**DEFAULTS, "MC_ROLLRATE_P": None, "MC_PITCHRATE_K": math.inf}
    got["MC_PITCHRATE_P"] = -0.15
    values, unusable = PX4_RATE_GAINS.usable(got)
    assert values == {"MC_ROLLRATE_K": 1.0}
    assert unusable == ["MC_ROLLRATE_P", "MC_PITCHRATE_K", "MC_PITCHRATE_P"]
    assert PX4_RATE_GAINS.usable(DEFAULTS) == (DEFAULTS, [])


def test_said_names_each_gain_and_the_stiffness() -> None:
    said = PX4_RATE_GAINS.said({**DEFAULTS, "MC_ROLLRATE_K": 2.0})
    assert said == ("MC_ROLLRATE_K 2, MC_ROLLRATE_P 0.15, MC_PITCHRATE_K 1, MC_PITCHRATE_P "
                    "0.15: 2x / 1x the default gain on roll / pitch")  # fmt: skip
