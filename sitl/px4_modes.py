"""PX4 flight modes as MAVLink carries them: main and sub mode packed in ``custom_mode``.

PX4's ``custom_mode`` holds the main mode in bits 16-23 and the sub mode in
bits 24-31 (``px4_custom_mode.h``); the names are pymavlink's. What the SITL's
PX4 personality does in each mode is :mod:`sitl.autopilot`'s docstring.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

__all__ = [
    "AUTO_SUB_LAND",
    "AUTO_SUB_LOITER",
    "MODE_LAND",
    "MODE_LOITER",
    "MODE_OFFBOARD",
    "FlightMode",
    "MainMode",
    "mode_name",
    "pack_custom_mode",
    "unpack_custom_mode",
]


class MainMode(IntEnum):
    """PX4 main modes (``px4_custom_mode.h``)."""

    MANUAL = 1
    ALTCTL = 2
    POSCTL = 3
    AUTO = 4
    ACRO = 5
    OFFBOARD = 6
    STABILIZED = 7


AUTO_SUB_LOITER = 3
"""PX4 AUTO sub mode LOITER (shown as HOLD by MAVSDK/QGC)."""
AUTO_SUB_LAND = 6
"""PX4 AUTO sub mode LAND."""

_AUTO_SUB_NAMES = {
    2: "TAKEOFF",
    3: "LOITER",
    4: "MISSION",
    5: "RTL",
    6: "LAND",
    7: "RTGS",
    8: "FOLLOWME",
}


def pack_custom_mode(main: int, sub: int = 0) -> int:
    """PX4 ``custom_mode``: ``main << 16 | sub << 24``.

    Raises
    ------
    ValueError
        If ``main`` or ``sub`` does not fit in a byte.
    """
    if not (0 <= main <= 255 and 0 <= sub <= 255):
        raise ValueError(f"expected main and sub modes in 0..255, got {main}, {sub}")
    return (main << 16) | (sub << 24)


def unpack_custom_mode(custom_mode: int) -> tuple[int, int]:
    """Split a PX4 ``custom_mode`` into ``(main, sub)``."""
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF


def mode_name(main: int, sub: int = 0) -> str:
    """Mode name as pymavlink's ``mode_string_v10`` spells PX4 modes.

    ``"OFFBOARD"``, ``"MANUAL"``...; AUTO sub modes by their own name (``"LAND"``,
    ``"LOITER"``); anything else ``"UNKNOWN"``.
    """
    if main == MainMode.AUTO:
        return _AUTO_SUB_NAMES.get(sub, "UNKNOWN")
    try:
        return MainMode(main).name
    except ValueError:
        return "UNKNOWN"


@dataclass(frozen=True)
class FlightMode:
    """A PX4 mode as a (main, sub) pair."""

    main: int
    sub: int = 0

    @property
    def custom_mode(self) -> int:
        return pack_custom_mode(self.main, self.sub)

    @property
    def name(self) -> str:
        return mode_name(self.main, self.sub)


MODE_OFFBOARD = FlightMode(MainMode.OFFBOARD)
MODE_LAND = FlightMode(MainMode.AUTO, AUTO_SUB_LAND)
MODE_LOITER = FlightMode(MainMode.AUTO, AUTO_SUB_LOITER)
