"""Speed of the plant: how many simulated seconds per wall-clock second.

``python -c "from sitl._bench import bench_sitl; print(bench_sitl())"``. Reference
figures measured for this project on a 2-core machine (plain-float RK4 ~30x real
time at 1 kHz; RotorPy 0.86x) are in ``docs/research/profiles.md#plant-speed``.
"""

from __future__ import annotations

import importlib.util
import logging
import math
import time
from pathlib import Path

import numpy as np

from companion.profile import VehicleProfile, load_profile
from sitl.batch import BatchQuadrotor
from sitl.physics import Quadrotor
from sitl.rotors import hover_motor_command
from sitl.vehicle_params import GRAVITY_M_S2

__all__ = ["bench_sitl"]

_log = logging.getLogger(__name__)

_PROFILE = Path(__file__).resolve().parent.parent / "vehicle_profiles" / "f450.yaml"


def _hover_speed_rad_s(profile: VehicleProfile) -> float:
    ph = profile.physics
    return math.sqrt(ph.mass_kg * GRAVITY_M_S2 / (profile.n_motors * ph.kf_n_per_rad_s2))


def _bench_scalar(profile: VehicleProfile, seconds: float) -> float:
    quad = Quadrotor(profile, rng=np.random.default_rng(0), dt_s=0.001)
    quad.set_state(pos_ned_m=(0.0, 0.0, -10.0), motor_w_rad_s=[_hover_speed_rad_s(profile)] * 4)
    cmd = [hover_motor_command(profile)] * profile.n_motors
    n_steps = max(1, round(seconds / quad.dt_s))
    t0 = time.perf_counter()
    for _ in range(n_steps):
        quad.step(cmd)
    wall_s = time.perf_counter() - t0
    return n_steps * quad.dt_s / wall_s


def _bench_batch(profile: VehicleProfile, n_vehicles: int, n_steps: int) -> float:
    batch = BatchQuadrotor(profile, n_vehicles, dt_s=0.001)
    batch.set_state(pos_ned_m=(0.0, 0.0, -10.0), motor_w_rad_s=_hover_speed_rad_s(profile))
    cmd = np.full((n_vehicles, profile.n_motors), hover_motor_command(profile))
    t0 = time.perf_counter()
    for _ in range(n_steps):
        batch.step(cmd)
    wall_s = time.perf_counter() - t0
    return n_vehicles * n_steps / wall_s


def _bench_rotorpy(seconds: float) -> float:
    """RotorPy's own multirotor at 1 kHz, hovering on constant motor speeds."""
    from rotorpy.vehicles.hummingbird_params import quad_params
    from rotorpy.vehicles.multirotor import Multirotor

    vehicle = Multirotor(quad_params)
    state = vehicle.initial_state
    w_hover = math.sqrt(
        quad_params["mass"] * GRAVITY_M_S2 / (quad_params["num_rotors"] * quad_params["k_eta"])
    )
    control = {"cmd_motor_speeds": [w_hover] * quad_params["num_rotors"]}
    dt_s = 0.001
    n_steps = max(1, round(seconds / dt_s))
    t0 = time.perf_counter()
    for _ in range(n_steps):
        state = vehicle.step(state, control, dt_s)
    return n_steps * dt_s / (time.perf_counter() - t0)


def bench_sitl(seconds: float = 3.0) -> dict[str, float]:
    """Measure the plant's speed.

    Parameters
    ----------
    seconds : float
        Simulated time (s) for the single-vehicle run; the batch run and RotorPy
        (if installed) use a fraction of it so the whole call stays well under 30 s.

    Returns
    -------
    dict
        ``physics_rt_factor``: simulated s per wall s, one F450 hovering at 1 kHz
        on constant commands, no sensors or MAVLink. ``batch_vehicle_steps_per_s``:
        vehicle-steps per wall s for N = 1000. ``rotorpy_rt_factor``: RotorPy's
        multirotor at 1 kHz, only present when ``import rotorpy`` works.
    """
    profile = load_profile(_PROFILE)
    out = {
        "physics_rt_factor": _bench_scalar(profile, seconds),
        "batch_vehicle_steps_per_s": _bench_batch(
            profile, 1000, max(10, round(100 * seconds / 3.0))
        ),
    }
    if importlib.util.find_spec("rotorpy") is not None:
        out["rotorpy_rt_factor"] = _bench_rotorpy(min(seconds, 1.0))
    _log.info("sitl bench: %s", out)
    return out
