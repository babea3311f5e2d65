r"""What the pilot's sticks may ask in the angle, altitude and position modes.

The limits are the autopilot's own: :mod:`companion.stacks` names, per stack,
the parameters it reads at start-up and their documented defaults, and builds
:class:`StickLimits` from them. Nothing here has a default: a law is always
handed the limits of the stack it flies beside, so the same full stick asks of
the companion what it asks of the stack's own mode.

The throttle as a climb rate: :mod:`companion.control.climb_limits`.

The roll and pitch sticks as a horizontal acceleration
------------------------------------------------------
The two deflections are one vector in the heading's frame, past the deadband on
its length and through the expo, at most 1 long; rotated to north and east it is
the stick :math:`\mathbf s` a horizontal shaper (:class:`HorizontalShaper`) turns
into the velocity setpoint :math:`\mathbf v` and its slope :math:`\mathbf a`, the
acceleration feedforward. Each stack has its own:

* :class:`Px4StickAcceleration`, PX4's Position mode (``MPC_POS_MODE`` 4,
  "Acceleration based", v1.16's default;
  ``src/modules/flight_mode_manager/tasks/Utility/StickAccelerationXY.cpp``): the
  stick asks :math:`\mathbf a_s = 2 A \mathbf s` (``MPC_ACC_HOR``: "because of drag
  the average acceleration is half"); a drag :math:`\mathbf d = (2A / V) b\,
  \hat{\mathbf v}\, w(|\mathbf v|)` (``MPC_VEL_MANUAL``) keeps the speed under
  :math:`V` and brakes, boosted when the sticks are centred by :math:`b`, a
  first-order filter (0.8 s) moving to :math:`\max(2, \sqrt V)` (1 while a stick
  is out), with :math:`w` the speed itself while :math:`b = 1`, blended into
  ``sqrt_linear`` (:math:`\sqrt{v}` below 1 m/s) as :math:`b` reaches 2;
  :math:`\mathbf a = \mathbf a_s - \mathbf d`, slewed at ``MPC_JERK_MAX``,
  bounded to :math:`g \tan` ``MPC_TILTMAX_AIR``; :math:`\dot{\mathbf v} =
  \mathbf a`. Below one step of drag with the sticks centred (or the stick's
  acceleration changing sign), :math:`\mathbf v = 0`. (``MPC_VEL_MAN_SIDE`` and
  ``MPC_VEL_MAN_BACK``, -1 by default, are not modelled.)
* :class:`Px4DirectVelocity` (``MPC_POS_MODE`` 0): :math:`\mathbf v = V \mathbf s`,
  no smoothing.
* :class:`LoiterStickAcceleration`, ArduCopter's LOITER
  (``libraries/AC_WPNav/AC_Loiter.cpp``, Copter-4.5): the stick is a lean angle
  up to the loiter angle :math:`\vartheta_L`, so an acceleration :math:`g \tan
  \vartheta_L\, \mathbf s`, reached through the attitude's input shaping (a
  first-order lag, ``ATC_INPUT_TC``); a drag :math:`g \tan\vartheta_L |\mathbf
  v| / V` (``LOIT_SPEED``); with the sticks centred for ``LOIT_BRK_DELAY``, a
  brake :math:`\min(K |\mathbf v|, B)` (``PSC_VELXY_P``/2, ``LOIT_BRK_ACCEL``:
  ArduPilot's ``sqrt_controller`` with the jerk as its limit, which is this up
  to ``LOIT_BRK_JERK``/:math:`K` m/s, beyond which :math:`B` binds at the
  defaults), its changes at most ``LOIT_BRK_JERK``; the speed never below zero, and
  zero below 1 cm/s with the sticks centred.

A position is held (:class:`~companion.control.hold_modes.HoldMode`) once the
sticks are centred and the shaper's velocity is back at zero.

Pure: no I/O, no clock; ``dt`` from the caller.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

from companion.control.climb_limits import ClimbLimits, check_share, expo_past_deadband
from companion.control.ultralocal import GRAVITY_M_S2, check_positive

__all__ = [
    "ClimbLimits",
    "HorizontalLimits",
    "HorizontalShaper",
    "LoiterStickAcceleration",
    "Px4DirectVelocity",
    "Px4StickAcceleration",
    "StickLimits",
    "expo_past_deadband",
]

Vec2 = tuple[float, float]
_ZERO2: Vec2 = (0.0, 0.0)
_EPS = 1.1920929e-07  # FLT_EPSILON, as PX4 compares its float setpoints
_LOITER_STOPPED_M_S = 0.01
"""ArduCopter's braking decays exponentially (its target creeps on for ever, a
position it keeps tracking); with the sticks centred, a setpoint this slow is zero."""


class HorizontalShaper(Protocol):
    """The sticks' horizontal velocity setpoint and its slope, as a stack shapes them."""

    velocity_ne_m_s: Vec2
    """The velocity setpoint, north and east, m/s."""
    accel_ne_m_s2: Vec2
    """Its slope (the acceleration feedforward), m/s^2."""

    def reset(self, velocity_ne_m_s: Vec2) -> None:
        """Start again from ``velocity_ne_m_s``, not accelerating."""
        ...

    def update(self, dt_s: float, stick_ne: Vec2) -> Vec2:
        """One step with the stick ``stick_ne`` (north, east, length <= 1; zero:
        centred); returns the velocity setpoint."""
        ...


