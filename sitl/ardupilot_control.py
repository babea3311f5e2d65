"""The ArduPilot personality's control primitives: gyro filter, rate PID, thrust curve.

Pure objects and functions after ArduPilot's own (``LowPassFilter2p``,
``AC_PID``, ``AP_Motors_Thrust_Linearization``, ``GCS_MAVLINK_Copter``'s
thrust-as-climb-rate); :class:`sitl.ardupilot.ArduCopter` runs them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

__all__ = [
    "ApAxisGains",
    "ApRatePid",
    "GyroLowPass",
    "actuator_to_thrust",
    "climb_rate_from_thrust",
    "thrust_to_actuator",
]


def _lowpass_alpha(dt_s: float, cutoff_hz: float) -> float:
    """ArduPilot ``calc_lowpass_alpha_dt``: 1 (no filtering) when the cutoff is 0."""
    if cutoff_hz <= 0.0 or dt_s <= 0.0:
        return 1.0
    rc = 1.0 / (2.0 * math.pi * cutoff_hz)
    return dt_s / (dt_s + rc)


class GyroLowPass:
    r"""Three-axis 2nd-order Butterworth low-pass (ArduPilot ``LowPassFilter2p``).

    Coefficients for sample rate :math:`f_s` and cutoff :math:`f_c`, with
    :math:`\Omega = \tan(\pi f_c / f_s)` and :math:`c = 1 + \sqrt2\,\Omega + \Omega^2`:
    :math:`b_0 = b_2 = \Omega^2/c`, :math:`b_1 = 2 b_0`,
    :math:`a_1 = 2(\Omega^2 - 1)/c`, :math:`a_2 = (1 - \sqrt2\,\Omega + \Omega^2)/c`.
    A cutoff of 0 passes the signal through.
    """

    def __init__(self, cutoff_hz: float) -> None:
        self.cutoff_hz = float(cutoff_hz)
        self._fs_hz = 0.0
        self._coef = (1.0, 0.0, 0.0, 0.0, 0.0)
        self._d1 = [0.0, 0.0, 0.0]
        self._d2 = [0.0, 0.0, 0.0]
        self._primed = False

    def _design(self, fs_hz: float) -> None:
        self._fs_hz = fs_hz
        fc = self.cutoff_hz
        if fc <= 0.0 or fc >= 0.5 * fs_hz:
            self._coef = (1.0, 0.0, 0.0, 0.0, 0.0)
            return
        ohm = math.tan(math.pi * fc / fs_hz)
        c = 1.0 + 2.0 * math.cos(math.pi / 4.0) * ohm + ohm * ohm
        b0 = ohm * ohm / c
        a1 = 2.0 * (ohm * ohm - 1.0) / c
        a2 = (1.0 - 2.0 * math.cos(math.pi / 4.0) * ohm + ohm * ohm) / c
        self._coef = (b0, 2.0 * b0, b0, a1, a2)

    def apply(self, x: Sequence[float], dt_s: float) -> tuple[float, float, float]:
        """Filter one sample taken ``dt_s`` after the previous one."""
        fs = 1.0 / dt_s if dt_s > 0.0 else self._fs_hz
        if fs > 0.0 and (self._fs_hz <= 0.0 or abs(fs - self._fs_hz) > 0.1 * self._fs_hz):
            self._design(fs)
        b0, b1, b2, a1, a2 = self._coef
        if not self._primed:
            # Start at steady state on the first sample (no start-up transient).
            for i in range(3):
                d = x[i] / (1.0 + a1 + a2) if b1 else 0.0
                self._d1[i] = self._d2[i] = d
            self._primed = True
        out = [0.0, 0.0, 0.0]
        for i in range(3):
            d0 = x[i] - self._d1[i] * a1 - self._d2[i] * a2
            out[i] = d0 * b0 + self._d1[i] * b1 + self._d2[i] * b2 if b1 else x[i]
            self._d2[i] = self._d1[i]
            self._d1[i] = d0
        return (out[0], out[1], out[2])

    def reset(self) -> None:
        self._primed = False


@dataclass(frozen=True)
class ApAxisGains:
    """``AC_PID`` gains of one axis (ATC_RAT_{RLL,PIT,YAW}_*)."""

    kp: float
    ki: float
    kd: float
    kff: float = 0.0
    imax: float = 0.5
    filt_t_hz: float = 20.0
    filt_e_hz: float = 0.0
    filt_d_hz: float = 20.0


class ApRatePid:
    r"""Three-axis ArduPilot rate controller (``AC_PID::update_all``), a pure object.

    Per axis, at the loop period ``dt_s``:

    .. math::  T_f \leftarrow T_f + \alpha_T (T - T_f), \qquad
               e \leftarrow e + \alpha_E ((T_f - \omega) - e), \\
               \dot e_f \leftarrow \dot e_f + \alpha_D (\tfrac{e - e_{prev}}{dt} - \dot e_f), \\
               I \leftarrow \operatorname{clip}(I + K_I e\,dt, \pm I_{max}), \qquad
               u = K_P e + I + K_D \dot e_f + K_{FF} T_f

    (D on the error, as ArduPilot does: a target step kicks D through the FLTT
    filter). The integrator does not grow while ``limit`` says the output
    saturated in the direction of the error. Outputs are normalised torques.
    """

    def __init__(self, gains: Sequence[ApAxisGains]) -> None:
        self.gains = tuple(gains)
        self._target = [0.0, 0.0, 0.0]
        self._error = [0.0, 0.0, 0.0]
        self._deriv = [0.0, 0.0, 0.0]
        self._integ = [0.0, 0.0, 0.0]
        self._reset = True

    @property
    def integrator(self) -> tuple[float, float, float]:
        i = self._integ
        return (i[0], i[1], i[2])

    def reset(self) -> None:
        """Forget the filters and the integrator."""
        self._integ = [0.0, 0.0, 0.0]
        self._reset = True

    def reset_integrator(self) -> None:
        self._integ = [0.0, 0.0, 0.0]

    def update(
        self,
        dt_s: float,
        target_rad_s: Sequence[float],
        measured_rad_s: Sequence[float],
        limit: Sequence[bool] = (False, False, False),
    ) -> tuple[float, float, float]:
        out = [0.0, 0.0, 0.0]
        for i in range(3):
            g = self.gains[i]
            tgt = target_rad_s[i]
            meas = measured_rad_s[i]
            if self._reset:
                self._target[i] = tgt
                self._error[i] = tgt - meas
                self._deriv[i] = 0.0
            else:
                prev_err = self._error[i]
                self._target[i] += _lowpass_alpha(dt_s, g.filt_t_hz) * (tgt - self._target[i])
                err = self._target[i] - meas
                self._error[i] += _lowpass_alpha(dt_s, g.filt_e_hz) * (err - self._error[i])
                raw_d = (self._error[i] - prev_err) / dt_s
                self._deriv[i] += _lowpass_alpha(dt_s, g.filt_d_hz) * (raw_d - self._deriv[i])
            e = self._error[i]
            integ = self._integ[i]
            if g.ki > 0.0 and (not limit[i] or integ * e < 0.0):
                integ = min(g.imax, max(-g.imax, integ + e * g.ki * dt_s))
            self._integ[i] = integ
            out[i] = g.kp * e + integ + g.kd * self._deriv[i] + g.kff * self._target[i]
        self._reset = False
        return (out[0], out[1], out[2])


def climb_rate_from_thrust(thrust: float, speed_up_m_s: float, speed_dn_m_s: float) -> float:
    """SET_ATTITUDE_TARGET thrust as a climb-rate request (``GCS_MAVLINK_Copter``).

    Clipped to [0, 1]; 0.5 holds altitude; 1 climbs at ``speed_up_m_s``; 0
    descends at ``speed_dn_m_s``. Returns m/s, positive up.
    """
    t = min(1.0, max(0.0, thrust))
    if t == 0.5:
        return 0.0
    if t > 0.5:
        return (t - 0.5) * 2.0 * speed_up_m_s
    return -(0.5 - t) * 2.0 * speed_dn_m_s


def thrust_to_actuator(thrust: float, expo: float) -> float:
    """``AP_Motors_Thrust_Linearization::apply_thrust_curve_and_volt_scaling`` (no battery)."""
    t = min(1.0, max(0.0, thrust))
    if abs(expo) < 1e-6:
        return t
    return ((expo - 1.0) + math.sqrt((1.0 - expo) ** 2 + 4.0 * expo * t)) / (2.0 * expo)


def actuator_to_thrust(actuator: float, expo: float) -> float:
    """Inverse of :func:`thrust_to_actuator`: ``(1 - expo) a + expo a^2``."""
    a = min(1.0, max(0.0, actuator))
    return (1.0 - expo) * a + expo * a * a
