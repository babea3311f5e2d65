"""Yaw's share of roll and pitch: given while the heading is lost, taken back after.

The rule (companion/control/yaw_share.py): the yaw rate error integrates while
yaw is saturated and leaks away otherwise; past LOST_ON_RAD the share rises at
RISE_PER_S (not while roll and pitch are saturated on their own), is kept while
the mixer uses it, and falls at FALL_PER_S once yaw fits alone.
"""

from __future__ import annotations

import math

import pytest

from companion.control.yaw_share import FALL_PER_S, LOST_ON_RAD, RISE_PER_S, YawShare

DT = 0.001


def run(share: YawShare, seconds: float, **sample: object) -> list[float]:
    return [share.update(DT, **sample) for _ in range(round(seconds / DT))]  # type: ignore[arg-type]


def test_a_flip_gives_no_share() -> None:
    """A flip saturates yaw for 0.3 s with 0.5 rad/s of yaw error (0.15 rad, under
    the threshold), roll saturated on its own: nothing is given, and it leaks away."""
    s = YawShare(0.5)
    flip = dict(yaw_error_rad_s=0.5, yaw_saturated=True, roll_pitch_saturated=True, used=0.0)
    assert max(run(s, 0.3, **flip)) == 0.0
    quiet = dict(yaw_error_rad_s=0.0, yaw_saturated=False, roll_pitch_saturated=False, used=0.0)
    run(s, 3.0, **quiet)
    assert abs(s.lost_rad) < 0.01 and s.value == 0.0


def test_a_heading_lost_to_saturation_is_given_a_share_and_it_is_taken_back() -> None:
    """Yaw saturated with 1 rad/s of error: past LOST_ON_RAD after 0.2 s, then the
    share rises to the most in 0.5 s at RISE_PER_S; kept while the mixer uses it;
    taken back at FALL_PER_S once yaw fits on its own."""
    s = YawShare(0.5)
    losing = dict(yaw_error_rad_s=-1.0, yaw_saturated=True, roll_pitch_saturated=False, used=0.0)
    got = run(s, 0.2 + 0.5 / RISE_PER_S + 0.01, **losing)
    first = next(i for i, v in enumerate(got) if v > 0.0) * DT
    assert first == pytest.approx(LOST_ON_RAD / 1.0, abs=2 * DT)
    assert got[-1] == 0.5
    helped = dict(yaw_error_rad_s=0.0, yaw_saturated=False, roll_pitch_saturated=True, used=0.3)
    assert min(run(s, 5.0, **helped)) == 0.5  # yaw fits with the share: it is kept
    alone = dict(yaw_error_rad_s=0.0, yaw_saturated=False, roll_pitch_saturated=False, used=0.0)
    back = run(s, 0.5 / FALL_PER_S + 0.01, **alone)
    assert back[round(1.0 / DT) - 1] == pytest.approx(0.5 - FALL_PER_S, abs=2 * DT)
    assert back[-1] == 0.0


def test_roll_and_pitch_saturated_on_their_own_have_nothing_to_give() -> None:
    s = YawShare(0.5)
    busy = dict(yaw_error_rad_s=2.0, yaw_saturated=True, roll_pitch_saturated=True, used=0.0)
    assert max(run(s, 2.0, **busy)) == 0.0
    assert s.lost_rad > LOST_ON_RAD  # the loss is known: given once they have room
    free = dict(yaw_error_rad_s=2.0, yaw_saturated=True, roll_pitch_saturated=False, used=0.0)
    assert run(s, 0.1, **free)[-1] == pytest.approx(0.1 * RISE_PER_S, abs=2 * DT)


def test_errors_that_change_sign_cancel() -> None:
    """A yaw saturated both ways in turn (an oscillation) loses no heading."""
    s = YawShare(0.5)
    for _ in range(50):
        for e in (1.0, -1.0):
            run(s, 0.1, yaw_error_rad_s=e, yaw_saturated=True, roll_pitch_saturated=False, used=0.0)
    assert s.value == 0.0


def test_no_share_when_the_most_is_zero_and_none_from_non_finite_input() -> None:
    off = YawShare(0.0)
    assert max(run(off, 2.0, yaw_error_rad_s=5.0, yaw_saturated=True,
                   roll_pitch_saturated=False, used=0.0)) == 0.0  # fmt: skip
    s = YawShare(0.5)
    s.update(DT, math.nan, True, False, 0.0)
    s.update(DT, math.inf, True, False, 0.0)
    assert s.lost_rad == 0.0 and s.value == 0.0
    run(s, 1.0, yaw_error_rad_s=1.0, yaw_saturated=True, roll_pitch_saturated=False, used=0.0)
    assert s.value > 0.0
    s.reset()
    assert s.value == 0.0 and s.lost_rad == 0.0