@dataclass(frozen=True)
class Px4StickAcceleration:
    """PX4's acceleration-based Position mode (module docstring).

    Attributes
    ----------
    deadband, expo
        ``MPC_HOLD_DZ``, ``MPC_XY_MAN_EXPO``.
    speed_max_m_s
        ``MPC_VEL_MANUAL``, m/s.
    accel_m_s2
        ``MPC_ACC_HOR``, m/s^2 (full stick asks twice this at rest).
    jerk_max_m_s3
        ``MPC_JERK_MAX``, m/s^3.
    tilt_max_deg
        ``MPC_TILTMAX_AIR``, deg: the acceleration asked at most ``g tan`` of it.
    """

    deadband: float
    expo: float
    speed_max_m_s: float
    accel_m_s2: float
    jerk_max_m_s3: float
    tilt_max_deg: float

    def __post_init__(self) -> None:
        check_share(self, ("deadband",), 1.0)
        check_share(self, ("expo",), 1.0 + 1e-9)
        check_positive(self, ("speed_max_m_s", "accel_m_s2", "jerk_max_m_s3", "tilt_max_deg"))
        if self.tilt_max_deg >= 90.0:
            raise ValueError(f"tilt_max_deg must be below 90, got {self.tilt_max_deg!r}")

    @property
    def full_stick_speed_m_s(self) -> float:
        return self.speed_max_m_s

    def summary(self) -> str:
        return (
            f"position sticks as PX4's (acceleration based): {self.speed_max_m_s:g} m/s, "
            f"{self.accel_m_s2:g} m/s^2, jerk {self.jerk_max_m_s3:g} m/s^3, tilt "
            f"{self.tilt_max_deg:g} deg, deadband {self.deadband:g}, expo {self.expo:g}"
        )

    def shaper(self) -> HorizontalShaper:
        return _Px4AccelerationShaper(self)


@dataclass(frozen=True)
class Px4DirectVelocity:
    """PX4's direct-velocity Position mode: ``MPC_HOLD_DZ``, ``MPC_XY_MAN_EXPO``,
    ``MPC_VEL_MANUAL`` (m/s)."""

    deadband: float
    expo: float
    speed_max_m_s: float

    def __post_init__(self) -> None:
        check_share(self, ("deadband",), 1.0)
        check_share(self, ("expo",), 1.0 + 1e-9)
        check_positive(self, ("speed_max_m_s",))

    @property
    def full_stick_speed_m_s(self) -> float:
        return self.speed_max_m_s

    def summary(self) -> str:
        return (
            f"position sticks as PX4's (direct velocity): {self.speed_max_m_s:g} m/s, "
            f"deadband {self.deadband:g}, expo {self.expo:g}"
        )

    def shaper(self) -> HorizontalShaper:
        return _DirectVelocityShaper(self.speed_max_m_s)


