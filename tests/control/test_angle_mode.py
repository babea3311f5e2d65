"""The angle mode's sticks to attitude setpoint, against analytic answers."""

from __future__ import annotations

import math

import pytest

from companion.control.angle_mode import AngleMode, stick_tilt_rad
from companion.control.attitude import DEFAULT_ATTITUDE_GAINS, AttitudeLoop, AttitudeSetpoint

MAX_TILT_DEG = 35.0  # PX4's MPC_MAN_TILT_MAX default
MAX = math.radians(MAX_TILT_DEG)
LEVEL = (1.0, 0.0, 0.0, 0.0)


@pytest.mark.parametrize(
    ("x", "expected"),
    [
        ((0.0, 0.0), (0.0, 0.0)),
        ((1.0, 0.0), (MAX, 0.0)),
        ((0.0, -0.5), (0.0, -0.5 * MAX)),
        ((1.0, 1.0), (MAX / math.sqrt(2.0), MAX / math.sqrt(2.0))),  # a diagonal: no further
        ((0.6, 0.6), (0.6 * MAX, 0.6 * MAX)),  # inside the circle: as asked
        ((math.nan, 1.0), (0.0, 0.0)),
    ],
)
def test_sticks_are_a_tilt_at_most_the_maximum(
    x: tuple[float, float], expected: tuple[float, float]
) -> None:
    assert stick_tilt_rad(*x, MAX) == pytest.approx(expected)


def test_the_reference_is_the_attitude_loops_for_the_sticks_setpoint() -> None:
    mode, loop = AngleMode(MAX_TILT_DEG), AttitudeLoop()
    for k in range(5):
        got = mode.reference(0.004, LEVEL, (0.0, 0.0, 0.0), (0.5, 0.0, 0.3), 0.2, on_ground=False)
        want = loop.update(
            0.004, LEVEL, (0.0, 0.0, 0.0), AttitudeSetpoint(0.5 * MAX, 0.0, None, 0.2)
        )
        assert got == want, k
    assert mode.setpoint == AttitudeSetpoint(0.5 * MAX, 0.0, None, 0.2)
    # The first sample: K_P times the error, the yaw rate as feedforward.
    first = AngleMode(MAX_TILT_DEG).reference(
        0.004, LEVEL, (0.0, 0.0, 0.0), (0.5, 0.0, 0.0), 0.0, on_ground=False
    )
    assert first[0] == pytest.approx(DEFAULT_ATTITUDE_GAINS.kp_roll_pitch_1_s * 0.5 * MAX)


def test_on_the_ground_no_rates_and_nothing_learnt() -> None:
    mode = AngleMode(MAX_TILT_DEG)
    tilted = (math.cos(0.1), math.sin(0.1), 0.0, 0.0)
    for _ in range(50):
        assert mode.reference(
            0.004, tilted, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), 1.0, on_ground=True
        ) == (
            0.0,
            0.0,
            0.0,
        )
    assert mode.loop.f_hat == (0.0, 0.0, 0.0)


def test_a_non_finite_stick_or_yaw_rate_is_centred() -> None:
    mode = AngleMode(MAX_TILT_DEG)
    mode.reference(0.004, LEVEL, (0.0, 0.0, 0.0), (math.inf, 0.0, 0.0), math.nan, on_ground=False)
    assert mode.setpoint == AttitudeSetpoint(0.0, 0.0, None, 0.0)


@pytest.mark.parametrize("deg", [0.0, -1.0, 61.0, math.nan])
def test_a_tilt_beyond_sense_is_refused(deg: float) -> None:
    with pytest.raises(ValueError, match="max_tilt_deg"):
        AngleMode(max_tilt_deg=deg)


def test_a_saturated_rate_loop_backs_the_roll_and_pitch_gain_off() -> None:
    # Roll saturated for good: the backoff's floor (0.55); the first sample after a
    # reset is K_P s times the error. Not known (rates output): no backoff.
    kp = DEFAULT_ATTITUDE_GAINS.kp_roll_pitch_1_s
    for sat, scale in (((True, False, False), 0.55), (None, 1.0)):
        mode = AngleMode(MAX_TILT_DEG)
        for _ in range(2000):
            mode.reference(0.004, LEVEL, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0,
                           on_ground=False, rate_saturated=sat)  # fmt: skip
        assert mode.backoff.scale == pytest.approx(scale)
        mode.loop.reset()  # the estimate afresh, the backoff kept
        first = mode.reference(
            0.004, LEVEL, (0.0, 0.0, 0.0), (0.5, 0.0, 0.0), 0.0, on_ground=False,
            rate_saturated=sat,
        )  # fmt: skip
        assert first[0] == pytest.approx(kp * scale * 0.5 * MAX)
    mode.reset()
    assert mode.backoff.scale == 1.0 and mode.loop.gain_scale == 1.0
