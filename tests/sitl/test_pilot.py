"""Tests of the simulated pilot: mapping, maneuver library, virtual pilot, loader."""

from __future__ import annotations

import hashlib
import itertools
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from companion.errors import ConfigError
from sitl.pilot import (
    DEFAULT_RATE_FULL_SCALE_DEG_S,
    MANEUVERS,
    PilotParams,
    PilotView,
    ScriptedPilot,
    Segment,
    Sticks,
    level_rates_rad_s,
    load_stick_script,
    make_pilot,
    rate_to_stick_us,
    stick_us_to_rate,
    stick_us_to_throttle,
    throttle_command,
)
from sitl.scenario import load_scenario
from sitl.world import flight_streams

SCENARIOS = Path(__file__).resolve().parents[2] / "sitl" / "sticks"
EXAMPLE = SCENARIOS / "example_sticks.yaml"
HOVER = 0.45
DT_S = 0.001
STEP_MANEUVERS = {"step-roll", "step-pitch", "step-yaw"}


def view(
    t_s: float = 10.0,
    *,
    roll: float = 0.0,
    pitch: float = 0.0,
    alt: float = 10.0,
    climb: float = 0.0,
    hover: float = HOVER,
) -> PilotView:
    return PilotView(t_s, roll, pitch, 0.0, (0.0, 0.0, 0.0), alt, climb, hover)


# --------------------------------------------------------------------------- kinematic model


@dataclass
class Flight:
    """Channels and states of a flight of a crude perfect-rate-tracking vehicle."""

    t_s: np.ndarray
    ch: np.ndarray  # (n, 4 + aux) us
    alt_m: np.ndarray
    tilt_deg: np.ndarray  # angle between body z and down


def _euler_zyx(R: np.ndarray) -> tuple[float, float, float]:
    pitch = math.asin(max(-1.0, min(1.0, -R[2, 0])))
    roll = math.atan2(R[2, 1], R[2, 2])
    yaw = math.atan2(R[1, 0], R[0, 0])
    return roll, pitch, yaw


def fly(pilot: ScriptedPilot, *, hover: float = HOVER, alt0: float = 0.0) -> Flight:
    """Vehicle rates = commanded rates; thrust = g * throttle / hover along body -z."""
    fs = pilot.params.rate_full_scale_deg_s
    n = round(pilot.duration_s / DT_S) + 1
    R = np.eye(3)
    alt, vz = alt0, 0.0
    rate = (0.0, 0.0, 0.0)
    ts = np.empty(n)
    alts = np.empty(n)
    tilts = np.empty(n)
    chans = []
    g = 9.80665
    for k in range(n):
        t = k * DT_S
        roll, pitch, yaw = _euler_zyx(R)
        s = pilot.sticks(PilotView(t, roll, pitch, yaw, rate, alt, vz, hover))
        c = s.channels()
        chans.append(c)
        ts[k], alts[k] = t, alt
        tilts[k] = math.degrees(math.acos(max(-1.0, min(1.0, R[2, 2]))))
        rate = (
            math.radians(stick_us_to_rate(c[0], fs[0])),
            math.radians(stick_us_to_rate(c[1], fs[1])),
            math.radians(stick_us_to_rate(c[3], fs[2])),
        )
        w = np.array(rate) * DT_S
        th = float(np.linalg.norm(w))
        if th > 0.0:
            K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / th
            R = R @ (np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K)
        acc_up = g * stick_us_to_throttle(c[2]) / hover * R[2, 2] - g
        vz += acc_up * DT_S
        alt += vz * DT_S
        if alt <= 0.0:
            alt, vz = 0.0, max(vz, 0.0)
    return Flight(ts, np.array(chans, dtype=float), alts, tilts)


@pytest.fixture(scope="module")
def paper_flight() -> tuple[ScriptedPilot, Flight]:
    pilot = make_pilot("paper-acro", rng=np.random.default_rng(7))
    assert isinstance(pilot, ScriptedPilot)
    return pilot, fly(pilot)


# --------------------------------------------------------------------------- mapping


