"""IMU model: gyro noise, bias drift, saturation, latency and the paper's filter.

For each sample, taken every ``1 / rate_hz`` seconds of simulation time, the gyro
reads

.. math::

    \\omega_m = \\mathrm{sat}_{\\pm\\omega_{max}}\\left(\\omega + b + \\sigma_w n\\right),
    \\qquad \\sigma_w = N_g \\sqrt{f_s},

    b_{k+1} = b_k + N_b \\sqrt{1/f_s}\\, n_b,

with ``N_g`` the white-noise density (rad/s/sqrt(Hz)), ``f_s`` the sample rate,
``N_b`` the bias random-walk density (rad/s²/sqrt(Hz)), ``n, n_b`` independent unit
normals and ``omega_max`` the full scale. The paper's first-stage (complementary)
filter then gives ``y_k = w omega_m,k + (1 - w) y_{k-1}`` (``w = 1`` disables it;
``y_0`` is the first measurement, so there is no start-up transient).

The sample is handed out ``latency_s`` after it was taken, stamped with the time it
was taken. The accelerometer is passed through noise-free and unfiltered: the
profile schema (:class:`companion.profile.ImuModel`) has no accelerometer terms.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from companion.profile import ImuModel

__all__ = ["Imu", "ImuSample"]

_log = logging.getLogger(__name__)

_BLOCK = 6 * 1024  # normal deviates drawn per generator call (see sitl.wind)


@dataclass(frozen=True)
class ImuSample:
    """One IMU sample.

    Attributes
    ----------
    time_s : float
        Simulation time at which the sample was measured (s), not when delivered.
    gyro_frd_rad_s : tuple of 3 float
        Body rates (FRD, rad/s) after noise, bias, saturation and filter.
    accel_frd_m_s2 : tuple of 3 float
        Specific force (FRD, m/s²), what an accelerometer reads (level at rest:
        ``(0, 0, -g)``).
    """

    time_s: float
    gyro_frd_rad_s: tuple[float, float, float]
    accel_frd_m_s2: tuple[float, float, float]


class Imu:
    """Gyro and accelerometer sampled from the physics.

    Parameters
    ----------
    model : ImuModel
        Rate, noise, range, latency and filter weight from the vehicle profile.
    rng : numpy.random.Generator
        Source of all sensor noise.
    dt_s : float
        Physics step (s) between calls to :meth:`update`. A ``rate_hz`` above
        ``1 / dt_s`` cannot be honoured; at most one sample is taken per call.
    """

    def __init__(self, model: ImuModel, *, rng: np.random.Generator, dt_s: float) -> None:
        if not (dt_s > 0.0 and math.isfinite(dt_s)):
            raise ValueError(f"dt_s: expected a finite step > 0 s, got {dt_s!r}")
        self.model = model
        self._rng = rng
        self.dt_s = float(dt_s)
        self.period_s = 1.0 / model.rate_hz
        if self.period_s < self.dt_s * (1.0 - 1e-9):
            _log.warning(
                "IMU rate %.1f Hz exceeds the physics rate %.1f Hz; sampling once per step",
                model.rate_hz,
                1.0 / self.dt_s,
            )
        self._sigma_white = model.gyro_noise_density_rad_s_sqrt_hz * math.sqrt(model.rate_hz)
        self._sigma_bias_step = model.gyro_bias_random_walk_rad_s2_sqrt_hz * math.sqrt(
            self.period_s
        )
        self._range_rad_s = math.radians(model.gyro_range_deg_s)
        self._w = float(model.first_stage_filter_weight)
        self._bias = [0.0, 0.0, 0.0]
        self._filtered: list[float] | None = None
        self._next_due_s: float | None = None
        self._queue: deque[ImuSample] = deque()
        self._noise: list[float] = []
        self._i_noise = 0
        # Half a physics step of slack absorbs rounding in accumulated times.
        self._eps_s = 0.5 * self.dt_s

    @property
    def bias_frd_rad_s(self) -> tuple[float, float, float]:
        """Current gyro bias (rad/s)."""
        return (self._bias[0], self._bias[1], self._bias[2])

    def _normal(self) -> float:
        if self._i_noise >= len(self._noise):
            self._noise = self._rng.standard_normal(_BLOCK).tolist()
            self._i_noise = 0
        n = self._noise[self._i_noise]
        self._i_noise += 1
        return n

    def _measure(self, t_s: float, rate: Sequence[float], force: Sequence[float]) -> ImuSample:
        sw = self._sigma_white
        sb = self._sigma_bias_step
        lim = self._range_rad_s
        bias = self._bias
        raw = [0.0, 0.0, 0.0]
        for i in range(3):
            v = float(rate[i]) + bias[i]
            if sw > 0.0:
                v += sw * self._normal()
            # The sensor clips its own reading, noise included.
            raw[i] = min(lim, max(-lim, v))
            if sb > 0.0:
                bias[i] += sb * self._normal()
        prev = self._filtered
        if prev is None or self._w >= 1.0:
            out = raw
        else:
            w = self._w
            out = [w * raw[i] + (1.0 - w) * prev[i] for i in range(3)]
        self._filtered = out
        return ImuSample(
            time_s=float(t_s),
            gyro_frd_rad_s=(out[0], out[1], out[2]),
            accel_frd_m_s2=(float(force[0]), float(force[1]), float(force[2])),
        )

    def update(
        self,
        t_s: float,
        rate_frd_rad_s: Sequence[float],
        specific_force_frd_m_s2: Sequence[float],
    ) -> ImuSample | None:
        """Feed the true state at ``t_s``; return a sample when one is delivered.

        Parameters
        ----------
        t_s : float
            Simulation time (s) of the physics state passed in.
        rate_frd_rad_s : sequence of 3 float
            True body rates (FRD, rad/s).
        specific_force_frd_m_s2 : sequence of 3 float
            True specific force (FRD, m/s²).

        Returns
        -------
        ImuSample or None
            The oldest sample whose ``time_s + latency_s <= t_s``, if any.
        """
        due = self._next_due_s
        if due is None or t_s >= due - self._eps_s:
            self._queue.append(self._measure(t_s, rate_frd_rad_s, specific_force_frd_m_s2))
            # Keep a fixed sample grid; skip missed slots after a jump in time.
            nxt = (t_s if due is None else due) + self.period_s
            while nxt <= t_s + self._eps_s:
                nxt += self.period_s
            self._next_due_s = nxt
        q = self._queue
        if q and q[0].time_s + self.model.latency_s <= t_s + self._eps_s:
            return q.popleft()
        return None
