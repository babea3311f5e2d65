r"""The reference prefilter: the pilot's rate command, smoothed, and its derivative.

The iPD (the paper's equation (ipd)) needs :math:`\ddot y_r`, the derivative
of the pilot's rate :math:`\dot y_r = \omega_r`. A stick moves in steps (one
per RC frame), so differentiating it gives spikes. Instead the rate goes
through a critically damped second-order filter (natural frequency
``prefilter_hz``, not in the paper), whose state is the filtered rate and its
derivative. Discretised exactly for a held input, it is unconditionally stable
for any dt. Without a prefilter the controller takes :math:`\ddot y_r` as the
backward difference of the raw reference (:class:`companion.control.mfc.MfcController`).
"""

from __future__ import annotations

import math

__all__ = ["ReferencePrefilter"]

Vec3 = tuple[float, float, float]

_DT_REL_TOL = 1e-3
"""As :data:`companion.control.identifier.DT_REL_TOL`: the exponential computed for
one dt serves every dt within this relative distance of it."""


class ReferencePrefilter:
    r"""Critically damped 2nd-order filters giving a smooth reference and its derivative.

    One filter per axis, sharing the natural frequency
    :math:`\omega_n = 2 \pi f_c`:
    :math:`\ddot x = \omega_n^2 (r - x) - 2 \omega_n \dot x`, discretised
    exactly for ``r`` held over the step (unconditionally stable for any dt):
    with :math:`z = x - r` and :math:`c = \dot z_0 + \omega_n z_0`,
    :math:`z(t) = (z_0 + c t) e^{-\omega_n t}` and
    :math:`\dot z(t) = (\dot z_0 - \omega_n c t) e^{-\omega_n t}`.
    The first sample initialises the output to the input, at rest.
    """

    __slots__ = ("_dt_last", "_ex", "_primed", "_v0", "_v1", "_v2", "_wn", "_x0", "_x1", "_x2")

    def __init__(self, cutoff_hz: float) -> None:
        if not (math.isfinite(cutoff_hz) and cutoff_hz > 0.0):
            raise ValueError(f"cutoff_hz must be > 0, got {cutoff_hz!r}")
        self._wn = 2.0 * math.pi * cutoff_hz
        self._dt_last = -1.0
        self._ex = 0.0
        self.reset()

    def reset(self) -> None:
        self._x0 = self._x1 = self._x2 = 0.0
        self._v0 = self._v1 = self._v2 = 0.0
        self._primed = False

    def update(self, dt_s: float, target: Vec3) -> tuple[Vec3, Vec3]:
        """Advance by ``dt_s`` toward ``target``; returns (reference, its derivative)."""
        r0, r1, r2, d0, d1, d2 = self.step(dt_s, target[0], target[1], target[2])
        return (r0, r1, r2), (d0, d1, d2)

    @property
    def rate(self) -> Vec3:
        return (self._x0, self._x1, self._x2)

    @property
    def rate_dot(self) -> Vec3:
        return (self._v0, self._v1, self._v2)

    def step(
        self, dt_s: float, t0: float, t1: float, t2: float
    ) -> tuple[float, float, float, float, float, float]:
        """:meth:`update` with flat arguments and result, for the per-sample path."""
        if not self._primed:
            self._primed = True
            self._x0, self._x1, self._x2 = t0, t1, t2
            self._v0 = self._v1 = self._v2 = 0.0
            return t0, t1, t2, 0.0, 0.0, 0.0
        wn = self._wn
        if abs(dt_s - self._dt_last) > _DT_REL_TOL * dt_s:  # the loop usually runs at a fixed rate
            self._dt_last = dt_s
            self._ex = math.exp(-wn * dt_s)
        ex = self._ex
        v0 = self._v0
        v1 = self._v1
        v2 = self._v2
        # Unrolled over the three axes: this runs once per IMU sample.
        z0 = self._x0 - t0
        z1 = self._x1 - t1
        z2 = self._x2 - t2
        c0 = v0 + wn * z0
        c1 = v1 + wn * z1
        c2 = v2 + wn * z2
        wdt = wn * dt_s
        self._x0 = x0 = t0 + (z0 + c0 * dt_s) * ex
        self._x1 = x1 = t1 + (z1 + c1 * dt_s) * ex
        self._x2 = x2 = t2 + (z2 + c2 * dt_s) * ex
        self._v0 = v0 = (v0 - wdt * c0) * ex
        self._v1 = v1 = (v1 - wdt * c1) * ex
        self._v2 = v2 = (v2 - wdt * c2) * ex
        return x0, x1, x2, v0, v1, v2