def test_stick_signs_and_ends() -> None:
    assert rate_to_stick_us(0.0, 720.0) == 1500
    assert rate_to_stick_us(720.0, 720.0) == 2000
    assert rate_to_stick_us(-720.0, 720.0) == 1000
    assert rate_to_stick_us(360.0, 720.0) == 1750  # roll right / nose up -> high pulse
    assert rate_to_stick_us(-180.0, 360.0) == 1250
    assert rate_to_stick_us(5000.0, 720.0) == 2000  # clamped
    assert rate_to_stick_us(-5000.0, 720.0) == 1000
    assert stick_us_to_rate(2000, 720.0) == 720.0
    assert stick_us_to_rate(1000, 360.0) == -360.0
    assert stick_us_to_rate(2500, 720.0) == 720.0  # clamped
    assert stick_us_to_rate(1600, 720.0) == pytest.approx(144.0)


@given(st.integers(1000, 2000), st.sampled_from([360.0, 720.0, 1000.0]))
def test_stick_round_trip_exact(us: int, fs: float) -> None:
    assert rate_to_stick_us(stick_us_to_rate(us, fs), fs) == us


@given(st.floats(-720.0, 720.0), st.sampled_from([360.0, 720.0]))
def test_rate_round_trip_within_half_a_microsecond(rate: float, fs: float) -> None:
    r = max(-fs, min(fs, rate))
    back = stick_us_to_rate(rate_to_stick_us(r, fs), fs)
    assert abs(back - r) <= 0.5 * fs / 500.0 + 1e-9


def test_sticks_channels_are_aetr() -> None:
    s = Sticks(1100, 1200, 1300, 1400, (2000, 1000))
    assert s.channels() == (1100, 1200, 1300, 1400, 2000, 1000)
    assert Sticks(1, 2, 3, 4).channels() == (1, 2, 3, 4)


# --------------------------------------------------------------------------- virtual pilot


def test_level_signs() -> None:
    k, lim = 5.0, math.radians(300.0)
    p, q = level_rates_rad_s(0.2, 0.0, k, lim)
    assert p < 0.0 and abs(q) < 1e-12  # rolled right -> roll left
    p, q = level_rates_rad_s(-0.2, 0.0, k, lim)
    assert p > 0.0
    p, q = level_rates_rad_s(0.0, 0.2, k, lim)
    assert q < 0.0 and abs(p) < 1e-12  # nose up -> nose down
    p, q = level_rates_rad_s(0.0, -0.2, k, lim)
    assert q > 0.0
    np.testing.assert_allclose(level_rates_rad_s(0.01, -0.02, k, lim), (-0.05, 0.1), rtol=1e-3)
    # Limited in norm, and rolls upright when inverted.
    p, q = level_rates_rad_s(2.5, 0.3, k, lim)
    assert math.hypot(p, q) == pytest.approx(lim)
    assert level_rates_rad_s(math.pi, 0.0, k, lim)[0] != 0.0


def test_level_other_axis_stays_small_through_a_flip() -> None:
    # Pitch levelling during a roll flip with a 2 deg pitch error, even inverted.
    _, q = level_rates_rad_s(math.pi - 0.01, math.radians(2.0), 5.0, 5.0, both_axes=False)
    assert abs(q) < 0.2


def test_pilot_levels_with_right_sign() -> None:
    for roll, pitch, sign_ch1, sign_ch2 in ((0.3, 0.0, -1, 0), (0.0, -0.3, 0, 1)):
        pilot = make_pilot("hover", rng=np.random.default_rng(0))
        s = pilot.sticks(view(10.0, roll=roll, pitch=pitch))
        assert np.sign(s.roll_us - 1500) == sign_ch1
        assert np.sign(s.pitch_us - 1500) == sign_ch2
        assert s.yaw_us == 1500


