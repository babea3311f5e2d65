"""Pilot sticks (RC microseconds) to rate references and thrust."""

from __future__ import annotations

import math

import pytest

from companion.control import AxisRates, StickMap
from companion.control.sticks import betaflight_rate_deg_s

DEG = math.pi / 180.0


@pytest.mark.parametrize(
    ("us", "x"), [(1000.0, -1.0), (1250.0, -0.5), (1500.0, 0.0), (1750.0, 0.5), (2000.0, 1.0)]
)
def test_linear_mapping_signs_and_ranges(us: float, x: float) -> None:
    cmd = StickMap().map([us, us, 1500.0, us])
    roll, pitch, yaw = cmd.rate_rad_s
    assert roll == pytest.approx(x * 720.0 * DEG, abs=1e-12)
    assert pitch == pytest.approx(x * 720.0 * DEG, abs=1e-12)
    assert yaw == pytest.approx(x * 360.0 * DEG, abs=1e-12)
    assert cmd.valid


def test_full_roll_right_is_720_deg_s() -> None:
    assert StickMap().map([2000, 1500, 1000, 1500]).rate_rad_s[0] == pytest.approx(4 * math.pi)


@pytest.mark.parametrize(
    ("us", "thrust"), [(1000.0, 0.0), (1250.0, 0.25), (2000.0, 1.0), (900.0, 0.0), (2100.0, 1.0)]
)
def test_throttle(us: float, thrust: float) -> None:
    assert StickMap().map([1500, 1500, us, 1500]).thrust == pytest.approx(thrust)


def test_deflection_beyond_endpoints_saturates() -> None:
    cmd = StickMap().map([2100.0, 900.0, 1500.0, 2200.0])
    assert cmd.valid
    assert cmd.rate_rad_s == pytest.approx((4 * math.pi, -4 * math.pi, 2 * math.pi))


def test_deadband() -> None:
    sm = StickMap(deadband_us=20.0)
    assert sm.map([1520, 1480, 1500, 1510]).rate_rad_s == (0.0, 0.0, 0.0)
    # Outside the band the remaining 480 us span the full range: (1760-1520)/480 = 0.5.
    assert sm.map([1760, 1500, 1500, 1500]).rate_rad_s[0] == pytest.approx(0.5 * 720 * DEG)
    assert sm.map([2000, 1500, 1500, 1500]).rate_rad_s[0] == pytest.approx(720 * DEG)


# Betaflight: rate = 200*r*x' / clamp(1 - |x|*s, 0.01, 1), x' = x|x|^3 e + x(1-e), cap 1998.
@pytest.mark.parametrize(
    ("x", "rc_rate", "super_rate", "expo", "deg_s"),
    [
        # x = 0.5, r = 1, s = 0.7, e = 0: x' = 0.5, denominator 1 - 0.35 = 0.65,
        # 200 * 0.5 / 0.65 = 153.846...
        (0.5, 1.0, 0.7, 0.0, 100.0 / 0.65),
        # Full stick: 200 / 0.3 = 666.67.
        (1.0, 1.0, 0.7, 0.0, 200.0 / 0.3),
        (-1.0, 1.0, 0.7, 0.0, -200.0 / 0.3),
        # Expo 0.5 at x = 0.5: x' = 0.5 * 0.125 * 0.5 + 0.5 * 0.5 = 0.28125;
        # 200 * 0.28125 / 0.65 = 86.538...
        (0.5, 1.0, 0.7, 0.5, 56.25 / 0.65),
        # r = 1.2, s = 0, x = 0.25: 200 * 1.2 * 0.25 = 60.
        (0.25, 1.2, 0.0, 0.0, 60.0),
        # r = 2.5, s = 0.99, full stick: denominator clamps at 0.01 -> 50000 -> cap 1998.
        (1.0, 2.5, 0.99, 0.0, 1998.0),
        (-1.0, 2.5, 0.99, 0.0, -1998.0),
        (0.0, 1.0, 0.7, 0.3, 0.0),
    ],
)
def test_betaflight_curve_by_hand(
    x: float, rc_rate: float, super_rate: float, expo: float, deg_s: float
) -> None:
    assert betaflight_rate_deg_s(x, rc_rate, super_rate, expo) == pytest.approx(deg_s, rel=1e-12)


def test_betaflight_curve_through_the_stick_map() -> None:
    bf = AxisRates(curve="betaflight", rc_rate=1.0, super_rate=0.7, expo=0.0)
    sm = StickMap(roll=bf, pitch=bf, yaw=bf)
    cmd = sm.map([1750, 1250, 1500, 2000])
    assert cmd.rate_rad_s == pytest.approx((100 / 0.65 * DEG, -100 / 0.65 * DEG, 200 / 0.3 * DEG))


@pytest.mark.parametrize("bad", [65535.0, 0.0, math.nan, math.inf, 700.0, 2300.0])
@pytest.mark.parametrize("channel", [0, 1, 2, 3])
def test_invalid_channel_centres_and_flags(bad: float, channel: int) -> None:
    """The invalid channel reads as centre stick (or zero throttle); valid is False."""
    chans = [1800.0, 1200.0, 1600.0, 1700.0]
    good = StickMap().map(chans)
    chans[channel] = bad
    cmd = StickMap().map(chans)
    assert not cmd.valid
    rates = list(good.rate_rad_s)
    thrust = good.thrust
    if channel == 2:
        thrust = 0.0
    else:
        rates[(0, 1, None, 2)[channel]] = 0.0  # type: ignore[index]
    assert cmd.rate_rad_s == pytest.approx(tuple(rates))
    assert cmd.thrust == thrust


def test_all_invalid_is_centre_sticks_zero_throttle() -> None:
    cmd = StickMap().map([65535.0, 0.0, math.nan, 65535.0])
    assert cmd == ((0.0, 0.0, 0.0), 0.0, False, (0.0, 0.0, 0.0))


def test_missing_channels() -> None:
    cmd = StickMap().map([1800.0, 1500.0])  # throttle and yaw missing
    assert not cmd.valid
    assert cmd.thrust == 0.0
    assert cmd.rate_rad_s == pytest.approx((0.6 * 720 * DEG, 0.0, 0.0))
    assert StickMap().map([]) == ((0.0, 0.0, 0.0), 0.0, False, (0.0, 0.0, 0.0))


def test_custom_channel_map() -> None:
    """TAER: throttle on ch1, roll ch2, pitch ch3, yaw ch4; channels = (roll, pitch, thr, yaw)."""
    sm = StickMap(channels=(2, 3, 1, 4))
    cmd = sm.map([1500.0, 2000.0, 1000.0, 1750.0])
    assert cmd.valid
    assert cmd.thrust == pytest.approx(0.5)
    assert cmd.rate_rad_s == pytest.approx((720 * DEG, -720 * DEG, 180 * DEG))
    # Mapped beyond the channels present: invalid.
    assert not StickMap(channels=(1, 2, 3, 16)).map([1500.0] * 8).valid


def test_the_deflections_are_the_sticks_past_the_deadband() -> None:
    sm = StickMap(deadband_us=20.0)
    # AETR: roll, pitch, throttle, yaw.
    assert StickMap().map([2000, 1250, 1500, 1600]).deflection == pytest.approx((1.0, -0.5, 0.2))
    assert sm.map([1510, 2000, 1500, 1000]).deflection == pytest.approx((0.0, 1.0, -1.0))
    assert sm.map([1760, 1500, 1500, 1500]).deflection[0] == pytest.approx(240 / 480)
    assert StickMap().map([1750, 1500, 1500, 1500]).deflection[0] == pytest.approx(0.5)
