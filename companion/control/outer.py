r"""The outer loops, cascaded on the rate loop: position and altitude to body rates and thrust.

The pure laws. The cascade, slowest first
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

Backing off when the rate loop saturates
----------------------------------------
The attitude (roll and pitch), velocity and position gains are scaled by
:math:`s \in [s_{min}, 1]` (:class:`SaturationBackoff`): :math:`s = 1` while the
rate loop's mixer saturated roll or pitch in less than ``saturation_low`` of the
recent samples (a first-order average over ``tau_s``), :math:`s_{min}` above
``saturation_high``, linear between; the same for the yaw, which gets only the
headroom the others leave (:mod:`~companion.control.mixer`), with its own,
higher thresholds (a vehicle near its thrust limit saturates the yaw now and
then in a plain hover); the lower scale of the two applies. A vehicle with the
authority and the thrust to spare flies the full gains; one whose rate loop
runs out of authority (a weak motor, little thrust margin) is asked for less,
before the collective the mixer shifts for its torques costs it its altitude
and the yaw its heading. The caller says which axes the rate loop saturated
(``rate_saturated``); without it (the autopilot's own rate loop, ``--output
rates``) the gains stay as they are.

No I/O, no clock: ``dt_s`` and the samples come from the caller.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple, Protocol

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
    "DEFAULT_SATURATION_BACKOFF",
    "GainBackoff",
    "OuterController",
    "OuterGains",
    "OuterLaw",
    "OuterOutput",
    "OuterSetpoint",
    "SaturationBackoff",
    "altitude_first_tilt_limit",
]


@dataclass(frozen=True)
class SaturationBackoff:
    """How far the outer gains back off when the rate loop saturates (module docstring).

    Attributes
    ----------
    scale_min
        :math:`s_{min}`, in (0, 1]: the gains' share left at full backoff (1: none).
    saturation_low, saturation_high
        Share of the recent samples with roll or pitch saturated at which the
        backoff starts and is complete, 0 <= low < high <= 1.
    yaw_saturation_low, yaw_saturation_high
        The same for the yaw.
    tau_s
        Time constant of the shares' averages, s.
    """

    scale_min: float = 0.55
    saturation_low: float = 0.02
    saturation_high: float = 0.10
    yaw_saturation_low: float = 0.10
    yaw_saturation_high: float = 0.30
    tau_s: float = 1.0

    def __post_init__(self) -> None:
        if not 0.0 < self.scale_min <= 1.0:
            raise ValueError(
                f"SaturationBackoff.scale_min must be in (0, 1], got {self.scale_min!r}"
            )
        for pre in ("", "yaw_"):
            lo, hi = getattr(self, f"{pre}saturation_low"), getattr(self, f"{pre}saturation_high")
            if not 0.0 <= lo < hi <= 1.0:
                raise ValueError(
                    f"SaturationBackoff needs 0 <= {pre}saturation_low < {pre}saturation_high "
                    f"<= 1, got {lo!r} and {hi!r}"
                )
        if not (math.isfinite(self.tau_s) and self.tau_s > 0.0):
            raise ValueError(f"SaturationBackoff.tau_s must be finite and > 0, got {self.tau_s!r}")

    def scale(self, roll_pitch_share: float, yaw_share: float = 0.0) -> float:
        """The gains' scale for the shares of samples with roll or pitch, and with
        yaw, saturated: the lower of the two ramps."""
        a = self._ramp(roll_pitch_share, self.saturation_low, self.saturation_high)
        b = self._ramp(yaw_share, self.yaw_saturation_low, self.yaw_saturation_high)
        return a if a < b else b

    def _ramp(self, share: float, lo: float, hi: float) -> float:
        if share <= lo:
            return 1.0
        if share >= hi:
            return self.scale_min
        return 1.0 - (1.0 - self.scale_min) * (share - lo) / (hi - lo)


DEFAULT_SATURATION_BACKOFF = SaturationBackoff()
"""The shipped backoff (``docs/research/outer.md``: the gains raised, backing off)."""


class GainBackoff:
    """The recent shares of saturated samples and the gain scale they give
    (:class:`SaturationBackoff`), for whichever loops the caller scales."""

    __slots__ = ("_b", "scale", "shares")

    def __init__(self, backoff: SaturationBackoff = DEFAULT_SATURATION_BACKOFF) -> None:
        self._b = backoff
        self.reset()

    def reset(self) -> None:
        self.shares = (0.0, 0.0)
        """Shares of the recent samples with roll or pitch, and with yaw, saturated."""
        self.scale = 1.0
        """The gains' scale now."""

    def update(self, dt_s: float, rate_saturated: tuple[bool, bool, bool] | None) -> float:
        """Count one sample (``None`` or a ``dt_s`` not finite and > 0: nothing
        known, nothing changes); returns the scale."""
        if rate_saturated is None or not (math.isfinite(dt_s) and dt_s > 0.0):
            return self.scale
        k = dt_s / self._b.tau_s
        k = k if k < 1.0 else 1.0
        rp, yw = self.shares
        rp += ((1.0 if rate_saturated[0] or rate_saturated[1] else 0.0) - rp) * k
        yw += ((1.0 if rate_saturated[2] else 0.0) - yw) * k
        self.shares = (rp, yw)
        self.scale = self._b.scale(rp, yw)
        return self.scale


