"""The --output rates default controller (companion/data/mfc_rates.yaml)."""

from __future__ import annotations

from companion.config import (
    DEFAULT_CONTROLLER,
    RATES_CONTROLLER,
    MfcConfig,
    default_controller,
    load_controller,
)


def test_rates_default_is_the_shipped_law_with_a_wider_margin() -> None:
    base = load_controller(DEFAULT_CONTROLLER)
    rates = load_controller(RATES_CONTROLLER)
    assert isinstance(base, MfcConfig) and isinstance(rates, MfcConfig)
    for axis in ("roll", "pitch"):
        b, r = getattr(base.axes, axis), getattr(rates.axes, axis)
        assert b.alpha_adapt is not None and r.alpha_adapt is not None
        assert (b.alpha_adapt.margin, r.alpha_adapt.margin) == (0.4, 1.0)
        # Everything else is the same law.
        assert b.model_copy(update={"alpha_adapt": None}) == r.model_copy(
            update={"alpha_adapt": None}
        )
    assert base.axes.yaw == rates.axes.yaw
    assert base.model_copy(update={"axes": None}) == rates.model_copy(update={"axes": None})


def test_default_controller_by_output() -> None:
    assert default_controller() == DEFAULT_CONTROLLER
    assert default_controller("actuator") == DEFAULT_CONTROLLER
    assert default_controller("rates") == RATES_CONTROLLER
