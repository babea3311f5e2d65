r"""PX4 v1.16's multicopter rate loop and control allocation, for the PX4 personality.

Written for the SITL from PX4's source and parameter reference, independently of
the companion's own laws (``companion.control``): the plant's autopilot must not
share a bug or a tuning choice with the product it tests.

Rate loop (``src/modules/mc_rate_control/MulticopterRateControl.cpp`` around
``src/lib/rate_control/rate_control.cpp``)
-------------------------------------------------------------------------
Per gyro sample, with ``dt`` from the sample stamps clamped to 0.125..20 ms:

* the body rate is the gyro through a 2nd-order low-pass at ``IMU_GYRO_CUTOFF``
  (40 Hz), and the angular acceleration the derivative of the unfiltered gyro
  through a 2nd-order low-pass at ``IMU_DGYRO_CUTOFF`` (30 Hz)
  (``src/modules/sensors/vehicle_angular_velocity/VehicleAngularVelocity.cpp``);
* a NaN setpoint component is replaced by the current rate (no error on that axis);
* per axis

  .. math:: \tau = K_P e + I - K_D \dot\omega_f + K_{FF}\,\omega_{sp},
            \qquad e = \omega_{sp} - \omega_f

  with the gains already multiplied by ``MC_*RATE_K`` (the ideal form);
* unless landed the integrator grows by :math:`f\,K_I e\,dt` with
  :math:`f = \max(0, 1 - (e / 400°/s)^2)`, the error clipped to zero in a direction
  the allocator reported saturated, and the result clamped to ``MC_*R_INT_LIM``;
* the yaw torque goes through a first-order low-pass at ``MC_YAW_TQ_CUTOFF`` (2 Hz);
* a non-finite torque is sent as 0. The torque is not clamped here: the allocator
  clips what it cannot give.

Defaults are PX4 v1.16's parameter reference (``parameters.json`` of the build):
``MC_ROLLRATE_P/I/D`` 0.15 / 0.2 / 0.003, ``MC_PITCHRATE_*`` the same, ``MC_YAWRATE_P/I/D``
0.2 / 0.1 / 0, every ``*_FF`` 0 and ``*_K`` 1, integrator limits 0.3.

Control allocation (``src/modules/control_allocator``)
-----------------------------------------------------
The effectiveness matrix of the rotors (``ActuatorEffectivenessRotors``: rotor
``i`` at ``p_i`` pushing along ``a = (0, 0, -1)`` gives the moment
``c_t (p_i × a) - c_t k_m a`` and the force ``c_t a``; ``k_m`` > 0 for a
counter-clockwise rotor) is pseudo-inverted and normalised
(``ControlAllocationPseudoInverse``: roll and pitch columns by the larger of
``sqrt(|col|^2 / (n_nonzero / 2))``, yaw by the column's largest entry, thrust by
the mean of its entries' magnitudes). On a square quad X a unit roll torque
moves each motor by 0.707 and a unit yaw torque by 1.

``ControlAllocationSequentialDesaturation`` with ``MC_AIRMODE`` 0 (the default):
mix roll, pitch and thrust; desaturate along the thrust column only by lowering
the thrust; then along the roll column, then the pitch column; add yaw; desaturate
along the yaw column with the upper bound raised by 15 % of the range
(``MINIMUM_YAW_MARGIN``); lower the thrust again if needed; clip to [0, 1]. Each
desaturation step moves the setpoint along its column by the gain that balances
the worst under- and overshoot (motors whose column entry is below 0.2 in
magnitude are left out), then by half the gain the result still needs. The torque
that did not fit is what the rate loop's integrator is stopped by
(``control_allocator_status.unallocated_torque``).

The allocator's [0, 1] is the motor's range from its armed idle to full
(``PWM_MAIN_MINn`` .. ``PWM_MAIN_MAXn``): :meth:`ControlAllocator.motor_commands`
maps it onto the plant's normalised command, ``idle + (1 - idle) u``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from sitl.ardupilot_control import GyroLowPass
from sitl.linalg import pseudo_inverse

if TYPE_CHECKING:
    from companion.profile import VehicleProfile

__all__ = [
    "PX4_V116_RATE_GAINS",
    "AllocationResult",
    "AngularVelocityFilter",
    "ControlAllocator",
    "Px4AxisGains",
    "Px4RateLoop",
    "RateControl",
    "thrust_for_command",
]

Vec3 = tuple[float, float, float]

DT_MIN_S = 0.000125
DT_MAX_S = 0.02
"""``MulticopterRateControl::Run`` clamps the loop's dt to this range."""
I_FACTOR_RATE_RAD_S = math.radians(400.0)
"""``RateControl::updateIntegral``: the integrator gain falls off with the rate error."""
MINIMUM_YAW_MARGIN = 0.15
"""``ControlAllocationSequentialDesaturation``: yaw may use 15 % above full."""
WEAK_EFFECTIVENESS = 0.2
"""``computeDesaturationGain`` ignores actuators with a smaller column entry."""