def test_altitude_hold_more_throttle_when_low() -> None:
    def thr(alt: float, climb: float = 0.0) -> int:
        pilot = make_pilot("hover", rng=np.random.default_rng(0))
        return pilot.sticks(view(10.0, alt=alt, climb=climb)).throttle_us

    low, at, high = thr(5.0), thr(10.0), thr(15.0)
    assert low > at > high
    assert at == 1000 + round(1000 * HOVER)  # hover feed-forward at the target
    assert thr(10.0, climb=2.0) < at < thr(10.0, climb=-2.0)  # damping


def test_throttle_tilt_compensation_and_inverted() -> None:
    prm = PilotParams()
    kw = {
        "altitude_m": 10.0,
        "climb_rate_m_s": 0.0,
        "target_altitude_m": 10.0,
        "climb_target_m_s": 0.0,
        "hover_throttle": 0.5,
        "params": prm,
    }
    assert throttle_command("hold", cos_tilt=1.0, **kw) == pytest.approx(0.5)  # type: ignore[arg-type]
    assert throttle_command("hold", cos_tilt=0.8, **kw) == pytest.approx(0.625)  # type: ignore[arg-type]
    inv = throttle_command("coast", cos_tilt=-1.0, **kw)  # type: ignore[arg-type]
    assert 0.0 < inv < 0.5
    assert throttle_command("climb", cos_tilt=1.0, **{**kw, "climb_target_m_s": 5.0}) > 0.5  # type: ignore[arg-type]


def test_rig_mode_constant_hover_throttle_and_levels() -> None:
    pilot = make_pilot("roll-flip", rng=np.random.default_rng(0), free_flight=False)
    thr = {pilot.sticks(view(t, alt=a, roll=0.1)).throttle_us for t, a in ((0.0, 0.0), (1.0, 30.0))}
    assert thr == {1000 + round(1000 * HOVER)}
    assert pilot.sticks(view(1.01, roll=0.1)).roll_us < 1500


def test_takeoff_ramps_throttle_from_idle() -> None:
    pilot = make_pilot("hover", rng=np.random.default_rng(0))
    first = pilot.sticks(view(0.0, alt=0.0))
    assert first.throttle_us == 1000
    later = pilot.sticks(view(0.01, alt=0.0))
    assert 1000 < later.throttle_us <= 1000 + 40 + 1  # 1000 us per 250 ms


# --------------------------------------------------------------------------- library


@pytest.mark.parametrize("name", sorted(MANEUVERS))
def test_library_channels_in_range_and_slew_limited(name: str) -> None:
    pilot = make_pilot(name, rng=np.random.default_rng(3))
    assert isinstance(pilot, ScriptedPilot)
    f = fly(pilot)
    assert f.ch.min() >= 1000 and f.ch.max() <= 2000
    assert f.t_s[-1] == pytest.approx(pilot.duration_s, abs=DT_S)
    d = np.abs(np.diff(f.ch[:, :4], axis=0))
    stick_max = 500.0 / pilot.params.stick_slew_s * DT_S + 1.0  # +1 us rounding
    thr_max = 1000.0 / pilot.params.throttle_slew_s * DT_S + 1.0
    assert d[:, 2].max() <= thr_max
    rates = d[:, [0, 1, 3]]
    if name in STEP_MANEUVERS:
        assert rates.max() > 100.0  # a step is a step
    else:
        assert rates.max() <= stick_max, name
    # The vehicle survives the crude closed loop and ends level.
    assert f.alt_m[int(4.0 / DT_S) :].min() > 2.0, name
    assert f.alt_m.max() < 40.0, name
    assert f.tilt_deg[-1] < 3.0, name


def test_random_pilot_deterministic_per_seed() -> None:
    def chans(seed: int) -> np.ndarray:
        pilot = make_pilot("acro-random", rng=np.random.default_rng(seed))
        assert isinstance(pilot, ScriptedPilot)
        return fly(pilot).ch

    a, b, c = chans(11), chans(11), chans(12)
    np.testing.assert_array_equal(a, b)
    assert a.shape != c.shape or not np.array_equal(a, c)


