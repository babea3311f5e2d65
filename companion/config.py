"""Controller configuration files, and the one place that turns config into laws.

A controller file is shared by every vehicle: it holds gains and stick curves,
never a vehicle's numbers. :func:`build_controller` combines it with a
vehicle profile's geometry (the mixer) and nothing else from the profile.
"""

from __future__ import annotations

import dataclasses
from importlib.resources import files
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

from pydantic import Field, field_validator, model_validator

from companion.control import (
    MAX_DELAY_S,
    AlphaAdaptation,
    AxisRates,
    MfcAxisGains,
    MfcController,
    MfcGains,
    Mixer,
    PidAxisGains,
    PidController,
    PidGains,
    StickMap,
)
from companion.profile import RateLimitDegS, VehicleProfile, rate_limit_validator
from companion.schema import StrictModel, load_yaml_model, real_number

__all__ = [
    "DEFAULT_CONTROLLER",
    "PID_DEFAULT_CONTROLLER",
    "RATES_CONTROLLER",
    "TABLE1_CONTROLLER",
    "MfcConfig",
    "PidConfig",
    "build_controller",
    "build_mixer",
    "build_stick_map",
    "default_controller",
    "load_controller",
    "mfc_gains",
    "pid_gains",
]

DEFAULT_CONTROLLER = Path(str(files("companion") / "data" / "mfc_default.yaml"))
RATES_CONTROLLER = Path(str(files("companion") / "data" / "mfc_rates.yaml"))
"""The default for ``--output rates``: the plant is the autopilot's closed rate loop."""


def default_controller(output: str = "actuator") -> Path:
    """The controller file used when none is given, for an output mode."""
    return RATES_CONTROLLER if output == "rates" else DEFAULT_CONTROLLER


PID_DEFAULT_CONTROLLER = Path(str(files("companion") / "data" / "pid_px4_default.yaml"))
TABLE1_CONTROLLER = Path(str(files("companion") / "data" / "mfc_table1.yaml"))
"""The paper's Table I, literally."""

_L = TypeVar("_L")


class AxisRatesConfig(StrictModel):
    curve: Literal["linear", "betaflight"] = "linear"
    max_deg_s: RateLimitDegS = Field(720.0, description="rate at full stick (linear curve), deg/s")
    rc_rate: float = Field(1.0, gt=0.0, le=3.0)
    super_rate: float = Field(0.7, ge=0.0, lt=1.0)
    expo: float = Field(0.0, ge=0.0, le=1.0)

    _rate = rate_limit_validator("max_deg_s", "a rate at full stick in %s deg/s")


