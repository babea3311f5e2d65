"""One flight of a campaign, as the grid names it (:class:`FlightSpec`).

Built by :mod:`sitl.lab.campaign`'s grid and flown there; its identity (the
flight's and the case's id) is :mod:`sitl.lab.campaign_store`'s. Both import it
from here, so neither imports the other for it.
"""

from __future__ import annotations

from dataclasses import dataclass

from companion.config import MfcConfig, PidConfig
from companion.profile import VehicleProfile
from sitl.scenario import Scenario

__all__ = ["FlightSpec"]


@dataclass(frozen=True)
class FlightSpec:
    """One flight of a campaign: what flies, how damaged, in which air, which seed."""

    profile_name: str
    profile: VehicleProfile
    damage: float
    gust_sigma_m_s: float
    seed: int
    controller_name: str
    controller: MfcConfig | PidConfig
    scenario: Scenario
