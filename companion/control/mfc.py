r"""The paper's three-axis controller, assembled: the class the rest of the code flies.

The scheme (the paper's Section III-B and its figure "Model-Free Control
Scheme"): one intelligent controller per axis, roll iPD, pitch iPD, yaw iP,
their outputs saturated and mixed to the four motors. :class:`MfcController`
composes the parts, each in its own module, and calls them in this order for
every IMU sample (:meth:`MfcController.update`):

1. :class:`~companion.control.prefilter.ReferencePrefilter`: the pilot's
   rates :math:`\dot y_r` smoothed, with their derivatives :math:`\ddot y_r`
   (without a prefilter, the backward difference of the raw reference);
2. :class:`~companion.control.intelligent.IntelligentController`, per axis:
   the paper's law with its estimate of ``F``, fed the command the mixer
   really applied last time;
3. :class:`~companion.control.mixer.Mixer`: normalised torques and the
   pilot's collective to motor commands, with air-mode saturation; it says what
   it applied, which goes back to step 2 at the next sample.

Then, once the command has left, :meth:`MfcController.learn` runs the
identification of each axis (:mod:`companion.control.identifier`), gated on
the pilot's collective and on the vehicle being in the air.

Unit convention under which Table I is used
-------------------------------------------
* ``y`` is the body-axis angle in **radians** (the integral of the gyro rate),
  so :math:`\dot y` is the gyro rate in rad/s and the pilot's rate command is
  :math:`\dot y_r`;
* ``u`` is in **PWM microseconds of differential motor command** about the
  throttle point, as in the paper's mixer (equation (motors)) on an 8-bit
  flight controller driving 1000-2000 us ESCs. A full-scale normalised torque
  of 1 is 500 us (one motor at the top of its range, its opposite at the
  bottom, at mid throttle): ``command_full_scale_us``, by which the law's output
  is divided before the mixer.

Why this reading: the paper asks that :math:`y^{(m)}`, ``F`` and
:math:`\alpha u` be "of the same order of magnitude" with :math:`\alpha = 1`.
For an F450 or a Tarot 650 one microsecond of differential command gives
about 0.2-0.35 rad/s^2 of angular acceleration: the same order as 1. In
deg/s it would be 13-18 deg/s^2 per us, a ratio the ``alpha``-mismatched
estimator loop cannot absorb (it limit-cycles: see
``tests/control/test_table1_units.py``).

:class:`PidController`, the PX4-style rate PID the paper compares with, is
assembled the same way (law, then mixer) behind the same interface.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple, Protocol

from companion.control.intelligent import IntelligentController, MfcAxisGains
from companion.control.mixer import Mixer
from companion.control.pid import PidGains, RatePid
from companion.control.prefilter import ReferencePrefilter
from companion.control.yaw_share import YawShare

__all__ = ["ControlOutput", "MfcController", "MfcGains", "PidController", "RateController"]

Vec3 = tuple[float, float, float]
_ZERO3: Vec3 = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class MfcGains:
    """The three axes plus shared settings, as the configuration file gives them
    (``companion.config``'s ``MfcConfig``, field for field; its schema holds the
    defaults and bounds). ``command_full_scale_us``: the command that makes a
    normalised torque of 1; ``adapt_min_thrust``: the identification learns only
    while the pilot's collective is at least this; ``dt_min_s``, ``dt_max_s``:
    the sample intervals the laws trust; ``yaw_share_max``: the most of roll and
    pitch the mixer may give yaw while the vehicle loses its heading
    (:class:`~companion.control.yaw_share.YawShare`)."""

    roll: MfcAxisGains
    pitch: MfcAxisGains
    yaw: MfcAxisGains
    command_full_scale_us: float
    prefilter_hz: float | None
    adapt_min_thrust: float
    dt_min_s: float
    dt_max_s: float
    yaw_share_max: float

    def axes(self) -> tuple[MfcAxisGains, MfcAxisGains, MfcAxisGains]:
        return (self.roll, self.pitch, self.yaw)


class ControlOutput(NamedTuple):
    """What a rate controller produced for one sample."""

    torque: Vec3
    """Normalised roll/pitch/yaw torque realised by the mixer, [-1, 1]."""
    thrust: float
    """Collective realised by the mixer, [0, 1]."""
    motors: tuple[float, ...]
    """Per-motor commands, [idle, 1]."""
    saturated_axes: tuple[bool, bool, bool]
    saturated_motors: tuple[bool, ...]
    u: Vec3
    """Law outputs before mixing, in the law's command units."""
    f_hat: Vec3
    """Estimates of F (rad/s^m); zeros for the PID."""
    error: Vec3
    """Rate tracking error omega - omega_r against the (filtered) reference, rad/s."""
    held: bool
    """True when this output repeats the last valid one (non-finite input)."""


