r"""The vertical loop: altitude and climb rate to the collective thrust.

Inputs are NED (``z`` and ``vz``, down positive, as ``LOCAL_POSITION_NED`` gives
them); inside, everything is up-positive: ``up_m = -z``, ``climb_m_s = -vz``.

Altitude (hold)
---------------
A proportional law, bounded: :math:`c_r = c_{ff} + K_z (h_{sp} - h)`, clamped to
[-``descent_max_m_s``, ``climb_max_m_s``] (without an altitude setpoint,
:math:`c_r = c_{ff}` clamped: climb-rate mode).

Climb rate (iP, order 1)
------------------------
.. math::  \dot c = F + \alpha\, T_\ell, \qquad
           T_\ell = -\frac{\hat F - \dot c_r + K_c (c - c_r)}{\alpha}

with ``c`` the climb rate (m/s), :math:`T_\ell` the *level-equivalent* collective
(normalised 0..1, the share of full thrust that acts vertically) and
:math:`\dot c_r` the setpoint's climb acceleration (feedforward, m/s^2). ``F``
holds gravity, drag, ground effect, the thrust curve's bend and the wind;
:math:`\dot c` is the finite difference of the measured climb rate (its window
mean telescopes: :math:`(c_k - c_{k-N})/T`), and the estimate is
:class:`~companion.control.ultralocal.LagAwareEstimate`, the lag standing for the
motors.

alpha and the hover thrust
--------------------------
Near hover the collective's effect is :math:`\partial \dot c / \partial T = p g /
T_h` for a thrust growing as :math:`T^p` (hover thrust :math:`T_h`): ``p = 1`` for a
linearised thrust curve (PX4's ``THR_MDL_FAC``, ArduPilot's ``MOT_THST_EXPO``), ``p
= 2`` for rotor speed proportional to the command (the bundled SITL, most ESCs
left alone). The window estimate's loop needs :math:`b / \alpha` below about 1.2
(:math:`b` the true slope; ``docs/research/outer.md``: 1.5 and above limit-cycles
with a motor lag and 40 ms of delay), so

.. math::  \alpha = p_{model}\, g / \hat T_h, \qquad p_{model} = 2

(``thrust_curve_exponent``): the steeper curve, so a linear one sees
:math:`b/\alpha = 1/2` (a slightly slower estimate), never the other way.

:math:`\hat T_h` is identified in flight: the model's own hover collective is
:math:`-\hat F / \alpha = L_\tau \bar T - \overline{\dot c} / \alpha` (the collective
that would make the window's acceleration zero). While the vehicle is near hover
(``|c| <= hover_learn_climb_max_m_s``, ``|mean accel| <=
hover_learn_accel_max_m_s2``, tilt within ``hover_learn_tilt_max_rad``, the
collective not at a limit, :attr:`on_ground` False), :math:`\hat T_h` moves toward
it with time constant ``hover_learn_tau_s``, clamped to [``hover_thrust_min``,
``hover_thrust_max``]. Near zero acceleration and level, the measurement does not
depend on the thrust curve. It starts at ``hover_thrust_initial`` or at the
caller's value (:meth:`VerticalLoop.reset`).

Tilt compensation
-----------------
The collective sent is :math:`T = T_\ell / \max(\cos\vartheta, \cos\vartheta_{max})`
(``tilt_compensation_max_rad``), clamped to [``thrust_min``, ``thrust_max``]: tilted
by :math:`\vartheta`, only :math:`T\cos\vartheta` holds the vehicle up. The
estimate learns from the level-equivalent collective really applied,
:math:`T \cos\vartheta` with the same bounded cosine. The division is exact for
a linear thrust curve; on a square law it gives a further :math:`1/\cos\vartheta`
of vertical force (15 % at 30 deg), which ``F`` absorbs like any other model
error, and which is why the hover thrust is learnt only near level.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

from companion.control.ultralocal import (
    DT_MAX_S,
    DT_MIN_S,
    GRAVITY_M_S2,
    LagAwareEstimate,
    check_positive,
)

__all__ = ["DEFAULT_VERTICAL_GAINS", "VerticalGains", "VerticalLoop", "VerticalSetpoint"]


@dataclass(frozen=True)
class VerticalGains:
    """The vertical loop's gains and bounds (one set: :data:`DEFAULT_VERTICAL_GAINS`).

    Attributes
    ----------
    kp_climb_1_s
        :math:`K_c`, 1/s: climb-rate error decay rate.
    kp_up_1_s
        :math:`K_z`, 1/s: altitude error to climb-rate reference.
    climb_max_m_s, descent_max_m_s
        Bounds of the climb-rate reference, m/s (both > 0).
    thrust_min, thrust_max
        Bounds of the collective, normalised (0 < min < max <= 1).
    window_s, inner_lag_s
        Window and lag (the motors) of the estimate of ``F``, s.
    thrust_curve_exponent
        :math:`p_{model}` in :math:`\\alpha = p g / \\hat T_h` (>= 1).
    hover_thrust_initial, hover_thrust_min, hover_thrust_max
        The hover-thrust estimate's start and bounds, normalised.
    hover_learn_tau_s
        Its time constant while learning, s.
    hover_learn_climb_max_m_s, hover_learn_accel_max_m_s2, hover_learn_tilt_max_rad
        "Near hover": it learns only within these, m/s, m/s^2 and rad.
    tilt_compensation_max_rad
        Tilt beyond which the compensation stops growing, rad, in (0, pi/2).
    """

    # kp_up_1_s 0.69 (was 0.6; docs/research/outer.md, "Tuning the one outer config"):
    # the most the design rule sqrt(kp_climb / kp_up) / 2 >= 0.95 allows at 2.5. A
    # higher climb gain would allow more, but overshoots a climb-rate step on a
    # linear thrust curve (b / alpha = 1/2) beyond 5 % (8.7 % at 3.7).
    kp_climb_1_s: float = 2.5
    kp_up_1_s: float = 0.69
    climb_max_m_s: float = 3.0
    descent_max_m_s: float = 1.5
    thrust_min: float = 0.12
    thrust_max: float = 0.9
    window_s: float = 0.1
    inner_lag_s: float = 0.08
    thrust_curve_exponent: float = 2.0
    hover_thrust_initial: float = 0.3
    hover_thrust_min: float = 0.1
    hover_thrust_max: float = 0.8
    hover_learn_tau_s: float = 2.0
    hover_learn_climb_max_m_s: float = 1.0
    hover_learn_accel_max_m_s2: float = 1.0
    hover_learn_tilt_max_rad: float = math.radians(15.0)
    tilt_compensation_max_rad: float = math.radians(60.0)

    def __post_init__(self) -> None:
        check_positive(
            self,
            (
                "kp_climb_1_s", "kp_up_1_s", "climb_max_m_s", "descent_max_m_s", "thrust_min",
                "thrust_max", "window_s", "thrust_curve_exponent", "hover_thrust_initial",
                "hover_thrust_min", "hover_thrust_max", "hover_learn_tau_s",
                "hover_learn_climb_max_m_s", "hover_learn_accel_max_m_s2",
                "hover_learn_tilt_max_rad", "tilt_compensation_max_rad",
            ),
        )  # fmt: skip
        check_positive(self, ("inner_lag_s",), zero_ok=True)
        name = type(self).__name__
        if not self.thrust_min < self.thrust_max <= 1.0:
            raise ValueError(
                f"{name}.thrust_max must be in (thrust_min, 1], got thrust_min "
                f"{self.thrust_min!r}, thrust_max {self.thrust_max!r}"
            )
        if not self.hover_thrust_min <= self.hover_thrust_max < 1.0:
            raise ValueError(
                f"{name}.hover_thrust_max must be in [hover_thrust_min, 1), got "
                f"hover_thrust_min {self.hover_thrust_min!r}, "
                f"hover_thrust_max {self.hover_thrust_max!r}"
            )
        if not self.hover_thrust_min <= self.hover_thrust_initial <= self.hover_thrust_max:
            raise ValueError(
                f"{name}.hover_thrust_initial must be in [hover_thrust_min, hover_thrust_max] "
                f"= [{self.hover_thrust_min!r}, {self.hover_thrust_max!r}], "
                f"got {self.hover_thrust_initial!r}"
            )
        if self.thrust_curve_exponent < 1.0:
            raise ValueError(
                f"{name}.thrust_curve_exponent must be >= 1, got {self.thrust_curve_exponent!r}"
            )
        if self.tilt_compensation_max_rad >= 0.5 * math.pi:
            raise ValueError(
                f"{name}.tilt_compensation_max_rad must be in (0, pi/2), "
                f"got {self.tilt_compensation_max_rad!r}"
            )


DEFAULT_VERTICAL_GAINS = VerticalGains()
"""The shipped vertical gains (``docs/research/outer.md``)."""


class VerticalSetpoint(NamedTuple):
    """What the vertical loop is asked to fly (up positive)."""

    climb_m_s: float = 0.0
    """Climb-rate reference (feedforward with an altitude setpoint), m/s."""
    up_m: float | None = None
    """Altitude to hold, m up (``-z`` NED); ``None``: climb-rate mode."""
    climb_accel_m_s2: float = 0.0
    """The climb-rate reference's derivative (feedforward), m/s^2."""


