"""The ArduPilot personality's parameters: their specs, defaults and the store.

``PARAM_REQUEST_READ`` / ``PARAM_REQUEST_LIST`` / ``PARAM_SET`` reach
:class:`ArduParams` through the face (``sitl.ardupilot_face``); the autopilot
(``sitl.ardupilot``) reads its values and listens for changes.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink

__all__ = ["PARAM_SPECS", "SITL_RATE_TUNE", "ArduParams", "ParamSpec"]

PARAM_INT8 = mavlink.MAV_PARAM_TYPE_INT8
PARAM_INT16 = mavlink.MAV_PARAM_TYPE_INT16
PARAM_INT32 = mavlink.MAV_PARAM_TYPE_INT32
PARAM_REAL32 = mavlink.MAV_PARAM_TYPE_REAL32
_INT_RANGE = {
    PARAM_INT8: (-128, 127),
    PARAM_INT16: (-32768, 32767),
    PARAM_INT32: (-(2**31), 2**31 - 1),
}


@dataclass(frozen=True)
class ParamSpec:
    """One ArduPilot parameter: name, default, MAVLink type, documented range."""

    name: str
    default: float
    param_type: int
    min_value: float = -math.inf
    max_value: float = math.inf
    doc: str = ""


def _rate_pid_specs(axis: str, p: float, i: float, d: float, flte: float) -> list[ParamSpec]:
    r32 = PARAM_REAL32
    return [
        ParamSpec(f"ATC_RAT_{axis}_P", p, r32, 0.0, 2.0, "rate P, output per rad/s"),
        ParamSpec(f"ATC_RAT_{axis}_I", i, r32, 0.0, 2.0, "rate I, output per rad"),
        ParamSpec(f"ATC_RAT_{axis}_D", d, r32, 0.0, 0.05, "rate D, output per rad/s^2"),
        ParamSpec(f"ATC_RAT_{axis}_FF", 0.0, r32, 0.0, 0.5, "rate feed-forward"),
        ParamSpec(f"ATC_RAT_{axis}_IMAX", 0.5, r32, 0.0, 1.0, "integrator limit"),
        ParamSpec(f"ATC_RAT_{axis}_FLTT", 20.0, r32, 0.0, 100.0, "target LPF, Hz (0 off)"),
        ParamSpec(f"ATC_RAT_{axis}_FLTE", flte, r32, 0.0, 100.0, "error LPF, Hz (0 off)"),
        ParamSpec(f"ATC_RAT_{axis}_FLTD", 20.0, r32, 0.0, 100.0, "D-term LPF, Hz (0 off)"),
    ]


PARAM_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("ARMING_CHECK", 1, PARAM_INT32, doc="0: skip the pre-arm checks"),
    ParamSpec("FS_OPTIONS", 16, PARAM_INT32, 0, 1023, "bit 2 (4): continue guided on RC loss"),
    ParamSpec("FS_THR_ENABLE", 1, PARAM_INT8, 0, 7, "RC loss: 0 off, 1 RTL, 3 land, 7 brake"),
    ParamSpec("GUID_OPTIONS", 0, PARAM_INT32, 0, 255, "bit 3 (8): thrust is thrust"),
    ParamSpec("GUID_TIMEOUT", 3.0, PARAM_REAL32, 0.1, 5.0, "s without targets before levelling"),
    ParamSpec("INS_GYRO_FILTER", 20, PARAM_INT16, 0, 256, "gyro LPF, Hz"),
    ParamSpec("LAND_SPEED", 50, PARAM_INT16, 30, 200, "final descent speed, cm/s"),
    ParamSpec("MAV_GCS_SYSID", 255, PARAM_INT16, 1, 255, "ground station sysid"),
    ParamSpec("MOT_SPIN_ARM", 0.10, PARAM_REAL32, 0.0, 0.2, "armed idle"),
    ParamSpec("MOT_SPIN_MAX", 0.95, PARAM_REAL32, 0.9, 1.0, "top of the output range"),
    ParamSpec("MOT_SPIN_MIN", 0.15, PARAM_REAL32, 0.0, 0.3, "bottom of the output range"),
    ParamSpec("MOT_THST_EXPO", 0.65, PARAM_REAL32, -1.0, 1.0, "thrust curve expo"),
    ParamSpec("RC_FS_TIMEOUT", 1.0, PARAM_REAL32, 0.1, 10.0, "s without RC before failsafe"),
    ParamSpec("SCHED_LOOP_RATE", 400, PARAM_INT16, 50, 2000, "main loop, Hz (at boot)"),
    ParamSpec("WPNAV_SPEED_DN", 150.0, PARAM_REAL32, 10, 500, "guided max descent, cm/s"),
    ParamSpec("WPNAV_SPEED_UP", 250.0, PARAM_REAL32, 10, 1000, "guided max climb, cm/s"),
    # AC_AttitudeControl_Multi.h defaults (AC_ATC_MULTI_RATE_*).
    *_rate_pid_specs("RLL", 0.135, 0.135, 0.0036, 0.0),
    *_rate_pid_specs("PIT", 0.135, 0.135, 0.0036, 0.0),
    *_rate_pid_specs("YAW", 0.180, 0.018, 0.0, 2.5),
)


class ArduParams:
    """ArduPilot-style parameter store (``PARAM_REQUEST_*`` / ``PARAM_SET``).

    Values are kept as the type says: integer types are rounded and saturated to
    the type's range (ArduPilot stores what it is sent; the documented range is
    not enforced, as in ``GCS_MAVLINK::handle_param_set``).
    """

    def __init__(self, specs: Sequence[ParamSpec] = PARAM_SPECS) -> None:
        self.specs = tuple(sorted(specs, key=lambda s: s.name))
        self._by_name = {s.name: s for s in self.specs}
        self._values = {s.name: float(s.default) for s in self.specs}
        self._listeners: list[Callable[[str, float], None]] = []

    def __contains__(self, name: str) -> bool:
        return name in self._by_name

    def __len__(self) -> int:
        return len(self.specs)

    def __getitem__(self, name: str) -> float:
        return self._values[name]

    def index(self, name: str) -> int:
        return self.specs.index(self._by_name[name])

    def by_index(self, index: int) -> ParamSpec | None:
        return self.specs[index] if 0 <= index < len(self.specs) else None

    def spec(self, name: str) -> ParamSpec | None:
        return self._by_name.get(name)

    def on_change(self, fn: Callable[[str, float], None]) -> None:
        """Call ``fn(name, value)`` after every successful :meth:`set`."""
        self._listeners.append(fn)

    def set(self, name: str, value: float) -> float:
        """Store ``value``; return what was stored.

        Raises
        ------
        KeyError
            For an unknown name.
        ValueError
            For a non-finite value.
        """
        spec = self._by_name[name]
        if not math.isfinite(value):
            raise ValueError(f"{name}: expected a finite value, got {value!r}")
        if spec.param_type in _INT_RANGE:
            lo, hi = _INT_RANGE[spec.param_type]
            value = float(min(hi, max(lo, round(value))))
        self._values[name] = float(value)
        for fn in self._listeners:
            fn(name, self._values[name])
        return self._values[name]


SITL_RATE_TUNE: tuple[tuple[str, float], ...] = tuple(
    (f"ATC_RAT_{axis}_{name}", value)
    for axis in ("RLL", "PIT")
    for name, value in (("P", 0.17), ("FLTT", 9.0), ("FLTD", 10.0))
)
"""Roll/pitch tune of the SITL airframe (ArduPilot defaults: P 0.135, FLTT 20, FLTD 20 Hz).

Chosen so a +1 rad/s roll-rate step on the F450 profile reaches 0.38 / 0.89 /
0.99 rad/s after 40 / 80 / 120 ms, as ArduCopter's own loop did (facts.md 10:
0.38 / 0.90 / 0.98); I, D, IMAX, FF and the yaw axis keep ArduPilot's defaults.
"""
