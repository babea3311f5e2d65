r"""An autopilot's input shaping of body-rate setpoints, as the law must see it.

ArduCopter flies a GUIDED body-rate setpoint (``SET_ATTITUDE_TARGET``, attitude
ignored) through ``AC_AttitudeControl::input_rate_bf_roll_pitch_yaw``: with
``ATC_RATE_FF_ENAB`` set (its default) the rate target moves towards the
setpoint by at most ``ATC_ACCEL_{R,P,Y}_MAX`` times the loop period (defaults
1100, 1100 and 270 deg/s\ :sup:`2`), an attitude target integrates that rate,
and the attitude error is fed back on top of it (ArduPilot
``libraries/AC_AttitudeControl/AC_AttitudeControl.cpp``, Copter 4.5). PX4's
offboard body rates reach its rate controller unshaped.

A law that wraps such a loop and does not know it fights the limit: it sees
the vehicle lag a setpoint the autopilot will not fly yet, raises its
correction, the autopilot slews that too and integrates it into its attitude
target, and the loop limit-cycles (measured on the real ArduCopter 4.5.6: the
yaw between +-220 deg/s commands at 1.3 Hz). So, with the autopilot's limits
given (:class:`RateShaper`):

* the law's reference is the pilot's rate shaped as the autopilot will shape
  it, :math:`\dot y_r[k] = \dot y_r[k-1] + \mathrm{clamp}(\dot y_{pilot} -
  \dot y_r[k-1], \pm a_{max} \Delta t)`: the law corrects what the
  autopilot's own loop leaves, not the limit;
* the setpoint sent moves by at most :math:`a_{max} \Delta t` from the last one
  sent, and the law is taught the correction that was sent, not the one it
  asked (as it is taught the mixer's saturation in actuator output);
* the correction is held within what the autopilot slews in over
  :data:`CORRECTION_HORIZON_S`, :math:`\pm a_{max} h` about the shaped
  reference: a larger one reaches the vehicle only after the slew, the law
  sees it late, keeps asking, and the loop limit-cycles with the slew (yaw,
  where :math:`a_{max}` is smallest: +-60 deg/s at 0.5 Hz once the stick
  centres, ``docs/research/realstack.md#ap-yaw-cycle``).

An axis whose limit is 0 or infinite is not shaped. Pure: no clock, ``dt``
from the samples.
"""

from __future__ import annotations

import math

__all__ = ["CORRECTION_HORIZON_S", "RateShaper"]

Vec3 = tuple[float, float, float]

CORRECTION_HORIZON_S = 0.05
"""The longest the autopilot may take to slew in the law's correction, s: the
setpoint stays within ``a_max`` times this of the shaped reference (ArduCopter's
defaults: 55 deg/s on roll and pitch, 13.5 on yaw)."""


def _toward(prev: float, want: float, step: float) -> float:
    if want > prev + step:
        return prev + step
    if want < prev - step:
        return prev - step
    return want


def _toward3(prev: Vec3, want: Vec3, accel: Vec3, span_s: float) -> Vec3:
    """``want`` moved at most ``accel * span_s`` from ``prev`` on each axis."""
    return (
        _toward(prev[0], want[0], accel[0] * span_s),
        _toward(prev[1], want[1], accel[1] * span_s),
        _toward(prev[2], want[2], accel[2] * span_s),
    )


class RateShaper:
    """Acceleration limits on a body-rate setpoint (rad/s^2 per axis; 0 or inf: none).

    Raises
    ------
    ValueError
        For a limit that is negative or NaN.
    """

    __slots__ = ("_shaped", "accel_max_rad_s2")

    def __init__(self, accel_max_rad_s2: Vec3) -> None:
        if not all(a >= 0.0 for a in accel_max_rad_s2):  # also False for NaN
            raise ValueError(f"accel_max_rad_s2 must be >= 0, got {accel_max_rad_s2}")
        self.accel_max_rad_s2: Vec3 = tuple(  # type: ignore[assignment]
            math.inf if a == 0.0 else float(a) for a in accel_max_rad_s2
        )
        self._shaped: Vec3 | None = None

    def reset(self) -> None:
        """Forget the shaped reference (an engagement starts from the pilot's)."""
        self._shaped = None

    def reference(self, dt_s: float, ref: Vec3) -> Vec3:
        """The pilot's rate ``ref`` shaped as the autopilot shapes a setpoint, rad/s."""
        prev = self._shaped
        if prev is None or not dt_s > 0.0:
            shaped = ref if prev is None else prev
        else:
            shaped = _toward3(prev, ref, self.accel_max_rad_s2, dt_s)
        if not (math.isfinite(shaped[0]) and math.isfinite(shaped[1]) and math.isfinite(shaped[2])):
            shaped = ref  # a non-finite pilot rate is the gate's to replace, not ours to keep
        self._shaped = shaped
        return shaped

    def within_reach(self, reference: Vec3, want: Vec3) -> Vec3:
        """``want`` held within ``a_max`` times :data:`CORRECTION_HORIZON_S` of
        ``reference`` on each axis (NaN: as it is, for the gate to replace)."""
        return _toward3(reference, want, self.accel_max_rad_s2, CORRECTION_HORIZON_S)

    def limit(self, dt_s: float, want: Vec3, last_sent: Vec3 | None) -> Vec3:
        """``want`` moved at most ``a_max * dt_s`` from ``last_sent`` (None: as it is)."""
        if last_sent is None or not dt_s > 0.0:
            return want
        return _toward3(last_sent, want, self.accel_max_rad_s2, dt_s)
