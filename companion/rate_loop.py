"""Which axes the law corrects with rates output, chosen from the autopilot's rate gains.

With rates output the law wraps the autopilot's own rate loop. Where that loop is
soft, the law's correction takes its lag away; where it is already stiff, the law
adds only noise, and correcting yaw alone tracks better
(``docs/research/realstack.md#law-axes``).

``--rates-law-axes auto`` (the default) reads the loop's proportional gain on roll
and pitch at start-up, as the product of the stack's parameters (PX4:
``MC_ROLLRATE_K`` times ``MC_ROLLRATE_P``), against the product of their defaults:
from :data:`STIFF` times that on, the law leaves the axis to the pilot's rate and
the lead. Yaw is always corrected. A stack without such parameters here
(ArduPilot) gets all three axes.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

__all__ = ["ALL_AXES", "PX4_RATE_GAINS", "STIFF", "LawAxes", "RateLoopGains"]

LawAxes = tuple[bool, bool, bool]
"""Per axis (roll, pitch, yaw), whether the law's correction is sent."""

ALL_AXES: LawAxes = (True, True, True)

STIFF = 1.5
"""The loop's proportional gain, over its default, from which the law's correction
on that axis no longer pays: from there correcting yaw alone tracked no worse than
the full law on the real PX4 SIH and on the bundled SITL's four paper vehicles
(``docs/research/realstack.md#law-axes-auto``)."""


@dataclass(frozen=True)
class RateLoopGains:
    """The parameters whose product is a stack's rate-loop proportional gain on roll
    and on pitch, each with its documented default."""

    roll: tuple[str, ...]
    pitch: tuple[str, ...]
    defaults: Mapping[str, float]

    @property
    def names(self) -> tuple[str, ...]:
        return (*self.roll, *self.pitch)

    def usable(self, got: Mapping[str, float | None]) -> tuple[dict[str, float], list[str]]:
        """The gains read that a choice can rest on (finite, positive), and the names
        of the others (not answered, or not so): with any of those, auto chooses all
        three axes."""
        values = {n: v for n in self.names if (v := got.get(n)) is not None and _positive(v)}
        return values, [n for n in self.names if n not in values]

    def stiffness(self, values: Mapping[str, float]) -> tuple[float, float]:
        """Roll's and pitch's proportional gain over their defaults' (a parameter
        ``values`` lacks takes its default)."""

        def ratio(names: tuple[str, ...]) -> float:
            out = 1.0
            for n in names:
                out *= values.get(n, self.defaults[n]) / self.defaults[n]
            return out

        return ratio(self.roll), ratio(self.pitch)

    def law_axes(self, values: Mapping[str, float]) -> LawAxes:
        """The axes the law corrects on a loop with these gains: yaw always, roll
        and pitch below :data:`STIFF`."""
        roll, pitch = self.stiffness(values)
        return (roll < STIFF, pitch < STIFF, True)

    def said(self, values: Mapping[str, float]) -> str:
        """The parameters as read, and the stiffness they make (for events and checks)."""
        shown = ", ".join(f"{n} {values.get(n, self.defaults[n]):g}" for n in self.names)
        roll, pitch = self.stiffness(values)
        return f"{shown}: {roll:.3g}x / {pitch:.3g}x the default gain on roll / pitch"


def _positive(v: float) -> bool:
    return math.isfinite(v) and v > 0.0


PX4_RATE_GAINS = RateLoopGains(
    # PX4 v1.16 parameter reference, Multicopter Rate Control: the rate loop's gain
    # K multiplies its P, I and D (K = 1, P = 0.15 by default on roll and pitch).
    roll=("MC_ROLLRATE_K", "MC_ROLLRATE_P"),
    pitch=("MC_PITCHRATE_K", "MC_PITCHRATE_P"),
    defaults={
        "MC_ROLLRATE_K": 1.0,
        "MC_ROLLRATE_P": 0.15,
        "MC_PITCHRATE_K": 1.0,
        "MC_PITCHRATE_P": 0.15,
    },
)
