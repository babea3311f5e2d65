r"""The outer loops, cascaded on the rate loop: position and altitude to body rates and thrust.

Issue #12, step one: the pure laws. The cascade, slowest first
(``docs/research/outer.md`` has the design, the numbers and what is not done)::

    position ─P─▶ velocity ref ─iP─▶ tilt (roll, pitch) ──┐
                  (bounded)          (bounded; altitude    │
                                      first)               ├─▶ attitude ─iP─▶ body-rate ref
    heading, yaw-rate feedforward ─────────────────────────┘        (to the rate loop, as it is)
    altitude ─P─▶ climb-rate ref ─iP─▶ collective ─(÷ cos tilt)─▶ thrust (to its mixer)

Each loop is an iP on an ultra-local model of order 1 with a known alpha
(:mod:`~companion.control.ultralocal`): attitude :math:`\alpha = 1` (kinematics),
horizontal velocity :math:`\alpha = g` (gravity), vertical velocity
:math:`\alpha = 2g/\hat T_h` (the hover thrust, identified in flight).

One update (:meth:`OuterController.update`), for one sample of attitude, position
and velocity:

1. :class:`~companion.control.vertical.VerticalLoop`: the collective, compensated
   for the measured tilt; its level-equivalent part :math:`T_\ell`.
2. Altitude first: the horizontal thrust may use only what the vertical leaves
   below ``thrust_max``, :math:`T_\ell \tan\vartheta \le \sqrt{T_{max}^2 - T_\ell^2}`,
   so the tilt limit is :math:`\min(\vartheta_{max}, \arccos(T_\ell / T_{max}))`
   (PX4's position controller limits its horizontal thrust the same way).
3. :class:`~companion.control.horizontal.HorizontalLoop`: roll and pitch at the
   heading setpoint (the current heading without one), within that limit.
4. :class:`~companion.control.attitude.AttitudeLoop`: the body-rate reference.

No I/O, no clock: ``dt_s`` and the samples come from the caller.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

from companion.control.attitude import (
    DEFAULT_ATTITUDE_GAINS,
    AttitudeGains,
    AttitudeLoop,
    AttitudeSetpoint,
)
from companion.control.horizontal import (
    DEFAULT_HORIZONTAL_GAINS,
    HorizontalGains,
    HorizontalLoop,
    HorizontalSetpoint,
)
from companion.control.quaternion import Quat, Vec3, normalise_or_none, yaw_rad
from companion.control.vertical import (
    DEFAULT_VERTICAL_GAINS,
    VerticalGains,
    VerticalLoop,
    VerticalSetpoint,
)

__all__ = [
    "DEFAULT_OUTER_GAINS",
    "OuterController",
    "OuterGains",
    "OuterOutput",
    "OuterSetpoint",
    "altitude_first_tilt_limit",
]


@dataclass(frozen=True)
class OuterGains:
    """The three loops' gains: one set for every vehicle (:data:`DEFAULT_OUTER_GAINS`)."""

    attitude: AttitudeGains = DEFAULT_ATTITUDE_GAINS
    vertical: VerticalGains = DEFAULT_VERTICAL_GAINS
    horizontal: HorizontalGains = DEFAULT_HORIZONTAL_GAINS


DEFAULT_OUTER_GAINS = OuterGains()
"""The shipped outer-loop gains (``docs/research/outer.md``: the bandwidth separation)."""


class OuterSetpoint(NamedTuple):
    """What the vehicle is asked to fly: position/velocity, altitude/climb, heading."""

    horizontal: HorizontalSetpoint = HorizontalSetpoint()
    vertical: VerticalSetpoint = VerticalSetpoint()
    yaw_rad: float | None = None
    """Heading to hold, rad; ``None``: the yaw follows ``yaw_rate_rad_s``."""
    yaw_rate_rad_s: float = 0.0
    """Yaw-rate feedforward about the NED vertical, rad/s."""


class OuterOutput(NamedTuple):
    """What the outer loops produced for one sample."""

    rate_ref_frd_rad_s: Vec3
    """Body-rate reference for the rate loop, FRD, rad/s."""
    thrust: float
    """Collective for the rate loop's mixer, normalised [thrust_min, thrust_max]."""
    attitude_setpoint: AttitudeSetpoint
    """What the attitude loop was asked (the horizontal loop's roll and pitch)."""
    level_thrust: float
    """The vertical loop's collective before tilt compensation."""
    tilt_limit_rad: float
    """The tilt allowed this sample (altitude first)."""
    tilt_limited: bool
    """Whether the horizontal loop's tilt was clamped (to its max or by altitude first)."""
    fault: bool
    """True when any loop replaced a non-finite input (each loop's ``fault`` says which)."""


