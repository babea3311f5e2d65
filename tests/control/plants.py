"""Synthetic plants and small helpers shared by the control-core tests.

Everything here is deterministic: randomness comes from a seeded
``np.random.Generator`` passed in by the test.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.control import (
    IntelligentController,
    MfcAxisGains,
    MfcController,
    Mixer,
    PidController,
)
from companion.profile import VehicleProfile, load_profile

ROOT = Path(__file__).resolve().parents[2]
F450 = ROOT / "vehicle_profiles" / "f450.yaml"

# PX4 quad-X output order, as in vehicle_profiles/f450.yaml:
# 1 front-right CCW, 2 rear-left CCW, 3 front-left CW, 4 rear-right CW.
QUAD_X_POSITIONS = ((1.0, 1.0), (-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0))
QUAD_X_SPINS = ("ccw", "ccw", "cw", "cw")


@functools.lru_cache(maxsize=1)
def f450_profile() -> VehicleProfile:
    return load_profile(F450)  # frozen model: safe to share


def f450_mixer() -> Mixer:
    """The geometry mixer of the shipped F450 profile (idle 0.05)."""
    from companion.config import build_mixer

    return build_mixer(f450_profile())


def quad_x_mixer(idle: float = 0.0) -> Mixer:
    return Mixer.from_geometry(QUAD_X_POSITIONS, QUAD_X_SPINS, idle=idle)


def torques_from_motors(mixer: Mixer, motors: tuple[float, ...]) -> np.ndarray:
    """Least-squares inverse of ``motor_i = t + 0.5*(R_i r + P_i p + Y_i y)``.

    Returns (thrust, roll, pitch, yaw).
    """
    r, p, y = (np.asarray(f) for f in mixer.factors())
    A = np.column_stack([np.ones_like(r), 0.5 * r, 0.5 * p, 0.5 * y])
    sol, *_ = np.linalg.lstsq(A, np.asarray(motors, dtype=float), rcond=None)
    return np.asarray(sol)


def timestamps_dt(rate_hz: float, n: int) -> np.ndarray:
    """dt as a real loop sees it: differences of sample timestamps ``k / rate_hz``."""
    t = np.arange(n + 1) / rate_hz
    return np.diff(t)


# ---------------------------------------------------------------------------
# Closed loop of one IntelligentController on a scalar plant.


@dataclass
class LoopResult:
    t: np.ndarray
    """Time since the initial error was set, s (first entry = one sample)."""
    e: np.ndarray
    """The controller's error e = y - y_r after each update, rad."""
    e_dot: np.ndarray
    u: np.ndarray


def run_axis_loop(
    gains: MfcAxisGains,
    *,
    b: float,
    c: float,
    disturbance: Callable[[float], float],
    ref_rate: Callable[[float], float],
    ref_rate_dot: Callable[[float], float],
    dt: float,
    warmup_s: float,
    duration_s: float,
    e0: float,
) -> LoopResult:
    """Run ``IntelligentController`` on a plant with the input held over each sample.

    ``order = 1`` (iP): first-order plant ``y' = -c*y + d(t) + b*u``, the gyro
    reads ``y'`` at the end of the interval.

    ``order = 2`` (iPD): second-order plant ``w' = -c*w + d(t) + b*u`` with
    ``w = y'``, the gyro reads ``w``.

    Integrated with RK4 on each interval. After ``warmup_s`` (estimator window
    filled, tracking settled) the controller's error is set to ``e0`` through
    its public attribute, and the run continues for ``duration_s``.
    """
    ctrl = IntelligentController(gains, command_full_scale_us=500.0)
    order = gains.order
    u = 0.0

    def f(t: float, s: float) -> float:
        return -c * s + disturbance(t) + b * u

    s = 0.0  # y for order 1, w for order 2
    t = 0.0
    n_warm = round(warmup_s / dt)
    n = n_warm + round(duration_s / dt)
    ts, es, eds, us = [], [], [], []
    t0 = 0.0
    for k in range(n):
        k1 = f(t, s)
        k2 = f(t + dt / 2, s + dt / 2 * k1)
        k3 = f(t + dt / 2, s + dt / 2 * k2)
        k4 = f(t + dt, s + dt * k3)
        s += dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        t += dt
        rate = f(t, s) if order == 1 else s
        if k == n_warm:
            ctrl.e = e0
            t0 = t - dt
        u = ctrl.update(dt, rate, ref_rate(t), ref_rate_dot(t))
        if k >= n_warm:
            ts.append(t - t0)
            es.append(ctrl.e)
            eds.append(ctrl.e_dot)
            us.append(u)
    return LoopResult(np.array(ts), np.array(es), np.array(eds), np.array(us))


# ---------------------------------------------------------------------------
# Three-axis rate plant driven through a mixer, for the assembled controllers.


@dataclass
class RatePlant3:
    """``w_i' = b_i * torque_i - drag_i * w_i + d_i(t)``, torques from the motors.

    The motors follow their commands through a first-order lag ``tau_s``
    (exact for a held command); the torques are recovered from the motor
    outputs with the mixer's own factors, so whatever the mixer realises is
    what the plant feels.
    """

    mixer: Mixer
    b: tuple[float, float, float]
    drag: tuple[float, float, float]
    disturbance: Callable[[float], tuple[float, float, float]]
    tau_s: float = 0.021
    substeps: int = 4

    def __post_init__(self) -> None:
        r, p, y = self.mixer.factors()
        # Orthogonal factors (quad-X): torque_a = sum(f_a,i * m_i) / (0.5 * |f_a|^2).
        self._rows = [(f, 0.5 * sum(x * x for x in f)) for f in (r, p, y)]
        n = self.mixer.n_motors
        self.motors = [0.5] * n
        self.w = [0.0, 0.0, 0.0]
        self.t = 0.0

    def step(self, dt: float, command: tuple[float, ...]) -> tuple[float, float, float]:
        h = dt / self.substeps
        a = math.exp(-h / self.tau_s) if self.tau_s > 0 else 0.0
        w = self.w
        for _ in range(self.substeps):
            self.motors = [c + (m - c) * a for m, c in zip(self.motors, command)]
            d = self.disturbance(self.t)
            for i, (f, norm) in enumerate(self._rows):
                tq = sum(fi * mi for fi, mi in zip(f, self.motors)) / norm
                w[i] += h * (self.b[i] * tq - self.drag[i] * w[i] + d[i])
            self.t += h
        return (w[0], w[1], w[2])


def run_rate_loop(
    ctrl: MfcController | PidController,
    plant: RatePlant3,
    ref: Callable[[float], tuple[float, float, float]],
    *,
    dt: float,
    duration_s: float,
    thrust: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Close the loop; returns (times, rate error w - w_ref per axis)."""
    n = round(duration_s / dt)
    command: tuple[float, ...] = tuple(plant.motors)
    ts = np.empty(n)
    err = np.empty((n, 3))
    for k in range(n):
        w = plant.step(dt, command)
        r = ref(plant.t)
        out = ctrl.update(dt, w, r, thrust)
        command = out.motors
        ts[k] = plant.t
        err[k] = (w[0] - r[0], w[1] - r[1], w[2] - r[2])
    return ts, err
