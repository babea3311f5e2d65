r"""What the autopilot's estimator streams: the truth with an EKF's errors, lag and rate.

The outer loops fly on ``ATTITUDE_QUATERNION`` and ``LOCAL_POSITION_NED``, not on
the true state. This model turns the plant's state into those two streams:

* each stream is sampled on its own fixed grid (attitude at the IMU rate,
  position and velocity at 50 Hz), stamped with the time it was taken, and handed
  out ``latency_s`` later (as :class:`sitl.imu.Imu` does);
* each sample is the truth plus an error. The errors of an EKF are not white:
  they are the slowly wandering residuals of the sensors it fuses (a GPS's
  multipath, a baro's drift, an accelerometer's bias in the tilt). Each error
  component is a first-order Gauss-Markov process (a discrete Ornstein-Uhlenbeck
  process, exact at any step),

  .. math::

      e_{k+1} = a\,e_k + \sigma\sqrt{1 - a^2}\,n_k, \qquad a = e^{-\Delta t/\tau},
      \qquad e_0 \sim \mathcal N(0, \sigma^2),

  stationary from the first sample, with standard deviation :math:`\sigma` and
  correlation time :math:`\tau`.

The attitude error is a small rotation in the world (NED) frame, its vector
:math:`(e_N, e_E, e_D)` (rad): the first two tilt the estimate, the third turns
its heading; :math:`q_{est} = \exp(e/2) \otimes q_{true}`. It is a Gauss-Markov
process plus a constant drawn once per flight (the real EKF2's tilt was off by up
to 2 deg on average, a different amount in each flight).

The position and velocity errors of an EKF are one error seen twice: when the
estimated position is off one way, the estimated velocity is off the same way.
Per NED axis (:class:`PositionVelocityError`), one unit Gauss-Markov driver
:math:`z` (``position_tau_s``) makes both: the position error is :math:`z`
low-passed over ``position_smoothing_s`` (an EKF's position moves smoothly; it
does not jump with each GNSS fix) and scaled to ``position_sigma_m``; the
velocity error is ``shared`` of :math:`z` and the rest a process of its own
(``velocity_tau_s``), scaled to ``velocity_sigma_m_s``. Their correlation is
``shared`` :math:`\sqrt{\tau/(\tau + \tau_f)}`.

The figures (:data:`EKF_GPS`), 1 sigma, are set from the real PX4 v1.16 EKF2
flying the real SIH quadrotor in a hover, its estimate against SIH's ground truth
(``docs/research/estimator.md`` gives the measurement; every spread and
correlation time of the position and velocity errors below comes within a
factor of 2 of it, most within 1.25):

==============  ====================  ==================  ===========================
what            sigma                 tau                 the real EKF2 (median of 3)
==============  ====================  ==================  ===========================
roll, pitch     0.7 deg, and 1 deg    3 s                 0.43-0.91 deg, 2.8-3.2 s;
                drawn once                                means -1.5 to 1.0 deg
heading         2.5 deg               60 s                2.7 deg, 29 s over 150 s
north, east     0.15 m                3.5 s, smoothed 1 s 0.12 / 0.18 m, 3.5-3.7 s
down            0.45 m                6.5 s, smoothed     0.39 m, 6.6 s
                                      1.5 s
velocity N, E   0.2 m/s, 0.95 shared  3 s                 0.16 / 0.27 m/s, 3.0-3.1 s
velocity D      0.19 m/s, 0.85 shared 4.5 s               0.19 m/s, 4.6 s
==============  ====================  ==================  ===========================

Correlation of the position and velocity errors: 0.84, 0.84, 0.76 (the real
0.85, 0.90, 0.74). The real heading was also off by 14-17 deg in every run, a
constant of SIH's magnetometer model as far as was looked: not modelled. The
real position estimate correlated best with the truth 0.23-0.30 s earlier; the
model's lag is its stream's (below), the cause of the real one not established.

Rates and lags: attitude at the IMU rate (``ATTITUDE_QUATERNION`` is IMU-based in
the SITL's faces; a companion may ask it at that rate), 10 ms late (the output
predictor is current, so this is the stream and the link); position and velocity
at 50 Hz (``MAV_CMD_SET_MESSAGE_INTERVAL``; the PX4 face's default is 10 Hz),
30 ms late (the output predictor's residual lag, plus the stream).

Seeding: :func:`estimator_seed_sequence` gives a stream independent of the
plant's, the IMU's, the wind's, the pilot's and the link's.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from sitl.frames import quat_mul
from sitl.physics import VehicleState

__all__ = [
    "EKF_GPS",
    "PERFECT",
    "AttitudeEstimate",
    "EstimatorModel",
    "EstimatorSpec",
    "GaussMarkov",
    "PositionEstimate",
    "PositionVelocityError",
    "estimator_seed_sequence",
    "rotation_vector_quat",
]

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]

_SEED_CHILD = 5
"""The estimator's spawn key under a flight seed (the link's is 4: sitl.link_model)."""


@dataclass(frozen=True)
class EstimatorSpec:
    """The estimator's errors, rates and lags (module docstring: the figures)."""

    attitude_sigma_rad: Vec3 = (math.radians(0.7), math.radians(0.7), math.radians(2.5))
    """Attitude error, 1 sigma, about north, east, down (tilt, tilt, heading), rad."""
    attitude_tau_s: Vec3 = (3.0, 3.0, 60.0)
    attitude_bias_sigma_rad: Vec3 = (math.radians(1.0), math.radians(1.0), 0.0)
    """A constant attitude error drawn once per flight, 1 sigma, rad."""
    position_sigma_m: Vec3 = (0.15, 0.15, 0.45)
    position_tau_s: Vec3 = (3.5, 3.5, 6.5)
    """The correlation time of the error's driver (shared with the velocity's)."""
    position_smoothing_s: Vec3 = (1.0, 1.0, 1.5)
    """The position error is its driver low-passed with this time constant (0: the
    driver itself)."""
    velocity_sigma_m_s: Vec3 = (0.2, 0.2, 0.19)
    velocity_tau_s: Vec3 = (3.0, 3.0, 4.5)
    """The correlation time of the velocity error's own part."""
    shared: Vec3 = (0.95, 0.95, 0.85)
    """How much of the velocity error is the position error's driver (a correlation,
    0: independent errors)."""
    attitude_rate_hz: float | None = None
    """``None``: at the IMU rate (one estimate per IMU sample, the caller's rate)."""
    attitude_latency_s: float = 0.010
    position_rate_hz: float = 50.0
    position_latency_s: float = 0.030

    def __post_init__(self) -> None:
        for name, sig, tau in (
            ("attitude", self.attitude_sigma_rad, self.attitude_tau_s),
            ("position", self.position_sigma_m, self.position_tau_s),
            ("velocity", self.velocity_sigma_m_s, self.velocity_tau_s),
        ):
            if not all(s >= 0.0 and math.isfinite(s) for s in sig):
                raise ValueError(f"{name} sigma: expected finite values >= 0, got {sig!r}")
            if not all(t > 0.0 and math.isfinite(t) for t in tau):
                raise ValueError(f"{name}_tau_s: expected finite values > 0 s, got {tau!r}")
        if not all(b >= 0.0 and math.isfinite(b) for b in self.attitude_bias_sigma_rad):
            raise ValueError(
                f"attitude_bias_sigma_rad: expected finite values >= 0, got "
                f"{self.attitude_bias_sigma_rad!r}"
            )
        if not all(f >= 0.0 and math.isfinite(f) for f in self.position_smoothing_s):
            raise ValueError(
                f"position_smoothing_s: expected finite values >= 0 s, got "
                f"{self.position_smoothing_s!r}"
            )
        if not all(0.0 <= r <= 1.0 for r in self.shared):
            raise ValueError(f"shared: expected values in [0, 1], got {self.shared!r}")
        for name in ("attitude_latency_s", "position_latency_s"):
            v = getattr(self, name)
            if not (0.0 <= v <= 1.0):
                raise ValueError(f"{name}: expected 0-1 s, got {v!r}")
        for name in ("attitude_rate_hz", "position_rate_hz"):
            v = getattr(self, name)
            if v is not None and not (0.0 < v <= 10000.0):
                raise ValueError(f"{name}: expected 0-10000 Hz, got {v!r}")


