r"""The loop's delay: identified with the lag, fed to the estimate of F, bounding kd.

The plant is :math:`\ddot y = F + b\,L_\tau u(t - D)`: a first-order actuator lag
behind a pure delay (a companion's link both ways), ``F`` slow. It is driven open
loop by random command steps, handed to the law as the command it applied
(``applied``), so the identifier learns from the window means exactly as in
flight (:meth:`IntelligentController.update`, then :meth:`~IntelligentController.learn`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from companion.config import (
    DEFAULT_CONTROLLER,
    AlphaAdaptConfig,
    MfcAxisConfig,
    MfcConfig,
    load_controller,
    mfc_gains,
)
from companion.control import AlphaAdaptation, IntelligentController, MfcAxisGains
from companion.control.identifier import PlantIdentifier
from companion.schema import format_validation_error
from tests.control.gains import adapt as adaptation
from tests.control.gains import axis as axis_gains
from tests.control.gains import law
from tests.control.plants import timestamps_dt

B = 0.3  # the plant's input gain, (rad/s^2) per us
TAUS = (0.01, 0.02, 0.04, 0.08)
DELAYS = (0.0, 0.004, 0.008, 0.012, 0.016, 0.024, 0.032, 0.048)  # the shipped candidates
MARGIN = 0.5
ADAPT = adaptation(
    alpha_min=0.03, alpha_max=10.0, margin=MARGIN, tau_candidates_s=TAUS, delay_candidates_s=DELAYS
)
FULL_SCALE = 500.0  # us: ``applied`` is a share of it


def _gains(adapt: AlphaAdaptation | None = ADAPT, **kw: Any) -> MfcAxisGains:
    """An iPD on the rate, unsaturated so the gains show in the command."""
    base: dict[str, Any] = {
        "order": 2, "alpha": 1.0, "window_s": 0.02, "kp": 0.0, "kd": 10.0,
        "output_limit_us": 1e4, "actuator_tau_s": 0.03, "alpha_adapt": adapt,
    }  # fmt: skip
    return axis_gains(**{**base, **kw})


def _fly(
    ax: IntelligentController,
    *,
    tau_s: float,
    delay_s: float,
    rate_hz: float = 250.0,
    seconds: float = 6.0,
    trace: list[tuple[float, float, float, float]] | None = None,
) -> float:
    """``seconds`` of random command steps (up to 150 us, every 60 ms) on
    y'' = F + B * L_tau(u(t - D)), F = 5 sin(0.5 t) - 2 y', learning; dt from
    sample timestamps. Returns the last rate. With ``trace``, notes after each
    sample the command the law computed and its alpha, lag and delay."""
    ax.adapting = True
    rng = np.random.default_rng(7)
    n_d = round(delay_s * rate_hz)
    hold = round(0.06 * rate_hz)
    sent = [0.0] * (n_d + 1)  # the commands of the last n_d + 1 intervals, newest last
    u = u_a = w = t = 0.0
    ident = ax._ident
    for i, dt in enumerate(timestamps_dt(rate_hz, round(seconds * rate_hz))):
        dt = float(dt)
        if i % hold == 0:
            u = float(rng.uniform(-150.0, 150.0))
        sent.append(u)
        del sent[0]
        acting = sent[0]  # the command of n_d intervals ago reaches the motors now
        k = -math.expm1(-dt / tau_s)
        mean_u_a = acting + (u_a - acting) * k * tau_s / dt  # exact for a held command
        u_a = acting + (u_a - acting) * (1.0 - k)
        w += (5.0 * math.sin(0.5 * t) - 2.0 * w + B * mean_u_a) * dt
        t += dt
        out = ax.update(dt, w, 0.0, 0.0, applied=u / FULL_SCALE)
        ax.learn()
        if trace is not None:
            assert ident is not None
            trace.append((out, ax.alpha, ax.tau_s, ident.delay))
    return w


def _delay(ax: IntelligentController) -> float:
    assert ax._ident is not None
    return ax._ident.delay


# ---------------------------------------------------------------------------
# 1-2. Identification of the delay.


@pytest.mark.parametrize("rate_hz", [250.0, 1000.0])
@pytest.mark.parametrize(
    ("delay_s", "tau_s"), [(0.0, 0.02), (0.016, 0.02), (0.016, 0.04), (0.032, 0.01)]
)
def test_identifies_the_delay_with_the_lag(rate_hz: float, delay_s: float, tau_s: float) -> None:
    """The delay is counted in 4 ms identification intervals, at 250 Hz (every sample)
    as at 1 kHz (every 4th); the lag and the slope are found through it."""
    ax = law(_gains())
    _fly(ax, tau_s=tau_s, delay_s=delay_s, rate_hz=rate_hz)
    assert _delay(ax) == pytest.approx(delay_s, abs=1e-9)
    assert ax.tau_s == tau_s
    assert ax.alpha == pytest.approx(MARGIN * B, rel=0.05)


def test_without_delay_candidates_nothing_changes() -> None:
    """No candidates is the candidate 0 alone: the same commands, alpha and lag, bit
    for bit, and the delay stays 0, even behind a 16 ms delay it cannot name."""
    traces = []
    for delays in ((), (0.0,)):
        adapt = adaptation(
            alpha_min=0.03, alpha_max=10.0, margin=MARGIN, tau_candidates_s=TAUS,
            delay_candidates_s=delays,
        )  # fmt: skip
        trace: list[tuple[float, float, float, float]] = []
        _fly(law(_gains(adapt)), tau_s=0.02, delay_s=0.016, trace=trace)
        traces.append(trace)
    assert traces[0] == traces[1]
    assert {delay for *_, delay in traces[0]} == {0.0}
    assert len({alpha for _, alpha, _, _ in traces[0]}) > 10  # it did learn


# ---------------------------------------------------------------------------
# 3. The margin a delay raises.

DELAY_MARGIN = adaptation(
    alpha_min=0.03, alpha_max=10.0, margin=0.4, delay_candidates_s=DELAYS,
    delay_margin_slope=0.5, delay_margin_free_ratio=0.3, delay_margin_max=0.6,
)  # fmt: skip


@pytest.mark.parametrize(
    ("margin", "delay_s", "tau_s", "want"),
    [
        (0.4, 0.0, 0.02, 0.4),  # no delay
        (0.4, 0.004, 0.02, 0.4),  # D / tau = 0.2, below the free ratio 0.3
        (0.4, 0.006, 0.02, 0.4),  # at the free ratio
        (0.4, 0.008, 0.02, 0.4 + 0.5 * (0.4 - 0.3)),  # 0.45
        (0.4, 0.012, 0.02, 0.4 + 0.5 * (0.6 - 0.3)),  # 0.55
        (0.4, 0.016, 0.02, 0.6),  # 0.65: capped at delay_margin_max
        (0.4, 0.048, 0.01, 0.6),  # 2.75: capped
        (0.4, 0.016, 0.08, 0.4),  # a slow lag: D / tau = 0.2
        (0.3, 0.004, 0.02, 0.3),  # a margin margin_for lowered stays below the free ratio
        (0.3, 0.008, 0.02, 0.45),  # and rises from the configured margin above it
        (0.7, 0.012, 0.02, 0.7),  # never lowered
        (0.4, 0.016, 0.0, 0.4),  # no lag to compare with
    ],
)
def test_margin_for_delay(margin: float, delay_s: float, tau_s: float, want: float) -> None:
    ident = PlantIdentifier(DELAY_MARGIN, alpha=1.0, tau_s=0.03)
    assert ident.margin_for_delay(margin, delay_s, tau_s) == pytest.approx(want, rel=1e-12)
    off = PlantIdentifier(ADAPT, alpha=1.0, tau_s=0.03)  # delay_margin_slope 0: off
    assert off.margin_for_delay(margin, delay_s, tau_s) == margin


@settings(max_examples=200, deadline=None)
@given(st.floats(0.01, 2.0), st.floats(0.0, 0.2), st.sampled_from(TAUS))
def test_margin_for_delay_only_raises_and_at_most_to_its_max(
    margin: float, delay_s: float, tau_s: float
) -> None:
    got = PlantIdentifier(DELAY_MARGIN, alpha=1.0, tau_s=0.03).margin_for_delay(
        margin, delay_s, tau_s
    )
    assert margin <= got <= max(margin, 0.6)


# ---------------------------------------------------------------------------
# 4. kd bounded by the delay.


@pytest.mark.parametrize(("delay_s", "kd", "kp"), [(0.016, 12.5, 25.0), (0.0, 25.0, 100.0)])
def test_kd_is_bounded_by_the_identified_delay(delay_s: float, kd: float, kp: float) -> None:
    """Gains given for a 40 ms lag, identified at 20 ms: kd 12.5 -> 25 and kp 25 -> 100.
    Behind 16 ms, delay_kd_limit 0.2 caps kd at 0.2 / 0.016 = 12.5 and kp by the same
    cut squared (iPD), to 25; without a delay they stay lag-scaled."""
    gains = _gains(kp=25.0, kd=12.5, actuator_tau_s=0.04, lag_scaled_gains=True, delay_kd_limit=0.2)
    ax = law(gains)
    w = _fly(ax, tau_s=0.02, delay_s=delay_s)
    assert (_delay(ax), ax.tau_s) == (pytest.approx(delay_s, abs=1e-9), 0.02)
    # The next command from public state: u = -(F_hat - y_r'' + kp e + kd e') / alpha.
    got = ax.update(0.004, w, w - 1.0, 0.0)
    assert ax.e_dot == pytest.approx(1.0) and abs(ax.e) > 0.05
    want = -(ax.f_hat + kp * ax.e + kd * ax.e_dot) / ax.alpha
    assert got == pytest.approx(want, rel=1e-9)


def test_the_shipped_roll_axis_behind_16_ms() -> None:
    """The shipped file's roll axis on b = 0.3, tau = 20 ms, D = 16 ms: D / tau = 0.8
    raises the margin 0.4 to min(0.6, 0.4 + 0.5 (0.8 - 0.3)) = 0.6, and kd (25 at
    30 ms, not raised for a faster lag) is capped at 0.2 / 0.016 = 12.5."""
    cfg = load_controller(DEFAULT_CONTROLLER)
    assert isinstance(cfg, MfcConfig)
    roll = mfc_gains(cfg).roll
    assert roll.alpha_adapt is not None
    assert roll.alpha_adapt.delay_candidates_s == DELAYS
    assert (roll.delay_kd_limit, roll.kd, roll.kp) == (0.2, 25.0, 0.0)
    ax = law(roll)
    w = _fly(ax, tau_s=0.02, delay_s=0.016)
    assert (_delay(ax), ax.tau_s) == (pytest.approx(0.016, abs=1e-9), 0.02)
    assert ax._ident is not None and ax._ident.margin == 0.6
    assert ax.alpha == pytest.approx(0.6 * B, rel=0.05)
    got = ax.update(0.004, w, w - 0.1, 0.0)
    assert abs(got) < roll.output_limit_us  # unsaturated, so kd shows
    assert got == pytest.approx(-(ax.f_hat + 12.5 * ax.e_dot) / ax.alpha, rel=1e-9)


# ---------------------------------------------------------------------------
# 5. The estimate of F uses the command that acted.


@pytest.mark.parametrize("rate_hz", [250.0, 1000.0])
@pytest.mark.parametrize(
    ("delays", "plant_delay_s", "seen_after_s"),
    [(DELAYS, 0.016, 0.016), (DELAYS, 0.0, 0.0), ((), 0.016, 0.0)],
    ids=["identified-16ms", "identified-0", "no-candidates"],
)
def test_f_hat_sees_a_command_step_one_identified_delay_later(
    rate_hz: float, delays: tuple[float, ...], plant_delay_s: float, seen_after_s: float
) -> None:
    """After identification (then frozen), the rate held still and the command at 0, a
    100 us step: F_hat = y'' - alpha L_tau(mean u(t - D)) is the analytic lag of the
    delayed window mean, unmoved for D, moving at once without a delay to use."""
    adapt = adaptation(
        alpha_min=0.03, alpha_max=10.0, margin=MARGIN, tau_candidates_s=TAUS,
        delay_candidates_s=delays,
    )  # fmt: skip
    ax = law(_gains(adapt))
    _fly(ax, tau_s=0.02, delay_s=plant_delay_s, rate_hz=rate_hz)
    assert _delay(ax) == pytest.approx(seen_after_s, abs=1e-9)
    ax.adapting = False
    dt = 1.0 / rate_hz
    for _ in range(round(1.5 * rate_hz)):  # window of zeros; the lag state dies out
        ax.update(dt, 0.0, 0.0, 0.0, applied=0.0)
        ax.learn()
    f0 = ax.f_hat
    f_hat = []
    for _ in range(round(0.06 * rate_hz)):
        ax.update(dt, 0.0, 0.0, 0.0, applied=100.0 / FULL_SCALE)
        ax.learn()
        f_hat.append(ax.f_hat)
    # The model: y'' = 0, u_a -> lag of the window mean (20 ms) of n samples ago.
    n = round(seen_after_s * rate_hz)
    n_win = round(0.02 * rate_hz)
    k = -math.expm1(-dt / ax.tau_s)
    u_a = -f0 / ax.alpha
    want = []
    for j in range(len(f_hat)):
        mean = 100.0 * min(j - n + 1, n_win) / n_win if j >= n else 0.0
        u_a += (mean - u_a) * k
        want.append(-ax.alpha * u_a)
    np.testing.assert_allclose(f_hat, want, rtol=1e-9, atol=1e-9)
    moved = [abs(f - f0) > 1e-6 for f in f_hat]
    assert moved.index(True) == n  # the first sample F_hat moves at
    assert abs(f_hat[n] - f0) > 0.01


# ---------------------------------------------------------------------------
# 6. Settings refused, each naming its field.


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"delay_candidates_s": (0.0, -0.004)}, "delay_candidates_s"),
        ({"delay_candidates_s": (0.0, 0.25)}, "delay_candidates_s"),
        ({"delay_candidates_s": (math.nan,)}, "delay_candidates_s"),
        ({"delay_margin_slope": 0.5, "delay_margin_max": 0.6}, "delay_margin_slope"),
        ({"delay_margin_slope": -0.1}, "delay_margin_slope"),
        ({"delay_margin_free_ratio": -0.1}, "delay_margin_free_ratio"),
        (
            {"delay_candidates_s": DELAYS, "delay_margin_slope": 0.5, "delay_margin_max": 0.3},
            "delay_margin_max",
        ),
    ],
)
def test_bad_delay_settings_are_refused(kwargs: dict[str, Any], field: str) -> None:
    with pytest.raises(ValueError, match=field):
        AlphaAdaptConfig(alpha_min=0.03, alpha_max=10.0, margin=0.4, **kwargs)


def test_delay_kd_limit_needs_a_delay_to_limit_kd_by() -> None:
    axis = {"order": 2, "alpha": 1.0, "window_s": 0.02, "kp": 0.0, "kd": 10.0}
    base = {"alpha_min": 0.03, "alpha_max": 10.0, "margin": MARGIN}
    no_delays = {**base, "tau_candidates_s": TAUS}
    delays = {**base, "tau_candidates_s": TAUS, "delay_candidates_s": DELAYS}
    for adapt, limit in ((no_delays, 0.2), (None, 0.2), (delays, -0.1), (delays, math.nan)):
        with pytest.raises(ValueError, match="delay_kd_limit"):
            MfcAxisConfig(**axis, alpha_adapt=adapt, delay_kd_limit=limit)
    cfg = MfcAxisConfig(**axis, alpha_adapt=delays, delay_kd_limit=0.2)
    assert cfg.delay_kd_limit == 0.2


def _shipped_with(path: str, value: Any) -> list[str]:
    """The problems ``key.path: message`` of the shipped controller with one key set."""
    cfg = load_controller(DEFAULT_CONTROLLER)
    raw = cfg.model_dump()
    assert MfcConfig.model_validate(raw) == cfg
    *parents, last = path.split(".")
    node = raw
    for p in parents:
        node = node[p]
    node[last] = value
    with pytest.raises(ValidationError) as info:
        MfcConfig.model_validate(raw)
    return format_validation_error(info.value)


@pytest.mark.parametrize(
    ("path", "value", "where", "says"),
    [
        (
            "axes.roll.alpha_adapt.delay_candidates_s", [0.0, 0.25],
            "axes.roll.alpha_adapt.delay_candidates_s.1", "less than or equal to 0.2",
        ),
        (
            "axes.roll.alpha_adapt.delay_candidates_s", [-0.004],
            "axes.roll.alpha_adapt.delay_candidates_s.0", "greater than or equal to 0",
        ),
        (
            "axes.roll.alpha_adapt.delay_candidates_s", [],
            "axes.roll.alpha_adapt", "delay_margin_slope needs delay_candidates_s",
        ),
        (
            "axes.roll.alpha_adapt.delay_margin_max", 0.3,
            "axes.roll.alpha_adapt", "delay_margin_max must not be below margin",
        ),
        (
            "axes.yaw.alpha_adapt.delay_candidates_s", [],
            "axes.yaw", "delay_kd_limit needs alpha_adapt.delay_candidates_s",
        ),
        ("axes.pitch.delay_kd_limit", -0.1, "axes.pitch.delay_kd_limit", "greater than"),
    ],
)  # fmt: skip
def test_bad_delay_settings_in_a_controller_file_are_refused(
    path: str, value: Any, where: str, says: str
) -> None:
    problems = _shipped_with(path, value)
    assert any(p.startswith(f"{where}:") and says in p for p in problems), problems
