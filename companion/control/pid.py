r"""PX4-style body-rate PID: the baseline the paper compares MFC with.

Per axis, with rate error :math:`e = \omega_{sp} - \omega` (rad/s):

.. math::  \tau = K_P e + I + K_{FF} \omega_{sp} - K_D \dot\omega_f,
           \qquad \dot I = K_I e \;(\text{clamped to } \pm I_{max})

where :math:`\dot\omega_f` is the measured angular acceleration through a
first-order low-pass (D on measurement, so setpoint steps do not kick). The
integrator stops growing in a direction the mixer reports saturated
(anti-windup), as PX4's ``RateControl::updateIntegral`` does with allocator
feedback. Output is normalised torque in [-1, 1].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["PidAxisGains", "PidGains", "RatePid"]

Vec3 = tuple[float, float, float]


_OUTPUT_LIMIT = 1.0
"""Each axis's output is a normalised torque: at most full scale either way."""


@dataclass(frozen=True)
class PidAxisGains:
    """Gains of one axis, in normalised torque per rad/s (PX4 MC_*RATE_* units), as
    the configuration file gives them (``companion.config``'s ``PidAxisConfig``,
    field for field; its schema holds the defaults and bounds; PX4's defaults are
    ``companion/data/pid_px4_default.yaml``)."""

    kp: float
    ki: float
    kd: float
    kff: float
    i_limit: float
    d_lpf_hz: float


@dataclass(frozen=True)
class PidGains:
    roll: PidAxisGains
    pitch: PidAxisGains
    yaw: PidAxisGains

    def axes(self) -> tuple[PidAxisGains, PidAxisGains, PidAxisGains]:
        return (self.roll, self.pitch, self.yaw)


class RatePid:
    """Three-axis PX4-style rate PID.

    Parameters
    ----------
    gains
        Per-axis gains.
    """

    __slots__ = ("_d_state", "_gains", "_integral", "_prev_rate", "_primed")

    def __init__(self, gains: PidGains) -> None:
        self._gains = gains.axes()
        self._integral = [0.0, 0.0, 0.0]
        self._prev_rate = [0.0, 0.0, 0.0]
        self._d_state = [0.0, 0.0, 0.0]
        self._primed = False

    @property
    def gains(self) -> PidGains:
        return PidGains(*self._gains)

    @property
    def integral(self) -> Vec3:
        i = self._integral
        return (i[0], i[1], i[2])

    def reset(self) -> None:
        """Forget the integrator and the derivative filter (on disarm)."""
        self._integral = [0.0, 0.0, 0.0]
        self._d_state = [0.0, 0.0, 0.0]
        self._primed = False

    def update(
        self,
        dt_s: float,
        setpoint_rad_s: Vec3,
        measured_rad_s: Vec3,
        saturated_pos: tuple[bool, bool, bool] = (False, False, False),
        saturated_neg: tuple[bool, bool, bool] = (False, False, False),
        *,
        integrate: bool = True,
    ) -> Vec3:
        """One update; returns normalised torques (roll, pitch, yaw).

        ``dt_s`` must be positive and finite (the caller clamps it). A
        non-finite setpoint component falls back to the measured rate (zero
        error), as PX4 does; ``saturated_pos``/``saturated_neg`` tell which
        directions the mixer could not realise last time, so the integrator
        does not wind up there. ``integrate`` False holds the integrator where it is
        (on the ground, as PX4's rate controller does while landed).
        """
        out = [0.0, 0.0, 0.0]
        primed = self._primed
        for i in range(3):
            g = self._gains[i]
            w = measured_rad_s[i]
            sp = setpoint_rad_s[i]
            if not math.isfinite(sp):
                sp = w
            e = sp - w
            # Derivative on measurement through a first-order low-pass.
            if primed:
                raw = (w - self._prev_rate[i]) / dt_s
                a = dt_s / (dt_s + 1.0 / (2.0 * math.pi * g.d_lpf_hz))
                self._d_state[i] += a * (raw - self._d_state[i])
            self._prev_rate[i] = w
            integ = self._integral[i]
            di = g.ki * e * dt_s
            if integrate and not (
                (di > 0.0 and saturated_pos[i]) or (di < 0.0 and saturated_neg[i])
            ):
                integ = min(g.i_limit, max(-g.i_limit, integ + di))
            self._integral[i] = integ
            u = g.kp * e + integ + g.kff * sp - g.kd * self._d_state[i]
            lim = _OUTPUT_LIMIT
            out[i] = lim if u > lim else (-lim if u < -lim else u)
        self._primed = True
        return (out[0], out[1], out[2])
