"""The --output rates default controller (companion/data/mfc_rates.yaml)."""

from __future__ import annotations

from companion.config import (
    DEFAULT_CONTROLLER,
    RATES_CONTROLLER,
    MfcConfig,
    default_controller,
    load_controller,
)


def test_rates_default_is_the_shipped_law_with_its_documented_changes() -> None:
    """mfc_rates.yaml differs from mfc_default.yaml only where its header says:
    roll/pitch margin 1.0 and kd 10, a 60 Hz prefilter, none of the lag
    scaling's later changes (authority easing, margin_min, lag_scaling_max and _min, the
    lag-scaled window), no identification of the loop's delay, the yaw margin left at 0.8,
    and no yaw share (the autopilot mixes)."""
    base = load_controller(DEFAULT_CONTROLLER)
    rates = load_controller(RATES_CONTROLLER)
    assert isinstance(base, MfcConfig) and isinstance(rates, MfcConfig)
    for axis in ("roll", "pitch"):
        b, r = getattr(base.axes, axis), getattr(rates.axes, axis)
        assert b.alpha_adapt is not None and r.alpha_adapt is not None
        assert (b.alpha_adapt.margin, r.alpha_adapt.margin) == (0.4, 1.0)
        assert (b.kd, r.kd) == (25.0, 10.0)
        assert (b.lag_scaling_authority_ref, r.lag_scaling_authority_ref) == (150.0, 0.0)
        assert (b.alpha_adapt.margin_min, r.alpha_adapt.margin_min) == (0.3, 0.0)
        assert (b.lag_scaling_max, r.lag_scaling_max) == (2.0, None)
        assert (b.lag_scaling_min, r.lag_scaling_min) == (0.7, None)
        assert (b.window_lag_scaled, r.window_lag_scaled) == (True, False)
        assert (b.delay_kd_limit, r.delay_kd_limit) == (0.2, 0.2)
        assert max(b.alpha_adapt.delay_candidates_s) == 0.048
        assert max(r.alpha_adapt.delay_candidates_s) == 0.096
        assert (b.alpha_adapt.delay_margin_slope, r.alpha_adapt.delay_margin_slope) == (0.5, 0.5)
        assert (b.alpha_adapt.delay_margin_max, r.alpha_adapt.delay_margin_max) == (0.6, 2.0)
        # Everything else is the same law.
        same = {
            "alpha_adapt": None, "kd": 0.0, "lag_scaling_authority_ref": 0.0,
            "lag_scaling_max": None, "lag_scaling_min": None, "delay_kd_limit": 0.0,
            "window_lag_scaled": False,
        }  # fmt: skip
        assert b.model_copy(update=same) == r.model_copy(update=same)
    no_delay = {"delay_kd_limit": 0.0, "alpha_adapt": None, "window_lag_scaled": False}
    b_yaw, r_yaw = base.axes.yaw, rates.axes.yaw
    assert b_yaw.model_copy(update=no_delay) == r_yaw.model_copy(update=no_delay)
    assert b_yaw.alpha_adapt is not None and r_yaw.alpha_adapt is not None
    assert (b_yaw.alpha_adapt.margin, r_yaw.alpha_adapt.margin) == (1.0, 0.8)
    assert (
        b_yaw.alpha_adapt.model_copy(update={"delay_candidates_s": (), "margin": 0.8})
        == r_yaw.alpha_adapt
    )
    assert b_yaw.window_lag_scaled and not r_yaw.window_lag_scaled
    assert (base.prefilter_hz, rates.prefilter_hz) == (30.0, 60.0)
    # The autopilot mixes with --output rates: no share of roll and pitch to give yaw.
    assert (base.yaw_share_max, rates.yaw_share_max) == (0.5, 0.0)
    same_top = {"axes": None, "prefilter_hz": None, "yaw_share_max": None}
    assert base.model_copy(update=same_top) == rates.model_copy(update=same_top)


def test_default_controller_by_output() -> None:
    assert default_controller() == DEFAULT_CONTROLLER
    assert default_controller("actuator") == DEFAULT_CONTROLLER
    assert default_controller("rates") == RATES_CONTROLLER