EKF_GPS = EstimatorSpec()
"""An EKF with GPS, baro and magnetometer (module docstring)."""

PERFECT = EstimatorSpec(
    attitude_sigma_rad=(0.0, 0.0, 0.0),
    attitude_bias_sigma_rad=(0.0, 0.0, 0.0),
    position_sigma_m=(0.0, 0.0, 0.0),
    velocity_sigma_m_s=(0.0, 0.0, 0.0),
    attitude_latency_s=0.0,
    position_latency_s=0.0,
)
"""The truth, at 50 Hz for position (for comparisons)."""


def estimator_seed_sequence(seed: int) -> np.random.SeedSequence:
    """The estimator's seed sequence for a flight seed."""
    return np.random.SeedSequence(seed, spawn_key=(_SEED_CHILD,))


class GaussMarkov:
    """Three independent first-order Gauss-Markov processes (module docstring).

    ``step(dt_s)`` advances them and returns the new values; the first call
    returns the stationary draw ``e_0``.
    """

    def __init__(self, sigma: Vec3, tau_s: Vec3, rng: np.random.Generator) -> None:
        self._sigma = sigma
        self._tau = tau_s
        self._rng = rng
        self._e: list[float] | None = None
        self._dt = -1.0
        self._a = (0.0, 0.0, 0.0)
        self._b = (0.0, 0.0, 0.0)

    def step(self, dt_s: float) -> Vec3:
        n = self._rng.standard_normal(3)
        s = self._sigma
        if self._e is None:
            e = [s[i] * float(n[i]) for i in range(3)]
        else:
            if dt_s != self._dt:
                self._dt = dt_s
                a = tuple(math.exp(-dt_s / t) for t in self._tau)
                self._a = (a[0], a[1], a[2])
                b = tuple(s[i] * math.sqrt(1.0 - a[i] * a[i]) for i in range(3))
                self._b = (b[0], b[1], b[2])
            p = self._e
            e = [self._a[i] * p[i] + self._b[i] * float(n[i]) for i in range(3)]
        self._e = e
        return (e[0], e[1], e[2])