def _hold_output(last: ControlOutput | None, mixer: Mixer) -> ControlOutput:
    if last is None:
        mix = mixer.mix(0.0, 0.0, 0.0, 0.0)
        return ControlOutput(
            _ZERO3, mix.thrust, mix.motors, (False,) * 3, mix.saturated_motors, _ZERO3, _ZERO3,
            _ZERO3, True,
        )  # fmt: skip
    return last._replace(held=True)


_NAN3: Vec3 = (math.nan, math.nan, math.nan)
_new_tuple = tuple.__new__  # see companion.control.mixer: cheaper than NamedTuple(...)
_isfinite = math.isfinite

LEGS_HOLD_RATE_RAD_S = 0.35
"""A vehicle its legs hold turns slower than this (20 deg/s, ten times the gyro's
noise on the legs with the motors spinning). Faster, with the landed state still
set, it is lifting off and tipping, or bouncing, and the rate law must fly it."""
LEGS_HOLD_QUIET_S = 0.5
"""How long the gyro must stay under :data:`LEGS_HOLD_RATE_RAD_S`, landed, before
the rate law starts afresh again (two periods of the 4 Hz landed state)."""


def _all_finite(dt_s: float, a: Vec3, b: Vec3, thrust: float) -> bool:
    # Summing is the cheapest finiteness test: inf/nan anywhere poisons the sum.
    return math.isfinite(dt_s + a[0] + a[1] + a[2] + b[0] + b[1] + b[2] + thrust)


class RateController(Protocol):
    """What the companion and the lab ask of a rate law (:class:`MfcController`,
    :class:`PidController`): one :meth:`update` per IMU sample."""

    mixer: Mixer
    on_ground: bool
    """The autopilot says the vehicle is on the ground: nothing is learnt."""
    nonfinite_events: int
    """Updates given a non-finite input (each held the last output)."""
    dt_clamped_events: int
    """Updates whose time step was clamped to the law's bounds."""
    yaw_share: YawShare
    """Yaw's share of roll and pitch offered to the mixer (``most`` 0: none)."""

    @property
    def held_on_ground(self) -> bool:
        """On the ground and held there: the law starts afresh on every sample."""
        ...

    @property
    def reference_rate_dot(self) -> Vec3:
        """The reference's derivative after the last update, rad/s^2."""
        ...

    def update(
        self, dt_s: float, rate_frd_rad_s: Vec3, rate_ref_rad_s: Vec3, thrust: float
    ) -> ControlOutput:
        """One control update from one IMU sample."""
        ...

    def learn(self) -> None:
        """Online identification for the sample just processed, once its command is out."""
        ...

    def reset(self) -> None:
        """Forget all state."""
        ...

    def teach_applied(self, torque: Vec3) -> None:
        """What of the last output was really applied, when not what the mixer achieved."""
        ...

    def identified(self) -> tuple[Vec3, Vec3, Vec3]:
        """Per axis, the model the law flies now: its input gain alpha, the
        actuator lag (s) and the loop's delay (s); NaN where it has none."""
        ...


