r"""Pilot sticks (RC microseconds) to body-rate references and thrust.

Conventions: channels in microseconds, 1000-2000 with centre 1500; default
channel map AETR (ch1 roll, ch2 pitch, ch3 throttle, ch4 yaw); signs FRD:
a channel above centre commands a positive rate (roll right, nose up, nose
right). Throttle 1000 us is 0, 2000 us is 1.

Rate curves, with :math:`x \in [-1, 1]` the normalised deflection:

* linear (default): :math:`\omega = x \cdot \omega_{max}` (roll/pitch 720
  deg/s, yaw 360 deg/s at full stick);
* Betaflight: :math:`x' = x |x|^3 e + x (1 - e)`,
  :math:`\omega = 200\, r\, x' / \mathrm{clamp}(1 - |x| s, 0.01, 1)`
  deg/s, capped at 1998 deg/s, with rc-rate ``r``, super-rate ``s`` and
  expo ``e``: Betaflight's ``applyBetaflightRates`` and its
  ``SETPOINT_RATE_LIMIT_MAX`` (``src/main/fc/rc.c``), for ``r`` up to 2 (above
  2 Betaflight steepens ``r``, which this mapping does not).

A channel value that is not finite or lies outside ``valid_range_us``
(missing channel, 65535 "unused", failsafe 0) is invalid: the caller decides
what to do (the mapping returns centre sticks and zero throttle for it and
says so).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, NamedTuple

__all__ = [
    "AxisRates",
    "PilotCommand",
    "StickMap",
    "betaflight_rate_deg_s",
    "joystick_channels",
    "linear_rate_deg_s",
]

_DEG = math.pi / 180.0


def linear_rate_deg_s(x: float, max_deg_s: float) -> float:
    """Linear curve: deflection ``x`` in [-1, 1] to deg/s."""
    return x * max_deg_s


def betaflight_rate_deg_s(x: float, rc_rate: float, super_rate: float, expo: float) -> float:
    """Betaflight's rate curve (see module docstring); ``x`` in [-1, 1]."""
    ax = abs(x)
    xe = x * ax * ax * ax * expo + x * (1.0 - expo)
    denom = min(1.0, max(0.01, 1.0 - ax * super_rate))
    rate = 200.0 * rc_rate * xe / denom
    return max(-1998.0, min(1998.0, rate))


@dataclass(frozen=True)
class AxisRates:
    """Curve of one axis."""

    curve: Literal["linear", "betaflight"] = "linear"
    max_deg_s: float = 720.0
    rc_rate: float = 1.0
    super_rate: float = 0.7
    expo: float = 0.0

    def rate_deg_s(self, x: float) -> float:
        if self.curve == "linear":
            return linear_rate_deg_s(x, self.max_deg_s)
        return betaflight_rate_deg_s(x, self.rc_rate, self.super_rate, self.expo)


class PilotCommand(NamedTuple):
    rate_rad_s: tuple[float, float, float]
    """Body-rate reference, FRD, rad/s."""
    thrust: float
    """Collective, [0, 1]."""
    valid: bool
    """False when any mapped channel was missing or out of range."""
    deflection: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Roll, pitch and yaw sticks, each in [-1, 1] past the deadband (above centre
    positive): what a self-levelling mode scales to angles."""


@dataclass(frozen=True)
class StickMap:
    """Channel map and rate curves.

    ``channels`` holds the 1-based channel numbers of (roll, pitch, throttle,
    yaw); AETR by default.
    """

    roll: AxisRates = AxisRates(max_deg_s=720.0)
    pitch: AxisRates = AxisRates(max_deg_s=720.0)
    yaw: AxisRates = AxisRates(max_deg_s=360.0)
    channels: tuple[int, int, int, int] = (1, 2, 3, 4)
    deadband_us: float = 0.0
    valid_range_us: tuple[float, float] = (800.0, 2200.0)

    def _deflection(self, us: float) -> float:
        d = us - 1500.0
        db = self.deadband_us
        if abs(d) <= db:
            return 0.0
        d = d - db if d > 0 else d + db
        x = d / (500.0 - db)
        return 1.0 if x > 1.0 else (-1.0 if x < -1.0 else x)

    def map(self, channels_us: Sequence[float]) -> PilotCommand:
        """Map raw channels (index 0 = ch1) to a rate reference and thrust."""
        lo, hi = self.valid_range_us
        vals = []
        valid = True
        for k, ch in enumerate(self.channels):
            v = float(channels_us[ch - 1]) if 0 < ch <= len(channels_us) else math.nan
            if not (math.isfinite(v) and lo <= v <= hi):
                valid = False
                v = 1000.0 if k == 2 else 1500.0  # centre sticks, throttle off
            vals.append(v)
        roll_us, pitch_us, thr_us, yaw_us = vals
        x = (self._deflection(roll_us), self._deflection(pitch_us), self._deflection(yaw_us))
        rates = (
            self.roll.rate_deg_s(x[0]) * _DEG,
            self.pitch.rate_deg_s(x[1]) * _DEG,
            self.yaw.rate_deg_s(x[2]) * _DEG,
        )
        thrust = min(1.0, max(0.0, (thr_us - 1000.0) / 1000.0))
        return PilotCommand(rates, thrust, valid, x)


def joystick_channels(
    v: Sequence[int], stick_channels: tuple[int, int, int, int]
) -> tuple[int, ...]:
    """MANUAL_CONTROL ``(x, y, z, r, enabled_extensions, aux1..aux6)`` as RC channels.

    The sticks go where the stick map reads them (``stick_channels``: roll,
    pitch, throttle, yaw), so a joystick flies like the radio it stands for:
    ``y`` (roll right +) and ``r`` (yaw right +) to ``1500 + v/2`` us; ``x``
    (pitch, stick forward +, nose down) to ``1500 - x/2`` (a high pitch
    channel is nose up here); ``z`` (thrust, 0..1000) to ``1000 + z``. The
    switches ``aux1..aux6`` (each -1000..1000, present when
    ``enabled_extensions`` bits 2..7 say so) become channels 5..10, so
    ``--engage-channel 5`` is ``aux1``; an absent one is centred (neither high
    nor low). A value beyond its range maps out of the valid pulse range, so
    the stick map calls the frame invalid."""
    x, y, z, r, ext = v[0], v[1], v[2], v[3], v[4]
    chans = [1500] * 18
    for i in range(6):
        if ext & (4 << i):
            chans[4 + i] = 1500 + v[5 + i] // 2
    roll_ch, pitch_ch, thr_ch, yaw_ch = stick_channels
    for ch, us in (
        (roll_ch, 1500 + y // 2),
        (pitch_ch, 1500 - x // 2),
        (thr_ch, 1000 + z),
        (yaw_ch, 1500 + r // 2),
    ):
        if 0 < ch <= 18:
            chans[ch - 1] = us
    return tuple(chans)
