r"""The throttle as a climb rate, in the altitude and position modes.

The stick's deflection from centre, :math:`x = 2 s - 1`, past a deadband
:math:`d` and rescaled, :math:`x_d = \mathrm{sign}(x)(|x| - d)/(1 - d)`, through an
expo :math:`e` (0 linear, 1 cubic: PX4's ``math::expo``), :math:`x_e = (1 - e) x_d
+ e x_d^3`, times the climb (``up_max_m_s``) or descent (``down_max_m_s``) rate.
Inside the deadband the altitude is held. The climb setpoint follows the stick's
at most ``accel_up_m_s2`` faster upwards and ``accel_down_m_s2`` downwards.

The limits are the autopilot's own (:mod:`companion.stacks` reads them);
:class:`~companion.control.stick_limits.StickLimits` holds them with the other
sticks'. Pure: no I/O, no clock; ``dt`` from the caller.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from companion.control.ultralocal import check_positive

__all__ = ["ClimbLimits", "check_share", "expo_past_deadband"]


def expo_past_deadband(x: float, deadband: float, expo: float) -> float:
    """A deflection ``x`` in [-1, 1] past ``deadband`` (rescaled to [-1, 1]), then
    through ``expo`` (0 linear, 1 cubic); 0 inside the deadband (module docstring)."""
    a = abs(x)
    if not a > deadband:  # also a NaN
        return 0.0
    d = min(1.0, (a - deadband) / (1.0 - deadband))
    e = (1.0 - expo) * d + expo * d * d * d
    return e if x > 0.0 else -e


def check_share(owner: object, names: tuple[str, ...], hi: float) -> None:
    for name in names:
        v = getattr(owner, name)
        if not (isinstance(v, (int, float)) and 0.0 <= v < hi):
            raise ValueError(f"{type(owner).__name__}.{name} must be in [0, {hi:g}), got {v!r}")


@dataclass(frozen=True)
class ClimbLimits:
    """The throttle as a climb rate (module docstring).

    Attributes
    ----------
    deadband
        Share of the stick's half-travel around centre that holds, in [0, 1).
    expo
        0 linear .. 1 cubic.
    up_max_m_s, down_max_m_s
        Full throttle's climb and zero throttle's descent, m/s (> 0).
    accel_up_m_s2, accel_down_m_s2
        The climb setpoint's largest rise and fall, m/s^2 (> 0).
    """

    deadband: float
    expo: float
    up_max_m_s: float
    down_max_m_s: float
    accel_up_m_s2: float
    accel_down_m_s2: float

    def __post_init__(self) -> None:
        check_share(self, ("deadband",), 1.0)
        check_share(self, ("expo",), 1.0 + 1e-9)
        check_positive(self, ("up_max_m_s", "down_max_m_s", "accel_up_m_s2", "accel_down_m_s2"))

    def summary(self) -> str:
        return (
            f"climb {self.up_max_m_s:g} up / {self.down_max_m_s:g} down m/s "
            f"({self.accel_up_m_s2:g} / {self.accel_down_m_s2:g} m/s^2), deadband "
            f"{self.deadband:g}, expo {self.expo:g}"
        )

    def climb_m_s(self, throttle: float) -> float | None:
        """The climb rate (m/s, up) for a throttle stick in [0, 1]; None inside the
        deadband (hold), and for a non-finite stick."""
        if not math.isfinite(throttle):
            return None
        x = expo_past_deadband(2.0 * min(1.0, max(0.0, throttle)) - 1.0, self.deadband, self.expo)
        if x == 0.0:
            return None
        return x * self.up_max_m_s if x > 0.0 else x * self.down_max_m_s

    def slew(self, current: float, target: float, dt_s: float) -> float:
        """``current`` moved toward ``target`` by at most the rise or fall times ``dt_s``."""
        if target > current:
            return min(target, current + self.accel_up_m_s2 * dt_s)
        return max(target, current - self.accel_down_m_s2 * dt_s)