@dataclass(frozen=True)
class LoiterStickAcceleration:
    """ArduCopter's LOITER (module docstring).

    Attributes
    ----------
    deadband
        The roll and pitch channels' dead zone, share of the half-travel.
    speed_max_m_s
        ``LOIT_SPEED``, m/s.
    angle_deg
        The loiter angle: ``LOIT_ANG_MAX``, or 2/3 of ``ANGLE_MAX`` when it is 0, deg.
    input_tc_s
        ``ATC_INPUT_TC``, s: how fast the lean angle follows the stick.
    brake_accel_m_s2, brake_jerk_m_s3, brake_delay_s
        ``LOIT_BRK_ACCEL``, ``LOIT_BRK_JERK``, ``LOIT_BRK_DELAY``.
    brake_gain_1_s
        Half ``PSC_VELXY_P``, 1/s.
    """

    deadband: float
    speed_max_m_s: float
    angle_deg: float
    input_tc_s: float
    brake_accel_m_s2: float
    brake_jerk_m_s3: float
    brake_delay_s: float
    brake_gain_1_s: float

    def __post_init__(self) -> None:
        check_share(self, ("deadband",), 1.0)
        check_positive(
            self,
            (
                "speed_max_m_s", "angle_deg", "brake_accel_m_s2", "brake_jerk_m_s3",
                "brake_gain_1_s",
            ),
        )  # fmt: skip
        check_positive(self, ("input_tc_s", "brake_delay_s"), zero_ok=True)
        if self.angle_deg >= 90.0:
            raise ValueError(f"angle_deg must be below 90, got {self.angle_deg!r}")

    @property
    def expo(self) -> float:
        return 0.0

    @property
    def accel_max_m_s2(self) -> float:
        """Full stick's acceleration, m/s^2: ``g tan`` of the loiter angle."""
        return GRAVITY_M_S2 * math.tan(math.radians(self.angle_deg))

    @property
    def full_stick_speed_m_s(self) -> float:
        return self.speed_max_m_s

    def summary(self) -> str:
        return (
            f"position sticks as ArduCopter's LOITER: {self.speed_max_m_s:g} m/s, lean "
            f"{self.angle_deg:.3g} deg ({self.accel_max_m_s2:.3g} m/s^2), brake "
            f"{self.brake_accel_m_s2:g} m/s^2 after {self.brake_delay_s:g} s, deadband "
            f"{self.deadband:g}"
        )

    def shaper(self) -> HorizontalShaper:
        return _LoiterShaper(self)


HorizontalLimits = Px4StickAcceleration | Px4DirectVelocity | LoiterStickAcceleration


@dataclass(frozen=True)
class MissionLimits:
    """How the stack's own mission speeds up and slows down along a leg: a
    mission file's defaults (:mod:`companion.mission`).

    Attributes
    ----------
    accel_m_s2
        Horizontal acceleration, m/s^2 (PX4 ``MPC_ACC_HOR``, ArduCopter ``WPNAV_ACCEL``).
    jerk_m_s3
        How fast it comes and goes, m/s^3 (PX4 ``MPC_JERK_AUTO``, ArduCopter ``WPNAV_JERK``).
    """

    accel_m_s2: float
    jerk_m_s3: float

    def __post_init__(self) -> None:
        check_positive(self, ("accel_m_s2", "jerk_m_s3"))

    def summary(self) -> str:
        return f"missions {self.accel_m_s2:g} m/s^2, jerk {self.jerk_m_s3:g} m/s^3"