class MfcController:
    """Roll iPD, pitch iPD, yaw iP, saturated and mixed: the paper's scheme.

    Composes a reference prefilter, one
    :class:`~companion.control.intelligent.IntelligentController` per axis and
    the mixer (module docstring).

    Parameters
    ----------
    gains
        The controller's settings (``companion.config.mfc_gains``).
    mixer
        Motor allocation from the vehicle's geometry (or the paper's equation).
    """

    def __init__(self, gains: MfcGains, mixer: Mixer) -> None:
        self.gains = gains
        self.mixer = mixer
        self._axes = tuple(
            IntelligentController(g, command_full_scale_us=gains.command_full_scale_us)
            for g in gains.axes()
        )
        self._filter = ReferencePrefilter(gains.prefilter_hz) if gains.prefilter_hz else None
        self._prev_ref: Vec3 | None = None  # without a prefilter: the last raw reference
        self._any_adapt = any(g.alpha_adapt is not None for g in gains.axes())
        self._adapt_thrust = gains.adapt_min_thrust
        self._scale = 1.0 / gains.command_full_scale_us
        self._mix = mixer.mix_fn  # Mixer.mix, bound for this geometry
        self._applied: Vec3 = _ZERO3
        self.yaw_share = YawShare(gains.yaw_share_max)
        """Yaw's share of roll and pitch, given while the heading is being lost."""
        self._dt_min = gains.dt_min_s
        self._dt_max = gains.dt_max_s
        self._last: ControlOutput | None = None
        self.nonfinite_events = 0
        self.dt_clamped_events = 0
        self.on_ground = False
        """Set while the autopilot reports the vehicle on the ground: the identifiers
        then learn nothing, whatever the collective. On the ground the command
        answers the gyro's noise and the "response" is that noise again, which a
        least-squares slope reads as a small input gain, the most aggressive alpha
        (docs/research/gains.md#small-motions). Not reset by :meth:`reset`: it is the
        autopilot's state, not the controller's.

        While the legs visibly hold the vehicle (:attr:`held_on_ground`: this flag
        and a quiet gyro), the law starts afresh every sample (:meth:`reset`), and
        what it identified goes too: an F learnt in the air (a damaged motor's
        torque) would hold its torque on the legs, saturate the mixer and cut the
        collective; one integrated on the ground (the legs' reaction, the gyro's
        noise) would be flown at take-off; and an alpha taught by a hop, from
        samples on the legs, kept a thrust-limited vehicle hopping
        (docs/research/outer.md). The flag alone is not enough: it comes late (4
        Hz, and the autopilot's detector), and a weak motor tips a vehicle at
        lift-off by 90 deg/s within the 0.25 s it takes to clear, which a law
        restarted on every one of those samples never stopped."""
        self._quiet_s = math.inf
        """Time since the gyro last read faster than :data:`LEGS_HOLD_RATE_RAD_S`."""

    @property
    def held_on_ground(self) -> bool:
        """:attr:`on_ground`, and the gyro quiet for :data:`LEGS_HOLD_QUIET_S`: the
        legs hold the vehicle, and the law starts afresh on every sample."""
        return self.on_ground and self._quiet_s >= LEGS_HOLD_QUIET_S

    def reset(self) -> None:
        """Forget all state (on disarm, hand-back, and every sample on the ground)."""
        for a in self._axes:
            a.reset()
        if self._filter is not None:
            self._filter.reset()
        self._prev_ref = None
        self._applied = _ZERO3
        self.yaw_share.reset()
        self._last = None
        self._quiet_s = math.inf

    def teach_applied(self, torque: Vec3) -> None:
        """What of the last output was really applied (normalised torques), when it
        was not what the mixer achieved: the estimators learn from it at the next
        update (an autopilot that slews a rate setpoint, companion.control.shaping)."""
        self._applied = torque

    def identified(self) -> tuple[Vec3, Vec3, Vec3]:
        """Per axis: alpha (rad/s^m per command unit), the actuator lag and the
        loop's delay (s), as configured or identified."""
        a0, a1, a2 = self._axes
        return (
            (a0.alpha, a1.alpha, a2.alpha),
            (a0.tau_s, a1.tau_s, a2.tau_s),
            (a0.delay_s, a1.delay_s, a2.delay_s),
        )

    @property
    def reference_rate_dot(self) -> Vec3:
        """Derivative of the prefiltered pilot rate after the last update, rad/s^2
        (zeros without a prefilter): what a feed-forward on the reference uses."""
        f = self._filter
        return f.rate_dot if f is not None else _ZERO3

    def learn(self) -> None:
        """Online identification for the sample just processed.

        Call after each :meth:`update`, once its command has been sent: it
        does not change that command, only the next ones, and keeping it off
        the path from sample to command keeps the loop's latency low.
        """
        if self._any_adapt:
            for a in self._axes:
                a.learn()

    def update(
        self, dt_s: float, rate_frd_rad_s: Vec3, rate_ref_rad_s: Vec3, thrust: float
    ) -> ControlOutput:
        """One control update from one IMU sample.

        Parameters
        ----------
        dt_s
            Time since the previous sample (from sample timestamps), s; clamped
            to ``[dt_min_s, dt_max_s]``.
        rate_frd_rad_s
            Measured body rates, rad/s.
        rate_ref_rad_s
            Pilot's body-rate command, rad/s.
        thrust
            Pilot's collective, [0, 1].
        """
        w0, w1, w2 = rate_frd_rad_s
        q0, q1, q2 = rate_ref_rad_s
        # One sum tests everything: a nan or inf anywhere poisons it (so does
        # an absurd magnitude near 1e308, which is no valid rate either).
        if not _isfinite(dt_s + w0 + w1 + w2 + q0 + q1 + q2 + thrust):
            self.nonfinite_events += 1
            return _hold_output(self._last, self.mixer)
        if dt_s < self._dt_min or dt_s > self._dt_max:
            self.dt_clamped_events += 1
            dt_s = self._dt_min if dt_s < self._dt_min else self._dt_max
        # 1. The reference: y_r' (r) and y_r'' (d) per axis.
        if self._filter is not None:
            r0, r1, r2, d0, d1, d2 = self._filter.step(dt_s, q0, q1, q2)
        else:
            r0, r1, r2 = q0, q1, q2
            prev = self._prev_ref
            if prev is None:
                d0 = d1 = d2 = 0.0
            else:
                d0 = (r0 - prev[0]) / dt_s
                d1 = (r1 - prev[1]) / dt_s
                d2 = (r2 - prev[2]) / dt_s
            self._prev_ref = rate_ref_rad_s
        # 2. The law on each axis, in command units. Teach the estimators what
        # was applied last time, not what was asked.
        a0, a1, a2 = self._axes
        lim = LEGS_HOLD_RATE_RAD_S
        if -lim < w0 < lim and -lim < w1 < lim and -lim < w2 < lim:
            self._quiet_s += dt_s
        else:
            self._quiet_s = 0.0
        if self.held_on_ground:  # the law starts afresh on the legs (on_ground)
            self.reset()
        if self._any_adapt:
            on = thrust >= self._adapt_thrust and not self.on_ground
            a0.adapting = a1.adapting = a2.adapting = on
        p0, p1, p2 = self._applied
        u0 = a0.update(dt_s, w0, r0, d0, p0)
        u1 = a1.update(dt_s, w1, r1, d1, p1)
        u2 = a2.update(dt_s, w2, r2, d2, p2)
        # 3. The mixer: normalised torques and the collective to motors, and what
        # of the torques it could apply (the law's next lesson); yaw's share of
        # roll and pitch for the next sample from what it did.
        s = self._scale
        share = self.yaw_share
        motors, achieved, sat_axes, sat_motors, thrust_eff, given = self._mix(
            thrust, u0 * s, u1 * s, u2 * s, share.value
        )
        self._applied = achieved
        share.update(dt_s, a2.e_dot, sat_axes[2], sat_axes[0] or sat_axes[1], given)
        out: ControlOutput = _new_tuple(
            ControlOutput,
            (
                achieved,
                thrust_eff,
                motors,
                sat_axes,
                sat_motors,
                (u0, u1, u2),
                (a0.f_hat, a1.f_hat, a2.f_hat),
                (a0.e_dot, a1.e_dot, a2.e_dot),
                False,
            ),
        )
        self._last = out
        return out