@dataclass(frozen=True)
class Px4AxisGains:
    """One axis of ``MC_{ROLL,PITCH,YAW}RATE_*``: P, I, D, FF, K and the integrator limit."""

    p: float
    i: float
    d: float
    ff: float = 0.0
    k: float = 1.0
    int_lim: float = 0.3


PX4_V116_RATE_GAINS: tuple[Px4AxisGains, Px4AxisGains, Px4AxisGains] = (
    Px4AxisGains(p=0.15, i=0.2, d=0.003),
    Px4AxisGains(p=0.15, i=0.2, d=0.003),
    Px4AxisGains(p=0.2, i=0.1, d=0.0),
)
"""PX4 v1.16 defaults (``mc_rate_control_params.c``; the parameter reference)."""


class RateControl:
    """PX4's ``RateControl``: a pure object whose only state is the integrator.

    Parameters
    ----------
    gains
        Roll, pitch, yaw; P, I and D are multiplied by ``k`` (``parameters_updated``).
    """

    def __init__(self, gains: Sequence[Px4AxisGains] = PX4_V116_RATE_GAINS) -> None:
        self.set_gains(gains)
        self._int = [0.0, 0.0, 0.0]
        self._sat_pos = (False, False, False)
        self._sat_neg = (False, False, False)

    def set_gains(self, gains: Sequence[Px4AxisGains]) -> None:
        """New gains; the integrator is kept (PX4's ``parameters_updated``)."""
        g = tuple(gains)
        self.gains = g
        self.kp = tuple(a.k * a.p for a in g)
        self.ki = tuple(a.k * a.i for a in g)
        self.kd = tuple(a.k * a.d for a in g)
        self.kff = tuple(a.ff for a in g)
        self.int_lim = tuple(a.int_lim for a in g)

    @property
    def integral(self) -> Vec3:
        i = self._int
        return (i[0], i[1], i[2])

    def reset_integral(self) -> None:
        self._int = [0.0, 0.0, 0.0]

    def set_saturation(self, positive: Sequence[bool], negative: Sequence[bool]) -> None:
        """The allocator's feedback: axes it could not push further up / down."""
        self._sat_pos = (bool(positive[0]), bool(positive[1]), bool(positive[2]))
        self._sat_neg = (bool(negative[0]), bool(negative[1]), bool(negative[2]))

    def update(
        self,
        rate: Sequence[float],
        rate_sp: Sequence[float],
        angular_accel: Sequence[float],
        dt_s: float,
        landed: bool,
    ) -> Vec3:
        """Torque setpoint (normalised, unclamped) for one sample."""
        out = [0.0, 0.0, 0.0]
        for i in range(3):
            err = rate_sp[i] - rate[i]
            out[i] = (
                self.kp[i] * err
                + self._int[i]
                - self.kd[i] * angular_accel[i]
                + self.kff[i] * rate_sp[i]
            )
            if landed:
                continue
            # Do not wind up further in a direction the motors cannot give.
            e = err
            if self._sat_pos[i] and e > 0.0:
                e = 0.0
            if self._sat_neg[i] and e < 0.0:
                e = 0.0
            fall_off = e / I_FACTOR_RATE_RAD_S
            factor = max(0.0, 1.0 - fall_off * fall_off)
            grown = self._int[i] + factor * self.ki[i] * e * dt_s
            if math.isfinite(grown):
                lim = self.int_lim[i]
                self._int[i] = lim if grown > lim else (-lim if grown < -lim else grown)
        return (out[0], out[1], out[2])