class VerticalLoop:
    """Climb rate (and altitude) to collective thrust (module docstring).

    Attributes (after each :meth:`update`)
    ---------------------------------------
    level_thrust
        :math:`T_\\ell`, the collective before tilt compensation, normalised.
    climb_ref_m_s
        The climb-rate reference flown, m/s.
    f_hat
        :math:`\\hat F`, m/s^2.
    saturated
        Whether the collective sent was at a bound.
    fault
        True when a non-finite input was replaced (see :meth:`update`).
    on_ground
        Set by the caller while the autopilot reports the vehicle on the ground:
        the hover thrust is then not learnt (a vehicle on its legs does not
        accelerate whatever the collective). Not reset by :meth:`reset`.
    """

    __slots__ = (
        "_alpha",
        "_climb_prev",
        "_cos_applied",
        "_cos_learn",
        "_cos_min",
        "_est",
        "_gains",
        "_hover",
        "_learn_dt",
        "_learn_k",
        "_out",
        "climb_ref_m_s",
        "dt_clamped_events",
        "f_hat",
        "fault",
        "level_thrust",
        "nonfinite_events",
        "on_ground",
        "saturated",
    )

    def __init__(self, gains: VerticalGains = DEFAULT_VERTICAL_GAINS) -> None:
        self._gains = gains
        self._est = LagAwareEstimate(gains.window_s, gains.inner_lag_s)
        self._cos_min = math.cos(gains.tilt_compensation_max_rad)
        self._cos_learn = math.cos(gains.hover_learn_tilt_max_rad)
        self._learn_dt = -1.0
        self._learn_k = 0.0
        self.on_ground = False
        self.nonfinite_events = 0
        self.dt_clamped_events = 0
        self.reset()

    @property
    def gains(self) -> VerticalGains:
        return self._gains

    @property
    def hover_thrust(self) -> float:
        """The hover-thrust estimate :math:`\\hat T_h`, normalised collective."""
        return self._hover

    @property
    def alpha(self) -> float:
        """:math:`\\alpha = p g / \\hat T_h`, (m/s^2) per unit collective."""
        return self._alpha

    def reset(
        self,
        thrust: float | None = None,
        hover_thrust: float | None = None,
        *,
        at_rest: bool = False,
    ) -> None:
        """Forget the window and the references.

        Parameters
        ----------
        thrust
            The level-equivalent collective flying when the loop takes over (the
            first output with a zero error is this); ``None``: the hover estimate.
        hover_thrust
            A prior for the hover-thrust estimate (the autopilot's hover
            parameter, the last flight's estimate), clamped to its bounds;
            ``None``: ``hover_thrust_initial``.
        at_rest
            The vehicle is not accelerating as the loop takes over (a hover, a
            steady climb): the window starts full of that rest, the collective
            held (:class:`~companion.control.ultralocal.LagAwareEstimate`), so its
            first intervals (the climb rate is differentiated from a position
            stream slower than the loop) do not each move ``F`` a window's worth.
        """
        g = self._gains
        h = g.hover_thrust_initial
        if hover_thrust is not None and math.isfinite(hover_thrust):
            h = min(max(hover_thrust, g.hover_thrust_min), g.hover_thrust_max)
        self._set_hover(h)
        t0 = h if thrust is None or not math.isfinite(thrust) else thrust
        t0 = min(max(t0, g.thrust_min), g.thrust_max)
        # F before the first interval: the value that makes the first output t0.
        self._est.reset(t0, -self._alpha * t0, at_rest=at_rest)
        self.f_hat = self._est.f_hat
        self._climb_prev: float | None = None
        self._out = t0
        self._cos_applied = 1.0
        self.level_thrust = t0
        self.climb_ref_m_s = 0.0
        self.saturated = False
        self.fault = False

    def _set_hover(self, h: float) -> None:
        self._hover = h
        self._alpha = self._gains.thrust_curve_exponent * GRAVITY_M_S2 / h

    def update(
        self,
        dt_s: float,
        z_ned_m: float,
        vz_ned_m_s: float,
        setpoint: VerticalSetpoint,
        *,
        cos_tilt: float = 1.0,
        applied: float | None = None,
    ) -> float:
        """One update; returns the collective thrust, normalised [thrust_min, thrust_max].

        Parameters
        ----------
        dt_s
            Time since the previous update, s; clamped to [DT_MIN_S, DT_MAX_S].
        z_ned_m, vz_ned_m_s
            Position and velocity along NED z (down positive), m and m/s.
        setpoint
            Climb rate, altitude (or none), climb acceleration.
        cos_tilt
            Cosine of the measured tilt (body z against the vertical; ``R[2][2]``).
        applied
            The collective really applied after the previous update, normalised
            (``None``: this loop's output as sent).

        Failure behaviour (:attr:`fault` set, :attr:`nonfinite_events` counted)
        -----------------------------------------------------------------------
        * ``dt_s`` exactly 0 (a restart: the first sample after an engagement): the
          last output (after :meth:`reset`, the collective it took over at), nothing
          learnt, no fault;
        * ``z`` or ``vz`` or ``dt_s`` non-finite (or ``dt_s < 0``): the hover-thrust
          estimate, tilt-compensated, and nothing learnt; the next valid sample
          starts a new finite difference;
        * setpoint non-finite: a climb-rate reference of zero (hold what altitude
          there is);
        * ``cos_tilt`` or ``applied`` non-finite: taken as level / as sent;
        * finite inputs so large that the climb's change overflows: nothing learnt
          from that sample (and ``F`` started again at the hover estimate should it
          have gone non-finite).
        """
        g = self._gains
        fault = False
        if not math.isfinite(cos_tilt):
            fault = True
            cos_tilt = 1.0
        c = cos_tilt if cos_tilt > self._cos_min else self._cos_min
        if applied is not None and not math.isfinite(applied):
            fault = True
            applied = None
        if dt_s == 0.0 and math.isfinite(z_ned_m + vz_ned_m_s):
            # A restart (the first sample after an engagement): nothing to learn from,
            # and the collective the loop took over at, unchanged.
            self._climb_prev = None
            self.fault = False
            return self._out
        if not (math.isfinite(dt_s + z_ned_m + vz_ned_m_s) and dt_s > 0.0):
            self.nonfinite_events += 1
            self.fault = True
            self._climb_prev = None
            t_level = self._hover
            out = min(max(t_level / c, g.thrust_min), g.thrust_max)
            self.level_thrust = t_level
            self._out = out
            self._cos_applied = c
            self.saturated = False
            return out
        if dt_s < DT_MIN_S or dt_s > DT_MAX_S:
            self.dt_clamped_events += 1
            dt_s = DT_MIN_S if dt_s < DT_MIN_S else DT_MAX_S
        up = -z_ned_m
        climb = -vz_ned_m_s

        # F, from the climb acceleration and the level-equivalent collective applied.
        est = self._est
        prev = self._climb_prev
        if prev is not None:
            accel = (climb - prev) / dt_s
            if math.isfinite(accel):
                u_prev = (self._out if applied is None else applied) * self._cos_applied
                est.update(dt_s, accel, u_prev, self._alpha)
            else:  # absurd finite climbs overflowed: nothing to learn from
                fault = True
            if math.isfinite(est.f_hat):
                self._learn_hover(dt_s, climb, cos_tilt)
            else:  # start F again at the hover estimate, as a reset does
                fault = True
                est.reset(self._hover, -self._alpha * self._hover)
        self._climb_prev = climb
        f = est.f_hat
        self.f_hat = f

        # The reference: altitude P, bounded, on top of the climb-rate feedforward.
        sp = setpoint
        up_sp = sp.up_m
        if not math.isfinite(
            sp.climb_m_s + sp.climb_accel_m_s2 + (0.0 if up_sp is None else up_sp)
        ):
            fault = True
            sp = VerticalSetpoint(0.0, None, 0.0)
            up_sp = None
        c_ref = sp.climb_m_s
        if up_sp is not None:
            c_ref += g.kp_up_1_s * (up_sp - up)
        if c_ref > g.climb_max_m_s:
            c_ref = g.climb_max_m_s
        elif c_ref < -g.descent_max_m_s:
            c_ref = -g.descent_max_m_s
        self.climb_ref_m_s = c_ref

        # iP, then tilt compensation; both bounded.
        t_level = -(f - sp.climb_accel_m_s2 + g.kp_climb_1_s * (climb - c_ref)) / self._alpha
        t_min, t_max = g.thrust_min, g.thrust_max
        t_level = min(max(t_level, t_min), t_max)
        out = t_level / c
        sat = out >= t_max or out <= t_min
        out = min(max(out, t_min), t_max)
        if not math.isfinite(out):  # an absurd finite input overflowed: start again
            fault = True
            t_level = out = min(max(self._hover / c, t_min), t_max)
            self.reset(out, self._hover)
        self.level_thrust = t_level
        self._out = out
        self._cos_applied = c
        self.saturated = sat
        if fault:
            self.nonfinite_events += 1
        self.fault = fault
        return out

    def _learn_hover(self, dt_s: float, climb: float, cos_tilt: float) -> None:
        """Move the hover-thrust estimate toward the model's hover collective,
        :math:`-\\hat F/\\alpha`, while near hover (module docstring)."""
        g = self._gains
        est = self._est
        if (
            self.on_ground
            or self.saturated
            or cos_tilt < self._cos_learn
            or abs(climb) > g.hover_learn_climb_max_m_s
            or abs(est.y_dot_mean) > g.hover_learn_accel_max_m_s2
        ):
            return
        if dt_s != self._learn_dt:
            self._learn_dt = dt_s
            self._learn_k = -math.expm1(-dt_s / g.hover_learn_tau_s)
        measured = -est.f_hat / self._alpha
        h = self._hover + (measured - self._hover) * self._learn_k
        self._set_hover(min(max(h, g.hover_thrust_min), g.hover_thrust_max))