class PidController:
    """The PX4-style PID with the same interface as :class:`MfcController`."""

    def __init__(self, gains: PidGains, mixer: Mixer, *, dt_min_s: float, dt_max_s: float) -> None:
        self.gains = gains
        self.mixer = mixer
        self._pid = RatePid(gains)
        self._dt_min = dt_min_s
        self._dt_max = dt_max_s
        self._last: ControlOutput | None = None
        self._sat_pos = (False, False, False)
        self._sat_neg = (False, False, False)
        self.yaw_share = YawShare(0.0)
        """Never offered: PX4's allocation puts roll and pitch first."""
        self.nonfinite_events = 0
        self.dt_clamped_events = 0
        self.on_ground = False
        """Same attribute as :attr:`MfcController.on_ground`: while True the integrator
        is held (a vehicle on its legs cannot turn, so a rate error there is no
        torque to trim; PX4's rate controller holds its integrator while landed)."""

    @property
    def held_on_ground(self) -> bool:
        """:attr:`on_ground` (same interface as :attr:`MfcController.held_on_ground`;
        the baseline's, as PX4 flies it, has no gyro gate)."""
        return self.on_ground

    def reset(self) -> None:
        self._pid.reset()
        self._last = None
        self._sat_pos = self._sat_neg = (False, False, False)

    def teach_applied(self, torque: Vec3) -> None:
        """Nothing to teach: the PID learns only its integral (same interface as
        :meth:`MfcController.teach_applied`)."""

    def identified(self) -> tuple[Vec3, Vec3, Vec3]:
        """No model: NaN (same interface as :meth:`MfcController.identified`)."""
        return (_NAN3, _NAN3, _NAN3)

    @property
    def reference_rate_dot(self) -> Vec3:
        """No reference prefilter: zeros (same interface as :class:`MfcController`)."""
        return _ZERO3

    def learn(self) -> None:
        """Nothing to learn: same interface as :meth:`MfcController.learn`."""

    def update(
        self, dt_s: float, rate_frd_rad_s: Vec3, rate_ref_rad_s: Vec3, thrust: float
    ) -> ControlOutput:
        """Same contract as :meth:`MfcController.update`."""
        if not _all_finite(dt_s, rate_frd_rad_s, rate_ref_rad_s, thrust):
            self.nonfinite_events += 1
            return _hold_output(self._last, self.mixer)
        if dt_s < self._dt_min or dt_s > self._dt_max:
            self.dt_clamped_events += 1
            dt_s = self._dt_min if dt_s < self._dt_min else self._dt_max
        u = self._pid.update(
            dt_s, rate_ref_rad_s, rate_frd_rad_s, self._sat_pos, self._sat_neg,
            integrate=not self.on_ground,
        )  # fmt: skip
        mix = self.mixer.mix(thrust, u[0], u[1], u[2])
        sat = mix.saturated_axes
        self._sat_pos = (sat[0] and u[0] > 0, sat[1] and u[1] > 0, sat[2] and u[2] > 0)
        self._sat_neg = (sat[0] and u[0] < 0, sat[1] and u[1] < 0, sat[2] and u[2] < 0)
        r = rate_ref_rad_s
        w = rate_frd_rad_s
        out = ControlOutput(
            mix.achieved,
            mix.thrust,
            mix.motors,
            sat,
            mix.saturated_motors,
            u,
            _ZERO3,
            (w[0] - r[0], w[1] - r[1], w[2] - r[2]),
            False,
        )
        self._last = out
        return out