@dataclass(frozen=True)
class OuterGains:
    """The three loops' gains: one set for every vehicle (:data:`DEFAULT_OUTER_GAINS`)."""

    attitude: AttitudeGains = DEFAULT_ATTITUDE_GAINS
    vertical: VerticalGains = DEFAULT_VERTICAL_GAINS
    horizontal: HorizontalGains = DEFAULT_HORIZONTAL_GAINS
    backoff: SaturationBackoff = DEFAULT_SATURATION_BACKOFF


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
    gain_scale: float = 1.0
    """The scale of the attitude, velocity and position gains this sample (backoff)."""


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


class _AttitudePart(Protocol):
    def reset(self) -> None: ...

    def update(
        self, dt_s: float, q_wxyz: Quat, rate_frd_rad_s: Vec3, setpoint: AttitudeSetpoint
    ) -> Vec3: ...


class _VerticalPart(Protocol):
    on_ground: bool
    climb_ref_m_s: float
    """The climb rate the loop flies to now, m/s (a hold is left from it)."""

    @property
    def hover_thrust(self) -> float:
        """The loop's estimate of the collective that hovers."""
        ...

    @property
    def saturated(self) -> bool:
        """Whether the last collective sat at a bound."""
        ...

    def update(
        self,
        dt_s: float,
        z_ned_m: float,
        vz_ned_m_s: float,
        setpoint: VerticalSetpoint,
        *,
        cos_tilt: float = 1.0,
        applied: float | None = None,
    ) -> float: ...


class _HorizontalPart(Protocol):
    velocity_ref_ne_m_s: tuple[float, float]
    """The velocity the loop flies to now, north and east, m/s."""

    def reset(self) -> None: ...


class OuterLaw(Protocol):
    """What the flight modes ask of outer loops (:class:`OuterController`; the
    lab's baseline, PX4's default cascade, is another): the cascade's
    :meth:`update`, and its attitude, vertical and horizontal parts for a mode
    that flies some of them alone."""

    @property
    def attitude(self) -> _AttitudePart: ...

    @property
    def vertical(self) -> _VerticalPart: ...

    @property
    def horizontal(self) -> _HorizontalPart: ...

    @property
    def gain_scale(self) -> float:
        """The scale on the gains (1: not backed off)."""
        ...

    def reset(
        self,
        thrust: float | None = None,
        hover_thrust: float | None = None,
        tilt_ne: tuple[float, float] = (0.0, 0.0),
        *,
        at_rest: bool = False,
    ) -> None:
        """Forget all state; take over at ``thrust`` (as :meth:`OuterController.reset`)."""
        ...

    def note_rate_saturation(
        self, dt_s: float, rate_saturated: tuple[bool, bool, bool] | None
    ) -> float:
        """One sample of the rate loop's saturation; returns the gains' scale."""
        ...

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
        rate_saturated: tuple[bool, bool, bool] | None = None,
    ) -> OuterOutput:
        """One update of the cascade."""
        ...


class OuterController:
    """Position/velocity, altitude/climb and heading to body rates and thrust.

    Composes the three loops (module docstring); each is reachable as an
    attribute (``attitude``, ``vertical``, ``horizontal``) for its diagnostics
    and, for the vertical loop, ``on_ground``.
    """

    __slots__ = ("_backoff", "_gains", "attitude", "horizontal", "vertical")

    def __init__(self, gains: OuterGains = DEFAULT_OUTER_GAINS) -> None:
        self._gains = gains
        self.attitude = AttitudeLoop(gains.attitude)
        self.vertical = VerticalLoop(gains.vertical)
        self.horizontal = HorizontalLoop(gains.horizontal)
        self._backoff = GainBackoff(gains.backoff)

    @property
    def gains(self) -> OuterGains:
        return self._gains

    @property
    def rate_saturation(self) -> tuple[float, float]:
        """Shares of the recent samples with roll or pitch, and with yaw, saturated."""
        return self._backoff.shares

    @property
    def gain_scale(self) -> float:
        """The scale of the attitude, velocity and position gains (backoff)."""
        return self._backoff.scale

    def reset(
        self,
        thrust: float | None = None,
        hover_thrust: float | None = None,
        tilt_ne: tuple[float, float] = (0.0, 0.0),
        *,
        at_rest: bool = False,
    ) -> None:
        """Forget all state (on disarm, on hand-back). ``thrust``, ``hover_thrust``
        and ``at_rest``: as :meth:`VerticalLoop.reset`; ``tilt_ne``: as
        :meth:`HorizontalLoop.reset`."""
        self.attitude.reset()
        self.vertical.reset(thrust, hover_thrust, at_rest=at_rest)
        self.horizontal.reset(tilt_ne)
        self._backoff.reset()
        self.attitude.set_gain_scale(1.0)
        self.horizontal.set_gain_scale(1.0)

    def note_rate_saturation(
        self, dt_s: float, rate_saturated: tuple[bool, bool, bool] | None
    ) -> float:
        """Count one sample of the rate loop's saturation and scale the gains by
        the backoff (``update`` does it; a caller flying the attitude loop alone,
        the angle sticks, calls it itself). Returns the scale."""
        b = self._backoff
        before = b.scale
        s = b.update(dt_s, rate_saturated)
        if s != before:
            self.attitude.set_gain_scale(s)
            self.horizontal.set_gain_scale(s)
        return s

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
        rate_saturated: tuple[bool, bool, bool] | None = None,
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
        rate_saturated
            Which axes (roll, pitch, yaw) the rate loop's mixer saturated after
            the previous update (``None``: not known; the backoff stays where it is).

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
        self.note_rate_saturation(dt_s, rate_saturated)

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
            self.gain_scale,
        )
