"""The last gate before the wire: NaN and inf on every field of both outputs."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from companion.control.gate import gate_actuator, gate_rates

NAN, INF = math.nan, math.inf
RATE_MAX = (3.0, 3.0, 2.0)
PILOT = (0.5, -0.25, 0.125)


@pytest.mark.parametrize("field", range(4))
@pytest.mark.parametrize("bad", [NAN, INF, -INF])
def test_actuator_every_field(field: int, bad: float) -> None:
    vals = [0.1, -0.2, 0.3, 0.6]
    vals[field] = bad
    controls, replaced = gate_actuator((vals[0], vals[1], vals[2]), vals[3], safe_thrust=0.42)
    assert all(math.isfinite(c) for c in controls)
    expected = list(vals)
    if bad != bad:
        expected[field] = 0.42 if field == 3 else 0.0  # no torque; the pilot's collective
        assert replaced == 1
    else:
        lo, hi = (0.0, 1.0) if field == 3 else (-1.0, 1.0)
        expected[field] = hi if bad > 0 else lo
        assert replaced == 0
    assert list(controls) == expected


@pytest.mark.parametrize("field", range(4))
@pytest.mark.parametrize("bad", [NAN, INF, -INF])
def test_rates_every_field(field: int, bad: float) -> None:
    vals = [0.1, -0.2, 0.3, 0.6]
    vals[field] = bad
    rates, thrust, replaced = gate_rates(vals[:3], vals[3], PILOT, RATE_MAX, safe_thrust=0.42)
    out = [*rates, thrust]
    assert all(math.isfinite(c) for c in out)
    expected = list(vals)
    if bad != bad:
        expected[field] = 0.42 if field == 3 else PILOT[field]  # the pilot's rate
        assert replaced == 1
    else:
        lo, hi = (0.0, 1.0) if field == 3 else (-RATE_MAX[field], RATE_MAX[field])
        expected[field] = hi if bad > 0 else lo
        assert replaced == 0
    assert out == expected


def test_a_safe_value_that_is_itself_bad_still_gives_a_value_in_range() -> None:
    controls, n = gate_actuator((NAN, NAN, NAN), NAN, safe_thrust=NAN)
    assert controls == (0.0, 0.0, 0.0, 0.0) and n == 4
    rates, thrust, n = gate_rates((NAN, NAN, NAN), NAN, (NAN, 9.0, -9.0), RATE_MAX, NAN)
    assert rates == (0.0, 3.0, -2.0) and thrust == 0.0 and n == 4


any_float = st.floats(allow_nan=True, allow_infinity=True)


@given(st.tuples(any_float, any_float, any_float), any_float, any_float)
def test_actuator_output_is_always_in_range(torque, thrust, safe) -> None:  # type: ignore[no-untyped-def]
    (r, p, y, t), _ = gate_actuator(torque, thrust, safe)
    assert all(-1.0 <= v <= 1.0 for v in (r, p, y)) and 0.0 <= t <= 1.0


@given(
    st.tuples(any_float, any_float, any_float),
    any_float,
    st.tuples(any_float, any_float, any_float),
    any_float,
)
def test_rates_output_is_always_in_range(rates, thrust, pilot, safe) -> None:  # type: ignore[no-untyped-def]
    out, t, _ = gate_rates(rates, thrust, pilot, RATE_MAX, safe)
    assert all(-m <= v <= m for v, m in zip(out, RATE_MAX)) and 0.0 <= t <= 1.0


def test_values_in_range_pass_unchanged() -> None:
    assert gate_actuator((0.1, -1.0, 1.0), 0.0, 0.5) == ((0.1, -1.0, 1.0, 0.0), 0)
    assert gate_rates((3.0, -3.0, 0.0), 1.0, PILOT, RATE_MAX, 0.5) == ((3.0, -3.0, 0.0), 1.0, 0)