@dataclass(frozen=True)
class StickLimits:
    """Everything the sticks may ask, one stack's (:mod:`companion.stacks` builds it).

    Attributes
    ----------
    tilt_max_deg
        Full stick's tilt in the angle and altitude modes, deg, in (0, 60].
    climb
        The throttle in the altitude and position modes.
    horizontal
        The roll and pitch sticks in the position mode.
    mission
        The stack's own mission's acceleration and jerk (a mission file's defaults).
    """

    tilt_max_deg: float
    climb: ClimbLimits
    horizontal: HorizontalLimits
    mission: MissionLimits

    def __post_init__(self) -> None:
        if not (0.0 < self.tilt_max_deg <= 60.0):
            raise ValueError(f"tilt_max_deg: expected (0, 60] deg, got {self.tilt_max_deg!r}")

    def summary(self) -> str:
        """The limits in a line (the run's ``stick_limits`` event)."""
        return (
            f"tilt {self.tilt_max_deg:g} deg; {self.climb.summary()}; "
            f"{self.horizontal.summary()}; {self.mission.summary()}"
        )


def sqrt_linear(x: float) -> float:
    """PX4's ``math::sqrt_linear``: sqrt below 1, linear above (0 below 0)."""
    if x < 0.0:
        return 0.0
    return math.sqrt(x) if x < 1.0 else x


class _Px4AccelerationShaper:
    __slots__ = ("_boost", "_l", "_slew", "accel_ne_m_s2", "velocity_ne_m_s")

    def __init__(self, limits: Px4StickAcceleration) -> None:
        self._l = limits
        self.reset(_ZERO2)

    def reset(self, velocity_ne_m_s: Vec2) -> None:
        self.velocity_ne_m_s = velocity_ne_m_s
        self.accel_ne_m_s2 = _ZERO2
        self._slew = _ZERO2  # the jerk-limited stick acceleration
        self._boost = 1.0

    def update(self, dt_s: float, stick_ne: Vec2) -> Vec2:
        lim = self._l
        if not dt_s > 0.0:
            return self.velocity_ne_m_s
        scale = 2.0 * lim.accel_m_s2
        an, ae = stick_ne[0] * scale, stick_ne[1] * scale
        # The brake boost: a first-order filter (0.8 s) to its target.
        centred = stick_ne[0] * stick_ne[0] + stick_ne[1] * stick_ne[1] < _EPS
        target = max(2.0, math.sqrt(lim.speed_max_m_s)) if centred else 1.0
        b = self._boost = self._boost + (target - self._boost) * dt_s / (0.8 + dt_s)
        # The drag: linear in the speed, blended to sqrt_linear as the boost goes from
        # 1 to 2 (braking reaches low speeds exactly).
        vn, ve = self.velocity_ne_m_s
        speed = math.hypot(vn, ve)
        mix = min(1.0, max(0.0, b - 1.0))
        k = scale / lim.speed_max_m_s * b * (mix * sqrt_linear(speed) + (1.0 - mix) * speed)
        drag = (k * vn / speed, k * ve / speed) if speed > 0.0 else _ZERO2
        prev = self.accel_ne_m_s2
        if (
            an * an + ae * ae < _EPS or _sign(prev[0]) != _sign(an) or _sign(prev[1]) != _sign(ae)
        ) and speed * speed < (drag[0] * drag[0] + drag[1] * drag[1]) * dt_s * dt_s:
            drag = _ZERO2
            vn = ve = 0.0
        an, ae = an - drag[0], ae - drag[1]
        # The jerk limit, per axis, each at its share of the change's direction.
        dn, de = an - prev[0], ae - prev[1]
        n = math.hypot(dn, de)
        jn, je = (abs(dn) / n, abs(de) / n) if n > 0.0 else (0.0, 0.0)
        step = lim.jerk_max_m_s3 * dt_s
        s = self._slew
        an = s[0] + max(-jn * step, min(jn * step, an - s[0]))
        ae = s[1] + max(-je * step, min(je * step, ae - s[1]))
        self._slew = (an, ae)
        a_max = GRAVITY_M_S2 * math.tan(math.radians(lim.tilt_max_deg))
        a = math.hypot(an, ae)
        if a > a_max:
            an, ae = an * a_max / a, ae * a_max / a
        self.accel_ne_m_s2 = (an, ae)
        self.velocity_ne_m_s = (vn + an * dt_s, ve + ae * dt_s)
        return self.velocity_ne_m_s