class PositionVelocityError:
    """The position and velocity errors of one estimate (module docstring): per axis,
    a unit Gauss-Markov driver ``z`` (``position_tau_s``); the position error is
    ``z`` low-passed (``position_smoothing_s``) and scaled to its sigma; the velocity
    error is ``shared`` of ``z`` and the rest its own unit process
    (``velocity_tau_s``), scaled to its sigma. Stationary from the first step."""

    def __init__(self, spec: EstimatorSpec, rng: np.random.Generator) -> None:
        r_drive, r_own, r_smooth = rng.spawn(3)
        one = (1.0, 1.0, 1.0)
        self._z = GaussMarkov(one, spec.position_tau_s, r_drive)
        self._w = GaussMarkov(one, spec.velocity_tau_s, r_own)
        self._rng = r_smooth
        self._spec = spec
        tau, tf = spec.position_tau_s, spec.position_smoothing_s
        # A first-order low-pass of a unit OU process: var = cov(z, s) = tau / (tau + tf).
        self._var = tuple(t / (t + f) for t, f in zip(tau, tf, strict=True))
        self._s: list[float] | None = None
        self._dt = -1.0
        self._k = (0.0, 0.0, 0.0)

    def step(self, dt_s: float) -> tuple[Vec3, Vec3]:
        sp = self._spec
        z, w = self._z.step(dt_s), self._w.step(dt_s)
        var = self._var
        if self._s is None:
            n = self._rng.standard_normal(3)
            s = [var[i] * z[i] + math.sqrt(max(0.0, var[i] - var[i] ** 2)) * float(n[i])
                 for i in range(3)]  # fmt: skip
        else:
            if dt_s != self._dt:
                self._dt = dt_s
                tf = sp.position_smoothing_s
                k = tuple(1.0 if f == 0.0 else 1.0 - math.exp(-dt_s / f) for f in tf)
                self._k = (k[0], k[1], k[2])
            s = [p + self._k[i] * (z[i] - p) for i, p in enumerate(self._s)]
        self._s = s
        ps, vs, r = sp.position_sigma_m, sp.velocity_sigma_m_s, sp.shared
        ep = tuple(ps[i] * s[i] / math.sqrt(var[i]) for i in range(3))
        ev = tuple(vs[i] * (r[i] * z[i] + math.sqrt(1.0 - r[i] * r[i]) * w[i]) for i in range(3))
        return (ep[0], ep[1], ep[2]), (ev[0], ev[1], ev[2])


def rotation_vector_quat(v: Vec3) -> Quat:
    """The unit quaternion of rotation vector ``v`` (axis times angle, rad): ``exp(v/2)``."""
    angle = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    if angle < 1e-12:
        return (1.0, 0.5 * v[0], 0.5 * v[1], 0.5 * v[2])
    s = math.sin(0.5 * angle) / angle
    return (math.cos(0.5 * angle), s * v[0], s * v[1], s * v[2])


@dataclass(frozen=True)
class AttitudeEstimate:
    """One ``ATTITUDE_QUATERNION`` as the model streams it."""

    time_s: float
    """When the state it estimates was (s), not when delivered."""
    q_wxyz: Quat


@dataclass(frozen=True)
class PositionEstimate:
    """One ``LOCAL_POSITION_NED`` as the model streams it."""

    time_s: float
    position_ned_m: Vec3
    velocity_ned_m_s: Vec3


