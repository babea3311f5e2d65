r"""The vertical loop (altitude P, climb-rate iP, hover thrust learnt) against analytic answers.

The plant, integrated here: a point mass along the vertical,
:math:`\dot c = g (T_r / T_h)^p \cos\vartheta - g - d\,c` (climb rate ``c`` up,
rotor collective :math:`T_r`, true hover thrust :math:`T_h`, thrust exponent
``p``, a fixed tilt, linear drag ``d``), :math:`T_r` following the command through
an optional first-order lag. At steady hover :math:`T_r \cos\vartheta = T_h`
whatever ``p``: that is what the hover-thrust estimate must find.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from companion.control.ultralocal import GRAVITY_M_S2 as G
from companion.control.vertical import (
    DEFAULT_VERTICAL_GAINS,
    VerticalGains,
    VerticalLoop,
    VerticalSetpoint,
)


class Flight(NamedTuple):
    t: np.ndarray
    up: np.ndarray
    climb: np.ndarray
    thrust: np.ndarray
    hover: np.ndarray
    loop: VerticalLoop


def fly(
    gains: VerticalGains = DEFAULT_VERTICAL_GAINS,
    *,
    sp: VerticalSetpoint,
    hover_true: float,
    exponent: float = 1.0,
    tilt_rad: float = 0.0,
    lag_s: float = 0.0,
    drag: float = 0.0,
    up0: float = 0.0,
    dt: float = 0.01,
    duration_s: float = 10.0,
    prior: float | None = None,
) -> Flight:
    loop = VerticalLoop(gains)
    loop.reset(thrust=hover_true / math.cos(tilt_rad) if prior is None else prior)
    up, climb = up0, 0.0
    rotor = hover_true / math.cos(tilt_rad)
    cos_t = math.cos(tilt_rad)
    n = round(duration_s / dt)
    sub = 10
    h = dt / sub
    k_lag = -math.expm1(-h / lag_s) if lag_s > 0.0 else 1.0
    rows = []
    for i in range(n):
        cmd = loop.update(dt, -up, -climb, sp, cos_tilt=cos_t)
        for _ in range(sub):
            rotor += (cmd - rotor) * k_lag
            a = G * (rotor / hover_true) ** exponent * cos_t - G - drag * climb
            up += climb * h + 0.5 * a * h * h
            climb += a * h
        rows.append(((i + 1) * dt, up, climb, cmd, loop.hover_thrust))
    arr = np.array(rows)
    return Flight(arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3], arr[:, 4], loop)


def test_climb_rate_converges_to_its_reference() -> None:
    f = fly(sp=VerticalSetpoint(climb_m_s=1.0), hover_true=0.3, duration_s=8.0)
    assert f.climb[-1] == pytest.approx(1.0, abs=1e-4)
    # The designed error decay exp(-kp t), slowed by the estimate (b/alpha = 1/2 on
    # this linear-thrust plant): within 5 % after 4 time constants (1.6 s) and 2 s.
    kc = DEFAULT_VERTICAL_GAINS.kp_climb_1_s
    assert np.all(np.abs(f.climb[f.t >= 4.0 / kc + 2.0] - 1.0) < 0.05)
    assert f.climb.max() < 1.05


@pytest.mark.parametrize(
    ("hover_true", "exponent", "initial"),
    [(0.5, 1.0, 0.3), (0.4, 2.0, 0.7), (0.65, 2.0, 0.3), (0.2, 1.0, 0.15)],
)
def test_hover_thrust_estimate_converges_from_a_wrong_start(
    hover_true: float, exponent: float, initial: float
) -> None:
    gains = dataclasses.replace(DEFAULT_VERTICAL_GAINS, hover_thrust_initial=initial)
    f = fly(
        gains,
        sp=VerticalSetpoint(up_m=0.0),
        hover_true=hover_true,
        exponent=exponent,
        duration_s=25.0,
    )
    # Time constant 2 s once near hover: after 25 s e^-10 of the start is left.
    assert f.hover[-1] == pytest.approx(hover_true, abs=1e-3)
    assert abs(f.up[-1]) < 1e-3
    assert np.all(np.abs(f.up) < 0.05)  # holding altitude all along


def test_tilted_the_collective_is_the_level_one_over_cos_tilt() -> None:
    # Linear thrust, tilted 10 deg (within the learning gate): the rotors give
    # T / cos 10 to hover and the estimate is the level-equivalent T.
    tilt = math.radians(10.0)
    f = fly(sp=VerticalSetpoint(up_m=0.0), hover_true=0.45, tilt_rad=tilt, duration_s=25.0)
    assert f.hover[-1] == pytest.approx(0.45, abs=1e-3)
    assert f.thrust[-1] == pytest.approx(0.45 / math.cos(tilt), abs=1e-6)
    # Tilted 30 deg: altitude held on 1/cos, the estimate not learnt (outside the gate).
    tilt = math.radians(30.0)
    f = fly(sp=VerticalSetpoint(up_m=0.0), hover_true=0.45, tilt_rad=tilt, duration_s=10.0)
    assert f.thrust[-1] == pytest.approx(0.45 / math.cos(tilt), abs=1e-4)
    assert np.all(f.hover == DEFAULT_VERTICAL_GAINS.hover_thrust_initial)
    assert abs(f.up[-1]) < 1e-3


@pytest.mark.parametrize(("hover_true", "bound"), [(0.85, 0.8), (0.07, 0.1)])
def test_a_hover_thrust_outside_the_bounds_is_clamped_and_altitude_still_held(
    hover_true: float, bound: float
) -> None:
    gains = dataclasses.replace(DEFAULT_VERTICAL_GAINS, thrust_min=0.02)
    f = fly(gains, sp=VerticalSetpoint(up_m=1.0), hover_true=hover_true, duration_s=25.0)
    assert f.hover[-1] == bound
    assert f.up[-1] == pytest.approx(1.0, abs=1e-3)  # F carries what alpha misses
    loop = VerticalLoop()
    loop.reset(hover_thrust=5.0)
    assert loop.hover_thrust == DEFAULT_VERTICAL_GAINS.hover_thrust_max
    loop.reset(hover_thrust=0.0)
    assert loop.hover_thrust == DEFAULT_VERTICAL_GAINS.hover_thrust_min


def test_alpha_is_the_square_law_slope_at_the_hover_estimate() -> None:
    loop = VerticalLoop()
    for h in (0.1, 0.3, 0.8):
        loop.reset(hover_thrust=h)
        assert loop.alpha == pytest.approx(2.0 * G / h, rel=1e-15)


def test_no_hover_learning_on_the_ground() -> None:
    loop = VerticalLoop()
    loop.on_ground = True
    for _ in range(2000):  # 20 s of sitting still at 0.2 collective
        loop.update(0.01, 0.0, 0.0, VerticalSetpoint(), applied=0.2)
    assert loop.hover_thrust == DEFAULT_VERTICAL_GAINS.hover_thrust_initial


def test_tilt_compensation_divides_by_cos_tilt_bounded() -> None:
    def first_output(cos_tilt: float) -> float:
        loop = VerticalLoop()
        loop.reset(thrust=0.4)
        return loop.update(0.01, 0.0, -0.2, VerticalSetpoint(), cos_tilt=cos_tilt)

    level = first_output(1.0)
    assert first_output(math.cos(math.radians(30.0))) == pytest.approx(
        level / math.cos(math.radians(30.0)), rel=1e-12
    )
    # Beyond tilt_compensation_max_rad (60 deg) the factor stays at 1 / cos 60 = 2,
    # inverted included.
    assert first_output(math.cos(math.radians(75.0))) == pytest.approx(2.0 * level, rel=1e-12)
    assert first_output(-1.0) == pytest.approx(2.0 * level, rel=1e-12)


def test_altitude_hold_from_below_without_overshoot() -> None:
    # Cascade of altitude P (0.6/s) on the climb iP (2.5/s): ideally critically
    # damped (zeta = sqrt(2.5 / 0.6) / 2 = 1.02); allow 2 % of the step for the
    # estimate's lag, on a plant with motor lag, drag and a square-law thrust.
    f = fly(
        sp=VerticalSetpoint(up_m=2.0),
        hover_true=0.45,
        exponent=2.0,
        lag_s=0.05,
        drag=0.3,
        duration_s=15.0,
    )
    assert f.up.max() < 2.0 + 0.02 * 2.0
    assert f.up[-1] == pytest.approx(2.0, abs=1e-3)


def test_climb_reference_is_bounded() -> None:
    g = DEFAULT_VERTICAL_GAINS
    loop = VerticalLoop()
    loop.update(0.01, 0.0, 0.0, VerticalSetpoint(up_m=50.0))  # 50 m below the setpoint
    assert loop.climb_ref_m_s == g.climb_max_m_s
    loop.update(0.01, 0.0, 0.0, VerticalSetpoint(up_m=-50.0))
    assert loop.climb_ref_m_s == -g.descent_max_m_s
    loop.update(0.01, 0.0, 0.0, VerticalSetpoint(climb_m_s=0.5, up_m=1.0))
    assert loop.climb_ref_m_s == pytest.approx(0.5 + g.kp_up_1_s * 1.0)


def test_ned_signs() -> None:
    # 10 m up (z = -10), climbing at 1 m/s (vz = -1), asked to hold 10 m: the climb
    # rate is 1 m/s too high, so the collective drops below the prior.
    loop = VerticalLoop()
    loop.reset(thrust=0.4)
    t = loop.update(0.01, -10.0, -1.0, VerticalSetpoint(up_m=10.0))
    assert loop.climb_ref_m_s == 0.0
    assert t < 0.4
    # Below the setpoint and still: more than the prior.
    loop.reset(thrust=0.4)
    assert loop.update(0.01, 0.0, 0.0, VerticalSetpoint(up_m=2.0)) > 0.4


def test_thrust_bounds_and_saturation_flag() -> None:
    g = DEFAULT_VERTICAL_GAINS
    loop = VerticalLoop()
    assert loop.update(0.01, 0.0, 20.0, VerticalSetpoint(climb_m_s=3.0)) == g.thrust_max
    assert loop.saturated
    loop.reset()
    assert loop.update(0.01, 0.0, -20.0, VerticalSetpoint(climb_m_s=-1.5)) == g.thrust_min
    assert loop.saturated


def test_non_finite_inputs_give_the_hover_thrust_and_the_flag() -> None:
    loop = VerticalLoop()
    loop.reset(hover_thrust=0.4)
    assert loop.update(0.01, math.nan, 0.0, VerticalSetpoint()) == pytest.approx(0.4)
    assert loop.fault
    # Tilt-compensated hover thrust when the tilt is known.
    assert loop.update(0.01, 0.0, math.inf, VerticalSetpoint(), cos_tilt=0.8) == pytest.approx(0.5)
    assert loop.update(math.nan, 0.0, 0.0, VerticalSetpoint()) == pytest.approx(0.4)
    # Setpoint non-finite: hold (climb reference 0), flagged.
    t = loop.update(0.01, 0.0, 0.0, VerticalSetpoint(climb_m_s=math.nan, up_m=3.0))
    assert loop.fault and loop.climb_ref_m_s == 0.0 and math.isfinite(t)
    loop.update(0.01, 0.0, 0.0, VerticalSetpoint())
    assert not loop.fault
    assert loop.nonfinite_events == 4


finite_or_not = st.one_of(
    st.floats(-1e6, 1e6), st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -1e308])
)


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(*[finite_or_not] * 8), min_size=1, max_size=5))
@example(  # found by a run under load: the climb's change overflowed, F went NaN
    [
        (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        (1e308, 0.0, -1e308, 0.0, 0.0, 0.0, 0.0, 0.0),
        (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0),
    ]
)
def test_never_a_non_finite_or_unbounded_thrust(samples: list[tuple[float, ...]]) -> None:
    g = DEFAULT_VERTICAL_GAINS
    loop = VerticalLoop()
    for s in samples:
        sp = VerticalSetpoint(s[3], s[4], s[5])
        t = loop.update(abs(s[0]), s[1], s[2], sp, cos_tilt=s[6], applied=s[7])
        assert math.isfinite(t) and g.thrust_min <= t <= g.thrust_max
        assert g.hover_thrust_min <= loop.hover_thrust <= g.hover_thrust_max


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"kp_climb_1_s": 0.0}, r"VerticalGains\.kp_climb_1_s must be finite and > 0"),
        ({"kp_up_1_s": math.nan}, r"VerticalGains\.kp_up_1_s"),
        ({"thrust_max": 1.5}, r"VerticalGains\.thrust_max must be in \(thrust_min, 1\]"),
        ({"thrust_min": 0.95}, r"VerticalGains\.thrust_max must be in \(thrust_min, 1\]"),
        ({"hover_thrust_initial": 0.9}, r"VerticalGains\.hover_thrust_initial must be in"),
        ({"hover_thrust_max": 1.0}, r"VerticalGains\.hover_thrust_max must be in"),
        ({"thrust_curve_exponent": 0.5}, r"VerticalGains\.thrust_curve_exponent must be >= 1"),
        ({"tilt_compensation_max_rad": 2.0}, r"VerticalGains\.tilt_compensation_max_rad"),
        ({"inner_lag_s": -1.0}, r"VerticalGains\.inner_lag_s must be finite and >= 0"),
        ({"hover_learn_tau_s": math.inf}, r"VerticalGains\.hover_learn_tau_s"),
    ],
)
def test_gains_validation_names_the_field(changes: dict[str, float], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        VerticalGains(**changes)


def test_the_restart_sample_keeps_the_collective_it_took_over_at() -> None:
    """dt 0 marks the first sample after an engagement: no jump to the hover estimate."""
    loop = VerticalLoop()
    loop.reset(thrust=0.55)
    out = loop.update(0.0, -5.0, 0.0, VerticalSetpoint(0.0, 5.0))
    assert out == pytest.approx(0.55) and not loop.fault and loop.nonfinite_events == 0
    assert loop.update(0.004, -5.0, 0.0, VerticalSetpoint(0.0, 5.0)) == pytest.approx(
        0.55, abs=0.01
    )
