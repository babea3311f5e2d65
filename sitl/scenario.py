"""Flight scenarios: what is flown, in what air, with which sensors, from which seed.

A scenario is data (``sitl/scenarios/<name>.yaml``), frozen in the repository
so a figure quoted anywhere can be regenerated. Everything random in a flight
derives from the scenario's ``seed``.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path
from typing import Annotated, Any

from pydantic import Field, field_validator

from companion.profile import (
    FilterWeight,
    GyroBiasWalk,
    GyroNoiseDensity,
    ImuLatencyS,
    ImuModel,
    ImuRateHz,
    VehicleProfile,
)
from companion.schema import StrictModel, load_yaml_model
from sitl.link_model import LINK_PROFILES, LinkSpec, parse_link
from sitl.wind import WindConfig

__all__ = [
    "GUST_SIGMA_MAX_M_S",
    "STEADY_WIND_MAX_M_S",
    "ImuOverride",
    "Scenario",
    "WindSpec",
    "list_scenarios",
    "load_scenario",
    "scenario_path",
]

SCENARIO_DIR = Path(str(files("sitl") / "scenarios"))

GUST_SIGMA_MAX_M_S = 20.0
"""The strongest turbulence a flight is given (per-axis sigma, m/s): a storm no
multirotor is flown in."""

STEADY_WIND_MAX_M_S = 30.0
"""The strongest steady wind a flight is given, per axis (m/s): a violent storm
(Beaufort 11); multirotors are rated for some 10-15 m/s."""

_WindMS = Annotated[float, Field(ge=-STEADY_WIND_MAX_M_S, le=STEADY_WIND_MAX_M_S)]


class WindSpec(StrictModel):
    steady_ned_m_s: tuple[_WindMS, _WindMS, _WindMS] = Field(
        (0.0, 0.0, 0.0), description="steady wind, NED, m/s (the air's velocity)"
    )
    gust_sigma_m_s: float = Field(0.0, ge=0.0, le=GUST_SIGMA_MAX_M_S)
    gust_length_m: float = Field(50.0, gt=0.0, le=2000.0)

    def config(self) -> WindConfig:
        return WindConfig(self.steady_ned_m_s, self.gust_sigma_m_s, self.gust_length_m)


class ImuOverride(StrictModel):
    """Fields replacing those of the profile's IMU model for this scenario."""

    rate_hz: ImuRateHz | None = Field(None, description="as the profile's imu.rate_hz, Hz")
    gyro_noise_density_rad_s_sqrt_hz: GyroNoiseDensity | None = Field(
        None, description="as the profile's, rad/s/sqrt(Hz)"
    )
    gyro_bias_random_walk_rad_s2_sqrt_hz: GyroBiasWalk | None = Field(
        None, description="as the profile's, rad/s^2/sqrt(Hz)"
    )
    latency_s: ImuLatencyS | None = Field(None, description="as the profile's, s")
    first_stage_filter_weight: FilterWeight | None = Field(None, description="as the profile's")

    def apply(self, model: ImuModel) -> ImuModel:
        update = {k: v for k, v in self.model_dump().items() if v is not None}
        return model.model_copy(update=update)


class Scenario(StrictModel):
    name: str = Field(min_length=1)
    description: str = ""
    seed: int = Field(ge=0)
    pilot: str = Field(min_length=1, description="maneuver name or stick-script path")
    duration_s: float | None = Field(None, gt=0.0, le=3600.0, description="default: the pilot's")
    free_flight: bool = True
    wind: WindSpec = WindSpec()
    imu: ImuOverride = ImuOverride()
    physics_dt_s: float = Field(0.001, gt=0.0, le=0.01)
    rc_rate_hz: float = Field(50.0, gt=0.0, le=1000.0)
    link: LinkSpec = Field(
        LINK_PROFILES["ideal"],
        description="the companion link: a profile name, fields as --link takes them, or a mapping",
    )

    @field_validator("link", mode="before")
    @classmethod
    def _link_by_name(cls, v: Any) -> Any:
        return parse_link(v) if isinstance(v, str) else v

    def imu_model(self, profile: VehicleProfile) -> ImuModel:
        return self.imu.apply(profile.physics.imu)


def scenario_path(name_or_path: str | Path) -> Path:
    """A bundled scenario's file from its name, or the path as given."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        return p
    return SCENARIO_DIR / f"{name_or_path}.yaml"


def list_scenarios() -> list[str]:
    """Names of the bundled scenarios."""
    return [p.stem for p in sorted(SCENARIO_DIR.glob("*.yaml"))]


def load_scenario(name_or_path: str | Path, *, check_pilot: bool = True) -> Scenario:
    """Load a bundled scenario by name, or a scenario file by path.

    ``check_pilot``: the scenario's pilot must be a maneuver name or an
    existing stick-script file (off when the caller flies another pilot).

    Raises
    ------
    companion.errors.ConfigError
        Naming the file and key path of every problem (or listing the bundled
        names when an unknown name is given).
    """
    from companion.errors import ConfigError

    p = scenario_path(name_or_path)
    if not p.exists():
        raise ConfigError(
            str(p), [f"no such scenario; bundled scenarios: {', '.join(list_scenarios())}"]
        )
    sc = load_yaml_model(p, Scenario)
    from sitl.pilot import MANEUVERS

    script = Path(sc.pilot)
    if check_pilot and sc.pilot not in MANEUVERS and not script.is_file():
        what = "no such stick-script file" if script.suffix in (".yaml", ".yml") else "unknown"
        raise ConfigError(
            str(p),
            [f"pilot: {what} {sc.pilot!r}; expected one of {', '.join(sorted(MANEUVERS))} "
             "or a stick-script file"],
        )  # fmt: skip
    return sc