def test_paper_acro_is_a_minute_of_real_acro(paper_flight: tuple[ScriptedPilot, Flight]) -> None:
    pilot, f = paper_flight
    assert 55.0 <= pilot.duration_s <= 65.0
    fs = DEFAULT_RATE_FULL_SCALE_DEG_S
    roll = (f.ch[:, 0] - 1500) / 500 * fs[0]
    pitch = (f.ch[:, 1] - 1500) / 500 * fs[1]
    yaw = (f.ch[:, 3] - 1500) / 500 * fs[2]
    assert max(np.abs(roll).max(), np.abs(pitch).max()) >= 700.0
    assert np.abs(roll).max() >= 700.0 and np.abs(pitch).max() >= 700.0
    # Yaw spins both ways: at least one turn each way at >= 250 deg/s.
    fast = np.abs(yaw) >= 250.0
    assert np.sum(yaw[fast] > 0) * DT_S * 250.0 >= 360.0
    assert np.sum(yaw[fast] < 0) * DT_S * 250.0 >= 360.0
    # Quick reversals: roll stick crosses from >= +250 to <= -250 deg/s within 0.2 s.
    hi = np.flatnonzero(roll >= 250.0)
    lo = np.flatnonzero(roll <= -250.0)
    assert any(np.any((lo > i) & (lo - i <= 200)) for i in hi[::10])


def test_paper_acro_altitude_and_returns_level(paper_flight: tuple[ScriptedPilot, Flight]) -> None:
    pilot, f = paper_flight
    after_takeoff = f.t_s >= 4.0
    assert f.alt_m[after_takeoff].min() > 2.0 and f.alt_m.max() < 40.0
    # Before each maneuver that follows a level gap, the vehicle is level again.
    segs = pilot.segments
    checked = 0
    for a, b in itertools.pairwise(segs):
        is_level = a.rate_deg_s == (None, None, None) and a.chirp is None
        if is_level and a.throttle == "hold" and b.t_s - a.t_s >= 1.0 and a.t_s > 0.0:
            k = round(b.t_s / DT_S) - 1
            assert f.tilt_deg[k] < 3.0, f"not level at t={b.t_s}"
            checked += 1
    assert checked >= 8
    assert f.tilt_deg[-1] < 3.0


def test_paper_acro_depends_on_rng_only() -> None:
    def first_frames(seed: int) -> list[tuple[int, ...]]:
        pilot = make_pilot("paper-acro", rng=np.random.default_rng(seed))
        return [pilot.sticks(view(0.001 * k, alt=10.0)).channels() for k in range(6000)]

    assert first_frames(1) == first_frames(1)
    assert first_frames(1) != first_frames(2)


# --------------------------------------------------------------------------- script files


def test_loader_parses_example() -> None:
    pilot = load_stick_script(EXAMPLE)
    assert pilot.duration_s == 30.0
    assert pilot.params.rate_full_scale_deg_s == (720.0, 720.0, 360.0)
    assert pilot.segments[0].t_s == 0.0
    assert pilot.scripted_rate_deg_s(9.8 + 0.2) == (720.0, None, None)
    f = fly(pilot)
    assert f.ch[0, 4] == 1000 and f.ch[-1, 4] == 2000  # engage switch on ch5
    assert f.ch.min() >= 1000 and f.ch.max() <= 2000
    assert f.alt_m[4000:].min() > 2.0 and f.tilt_deg[-1] < 3.0
    # make_pilot accepts the path as well.
    assert make_pilot(str(EXAMPLE), rng=np.random.default_rng(0)).duration_s == 30.0


