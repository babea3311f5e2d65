"""RC frames and stick maths.

* RC channels are pulse widths in microseconds, 1000..2000, centre 1500, AETR map:
  ch1 roll, ch2 pitch, ch3 throttle, ch4 yaw, ch5.. auxiliary switches.
* Body frame FRD; signs follow the rates they command:

  - ch1 > 1500 (stick right)  -> +p, roll right;
  - ch2 > 1500                -> +q, nose up.  **Project convention**: a high ch2
    pulse is "stick back".  This is the ArduPilot default (the pitch bar moves
    opposite to the physical stick), and the opposite sign of MAVLink
    ``MANUAL_CONTROL.x`` (positive = stick forward = nose down);
  - ch4 > 1500 (stick right)  -> +r, nose right;
  - ch3 throttle: 1000 -> 0, 2000 -> 1 (normalised collective thrust).

* Stick-to-rate is linear (no expo): ``rate = (us - 1500) / 500 * full_scale``,
  full scale 720 deg/s on roll and pitch and 360 deg/s on yaw by default.  The
  companion has its own mapping; this one is only for authoring.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = [
    "DEFAULT_RATE_FULL_SCALE_DEG_S",
    "RC_HALF_SPAN_US",
    "RC_MAX_US",
    "RC_MID_US",
    "RC_MIN_US",
    "Sticks",
    "rate_to_stick_us",
    "stick_us_to_rate",
    "stick_us_to_throttle",
    "throttle_to_stick_us",
]

RC_MIN_US = 1000
RC_MID_US = 1500
RC_MAX_US = 2000
RC_HALF_SPAN_US = 500.0
DEFAULT_RATE_FULL_SCALE_DEG_S: tuple[float, float, float] = (720.0, 720.0, 360.0)


def rate_to_stick_us(rate_deg_s: float, full_scale_deg_s: float) -> int:
    """Map a body rate to a stick pulse, linear and clamped.

    ``us = clamp(round(1500 + 500 * rate / full_scale), 1000, 2000)``

    Parameters
    ----------
    rate_deg_s : float
        Desired body rate, deg/s (FRD sign: + roll right, nose up, nose right).
    full_scale_deg_s : float
        Rate at full deflection (500 us from centre), deg/s, > 0.

    Returns
    -------
    int
        Pulse width, us, in 1000..2000.
    """
    us = RC_MID_US + RC_HALF_SPAN_US * rate_deg_s / full_scale_deg_s
    if us <= RC_MIN_US:
        return RC_MIN_US
    if us >= RC_MAX_US:
        return RC_MAX_US
    return math.floor(us + 0.5)


def stick_us_to_rate(us: float, full_scale_deg_s: float) -> float:
    """Map a stick pulse to a body rate, the inverse of :func:`rate_to_stick_us`.

    ``rate = (clamp(us, 1000, 2000) - 1500) / 500 * full_scale``

    Parameters
    ----------
    us : float
        Pulse width, us; values outside 1000..2000 are clamped.
    full_scale_deg_s : float
        Rate at full deflection, deg/s.

    Returns
    -------
    float
        Body rate, deg/s.
    """
    us = min(max(float(us), RC_MIN_US), RC_MAX_US)
    return (us - RC_MID_US) / RC_HALF_SPAN_US * full_scale_deg_s


def throttle_to_stick_us(throttle: float) -> int:
    """Map a normalised throttle (0..1, clamped) to ch3, 1000..2000 us."""
    us = RC_MIN_US + 1000.0 * min(max(throttle, 0.0), 1.0)
    return math.floor(us + 0.5)


def stick_us_to_throttle(us: float) -> float:
    """Map ch3 (us, clamped to 1000..2000) to a normalised throttle, 0..1."""
    return (min(max(float(us), RC_MIN_US), RC_MAX_US) - RC_MIN_US) / 1000.0


@dataclass(frozen=True)
class Sticks:
    """One RC frame, pulse widths in us (1000..2000), AETR.

    Attributes
    ----------
    roll_us, pitch_us, throttle_us, yaw_us : int
        ch1..ch4.
    aux_us : tuple of int
        ch5 onwards (e.g. an engage switch), may be empty.
    """

    roll_us: int
    pitch_us: int
    throttle_us: int
    yaw_us: int
    aux_us: tuple[int, ...] = ()

    def channels(self) -> tuple[int, ...]:
        """Return ``(ch1, ch2, ch3, ch4, *aux)`` in AETR order, us."""
        return (self.roll_us, self.pitch_us, self.throttle_us, self.yaw_us, *self.aux_us)
