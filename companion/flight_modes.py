"""The ``--mode`` choices: what each flies, its outer law and the estimates it needs.

Chosen once per run (:data:`FLIGHT_MODES`); :class:`companion.modes.ModeLaws`
flies the one chosen.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from companion.control.angle_mode import AngleMode
from companion.control.hold_modes import HoldMode
from companion.control.mfc import RateController
from companion.control.outer import OuterLaw
from companion.control.stick_limits import StickLimits

__all__ = ["FLIGHT_MODES", "FlightMode"]


@dataclass(frozen=True)
class FlightMode:
    """One ``--mode``: what the sticks ask, and what it flies on."""

    name: str
    description: str
    """What the sticks fly, for the run's ``mode`` event."""
    law: Callable[[StickLimits, OuterLaw | None], AngleMode | HoldMode] | None = None
    """Its outer law, given the stack's stick limits and the outer loops it flies
    (None: its own); None: the sticks are the rate loop's reference."""
    needs_position: bool = False
    flies_missions: bool = False
    """``--mission`` flies its waypoints in this mode."""

    @property
    def needs_attitude(self) -> bool:
        return self.law is not None

    @property
    def shares_yaw(self) -> bool:
        """Whether the rate loop may give yaw a share of roll and pitch while the
        heading is being lost (:class:`companion.control.yaw_share.YawShare`): in
        the modes that fly the attitude for the pilot, a vehicle that spins has
        failed the mode; in rates the pilot flies yaw, and roll and pitch stay
        first (an acro flip needs all of them)."""
        return self.needs_attitude

    def fit(self, controller: RateController) -> None:
        """The rate loop as this mode flies it: no yaw share where it offers none
        (the flight core at start, replay for the mode its log recorded)."""
        if not self.shares_yaw:
            controller.yaw_share.most = 0.0


FLIGHT_MODES: dict[str, FlightMode] = {
    m.name: m
    for m in (
        FlightMode("rates", "rates: sticks to body rates, the rate loop's reference"),
        FlightMode(
            "angle",
            "angle: sticks to roll and pitch angles up to the autopilot's own limit and a "
            "yaw rate, on the autopilot's ATTITUDE_QUATERNION",
            law=lambda limits, _outer: AngleMode(limits.tilt_max_deg),
        ),
        FlightMode(
            "altitude",
            "altitude: sticks to roll and pitch angles, a climb rate (the altitude held "
            "at mid-stick) and a yaw rate, within the autopilot's own limits, on "
            "ATTITUDE_QUATERNION and LOCAL_POSITION_NED",
            law=lambda limits, outer: HoldMode(position=False, limits=limits, outer=outer),
            needs_position=True,
        ),
        FlightMode(
            "position",
            "position: sticks to a horizontal velocity and a climb rate (the position "
            "and altitude held at mid-stick) and a yaw rate, shaped as the autopilot's own "
            "Position mode shapes them, on ATTITUDE_QUATERNION and LOCAL_POSITION_NED",
            law=lambda limits, outer: HoldMode(position=True, limits=limits, outer=outer),
            needs_position=True,
            flies_missions=True,
        ),
    )
}
"""Every ``--mode``, by name."""