@pytest.mark.parametrize("path", sorted(SCENARIOS.glob("*.yaml")), ids=lambda p: p.name)
def test_every_bundled_script_loads(path: Path) -> None:
    assert load_stick_script(path).duration_s > 0.0


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("duration_s: 5\nsegments:\n  - {t_s: 0, level: true, ramp_s: -1}\n", "segments.0.ramp_s"),
        ("duration_s: 5\nsegments:\n  - {t_s: 0, level: true, wobble: 3}\n", "segments.0.wobble"),
        ("segments:\n  - {t_s: 0, level: true}\n", "duration_s"),
        ("duration_s: 5\nsegments:\n  - {t_s: 0, rate_deg_s: [1, 2]}\n", "segments.0.rate_deg_s"),
        ("duration_s: 5\nsegments:\n  - {t_s: 0}\n", "exactly one of"),
        (
            "duration_s: 5\nsegments:\n  - {t_s: 0, level: true}\n  - {t_s: 0, level: true}\n",
            "segments.1.t_s",
        ),
        (
            "duration_s: 5\nrate_full_scale_deg_s: [720, 0, 360]\n"
            "segments:\n  - {t_s: 0, level: true}\n",
            "rate_full_scale_deg_s",
        ),
        ("- just a list\n", "top level"),
        ("duration_s: [unclosed\n", "not valid YAML"),
    ],
)
def test_loader_rejects_bad_file(tmp_path: Path, text: str, field: str) -> None:
    bad = tmp_path / "bad_sticks.yaml"
    bad.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_stick_script(bad)
    assert isinstance(exc.value, ValueError)
    msg = str(exc.value)
    assert "bad_sticks.yaml" in msg
    assert field in msg


def test_unknown_spec_is_rejected() -> None:
    with pytest.raises(ValueError, match="unknown pilot"):
        make_pilot("loop-de-loop", rng=np.random.default_rng(0))
    with pytest.raises(ConfigError, match="cannot read"):
        make_pilot("nope/missing.yaml", rng=np.random.default_rng(0))


def test_segment_step_jumps_and_ramp_is_linear() -> None:
    pilot = ScriptedPilot(
        [
            Segment(0.0),
            Segment(1.0, rate_deg_s=(360.0, None, None), step=True),
            Segment(2.0, rate_deg_s=(0.0, None, None), ramp_s=0.5),
        ],
        3.0,
    )
    assert pilot.scripted_rate_deg_s(1.5) == (360.0, None, None)
    assert pilot.scripted_rate_deg_s(2.25)[0] == pytest.approx(180.0)
    pilot.sticks(view(0.999))
    assert pilot.sticks(view(1.0)).roll_us == 1750  # jump, no slew
    assert pilot.sticks(view(2.1)).roll_us == 1750 - 50  # ramped 360 -> 0 over 0.5 s


def test_sticks_is_cheap() -> None:
    import time

    pilot = make_pilot("paper-acro", rng=np.random.default_rng(0))
    views = [view(0.001 * k, roll=0.1, pitch=-0.05) for k in range(20000)]
    t0 = time.perf_counter()
    for v in views:
        pilot.sticks(v)
    per_call_us = (time.perf_counter() - t0) / len(views) * 1e6
    assert per_call_us < 100.0  # generous for CI; measured ~3 us on a desktop


# --------------------------------------------------------------------------- frozen


def test_paper_acro_is_frozen() -> None:
    """The test flight every quoted figure comes from, pinned by digest.

    The stick frames the paper-acro pilot gives over its 60 s (seen from a level
    vehicle at 10 m, every 10 ms) and the first draws of the plant, IMU and wind
    streams from its seed. If this fails, the flight changed (a new numpy whose
    generators draw differently, or an edit to the scenario or the pilot): every
    figure measured on paper-acro in the docs must be measured again.
    """
    sc = load_scenario("paper-acro")
    assert sc.seed == 20200318
    streams = flight_streams(sc.seed)
    pilot = make_pilot(sc.pilot, rng=streams["pilot"], free_flight=sc.free_flight)
    assert pilot.duration_s == 60.0
    frames = [pilot.sticks(view(0.01 * k)).channels() for k in range(6001)]
    digest = hashlib.sha256(repr(frames).encode()).hexdigest()
    assert digest == "1bd9b12975c13a8ba9ce7d135a4d3dff96d19e1b4dc3451eaea7a15f090751dd"
    draws = np.concatenate([streams[n].standard_normal(16) for n in ("plant", "imu", "wind")])
    digest = hashlib.sha256(draws.round(12).tobytes()).hexdigest()
    assert digest == "d811949693deba07a55a9ad72ab3a4385193a395bc8775aa95c92523cdd610d1"
