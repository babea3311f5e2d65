"""Yaw's share of roll and pitch, given while the vehicle is losing its heading.

The mixer flies roll and pitch first: yaw gets the headroom they leave. On a
vehicle with a weak motor that headroom can be none for as long as it flies,
and the vehicle turns where yaw drives it, whatever is asked. A fixed rule
that puts yaw first stops that and makes every other damaged vehicle pay on
its paths (docs/research/outer.md, "Yaw ahead of roll and pitch in the
mixer"). So the share follows the flight:

* **The signal: the heading lost to saturation.** While the mixer could not
  give yaw what the law asked, the yaw rate error is integrated; otherwise the
  integral leaks away over :data:`LEAK_S`. It is the heading the rate loop
  failed to deliver because yaw had no room, in radians, and it needs no
  heading estimate, so it works in rate mode as in the outer modes. A flip
  saturates yaw too, but briefly, and the pilot is not turning then: its yaw
  error integrates to a few degrees and leaks away.
* **Given** while that loss is past :data:`LOST_ON_RAD` and roll and pitch
  are not saturated on their own (a vehicle using all of its roll and pitch
  has none to spare): the share rises at :data:`RISE_PER_S` up to the
  configured most.
* **Kept** while yaw needs it (the mixer used some of it this sample, or yaw
  is still saturated), **taken back** at :data:`FALL_PER_S` once yaw fits on
  its own.

The share is the fraction by which the mixer may shrink roll and pitch while
yaw does not fit (:meth:`companion.control.mixer.Mixer.mix`): for yaw's room,
or, at the top of the collective, for the lift the air mode cut so they fit (a
weak motor's vehicle is short of both at once). The mixer reports the part it
used, and roll and pitch as saturated, so the laws learn what was applied.

Only the modes that fly the attitude for the pilot offer it
(:attr:`companion.flight_modes.FlightMode.shares_yaw`); in rates the pilot flies
yaw and roll and pitch stay first. Measured: docs/research/mixer.md, "Yaw's
share on demand".
"""

from __future__ import annotations

__all__ = ["FALL_PER_S", "LEAK_S", "LOST_ON_RAD", "RISE_PER_S", "YawShare"]

LOST_ON_RAD = 0.2
"""Heading lost to yaw saturation (rad, about 11 deg) before yaw is given a share."""
LEAK_S = 1.0
"""Time constant over which a heading loss is forgotten once yaw fits again (s)."""
RISE_PER_S = 1.0
"""How fast the share is given (fraction per second: half of roll and pitch in 0.5 s)."""
FALL_PER_S = 0.2
"""How fast the share is taken back once yaw fits on its own (fraction per second)."""


class YawShare:
    """The share, updated once per sample from what the mixer did.

    Parameters
    ----------
    most
        The largest share (``yaw_share_max`` in the controller's file); 0 keeps
        roll and pitch first always.
    """

    __slots__ = ("lost_rad", "most", "value")

    def __init__(self, most: float) -> None:
        self.most = float(most)
        self.value = 0.0
        """The share offered to the mixer at the next sample, [0, most]."""
        self.lost_rad = 0.0
        """The heading lost to yaw saturation (signed, rad)."""

    def reset(self) -> None:
        self.value = 0.0
        self.lost_rad = 0.0

    def update(
        self,
        dt_s: float,
        yaw_error_rad_s: float,
        yaw_saturated: bool,
        roll_pitch_saturated: bool,
        used: float,
    ) -> float:
        """The share for the next sample, from this sample's yaw rate error (rad/s,
        measured minus asked), whether yaw and roll or pitch were saturated, and
        the share the mixer used."""
        if self.most <= 0.0:
            return 0.0
        if yaw_saturated:
            lost = self.lost_rad + yaw_error_rad_s * dt_s
            self.lost_rad = lost if lost - lost == 0.0 else 0.0  # never non-finite
        else:
            self.lost_rad -= self.lost_rad * min(1.0, dt_s / LEAK_S)
        value = self.value
        if self.lost_rad > LOST_ON_RAD or self.lost_rad < -LOST_ON_RAD:
            if not roll_pitch_saturated or used > 0.0:
                value += RISE_PER_S * dt_s
        elif used <= 0.0 and not yaw_saturated:
            value -= FALL_PER_S * dt_s
        self.value = 0.0 if value < 0.0 else (self.most if value > self.most else value)
        return self.value
