"""Mixer: geometry, the paper's equation, saturation priority, and the unrolled path.

Convention (mixer docstring): ``motor_i = thrust + 0.5*(R_i*roll + P_i*pitch + Y_i*yaw)``
with ``R_i = -y_i/max|y|``, ``P_i = x_i/max|x|``, ``Y_i = +1`` for ccw, -1 for cw.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.control import Mixer
from tests.control.plants import f450_mixer, quad_x_mixer, torques_from_motors

# ---------------------------------------------------------------------------
# Geometry and signs.


def test_f450_factors_px4_quad_x() -> None:
    """PX4 order: 1 front-right CCW, 2 rear-left CCW, 3 front-left CW, 4 rear-right CW."""
    m = f450_mixer()
    roll, pitch, yaw = m.factors()
    # +roll (roll right) raises the left motors (y < 0): 2 and 3.
    assert roll == (-1.0, 1.0, 1.0, -1.0)
    # +pitch (nose up) raises the front motors: 1 and 3.
    assert pitch == (1.0, -1.0, 1.0, -1.0)
    # +yaw (nose right) raises the CCW motors: 1 and 2.
    assert yaw == (1.0, 1.0, -1.0, -1.0)
    assert m.idle == 0.05
    assert m.n_motors == 4


@pytest.mark.parametrize(
    ("axis", "up", "down"),
    [(0, {1, 2}, {0, 3}), (1, {0, 2}, {1, 3}), (2, {0, 1}, {2, 3})],
)
def test_f450_positive_torque_moves_the_right_motors(
    axis: int, up: set[int], down: set[int]
) -> None:
    m = f450_mixer()
    tq = [0.0, 0.0, 0.0]
    tq[axis] = 0.2
    res = m.mix(0.5, *tq)
    for i in up:
        assert res.motors[i] == pytest.approx(0.6)
    for i in down:
        assert res.motors[i] == pytest.approx(0.4)


def test_paper_mixer_signs_match_the_paper_text() -> None:
    """'+' frame: 1 front CW, 2 right CCW, 3 back CW, 4 left CCW (motor k = index k-1)."""
    m = Mixer.paper()
    base = np.array(m.mix(0.5, 0.0, 0.0, 0.0).motors)
    # Rolling right: motor 4 up, motor 2 down, 1 and 3 unchanged.
    d = np.array(m.mix(0.5, 0.2, 0.0, 0.0).motors) - base
    np.testing.assert_allclose(d, [0.0, -0.1, 0.0, 0.1], atol=1e-15)
    # Pitching forward (nose down = negative FRD pitch): motor 3 up, motor 1 down.
    d = np.array(m.mix(0.5, 0.0, -0.2, 0.0).motors) - base
    np.testing.assert_allclose(d, [-0.1, 0.0, 0.1, 0.0], atol=1e-15)
    # Yawing counter-clockwise seen from above (nose left = negative FRD yaw):
    # the clockwise motors 1 and 3 up, the counter-clockwise 2 and 4 down.
    d = np.array(m.mix(0.5, 0.0, 0.0, -0.2).motors) - base
    np.testing.assert_allclose(d, [0.1, -0.1, 0.1, -0.1], atol=1e-15)


def test_paper_equation_rows() -> None:
    """u1 = ut - u_theta - u_psi, u2 = ut - u_phi + u_psi, u3 = ut + u_theta - u_psi,
    u4 = ut + u_phi + u_psi with u_phi = roll/2, u_theta = -pitch/2, u_psi = yaw/2."""
    m = Mixer.paper()
    ut, roll, pitch, yaw = 0.5, 0.1, -0.06, 0.04
    u_phi, u_theta, u_psi = roll / 2, -pitch / 2, yaw / 2
    expected = [ut - u_theta - u_psi, ut - u_phi + u_psi, ut + u_theta - u_psi, ut + u_phi + u_psi]
    np.testing.assert_allclose(m.mix(ut, roll, pitch, yaw).motors, expected, rtol=1e-15)


def test_from_geometry_plus_layout_equals_paper() -> None:
    L = 0.225
    plus = Mixer.from_geometry(
        [(L, 0.0, 0.0), (0.0, L, 0.0), (-L, 0.0, 0.0), (0.0, -L, 0.0)],
        ["cw", "ccw", "cw", "ccw"],
    )
    for got, want in zip(plus.factors(), Mixer.paper().factors()):
        np.testing.assert_array_equal(np.array(got) + 0.0, np.array(want) + 0.0)


def test_from_geometry_rejects_bad_input() -> None:
    with pytest.raises(ValueError):
        Mixer.from_geometry([(1, 0), (-1, 0), (0.5, 0), (-0.5, 0)], ["cw", "ccw", "cw", "ccw"])
    with pytest.raises(ValueError):
        Mixer.from_geometry([(1, 1), (-1, -1), (1, -1), (-1, 1)], ["cw", "ccw", "cw", "up"])
    with pytest.raises(ValueError):
        Mixer.from_geometry([(1, 1), (-1, -1), (1, -1)], ["cw", "ccw", "cw", "ccw"])
    with pytest.raises(ValueError):
        Mixer([1, -1, 1], [1, -1, 1], [1, -1])
    with pytest.raises(ValueError):
        Mixer([1, -1, 1], [1, -1, 1], [1, -1, 1], idle=0.5)


# ---------------------------------------------------------------------------
# Allocation.


def test_unsaturated_allocation_round_trips() -> None:
    m = f450_mixer()
    rng = np.random.default_rng(5)
    for _ in range(200):
        thrust = rng.uniform(0.3, 0.7)
        r, p, y = rng.uniform(-0.15, 0.15, 3)
        res = m.mix(thrust, r, p, y)
        np.testing.assert_allclose(
            torques_from_motors(m, res.motors), [thrust, r, p, y], atol=1e-12
        )
        np.testing.assert_allclose(res.achieved, [r, p, y], rtol=1e-15)
        assert res.thrust == thrust
        assert res.saturated_axes == (False, False, False)
        assert res.saturated_motors == (False,) * 4


def test_yaw_gives_way_to_roll() -> None:
    """Large yaw with roll at mid throttle, F450 (idle 0.05).

    roll 0.8 -> d = 0.5*0.8*R = (-0.4, 0.4, 0.4, -0.4), fits, thrust stays 0.5.
    Yaw room per motor (yaw factor 0.5*Y = +-0.5, request 0.8):
    m2 (d=+0.4, up): (1-0.5-0.4)/0.4 = 0.25; m4 (d=-0.4, down): (0.05-0.5+0.4)/-0.4 = 0.125.
    So yaw is scaled by 0.125: 0.1 realised. Motors 0.15, 0.95, 0.85, 0.05.
    """
    m = f450_mixer()
    res = m.mix(0.5, 0.8, 0.0, 0.8)
    np.testing.assert_allclose(res.achieved, [0.8, 0.0, 0.1], rtol=1e-12)
    np.testing.assert_allclose(res.motors, [0.15, 0.95, 0.85, 0.05], rtol=1e-12)
    assert res.saturated_axes == (False, False, True)
    assert res.saturated_motors == (False, False, False, True)
    assert res.thrust == 0.5
    # What the motors do is what the result says was achieved.
    np.testing.assert_allclose(torques_from_motors(m, res.motors)[1:], res.achieved, atol=1e-12)


def test_yaw_never_moves_the_collective() -> None:
    """Yaw gets the headroom the collective leaves; the collective stays (F450, idle 0.05).

    At 0.9 a yaw request of 0.4 (0.2 per motor) has room for (1 - 0.9) / 0.2 = 0.5
    of it; at 0.1 a request of 1 (0.5 per motor) has (0.1 - 0.05) / 0.5 = 0.1 of it.
    """
    m = f450_mixer()
    res = m.mix(0.9, 0.0, 0.0, 0.4)
    assert res.thrust == 0.9
    assert res.achieved[2] == pytest.approx(0.2)
    assert res.saturated_axes == (False, False, True)
    res = m.mix(0.1, 0.0, 0.0, 1.0)
    assert res.thrust == 0.1
    assert res.achieved[2] == pytest.approx(0.1)
    assert res.saturated_axes == (False, False, True)


def test_roll_and_pitch_scaled_together_when_they_exceed_the_range() -> None:
    """roll = pitch = 1: d = (0, 0, 1, -1) spreads 2 > 1 - idle = 0.95: scale 0.475."""
    res = f450_mixer().mix(0.5, 1.0, 1.0, 0.0)
    np.testing.assert_allclose(res.achieved, [0.475, 0.475, 0.0], rtol=1e-12)
    assert res.saturated_axes == (True, True, False)
    np.testing.assert_allclose(res.motors, [0.525, 0.525, 1.0, 0.05], rtol=1e-12)


@pytest.mark.parametrize(
    ("thrust", "t_eff", "motors"),
    [
        # Zero throttle: collective raised so the low motors sit at idle.
        (0.0, 0.3, [0.05, 0.55, 0.55, 0.05]),
        # Full throttle: collective lowered so the high motors sit at 1.
        (1.0, 0.75, [0.5, 1.0, 1.0, 0.5]),
    ],
)
def test_air_mode_keeps_roll_authority(thrust: float, t_eff: float, motors: list[float]) -> None:
    res = f450_mixer().mix(thrust, 0.5, 0.0, 0.0)
    assert res.achieved == (0.5, 0.0, 0.0)
    assert res.saturated_axes == (False, False, False)
    assert res.thrust == pytest.approx(t_eff)
    np.testing.assert_allclose(res.motors, motors, rtol=1e-12)
    assert res.saturated_motors == tuple(mi in (0.05, 1.0) for mi in res.motors)


def test_zero_command_sits_at_idle() -> None:
    res = f450_mixer().mix(0.0, 0.0, 0.0, 0.0)
    assert res.motors == (0.05,) * 4
    assert res.saturated_motors == (True,) * 4
    assert res.thrust == 0.05


def test_request_beyond_full_scale_is_reported_saturated() -> None:
    """MixResult.saturated_axes: True where the realised torque is smaller than
    the requested one. A roll request of 2 on an idle-0 quad realises 1."""
    res = quad_x_mixer(idle=0.0).mix(0.5, 2.0, 0.0, 0.0)
    assert res.achieved[0] == 1.0
    assert res.saturated_axes[0], "realised 1.0 of a 2.0 request but not flagged saturated"


def test_non_finite_inputs_are_treated_as_zero() -> None:
    """Mixer.mix docstring: "Non-finite inputs are treated as zero"."""
    m = f450_mixer()
    zero = m.mix(0.5, 0.0, 0.0, 0.0)
    assert m.mix(math.nan, 0.0, 0.0, 0.0).thrust == 0.05  # NaN thrust -> 0 -> idle
    assert m.mix(0.5, math.nan, math.nan, math.nan) == zero
    assert m.mix(0.5, math.inf, 0.0, 0.0) == zero
    assert m.mix(0.5, 0.0, -math.inf, 0.0) == zero


def test_zero_yaw_factor_mixer_does_not_divide_by_zero() -> None:
    # Motors 2 and 4 take no part in yaw: the generic path must skip them.
    m = Mixer([-1.0, 1.0, 1.0, -1.0], [1.0, -1.0, 1.0, -1.0], [1.0, 0.0, -1.0, 0.0])
    res = m.mix(0.5, 0.1, 0.1, 0.9)
    assert all(math.isfinite(x) and 0.0 <= x <= 1.0 for x in res.motors)
    # Roll/pitch first: d = (0, 0, 0.1, -0.1). Yaw room: motor 1 (+0.5*0.9)
    # (1 - 0.5 - 0)/0.45 = 1.11, motor 3 (-0.45): (0 - 0.5 - 0.1)/-0.45 = 1.33.
    np.testing.assert_allclose(res.achieved, [0.1, 0.1, 0.9], rtol=1e-12)
    np.testing.assert_allclose(res.motors, [0.95, 0.5, 0.15, 0.4], rtol=1e-12)
    # Saturating yaw on the remaining motors: (1 - 0.9)/0.5 = 0.2 of it at 0.9
    # (the collective does not move for yaw).
    res = m.mix(0.9, 0.0, 0.0, 1.0)
    np.testing.assert_allclose(res.achieved, [0.0, 0.0, 0.2], rtol=1e-12)
    assert res.thrust == 0.9
    assert res.saturated_axes == (False, False, True)


def test_subnormal_yaw_request_does_not_crash() -> None:
    """0.5 * 5e-324 underflows to 0.0, and the yaw headroom divides by it."""
    m = f450_mixer()
    res = m.mix(0.5, 0.0, 0.0, 5e-324)
    assert res.motors == (0.5,) * 4


# ---------------------------------------------------------------------------
# The unrolled quad path is the generic path.

finite_or_not = st.one_of(
    st.floats(-2.0, 2.0, allow_subnormal=False),  # subnormals: see the test above
    st.sampled_from([0.0, -0.0, 1.0, -1.0, math.nan, math.inf, -math.inf, 0.999999999]),
)


@settings(max_examples=400, deadline=None)
@given(
    thrust=finite_or_not,
    roll=finite_or_not,
    pitch=finite_or_not,
    yaw=finite_or_not,
    idle=st.sampled_from([0.0, 0.05, 0.2]),
    share=st.sampled_from([0.0, 0.3, 0.5, 0.9, math.nan]),
)
def test_quad_path_equals_generic_path(
    thrust: float, roll: float, pitch: float, yaw: float, idle: float, share: float
) -> None:
    m = quad_x_mixer(idle=idle)
    assert m._quad  # the fast path is the one used
    quad = m._mix_quad(thrust, roll, pitch, yaw, share)
    generic = m._mix_generic(thrust, roll, pitch, yaw, share)
    assert quad.yaw_share == generic.yaw_share
    assert quad.saturated_axes == generic.saturated_axes
    assert quad.saturated_motors == generic.saturated_motors
    np.testing.assert_allclose(quad.motors, generic.motors, rtol=0, atol=1e-15)
    np.testing.assert_allclose(quad.achieved, generic.achieved, rtol=0, atol=1e-15)
    np.testing.assert_allclose(quad.thrust, generic.thrust, rtol=0, atol=1e-15)


@settings(max_examples=400, deadline=None)
@given(
    thrust=st.floats(0.0, 1.0),
    roll=st.floats(-1.0, 1.0),
    pitch=st.floats(-1.0, 1.0),
    yaw=st.floats(-1.0, 1.0),
    idle=st.sampled_from([0.0, 0.05, 0.2]),
)
def test_yaw_never_costs_roll_pitch_or_the_collective(
    thrust: float, roll: float, pitch: float, yaw: float, idle: float
) -> None:
    """Against the same request without yaw: roll, pitch and the collective as before."""
    m = quad_x_mixer(idle=idle)
    got, ref = m.mix(thrust, roll, pitch, yaw), m.mix(thrust, roll, pitch, 0.0)
    assert got.achieved[:2] == ref.achieved[:2]
    assert got.thrust == ref.thrust
    assert all(idle <= x <= 1.0 for x in got.motors)


# ---------------------------------------------------------------------------
# Yaw's share of roll and pitch (companion.control.yaw_share decides it).


def test_a_yaw_share_gives_yaw_roll_and_pitch_up_to_the_share() -> None:
    """The F450 case above (roll 0.8, yaw 0.8 at 0.5): yaw fits once roll and
    pitch are shrunk to f <= 0.125 (motor 3: 0.5 - 0.4 f - 0.4 >= 0.05).

    With a share of 0.5 (f = 0.5) it does not: yaw gets min((0.5 - 0.2) / 0.4,
    (0.45 - 0.2) / 0.4) = 0.625 of its request, 0.5 realised, roll 0.4; with 0.9
    the whole yaw fits at the least shrink that allows it (the bisection's 1/256).
    """
    m = f450_mixer()
    half = m.mix(0.5, 0.8, 0.0, 0.8, yaw_share=0.5)
    np.testing.assert_allclose(half.achieved, [0.4, 0.0, 0.5], rtol=1e-12)
    assert half.yaw_share == pytest.approx(0.5)
    assert half.saturated_axes == (True, False, True)  # the laws learn what was applied
    assert half.thrust == 0.5  # yaw never moves the collective
    np.testing.assert_allclose(torques_from_motors(m, half.motors)[1:], half.achieved, atol=1e-12)
    most = m.mix(0.5, 0.8, 0.0, 0.8, yaw_share=0.9)
    assert most.achieved[2] == pytest.approx(0.8)
    assert most.saturated_axes[2] is False
    assert 0.8 * 0.125 - 0.9 / 256 * 0.8 <= most.achieved[0] <= 0.8 * 0.125
    assert most.yaw_share == pytest.approx(0.875, abs=0.9 / 256)


def test_a_share_not_needed_changes_nothing() -> None:
    """Yaw that fits, or no yaw: the share is not used and the result is the plain one."""
    m = f450_mixer()
    for args in ((0.5, 0.2, 0.1, 0.1), (0.5, 0.8, 0.0, 0.0), (0.9, 0.0, 0.0, 0.1)):
        plain, shared = m.mix(*args), m.mix(*args, yaw_share=0.5)
        assert shared == plain
        assert shared.yaw_share == 0.0


@settings(max_examples=400, deadline=None)
@given(
    thrust=st.floats(0.0, 1.0),
    roll=st.floats(-1.0, 1.0),
    pitch=st.floats(-1.0, 1.0),
    yaw=st.floats(-1.0, 1.0),
    share=st.floats(0.0, 1.0),
    idle=st.sampled_from([0.0, 0.05, 0.2]),
)
def test_a_share_costs_roll_and_pitch_at_most_the_share_for_yaw_or_lift(
    thrust: float, roll: float, pitch: float, yaw: float, share: float, idle: float
) -> None:
    m = quad_x_mixer(idle=idle)
    got, plain = m.mix(thrust, roll, pitch, yaw, yaw_share=share), m.mix(thrust, roll, pitch, yaw)
    assert all(idle <= x <= 1.0 for x in got.motors)
    assert 0.0 <= got.yaw_share <= share
    for a in (0, 1):  # shrunk by no more than the share, never grown
        assert abs(got.achieved[a]) <= abs(plain.achieved[a]) + 1e-12
        assert abs(got.achieved[a]) >= (1.0 - share) * abs(plain.achieved[a]) - 1e-12
    # Given for yaw, or at the top of the collective for the lift the air mode cut.
    assert abs(got.achieved[2]) >= abs(plain.achieved[2]) - 1e-12 or got.thrust > plain.thrust
    # The collective moves only back toward the one asked (less air-mode shift).
    asked = max(thrust, idle)
    assert abs(got.thrust - asked) <= abs(plain.thrust - asked) + 1e-12
    if got.yaw_share == 0.0:
        assert got == plain
