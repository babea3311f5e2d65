"""The laws' settings for unit tests: the configuration schema's defaults
(``companion.config``, where each gain is defined once) with what a test sets.

Unlike a configuration file, the values a test gives are not bounded by the
schema: a unit test of a law may ask for an unsaturated output (``1e9``)."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel

from companion.config import (
    PID_DEFAULT_CONTROLLER,
    TABLE1_CONTROLLER,
    AlphaAdaptConfig,
    MfcAxisConfig,
    MfcConfig,
    PidAxisConfig,
    PidConfig,
    load_controller,
    mfc_gains,
    pid_gains,
)
from companion.control import (
    AlphaAdaptation,
    IntelligentController,
    MfcAxisGains,
    MfcGains,
    Mixer,
    PidAxisGains,
    PidController,
    PidGains,
)

FULL_SCALE_US = float(MfcConfig.model_fields["command_full_scale_us"].default)


def _with_defaults(model: type[BaseModel], given: dict[str, Any]) -> dict[str, Any]:
    values = dict(given)
    for name, spec in model.model_fields.items():
        if name not in values and not spec.is_required():
            values[name] = spec.default
    return values


def axis(**given: Any) -> MfcAxisGains:
    """One MFC axis: ``order``, ``alpha``, ``window_s``, ``kp`` given, the rest the
    schema's defaults unless given."""
    return MfcAxisGains(**_with_defaults(MfcAxisConfig, given))


def adapt(**given: Any) -> AlphaAdaptation:
    """The identification's settings: ``alpha_min``, ``alpha_max`` given."""
    return AlphaAdaptation(**_with_defaults(AlphaAdaptConfig, given))


def pid_axis(**given: Any) -> PidAxisGains:
    """One PID axis: ``kp``, ``ki``, ``kd`` given."""
    return PidAxisGains(**_with_defaults(PidAxisConfig, given))


def law(gains: MfcAxisGains) -> IntelligentController:
    """One axis's law at the schema's default command full scale."""
    return IntelligentController(gains, command_full_scale_us=FULL_SCALE_US)


def table_one() -> MfcGains:
    """The paper's Table I, as shipped (``companion/data/mfc_table1.yaml``)."""
    cfg = load_controller(TABLE1_CONTROLLER)
    assert isinstance(cfg, MfcConfig)
    return mfc_gains(cfg)


def pid_controller(gains: PidGains, mixer: Mixer) -> PidController:
    """The PID with the schema's sample-interval bounds."""
    fields = PidConfig.model_fields
    return PidController(
        gains,
        mixer,
        dt_min_s=float(fields["dt_min_s"].default),
        dt_max_s=float(fields["dt_max_s"].default),
    )


def px4_default_pid() -> PidGains:
    """PX4's default rate PID, as shipped (``companion/data/pid_px4_default.yaml``)."""
    cfg = load_controller(PID_DEFAULT_CONTROLLER)
    assert isinstance(cfg, PidConfig)
    return pid_gains(cfg)
