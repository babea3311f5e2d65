"""The autopilot's input shaping as the law sees it (companion.control.shaping)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from companion.control.shaping import CORRECTION_HORIZON_S, RateShaper

DT = 0.005


def test_the_reference_slews_at_the_limit_and_settles_on_the_pilots_rate() -> None:
    shaper = RateShaper((10.0, 20.0, 0.0))  # rad/s^2; yaw unlimited
    assert shaper.reference(0.0, (0.0, 0.0, 0.0)) == (0.0, 0.0, 0.0)  # primed
    out = [shaper.reference(DT, (1.0, -1.0, 3.0)) for _ in range(30)]
    assert out[0] == pytest.approx((10.0 * DT, -20.0 * DT, 3.0))
    assert out[9] == pytest.approx((10 * 10.0 * DT, -1.0, 3.0))  # pitch got there at k = 9
    assert out[-1] == (1.0, -1.0, 3.0)  # roll got there at k = 19, and stays


def test_the_first_reference_after_a_reset_is_the_pilots() -> None:
    shaper = RateShaper((10.0, 10.0, 10.0))
    shaper.reference(DT, (0.0, 0.0, 0.0))
    shaper.reference(DT, (5.0, 5.0, 5.0))
    shaper.reset()
    assert shaper.reference(DT, (5.0, -5.0, 1.0)) == (5.0, -5.0, 1.0)


def test_a_time_step_of_nothing_holds_the_reference() -> None:
    shaper = RateShaper((10.0, 10.0, 10.0))
    shaper.reference(DT, (0.0, 0.0, 0.0))
    assert shaper.reference(0.0, (1.0, 1.0, 1.0)) == (0.0, 0.0, 0.0)


def test_the_setpoint_moves_at_most_the_limit_from_the_last_sent() -> None:
    shaper = RateShaper((10.0, 10.0, math.inf))
    assert shaper.limit(DT, (1.0, -1.0, 5.0), None) == (1.0, -1.0, 5.0)
    assert shaper.limit(DT, (1.0, -1.0, 5.0), (0.0, 0.0, 0.0)) == pytest.approx((0.05, -0.05, 5.0))
    assert shaper.limit(DT, (0.01, 0.0, 0.0), (0.0, 0.0, 0.0)) == (0.01, 0.0, 0.0)


def test_the_correction_is_held_within_what_the_slew_brings_in_over_the_horizon() -> None:
    shaper = RateShaper((10.0, 20.0, math.inf))
    reach = (10.0 * CORRECTION_HORIZON_S, 20.0 * CORRECTION_HORIZON_S)
    ref = (1.0, -1.0, 0.5)
    held = shaper.within_reach(ref, (5.0, -5.0, 9.0))
    assert held == pytest.approx((1.0 + reach[0], -1.0 - reach[1], 9.0))  # yaw unlimited
    small = (1.0 + 0.5 * reach[0], -1.0, 0.5)
    assert shaper.within_reach(ref, small) == small
    nan = shaper.within_reach(ref, (math.nan, 0.0, 0.0))  # the gate's to replace
    assert math.isnan(nan[0]) and nan[1] == pytest.approx(-1.0 + reach[1])


def test_a_negative_or_nan_limit_is_refused() -> None:
    with pytest.raises(ValueError):
        RateShaper((-1.0, 1.0, 1.0))
    with pytest.raises(ValueError):
        RateShaper((math.nan, 1.0, 1.0))


# Rates a gyro or a stick can give (|w| <= 100 rad/s), and what is no number at all.
anything = st.one_of(st.floats(-100.0, 100.0), st.sampled_from([math.nan, math.inf, -math.inf]))


@given(
    st.lists(st.tuples(st.floats(0.0, 0.05), anything, anything, anything), max_size=40),
    st.tuples(st.floats(0.0, 1e4), st.floats(0.0, 1e4), st.floats(0.0, 1e4)),
)
def test_a_finite_pilot_rate_always_gives_a_finite_reference_within_the_limit(
    samples: list[tuple[float, float, float, float]], accel: tuple[float, float, float]
) -> None:
    shaper = RateShaper(accel)
    prev: tuple[float, float, float] | None = None
    for dt, a, b, c in samples:
        out = shaper.reference(dt, (a, b, c))
        if not all(math.isfinite(v) for v in (a, b, c)):
            prev = None  # the gate's to replace: the shaper starts again from the next
            continue
        assert all(math.isfinite(v) for v in out)
        if prev is not None and dt > 0.0:
            for v, p, lim in zip(out, prev, shaper.accel_max_rad_s2, strict=True):
                assert abs(v - p) <= lim * dt * (1 + 1e-9) + 1e-12
        prev = out