class AngularVelocityFilter:
    """PX4's ``VehicleAngularVelocity``: the filtered rate and its filtered derivative.

    Parameters
    ----------
    gyro_cutoff_hz
        ``IMU_GYRO_CUTOFF`` (40 Hz): 2nd-order low-pass on the rate.
    dgyro_cutoff_hz
        ``IMU_DGYRO_CUTOFF`` (30 Hz): 2nd-order low-pass on the derivative of the
        unfiltered rate (the D term's input).
    """

    def __init__(self, gyro_cutoff_hz: float = 40.0, dgyro_cutoff_hz: float = 30.0) -> None:
        self._rate = GyroLowPass(gyro_cutoff_hz)
        self._accel = GyroLowPass(dgyro_cutoff_hz)
        self._prev: Vec3 | None = None

    def reset(self) -> None:
        self._rate.reset()
        self._accel.reset()
        self._prev = None

    def apply(self, gyro: Sequence[float], dt_s: float) -> tuple[Vec3, Vec3]:
        """``(rate, angular_acceleration)`` after the gyro sample ``gyro`` (rad/s)."""
        g = (float(gyro[0]), float(gyro[1]), float(gyro[2]))
        prev = self._prev if self._prev is not None else g
        self._prev = g
        raw_accel = ((g[0] - prev[0]) / dt_s, (g[1] - prev[1]) / dt_s, (g[2] - prev[2]) / dt_s)
        return self._rate.apply(g, dt_s), self._accel.apply(raw_accel, dt_s)


def thrust_for_command(motor_command: float, idle: float) -> float:
    """The allocator's collective (0 idle, 1 full) that gives the plant's ``motor_command``."""
    span = 1.0 - idle
    return min(max((motor_command - idle) / span, 0.0), 1.0) if span > 0.0 else 0.0


@dataclass(frozen=True)
class AllocationResult:
    """What :meth:`ControlAllocator.allocate` produced.

    ``actuators`` in [0, 1] (idle to full); ``unallocated`` the torque that did not
    fit (setpoint minus achieved, normalised); ``saturated_positive`` /
    ``saturated_negative`` the rate loop's integrator feedback.
    """

    actuators: tuple[float, ...]
    unallocated: Vec3
    saturated_positive: tuple[bool, bool, bool]
    saturated_negative: tuple[bool, bool, bool]


