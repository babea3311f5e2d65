"""A 6-DOF-lite multirotor for the outer-loop tests: a point mass under a tilted
thrust, with a first-order body-rate response, a thrust lag and an optional delay.

Not the SITL (``sitl`` is the lab's, and these tests want a plant whose every term
is written down here):

* body rates follow the rate reference through a first-order lag ``rate_tau_s``
  after ``delay_s`` (a rate loop that works, seen from outside);
* the attitude integrates the body rates exactly for rates held over a substep;
* the collective reaches the rotors through a first-order lag ``thrust_tau_s``
  after the same delay, and gives a specific thrust ``g (T / T_hover)^p`` along
  body -z (``p = thrust_exponent``: 1 linearised, 2 rotor speed ~ command);
* ``a = R(q) (0, 0, -f) + (0, 0, g) - drag v + wind``, NED.

Deterministic, plain floats, held inputs, ``substeps`` semi-implicit steps per
control interval.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

from companion.control.quaternion import Quat, Vec3, quat_mul

G = 9.80665


def quat_exp_step(q: Quat, w: Vec3, h: float) -> Quat:
    """``q ⊗ exp(w h / 2)``: the attitude after body rates ``w`` held for ``h``."""
    n = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    a = 0.5 * n * h
    if n < 1e-12:
        dq = (1.0, 0.5 * h * w[0], 0.5 * h * w[1], 0.5 * h * w[2])
    else:
        s = math.sin(a) / n
        dq = (math.cos(a), s * w[0], s * w[1], s * w[2])
    r = quat_mul(q, dq)
    m = math.sqrt(sum(c * c for c in r))
    return (r[0] / m, r[1] / m, r[2] / m, r[3] / m)


@dataclass
class PointMassPlant:
    hover_thrust: float = 0.45
    thrust_exponent: float = 2.0
    rate_tau_s: float = 0.04
    thrust_tau_s: float = 0.03
    delay_s: float = 0.0
    drag_1_s: float = 0.2
    wind_accel_ned: Vec3 = (0.0, 0.0, 0.0)
    substeps: int = 4
    p: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    v: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    q: Quat = (1.0, 0.0, 0.0, 0.0)
    w: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    thrust: float = -1.0  # < 0: start at the hover thrust
    t: float = 0.0

    def __post_init__(self) -> None:
        if self.thrust < 0.0:
            self.thrust = self.hover_thrust
        self._queue: deque[tuple[Vec3, float]] = deque()

    def step(self, dt: float, rate_ref: Vec3, thrust_cmd: float) -> None:
        """Advance by ``dt`` with the commands held (after the delay)."""
        n_delay = round(self.delay_s / dt)
        self._queue.append((rate_ref, thrust_cmd))
        if len(self._queue) > n_delay:
            rate_ref, thrust_cmd = self._queue.popleft()
        else:
            rate_ref, thrust_cmd = (0.0, 0.0, 0.0), self.hover_thrust
        h = dt / self.substeps
        kw = -math.expm1(-h / self.rate_tau_s)
        kt = -math.expm1(-h / self.thrust_tau_s)
        for _ in range(self.substeps):
            w = self.w
            for i in range(3):
                w[i] += (rate_ref[i] - w[i]) * kw
            self.q = quat_exp_step(self.q, (w[0], w[1], w[2]), h)
            self.thrust += (thrust_cmd - self.thrust) * kt
            f = G * (max(self.thrust, 0.0) / self.hover_thrust) ** self.thrust_exponent
            qw, qx, qy, qz = self.q
            bz = (
                2.0 * (qx * qz + qw * qy),
                2.0 * (qy * qz - qw * qx),
                1.0 - 2.0 * (qx * qx + qy * qy),
            )
            for i in range(3):
                a = -f * bz[i] + (G if i == 2 else 0.0) - self.drag_1_s * self.v[i]
                a += self.wind_accel_ned[i]
                self.v[i] += a * h
                self.p[i] += self.v[i] * h
            self.t += h