def altitude_first_tilt_limit(level_thrust: float, thrust_max: float, tilt_max_rad: float) -> float:
    r"""The tilt the horizontal loop may use, rad: :math:`\min(\vartheta_{max},
    \arccos(T_\ell / T_{max}))`, 0 when :math:`T_\ell \ge T_{max}`.

    Tilted by :math:`\vartheta` with the vertical thrust kept, the collective is
    :math:`T_\ell / \cos\vartheta`; it stays within :math:`T_{max}` up to that angle.
    """
    if level_thrust >= thrust_max:
        return 0.0
    if level_thrust <= 0.0:
        return tilt_max_rad
    lim = math.acos(level_thrust / thrust_max)
    return lim if lim < tilt_max_rad else tilt_max_rad


class OuterController:
    """Position/velocity, altitude/climb and heading to body rates and thrust.

    Composes the three loops (module docstring); each is reachable as an
    attribute (``attitude``, ``vertical``, ``horizontal``) for its diagnostics
    and, for the vertical loop, ``on_ground``.
    """

    __slots__ = ("_gains", "attitude", "horizontal", "vertical")

    def __init__(self, gains: OuterGains = DEFAULT_OUTER_GAINS) -> None:
        self._gains = gains
        self.attitude = AttitudeLoop(gains.attitude)
        self.vertical = VerticalLoop(gains.vertical)
        self.horizontal = HorizontalLoop(gains.horizontal)

    @property
    def gains(self) -> OuterGains:
        return self._gains

    def reset(self, thrust: float | None = None, hover_thrust: float | None = None) -> None:
        """Forget all state (on disarm, on hand-back). ``thrust`` and
        ``hover_thrust``: as :meth:`VerticalLoop.reset`."""
        self.attitude.reset()
        self.vertical.reset(thrust, hover_thrust)
        self.horizontal.reset()

    def update(
        self,
        dt_s: float,
        q_wxyz: Quat,
        rate_frd_rad_s: Vec3,
        position_ned_m: Vec3,
        velocity_ned_m_s: Vec3,
        setpoint: OuterSetpoint,
        *,
        applied_thrust: float | None = None,
    ) -> OuterOutput:
        """One update of the cascade.

        Parameters
        ----------
        dt_s
            Time since the previous update (sample timestamps), s.
        q_wxyz
            Attitude estimate, body FRD to NED.
        rate_frd_rad_s
            Measured body rates, rad/s.
        position_ned_m, velocity_ned_m_s
            Local position (m) and velocity (m/s), NED.
        setpoint
            Horizontal, vertical and heading setpoints.
        applied_thrust
            The collective the mixer really applied after the previous update
            (``None``: as sent).

        Each loop handles its own non-finite inputs (their ``update`` docstrings);
        an attitude estimate that is not a rotation counts as level at an unknown
        heading (no tilt compensation, the horizontal loop holds level).
        """
        q = normalise_or_none(q_wxyz)
        if q is None:
            cos_tilt = 1.0
            heading = math.nan
        else:
            cos_tilt = 1.0 - 2.0 * (q[1] * q[1] + q[2] * q[2])
            heading = yaw_rad(q)
        yaw_sp = setpoint.yaw_rad
        if yaw_sp is not None:
            heading = yaw_sp

        vert = self.vertical
        thrust = vert.update(
            dt_s,
            position_ned_m[2],
            velocity_ned_m_s[2],
            setpoint.vertical,
            cos_tilt=cos_tilt,
            applied=applied_thrust,
        )
        vg = vert.gains
        hg = self.horizontal.gains
        tilt_lim = altitude_first_tilt_limit(vert.level_thrust, vg.thrust_max, hg.tilt_max_rad)

        hor = self.horizontal
        roll, pitch = hor.update(
            dt_s,
            (position_ned_m[0], position_ned_m[1]),
            (velocity_ned_m_s[0], velocity_ned_m_s[1]),
            heading,
            setpoint.horizontal,
            tilt_limit_rad=tilt_lim,
        )
        att_sp = AttitudeSetpoint(roll, pitch, yaw_sp, setpoint.yaw_rate_rad_s)
        att = self.attitude
        rate_ref = att.update(dt_s, q_wxyz, rate_frd_rad_s, att_sp)
        return OuterOutput(
            rate_ref,
            thrust,
            att_sp,
            vert.level_thrust,
            tilt_lim,
            hor.limited,
            att.fault or vert.fault or hor.fault,
        )