class EstimatorModel:
    """The truth to the estimator's two streams (module docstring).

    Parameters
    ----------
    spec
        Errors, rates, lags.
    rng
        Source of every error (:func:`estimator_seed_sequence`).
    dt_s
        The physics step between calls to :meth:`update`, s.
    imu_rate_hz
        The IMU's rate: the attitude stream's when ``spec.attitude_rate_hz`` is None.
    """

    def __init__(
        self, spec: EstimatorSpec, *, rng: np.random.Generator, dt_s: float, imu_rate_hz: float
    ) -> None:
        if not (dt_s > 0.0 and math.isfinite(dt_s)):
            raise ValueError(f"dt_s: expected a finite step > 0 s, got {dt_s!r}")
        self.spec = spec
        att_rate = spec.attitude_rate_hz if spec.attitude_rate_hz is not None else imu_rate_hz
        self.attitude_period_s = 1.0 / att_rate
        self.position_period_s = 1.0 / spec.position_rate_hz
        # One generator each, so the attitude rate does not shift the position's numbers.
        r_att, r_pos, r_bias = rng.spawn(3)
        self._att_err = GaussMarkov(spec.attitude_sigma_rad, spec.attitude_tau_s, r_att)
        self._pos_vel_err = PositionVelocityError(spec, r_pos)
        b = r_bias.standard_normal(3) * np.asarray(spec.attitude_bias_sigma_rad)
        self.attitude_bias_rad: Vec3 = (float(b[0]), float(b[1]), float(b[2]))
        """This flight's constant attitude error (about north, east, down), rad."""
        self._eps_s = 0.5 * dt_s
        self._next_att: float | None = None
        self._next_pos: float | None = None
        self._att_q: deque[AttitudeEstimate] = deque()
        self._pos_q: deque[PositionEstimate] = deque()
        self.attitude: AttitudeEstimate | None = None
        """The newest attitude estimate delivered (None before the first)."""
        self.position: PositionEstimate | None = None
        """The newest position estimate delivered (None before the first)."""

    def _due(self, t_s: float, nxt: float | None, period: float) -> tuple[bool, float | None]:
        if nxt is not None and t_s < nxt - self._eps_s:
            return False, nxt
        new = (t_s if nxt is None else nxt) + period
        while new <= t_s + self._eps_s:
            new += period
        return True, new

    def update(self, state: VehicleState) -> tuple[bool, bool]:
        """Feed the true state; returns whether a new attitude / position estimate
        was delivered (then in :attr:`attitude` / :attr:`position`)."""
        t = state.t_s
        sp = self.spec
        due, self._next_att = self._due(t, self._next_att, self.attitude_period_s)
        if due:
            e = self._att_err.step(self.attitude_period_s)
            b = self.attitude_bias_rad
            e = (e[0] + b[0], e[1] + b[1], e[2] + b[2])
            q = quat_mul(rotation_vector_quat(e), state.q_wxyz)
            self._att_q.append(AttitudeEstimate(t, q))
        due, self._next_pos = self._due(t, self._next_pos, self.position_period_s)
        if due:
            ep, ev = self._pos_vel_err.step(self.position_period_s)
            p, v = state.pos_ned_m, state.vel_ned_m_s
            self._pos_q.append(
                PositionEstimate(
                    t,
                    (p[0] + ep[0], p[1] + ep[1], p[2] + ep[2]),
                    (v[0] + ev[0], v[1] + ev[1], v[2] + ev[2]),
                )
            )
        new_att = new_pos = False
        aq, pq = self._att_q, self._pos_q
        while aq and aq[0].time_s + sp.attitude_latency_s <= t + self._eps_s:
            self.attitude = aq.popleft()
            new_att = True
        while pq and pq[0].time_s + sp.position_latency_s <= t + self._eps_s:
            self.position = pq.popleft()
            new_pos = True
        return new_att, new_pos

    def begin(self, state: VehicleState) -> None:
        """Start the streams on ``state``: its first samples, taken now, are
        delivered at once (no lag) in :attr:`attitude` and :attr:`position`.

        For a model started afresh while the vehicle sits still (the SITL's, at a
        flight's start on arming): its stream goes on without a gap, and without
        the previous model's last estimate, so what follows depends only on the
        seed and the state, not on when the flight started. Call it instead of
        the first :meth:`update`; later samples keep their lag.
        """
        if self._next_att is not None or self._next_pos is not None:
            raise RuntimeError("begin() starts a new model: call it before any update()")
        self.update(state)
        if self._att_q:
            self.attitude = self._att_q.pop()
            self._att_q.clear()
        if self._pos_q:
            self.position = self._pos_q.pop()
            self._pos_q.clear()