def _sign(x: float) -> int:
    """PX4's ``math::sign``: -1, 0 or 1."""
    return (x > 0.0) - (x < 0.0)


class _DirectVelocityShaper:
    __slots__ = ("_v", "accel_ne_m_s2", "velocity_ne_m_s")

    def __init__(self, speed_max_m_s: float) -> None:
        self._v = speed_max_m_s
        self.reset(_ZERO2)

    def reset(self, velocity_ne_m_s: Vec2) -> None:
        self.velocity_ne_m_s = velocity_ne_m_s
        self.accel_ne_m_s2 = _ZERO2

    def update(self, dt_s: float, stick_ne: Vec2) -> Vec2:
        self.velocity_ne_m_s = (stick_ne[0] * self._v, stick_ne[1] * self._v)
        return self.velocity_ne_m_s


class _LoiterShaper:
    __slots__ = ("_brake", "_centred_s", "_l", "_pilot", "accel_ne_m_s2", "velocity_ne_m_s")

    def __init__(self, limits: LoiterStickAcceleration) -> None:
        self._l = limits
        self.reset(_ZERO2)

    def reset(self, velocity_ne_m_s: Vec2) -> None:
        self.velocity_ne_m_s = velocity_ne_m_s
        self.accel_ne_m_s2 = _ZERO2
        self._pilot = _ZERO2  # the lean angle's acceleration, lagging the stick's
        self._brake = 0.0
        self._centred_s = 0.0

    def update(self, dt_s: float, stick_ne: Vec2) -> Vec2:
        lim = self._l
        if not dt_s > 0.0:
            return self.velocity_ne_m_s
        a_max = lim.accel_max_m_s2
        want = (stick_ne[0] * a_max, stick_ne[1] * a_max)
        tc = lim.input_tc_s
        k = 1.0 if tc <= 0.0 else dt_s / (tc + dt_s)
        p = self._pilot
        p = (p[0] + (want[0] - p[0]) * k, p[1] + (want[1] - p[1]) * k)
        self._pilot = p
        vn, ve = self.velocity_ne_m_s[0] + p[0] * dt_s, self.velocity_ne_m_s[1] + p[1] * dt_s
        speed = math.hypot(vn, ve)
        centred = stick_ne == _ZERO2
        self._centred_s = self._centred_s + dt_s if centred else 0.0
        if speed > 0.0:
            un, ue = vn / speed, ve / speed
            drag = a_max * speed / lim.speed_max_m_s
            want_brake = 0.0
            if centred and self._centred_s > lim.brake_delay_s:
                want_brake = min(lim.brake_gain_1_s * speed, lim.brake_accel_m_s2)
            j = lim.brake_jerk_m_s3 * dt_s
            self._brake += max(-j, min(j, want_brake - self._brake))
            speed = max(speed - (drag + self._brake) * dt_s, 0.0)
            if centred and speed < _LOITER_STOPPED_M_S:
                speed = 0.0  # its decay is exponential: stopped, so a hold can lock
            vn, ve = un * speed, ue * speed
        v_max = lim.speed_max_m_s
        s = math.hypot(vn, ve)
        if s > v_max:
            vn, ve = vn * v_max / s, ve * v_max / s
        v0 = self.velocity_ne_m_s
        self.accel_ne_m_s2 = ((vn - v0[0]) / dt_s, (ve - v0[1]) / dt_s)
        self.velocity_ne_m_s = (vn, ve)
        return self.velocity_ne_m_s
