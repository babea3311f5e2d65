"""ArduCopter's flight modes: the numbers HEARTBEAT carries and the groups the rules use.

What the SITL's ArduPilot personality does in each mode is :mod:`sitl.ardupilot`'s
docstring.
"""

from __future__ import annotations

from enum import IntEnum

__all__ = ["FLYABLE", "GUIDED", "MANUAL_THROTTLE", "NEEDS_POSITION", "CopterMode"]


class CopterMode(IntEnum):
    """ArduCopter mode numbers (``ArduCopter/mode.h``, ``Mode::Number``)."""

    STABILIZE = 0
    ACRO = 1
    ALT_HOLD = 2
    AUTO = 3
    GUIDED = 4
    LOITER = 5
    RTL = 6
    LAND = 9
    BRAKE = 17
    GUIDED_NOGPS = 20

    @property
    def custom_mode(self) -> int:
        return int(self)


FLYABLE = {
    CopterMode.STABILIZE,
    CopterMode.ACRO,
    CopterMode.ALT_HOLD,
    CopterMode.GUIDED,
    CopterMode.LOITER,
    CopterMode.LAND,
    CopterMode.BRAKE,
    CopterMode.GUIDED_NOGPS,
}
"""The modes this SITL flies (AUTO and RTL need navigation it does not have)."""
GUIDED = {CopterMode.GUIDED, CopterMode.GUIDED_NOGPS}
"""The modes a companion's SET_ATTITUDE_TARGET drives."""
MANUAL_THROTTLE = {CopterMode.STABILIZE, CopterMode.ACRO}
"""The modes refused during the radio failsafe."""
NEEDS_POSITION = {CopterMode.LOITER, CopterMode.BRAKE}
"""The modes that need a position estimate."""