class ControlAllocator:
    """PX4's multicopter allocation (pseudo-inverse, sequential desaturation, airmode 0).

    Parameters
    ----------
    positions_frd_m
        Rotor positions (``CA_ROTORn_PX/PY``), m; only the ratios matter.
    spins
        ``"ccw"`` (``CA_ROTORn_KM`` > 0) or ``"cw"`` per rotor, seen from above.
    km
        ``|CA_ROTORn_KM|`` (0.05): scales the yaw row before normalisation only.
    idle
        The armed idle as a normalised motor command (the plant's), for
        :meth:`motor_commands`.
    """

    def __init__(
        self,
        positions_frd_m: Sequence[Sequence[float]],
        spins: Sequence[str],
        *,
        km: float = 0.05,
        idle: float = 0.0,
    ) -> None:
        n = len(positions_frd_m)
        if n < 4 or len(spins) != n:
            raise ValueError("expected at least 4 rotors and one spin per rotor")
        if not 0.0 <= idle < 1.0:
            raise ValueError(f"idle must be in [0, 1), got {idle!r}")
        eff = np.zeros((6, n))
        for i, (p, s) in enumerate(zip(positions_frd_m, spins, strict=True)):
            if s not in ("cw", "ccw"):
                raise ValueError(f"spin must be 'cw' or 'ccw', got {s!r}")
            px, py = float(p[0]), float(p[1])
            k = km if s == "ccw" else -km
            # moment = p x a - k a with a = (0, 0, -1) (a rotor's height drops out);
            # force = a. c_t = 1: it cancels in the normalisation.
            eff[:, i] = (-py, px, k, 0.0, 0.0, -1.0)
        try:
            mix = np.array(pseudo_inverse(eff.tolist()))  # n x 6, the same bits everywhere
        except ValueError:  # a degenerate geometry: LAPACK's, whatever the machine
            mix = np.linalg.pinv(eff)
        scale = np.ones(6)
        nz_r = int(np.count_nonzero(np.abs(mix[:, 0]) > 1e-3))
        nz_p = int(np.count_nonzero(np.abs(mix[:, 1]) > 1e-3))
        roll_s = math.sqrt(float(mix[:, 0] @ mix[:, 0]) / (nz_r / 2.0)) if nz_r else 1.0
        pitch_s = math.sqrt(float(mix[:, 1] @ mix[:, 1]) / (nz_p / 2.0)) if nz_p else 1.0
        scale[0] = scale[1] = max(roll_s, pitch_s)
        scale[2] = float(mix[:, 2].max())
        col = np.abs(mix[:, 5])
        nz_t = int(np.count_nonzero(col > np.finfo(np.float32).eps))
        scale[5] = float(col.sum()) / nz_t if nz_t else 1.0
        mix = mix / scale
        self.n_motors = n
        self.idle = float(idle)
        self._eff = eff
        self._scale = scale
        self._roll = tuple(float(v) for v in mix[:, 0])
        self._pitch = tuple(float(v) for v in mix[:, 1])
        self._yaw = tuple(float(v) for v in mix[:, 2])
        self._thrust_z = tuple(float(v) for v in mix[:, 5])

    @classmethod
    def from_profile(cls, profile: VehicleProfile) -> ControlAllocator:
        """The allocator of a vehicle profile, its idle the profile's ``limits.motor_idle``.

        ``physics.mixer: paper`` is the paper's '+' frame (motors front, right,
        back, left; 1 and 3 clockwise), allocated the same way.
        """
        idle = float(profile.limits.motor_idle)
        if profile.physics.mixer == "paper":
            pos = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (-1.0, 0.0, 0.0), (0.0, -1.0, 0.0))
            return cls(pos, ("cw", "ccw", "cw", "ccw"), idle=idle)
        motors = profile.frame.motors
        return cls([m.position_frd_m for m in motors], [m.spin for m in motors], idle=idle)

    def columns(self) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
        """The normalised roll, pitch and yaw columns (per motor)."""
        return self._roll, self._pitch, self._yaw

    @staticmethod
    def _gain(vec: Sequence[float], u: list[float], hi: float) -> float:
        k_min = 0.0
        k_max = 0.0
        for ui, vi in zip(u, vec):
            if abs(vi) < WEAK_EFFECTIVENESS:
                continue
            if ui < 0.0:
                k = -ui / vi
            elif ui > hi:
                k = (hi - ui) / vi
            else:
                continue
            k_min = min(k_min, k)
            k_max = max(k_max, k)
        return k_min + k_max

    def _desaturate(
        self, u: list[float], vec: Sequence[float], *, hi: float = 1.0, lower_only: bool = False
    ) -> None:
        """Move ``u`` along ``vec`` to reduce saturation (two steps, the second halved).

        ``lower_only`` (the thrust column, airmode off): only a positive gain along
        the negative thrust column, which lowers the thrust, is applied.
        """
        g = self._gain(vec, u, hi)
        if lower_only and g < 0.0:
            return
        for i, vi in enumerate(vec):
            u[i] += g * vi
        g = 0.5 * self._gain(vec, u, hi)
        for i, vi in enumerate(vec):
            u[i] += g * vi

    def allocate(self, torque: Sequence[float], thrust: float) -> AllocationResult:
        """Allocate a normalised torque (roll, pitch, yaw) and a collective in [0, 1].

        Non-finite inputs read as 0.
        """
        r, p, y = (float(v) if math.isfinite(v) else 0.0 for v in torque[:3])
        t = float(thrust) if math.isfinite(thrust) else 0.0
        tz = -t  # PX4's thrust setpoint points up: negative z
        u = [
            self._roll[i] * r + self._pitch[i] * p + self._thrust_z[i] * tz
            for i in range(self.n_motors)
        ]
        self._desaturate(u, self._thrust_z, lower_only=True)
        self._desaturate(u, self._roll)
        self._desaturate(u, self._pitch)
        for i in range(self.n_motors):
            u[i] += self._yaw[i] * y
        self._desaturate(u, self._yaw, hi=1.0 + MINIMUM_YAW_MARGIN)
        self._desaturate(u, self._thrust_z, lower_only=True)
        clipped = tuple(0.0 if v < 0.0 else (1.0 if v > 1.0 else v) for v in u)
        achieved = self._eff[:3] @ np.asarray(clipped) * self._scale[:3]
        un = (r - float(achieved[0]), p - float(achieved[1]), y - float(achieved[2]))
        if un[0] * un[0] + un[1] * un[1] + un[2] * un[2] < 1e-6:
            # torque_setpoint_achieved: no feedback to the rate loop.
            no = (False, False, False)
            return AllocationResult(clipped, un, no, no)
        eps = float(np.finfo(np.float32).eps)
        pos = (un[0] > eps, un[1] > eps, un[2] > eps)
        neg = (un[0] < -eps, un[1] < -eps, un[2] < -eps)
        return AllocationResult(clipped, un, pos, neg)

    def motor_commands(self, actuators: Sequence[float]) -> tuple[float, ...]:
        """The plant's motor commands for actuator values in [0, 1]: idle to full."""
        idle = self.idle
        span = 1.0 - idle
        return tuple(idle + span * a for a in actuators)

    def mix(self, thrust: float, roll: float, pitch: float, yaw: float) -> tuple[float, ...]:
        """Motor commands of an actuator-control setpoint (PX4 <= 1.13's
        ``SET_ACTUATOR_CONTROL_TARGET`` group 0, allocated the same way)."""
        return self.motor_commands(self.allocate((roll, pitch, yaw), thrust).actuators)


