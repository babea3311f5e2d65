"""A campaign file: the grid of ``companion campaign --grid FILE``, in YAML.

Every key is optional; the defaults are the command's own::

    scenario: train-acro          # name or file
    duration_s: 20                # fly only the first seconds (null: the whole scenario)
    profiles: [f450, x500]        # names in vehicle_profiles/, or files [default: all]
    controllers: [mfc_default, pid_tarot_tuned]   # shipped names or files
    damage: [1.0, 0.8, 0.6]       # motor 1 efficiency factors, each in (0, 1]
    gust_sigma_m_s: [0, 2]        # wind gust sigmas, m/s
    seeds: {first: 1000, count: 3}   # or a list: [1000, 1007]
    oracle: true                  # fly the oracle once per case
    link: null                    # ideal, uart, usb-serial, ... or fields (delay_ms=5)

Files named in it (profiles, controllers, a scenario file) are read relative to
the campaign file's folder. The grid it describes is expanded lazily
(:class:`sitl.lab.campaign.Grid`): ten thousand seeds cost a range, not ten
thousand flights held in memory.
"""

from __future__ import annotations

import math
from importlib.resources import files
from pathlib import Path
from typing import Annotated

from pydantic import Discriminator, Field, Tag, field_validator

from companion.profile import FLIGHT_MAX_S
from companion.schema import StrictModel, load_yaml_model
from sitl.scenario import GUST_SIGMA_MAX_M_S

__all__ = [
    "CampaignFile",
    "SeedRange",
    "load_campaign_file",
    "resolve_controller",
    "resolve_profile",
]

MAX_AXIS_VALUES = 100_000
"""Values one axis may list (seeds by ``first``/``count`` are not listed)."""
MAX_FLIGHTS = 10_000_000
"""Flights one grid may expand to (checked by the command, which knows the default
profiles): a typo of three extra zeros is refused, not flown."""


class SeedRange(StrictModel):
    """``count`` consecutive seeds from ``first``."""

    first: Annotated[int, Field(ge=0, lt=2**32, description="the first seed")]
    count: Annotated[int, Field(ge=1, le=MAX_FLIGHTS, description="how many seeds")]

    def values(self) -> range:
        return range(self.first, self.first + self.count)


_GustSigmaMS = Annotated[float, Field(ge=0.0, le=GUST_SIGMA_MAX_M_S)]


class CampaignFile(StrictModel):
    """The grid a campaign flies: profiles x damage x gust sigmas x seeds x controllers, on
    one scenario."""

    scenario: str = Field("train-acro", description="scenario name, or file beside this one")
    duration_s: Annotated[float, Field(gt=0.0, le=FLIGHT_MAX_S)] | None = Field(
        20.0, description="fly only the first seconds, s; null: the whole scenario"
    )
    profiles: Annotated[list[str], Field(min_length=1, max_length=MAX_AXIS_VALUES)] | None = Field(
        None, description="names in vehicle_profiles/ or files; null: every profile there"
    )
    controllers: Annotated[list[str], Field(min_length=1, max_length=MAX_AXIS_VALUES)] | None = (
        Field(
            None,
            description="shipped names (mfc_default) or files; null: mfc_default and "
            "pid_tarot_tuned",
        )
    )
    damage: Annotated[list[float], Field(min_length=1, max_length=MAX_AXIS_VALUES)] = Field(
        [1.0, 0.8, 0.6], description="motor 1 thrust and torque efficiency factors, each in (0, 1]"
    )
    gust_sigma_m_s: Annotated[
        list[_GustSigmaMS], Field(min_length=1, max_length=MAX_AXIS_VALUES)
    ] = Field([0.0, 2.0], description="wind gust sigmas replacing the scenario's, m/s")
    seeds: Annotated[
        Annotated[SeedRange, Tag("range")]
        | Annotated[
            list[Annotated[int, Field(ge=0, lt=2**32)]],
            Field(min_length=1, max_length=MAX_AXIS_VALUES),
            Tag("list"),
        ],
        Discriminator(lambda v: "range" if isinstance(v, dict | SeedRange) else "list"),
    ] = Field(
        SeedRange(first=1000, count=3),
        description="{first, count} (a range: a million seeds cost nothing), or a list",
    )
    oracle: bool = Field(True, description="fly the oracle once per case")
    link: str | None = Field(
        None,
        description="the companion link: ideal, uart, usb-serial, ... or fields "
        "(delay_ms=5); null: the scenario's",
    )

    @field_validator("damage")
    @classmethod
    def _efficiencies(cls, v: list[float]) -> list[float]:
        bad = [x for x in v if not (math.isfinite(x) and 0.0 < x <= 1.0)]
        if bad:
            raise ValueError("expected efficiencies in (0, 1]")
        return v

    @field_validator("link")
    @classmethod
    def _link(cls, v: str | None) -> str | None:
        if v is not None:
            from sitl.link_model import parse_link

            parse_link(v)  # its ValueError names the part that is wrong
        return v

    def seed_values(self) -> range | list[int]:
        return self.seeds.values() if isinstance(self.seeds, SeedRange) else list(self.seeds)


def resolve_profile(name: str, base: Path | None = None) -> Path:
    """A profile's file: ``name`` itself when it is a file or ends in ``.yaml``
    (relative to ``base``), else ``vehicle_profiles/<name>.yaml`` here or in the
    project."""
    p = Path(name)
    if base is not None and not p.is_absolute() and (p.suffix in (".yaml", ".yml") or "/" in name):
        p = base / p
    if p.suffix in (".yaml", ".yml") or p.exists():
        return p
    root = Path(__file__).resolve().parents[2]
    for folder in (Path("vehicle_profiles"), root / "vehicle_profiles"):
        if (folder / f"{name}.yaml").exists():
            return folder / f"{name}.yaml"
    return Path("vehicle_profiles") / f"{name}.yaml"


def resolve_controller(name: str, base: Path | None = None) -> str:
    """A controller's file: ``name`` relative to ``base`` when it names a file, else
    the shipped ``companion/data/<name>.yaml``."""
    p = Path(name)
    if p.suffix in (".yaml", ".yml") or "/" in name:
        return str(base / p if base is not None and not p.is_absolute() else p)
    return str(files("companion") / "data" / f"{name}.yaml")


def load_campaign_file(path: str | Path) -> CampaignFile:
    """Read and validate a campaign file.

    Raises
    ------
    companion.errors.ConfigError
        Naming the file and each offending key (``seeds.count``, ``damage``, ...).
    """
    return load_yaml_model(path, CampaignFile)
