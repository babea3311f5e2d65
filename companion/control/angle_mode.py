"""The angle mode: the pilot's sticks as angles, flown by the attitude loop.

``companion run --mode angle``. The roll and pitch sticks ask for a roll and a
pitch angle (self-levelling: centred sticks are level), the yaw stick for a yaw
rate about the vertical, the throttle for the collective as in rates mode. The
attitude loop (:class:`companion.control.attitude.AttitudeLoop`, one set of gains
for every vehicle) turns them and the autopilot's attitude estimate into the body
rates the rate loop then flies, unchanged.

Sticks to angles (PX4's Stabilized mode does the same)
------------------------------------------------------
The two stick deflections :math:`(x_r, x_p) \\in [-1, 1]^2` are one tilt vector:
:math:`\\theta_{max} (x_r, x_p)`, shortened to :math:`\\theta_{max}` when longer
(a diagonal stick does not tilt further than a straight one). Above centre is
positive (roll right, nose up), as in rates mode. :math:`\\theta_{max}` is the
stack's own (PX4 ``MPC_MAN_TILT_MAX``, ArduCopter ``ANGLE_MAX``: read from its
parameters, :mod:`companion.stacks`). No heading is held: the yaw follows the yaw stick's
rate (the stick's rate curve, as in rates mode).

On the ground (the autopilot's landed state) the attitude loop is held reset and
asks for no rates: a vehicle on its legs cannot turn, and an attitude error left
to the loop would grow its output until the mixer cut the collective.

Pure: no I/O, no clock. What happens without a fresh estimate is the caller's
(the app's stale-estimate failsafe).
"""

from __future__ import annotations

import math

from companion.control.attitude import (
    DEFAULT_ATTITUDE_GAINS,
    AttitudeGains,
    AttitudeLoop,
    AttitudeSetpoint,
)
from companion.control.outer import (
    DEFAULT_SATURATION_BACKOFF,
    GainBackoff,
    SaturationBackoff,
)
from companion.control.quaternion import Quat, Vec3

__all__ = ["AngleMode", "stick_tilt_rad"]

_ZERO3: Vec3 = (0.0, 0.0, 0.0)


def stick_tilt_rad(x_roll: float, x_pitch: float, max_tilt_rad: float) -> tuple[float, float]:
    """Roll and pitch angles (rad) for the two stick deflections, the tilt at most
    ``max_tilt_rad`` (module docstring); a non-finite deflection is centred."""
    if not math.isfinite(x_roll + x_pitch):
        return 0.0, 0.0
    r, p = x_roll * max_tilt_rad, x_pitch * max_tilt_rad
    n = math.hypot(r, p)
    if n > max_tilt_rad:
        r, p = r * max_tilt_rad / n, p * max_tilt_rad / n
    return r, p


class AngleMode:
    """Sticks and the attitude estimate to the rate loop's reference (module docstring).

    Parameters
    ----------
    max_tilt_deg
        Full stick's tilt, deg, in (0, 60]: the stack's
        (:attr:`~companion.control.stick_limits.StickLimits.tilt_max_deg`).
    gains
        The attitude loop's (:data:`DEFAULT_ATTITUDE_GAINS`: one set for every vehicle).
    """

    def __init__(
        self,
        max_tilt_deg: float,
        gains: AttitudeGains = DEFAULT_ATTITUDE_GAINS,
        backoff: SaturationBackoff = DEFAULT_SATURATION_BACKOFF,
    ) -> None:
        if not (0.0 < max_tilt_deg <= 60.0):
            raise ValueError(f"max_tilt_deg: expected (0, 60] deg, got {max_tilt_deg!r}")
        self.loop = AttitudeLoop(gains)
        self.backoff = GainBackoff(backoff)
        """The roll and pitch gain's backoff while the rate loop saturates
        (:class:`~companion.control.outer.SaturationBackoff`)."""
        self.max_tilt_rad = math.radians(max_tilt_deg)
        self.setpoint = AttitudeSetpoint()
        """The last setpoint asked of the attitude loop."""

    def reset(self) -> None:
        """Forget what the attitude loop learnt (on engagement, a clock reset)."""
        self.loop.reset()
        self.backoff.reset()
        self.loop.set_gain_scale(1.0)

    def reference(
        self,
        dt_s: float,
        q_wxyz: Quat,
        gyro_frd_rad_s: Vec3,
        deflection: tuple[float, float, float],
        yaw_rate_rad_s: float,
        *,
        on_ground: bool,
        rate_saturated: tuple[bool, bool, bool] | None = None,
    ) -> Vec3:
        """The body-rate reference (FRD, rad/s) for this sample.

        Parameters
        ----------
        dt_s
            Time since the previous sample, s.
        q_wxyz
            The autopilot's attitude estimate (body FRD to NED).
        gyro_frd_rad_s
            This sample's body rates.
        deflection
            Roll, pitch, yaw stick deflections in [-1, 1] (the yaw's is unused:
            ``yaw_rate_rad_s`` is the yaw stick through its rate curve).
        yaw_rate_rad_s
            The pilot's yaw rate about the vertical, rad/s.
        on_ground
            The autopilot says the vehicle is landed.
        rate_saturated
            Which axes our rate loop's mixer saturated on the last command
            (``None``: not known): the backoff of the roll and pitch gain.
        """
        roll, pitch = stick_tilt_rad(deflection[0], deflection[1], self.max_tilt_rad)
        yaw_rate = yaw_rate_rad_s if math.isfinite(yaw_rate_rad_s) else 0.0
        self.setpoint = AttitudeSetpoint(roll, pitch, None, yaw_rate)
        if on_ground:
            self.loop.reset()
            return _ZERO3
        b = self.backoff
        before = b.scale
        if b.update(dt_s, rate_saturated) != before:
            self.loop.set_gain_scale(b.scale)
        return self.loop.update(dt_s, q_wxyz, gyro_frd_rad_s, self.setpoint)