class Px4RateLoop:
    """The rate-control path of PX4 v1.16 from a gyro sample to motor commands.

    Owns the angular-velocity filter, :class:`RateControl`, the yaw-torque
    low-pass and the :class:`ControlAllocator`, and carries the allocator's
    saturation back to the integrator on the next sample, as PX4's topics do.

    Parameters
    ----------
    allocator
        The vehicle's allocation.
    gains
        The rate gains (:data:`PX4_V116_RATE_GAINS`).
    yaw_torque_cutoff_hz
        ``MC_YAW_TQ_CUTOFF`` (2 Hz; 0 disables).
    gyro_cutoff_hz, dgyro_cutoff_hz
        ``IMU_GYRO_CUTOFF`` (40 Hz), ``IMU_DGYRO_CUTOFF`` (30 Hz).
    """

    def __init__(
        self,
        allocator: ControlAllocator,
        gains: Sequence[Px4AxisGains] = PX4_V116_RATE_GAINS,
        *,
        yaw_torque_cutoff_hz: float = 2.0,
        gyro_cutoff_hz: float = 40.0,
        dgyro_cutoff_hz: float = 30.0,
    ) -> None:
        self.allocator = allocator
        self.control = RateControl(gains)
        self.filter = AngularVelocityFilter(gyro_cutoff_hz, dgyro_cutoff_hz)
        self.yaw_torque_cutoff_hz = float(yaw_torque_cutoff_hz)
        self._yaw_tq = 0.0
        self.rate_rad_s: Vec3 = (0.0, 0.0, 0.0)
        self.angular_accel_rad_s2: Vec3 = (0.0, 0.0, 0.0)

    def reset(self) -> None:
        """Disarmed: the integrator, the saturation feedback and the yaw low-pass
        forget (the gyro filter runs on, as PX4's sensors module does)."""
        self.control.reset_integral()
        self.control.set_saturation((False,) * 3, (False,) * 3)
        self._yaw_tq = 0.0

    def filter_gyro(self, gyro: Sequence[float], dt_s: float) -> None:
        """Run the angular-velocity filter on a sample (every sample, armed or not)."""
        self.rate_rad_s, self.angular_accel_rad_s2 = self.filter.apply(gyro, dt_s)

    def torque(self, rate_sp: Sequence[float], dt_s: float, *, landed: bool) -> Vec3:
        """Torque setpoint for the rate setpoint (NaN: hold the current rate)."""
        w = self.rate_rad_s
        sp = tuple(rate_sp[i] if math.isfinite(rate_sp[i]) else w[i] for i in range(3))
        tq = self.control.update(w, sp, self.angular_accel_rad_s2, dt_s, landed)
        yaw = tq[2]
        fc = self.yaw_torque_cutoff_hz
        if fc > 0.0 and math.isfinite(yaw):
            # AlphaFilter: starts from 0, as PX4's does at boot.
            alpha = dt_s / (dt_s + 1.0 / (2.0 * math.pi * fc))
            self._yaw_tq += alpha * (yaw - self._yaw_tq)
            yaw = self._yaw_tq
        return (
            tq[0] if math.isfinite(tq[0]) else 0.0,
            tq[1] if math.isfinite(tq[1]) else 0.0,
            yaw if math.isfinite(yaw) else 0.0,
        )

    def allocate(self, torque: Sequence[float], thrust: float) -> AllocationResult:
        """Allocate and keep the saturation for the integrator's next update."""
        res = self.allocator.allocate(torque, thrust)
        self.control.set_saturation(res.saturated_positive, res.saturated_negative)
        return res