class SticksConfig(StrictModel):
    channels: tuple[int, int, int, int] = (1, 2, 3, 4)
    roll: AxisRatesConfig = AxisRatesConfig(max_deg_s=720.0)
    pitch: AxisRatesConfig = AxisRatesConfig(max_deg_s=720.0)
    yaw: AxisRatesConfig = AxisRatesConfig(max_deg_s=360.0)
    deadband_us: float = Field(
        0.0, ge=0.0, le=100.0, description="stick dead band around centre, us"
    )

    @field_validator("channels")
    @classmethod
    def _channels(cls, v: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
        if len(set(v)) != 4 or not all(1 <= c <= 18 for c in v):
            raise ValueError("expected four distinct channel numbers in 1..18")
        return v


_LagS = Annotated[float, Field(ge=0.0, le=0.5)]
_DelayS = Annotated[float, Field(ge=0.0, le=MAX_DELAY_S)]


class AlphaAdaptConfig(StrictModel):
    """Online alpha scaling (companion.control.identifier.AlphaAdaptation)."""

    alpha_min: float = Field(gt=0.0, le=1e6)
    alpha_max: float = Field(gt=0.0, le=1e6)
    margin: float = Field(1.0, gt=0.0, le=10.0)
    memory_s: float = Field(2.0, gt=0.0, le=600.0)
    highpass_s: float = Field(0.05, gt=0.0, le=10.0)
    min_excitation_us: float = Field(10.0, ge=0.0, le=1000.0)
    min_samples_weight_us2: float = Field(
        2.0e4,
        ge=0.0,
        le=1e8,
        description="excitation needed before a slope is used, us^2 (1e8: 100 us over "
        "10 000 samples)",
    )
    tau_candidates_s: tuple[_LagS, ...] = Field(
        (),
        max_length=8,
        description="actuator lags the identifier chooses from, s (empty: actuator_tau_s only)",
    )
    min_response_rad_s2: float = Field(
        2.0,
        ge=0.0,
        le=10.0,
        description="smallest response the identifier learns from; measured with "
        "check-config --fly: 10 flies every reference vehicle, 40 ruins the F450's roll",
    )
    margin_min: float = Field(
        0.0,
        ge=0.0,
        le=10.0,
        description="lowest margin on a lag slower than actuator_tau_s (falls as "
        "sqrt(actuator_tau_s/tau), eased on weak vehicles); 0: constant margin",
    )
    delay_candidates_s: tuple[_DelayS, ...] = Field(
        (),
        max_length=12,
        description="loop delays (the link both ways) the identifier chooses from, s; "
        "empty: none identified",
    )
    delay_margin_slope: float = Field(
        0.0,
        ge=0.0,
        le=10.0,
        description="margin rise per unit of identified delay over identified lag; 0: off",
    )
    delay_margin_free_ratio: float = Field(
        0.0, ge=0.0, le=10.0, description="delay over lag the margin does not rise for"
    )
    delay_margin_max: float = Field(
        0.0, ge=0.0, le=10.0, description="highest margin a delay raises it to"
    )

    @model_validator(mode="after")
    def _range(self) -> AlphaAdaptConfig:
        if self.alpha_min > self.alpha_max:
            raise ValueError("alpha_min must not exceed alpha_max")
        if self.margin_min > self.margin:
            raise ValueError("margin_min must not exceed margin")
        if self.delay_margin_slope > 0.0:
            if not self.delay_candidates_s:
                raise ValueError("delay_margin_slope needs delay_candidates_s")
            if self.delay_margin_max < self.margin:
                raise ValueError("delay_margin_max must not be below margin")
        return self


class MfcAxisConfig(StrictModel):
    order: Literal[1, 2]
    alpha: float = Field(
        ge=1e-6,
        le=1e6,
        description="(rad/s^m) per us; positive: a positive command accelerates the axis "
        "positively (the mixer's convention), so a negative alpha is positive feedback",
    )
    window_s: float = Field(gt=0.0, le=0.5)
    kp: float = Field(ge=0.0, le=1000.0)
    kd: float = Field(0.0, ge=0.0, le=100.0)
    output_limit_us: float = Field(500.0, gt=0.0, le=1000.0)
    error_limit_rad: float = Field(0.5, gt=0.0, le=3.2)
    estimator: Literal["window", "algebraic"] = "window"
    actuator_tau_s: float = Field(
        0.0, ge=0.0, le=0.2, description="motor lag assumed in the F estimate; 0: none (paper)"
    )
    alpha_adapt: AlphaAdaptConfig | None = None
    lag_scaled_gains: bool = False
    lag_scaling_authority_ref: float = Field(
        0.0,
        ge=0.0,
        le=1e5,
        description="rad/s^m at full-scale command; above it a slow lag cuts kd less "
        "(by sqrt(authority/ref), at most back to kd); 0: off",
    )
    lag_scaling_max: float | None = Field(
        None,
        ge=1.0,
        le=100.0,
        description="largest factor a lag faster than actuator_tau_s raises the gains by; "
        "null: no cap",
    )
    lag_scaling_min: float | None = Field(
        None,
        gt=0.0,
        le=1.0,
        description="smallest factor a lag slower than actuator_tau_s cuts the gains to; "
        "null: no floor",
    )
    window_lag_scaled: bool = Field(
        False,
        description="a lag faster than actuator_tau_s shortens window_s by the factor it "
        "raises the gains by (at most lag_scaling_max)",
    )
    delay_kd_limit: float = Field(
        0.0,
        ge=0.0,
        le=10.0,
        description="kd at most this over the identified loop delay (1/s * s); 0: off",
    )

    @model_validator(mode="after")
    def _adapt_requirements(self) -> MfcAxisConfig:
        if self.alpha_adapt is not None and self.estimator != "window":
            raise ValueError("alpha_adapt needs estimator: window")
        if self.actuator_tau_s > 0.0 and self.estimator != "window":
            raise ValueError("actuator_tau_s needs estimator: window")
        adapt = self.alpha_adapt
        if adapt is not None and adapt.margin_min > 0.0 and self.actuator_tau_s <= 0.0:
            raise ValueError("alpha_adapt.margin_min needs actuator_tau_s > 0")
        # Settings that would reach nothing are refused rather than ignored.
        if self.lag_scaled_gains and (adapt is None or self.actuator_tau_s <= 0.0):
            raise ValueError("lag_scaled_gains needs alpha_adapt and actuator_tau_s > 0")
        if not self.lag_scaled_gains and (
            self.lag_scaling_max is not None or self.lag_scaling_min is not None
        ):
            raise ValueError("lag_scaling_max and lag_scaling_min need lag_scaled_gains")
        if self.window_lag_scaled and not (self.lag_scaled_gains and self.estimator == "window"):
            raise ValueError("window_lag_scaled needs lag_scaled_gains and estimator: window")
        if (
            self.lag_scaling_authority_ref > 0.0
            and not self.lag_scaled_gains
            and (adapt is None or adapt.margin_min <= 0.0)
        ):
            raise ValueError(
                "lag_scaling_authority_ref needs lag_scaled_gains or alpha_adapt.margin_min > 0"
            )
        if self.delay_kd_limit > 0.0 and (adapt is None or not adapt.delay_candidates_s):
            raise ValueError("delay_kd_limit needs alpha_adapt.delay_candidates_s")
        return self

    @field_validator("alpha", mode="before")
    @classmethod
    def _alpha(cls, raw: Any) -> Any:
        # Before pydantic's range: a sign error is named as such.
        if (v := real_number(raw)) is not None and v <= 0.0:
            raise ValueError(
                "expected a positive value in [1e-6, 1e6] (a negative alpha turns the law's "
                "feedback positive)"
            )
        return raw

    @model_validator(mode="after")
    def _alpha_in_adapt_range(self) -> MfcAxisConfig:
        adapt = self.alpha_adapt
        if adapt is not None and not adapt.alpha_min <= self.alpha <= adapt.alpha_max:
            raise ValueError(
                f"alpha {self.alpha:g} (the value until identified) must lie within "
                f"alpha_adapt's [{adapt.alpha_min:g}, {adapt.alpha_max:g}]"
            )
        return self


class MfcAxes(StrictModel):
    roll: MfcAxisConfig
    pitch: MfcAxisConfig
    yaw: MfcAxisConfig


class PidAxisConfig(StrictModel):
    kp: float = Field(ge=0.0, le=10.0)
    ki: float = Field(ge=0.0, le=10.0)
    kd: float = Field(ge=0.0, le=1.0)
    kff: float = Field(0.0, ge=0.0, le=10.0)
    i_limit: float = Field(0.3, ge=0.0, le=1.0)
    d_lpf_hz: float = Field(20.0, gt=0.0, le=1000.0)


class PidAxes(StrictModel):
    roll: PidAxisConfig
    pitch: PidAxisConfig
    yaw: PidAxisConfig


class _LoopConfig(StrictModel):
    dt_min_s: float = Field(0.000125, gt=0.0, le=0.01)
    dt_max_s: float = Field(0.02, gt=0.0, le=0.1)
    sticks: SticksConfig = SticksConfig()

    @model_validator(mode="after")
    def _dt(self) -> _LoopConfig:
        if self.dt_min_s >= self.dt_max_s:
            raise ValueError("dt_min_s must be below dt_max_s")
        return self


OUTPUT_LIMIT_MIN_FRACTION = 0.25
"""An axis's output limit is at least this share of the command's full scale:
measured with check-config --fly, a roll limit of 125 us (of 500) flies every
reference vehicle and 50 us crashes the Tarot."""


class MfcConfig(_LoopConfig):
    kind: Literal["mfc"]
    command_full_scale_us: float = Field(
        500.0,
        ge=100.0,
        le=1000.0,
        description="the command (us) the mixer takes as full scale: a PWM half-span is "
        "400-500 us; 100 still flies every reference vehicle, 0.51 makes the gain 1000x",
    )
    prefilter_hz: float | None = Field(20.0, gt=0.0, le=500.0)
    adapt_min_thrust: float = Field(0.15, ge=0.0, le=1.0)
    yaw_share_max: float = Field(
        0.0,
        ge=0.0,
        le=0.9,
        description="the largest fraction of roll and pitch the mixer may give yaw while "
        "the vehicle loses its heading to yaw saturation (0: roll and pitch first always, "
        "the paper's mixer)",
    )
    axes: MfcAxes

    @model_validator(mode="after")
    def _authority(self) -> MfcConfig:
        floor = OUTPUT_LIMIT_MIN_FRACTION * self.command_full_scale_us
        for name in ("roll", "pitch", "yaw"):
            limit = getattr(self.axes, name).output_limit_us
            if limit < floor:
                raise ValueError(
                    f"axes.{name}.output_limit_us {limit:g} leaves the law too little "
                    f"authority: expected at least {OUTPUT_LIMIT_MIN_FRACTION:g} x "
                    f"command_full_scale_us = {floor:g}"
                )
        return self


class PidConfig(_LoopConfig):
    kind: Literal["pid"]
    axes: PidAxes


def load_controller(path: str | Path = DEFAULT_CONTROLLER) -> MfcConfig | PidConfig:
    """Load and validate a controller file.

    Raises
    ------
    companion.errors.ConfigError
        Naming the file and the key path of every problem.
    """
    from companion.errors import ConfigError
    from companion.schema import read_yaml

    p = Path(path)
    # Validate through the wrapper but report paths as the user wrote them.
    raw = read_yaml(p)
    if not isinstance(raw, dict):
        raise ConfigError(str(p), ["(top level): expected a mapping of keys"])
    if raw.get("kind") not in ("mfc", "pid"):
        raise ConfigError(str(p), [f"kind: expected 'mfc' or 'pid', got {raw.get('kind')!r}"])
    if raw["kind"] == "mfc":
        return load_yaml_model(p, MfcConfig)
    return load_yaml_model(p, PidConfig)


def build_mixer(profile: VehicleProfile) -> Mixer:
    """The mixer from the profile's geometry (never its physics)."""
    return Mixer.from_geometry(
        [m.position_frd_m for m in profile.frame.motors],
        [m.spin for m in profile.frame.motors],
        idle=profile.limits.motor_idle,
    )


def build_stick_map(cfg: MfcConfig | PidConfig) -> StickMap:
    s = cfg.sticks

    def axis(a: AxisRatesConfig) -> AxisRates:
        return AxisRates(a.curve, a.max_deg_s, a.rc_rate, a.super_rate, a.expo)

    return StickMap(axis(s.roll), axis(s.pitch), axis(s.yaw), s.channels, s.deadband_us)


def _law_settings(cls: type[_L], model: StrictModel, **given: Any) -> _L:
    """``cls`` (a law's frozen dataclass) from ``model``, field for field under the
    same names, nested settings too; ``given`` are the fields the caller builds
    itself. The schema is the one place a gain has its default, unit and bounds:
    a law field the schema lacks is an AttributeError here (and a test)."""
    values = dict(given)
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        if f.name not in values:
            v = getattr(model, f.name)
            nested = isinstance(v, AlphaAdaptConfig)
            values[f.name] = _law_settings(AlphaAdaptation, v) if nested else v
    return cls(**values)


def mfc_gains(cfg: MfcConfig) -> MfcGains:
    """The laws' settings from a validated MFC configuration."""
    return _law_settings(
        MfcGains,
        cfg,
        roll=_law_settings(MfcAxisGains, cfg.axes.roll),
        pitch=_law_settings(MfcAxisGains, cfg.axes.pitch),
        yaw=_law_settings(MfcAxisGains, cfg.axes.yaw),
    )


def pid_gains(cfg: PidConfig) -> PidGains:
    """The PID's gains from a validated PID configuration."""
    return PidGains(
        roll=_law_settings(PidAxisGains, cfg.axes.roll),
        pitch=_law_settings(PidAxisGains, cfg.axes.pitch),
        yaw=_law_settings(PidAxisGains, cfg.axes.yaw),
    )


def build_controller(
    cfg: MfcConfig | PidConfig, profile: VehicleProfile
) -> MfcController | PidController:
    """Turn a controller config and a vehicle's geometry into a rate controller."""
    mixer = build_mixer(profile)
    if isinstance(cfg, MfcConfig):
        return MfcController(mfc_gains(cfg), mixer)
    return PidController(pid_gains(cfg), mixer, dt_min_s=cfg.dt_min_s, dt_max_s=cfg.dt_max_s)
