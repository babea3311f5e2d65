"""What the motion of a paper flight allows, read from the flight and the vehicle.

The acceleration floor (no controller can track better with the vehicle's peak
angular acceleration), the ideal tracker (a controller that knows the plant and
brakes on its time-optimal curve, without preview) seen through the gyro filter
and, over a companion link, one round trip late; the share of the error right
after fast stick changes; and each vehicle's input gain and motor lag.
"""

from __future__ import annotations

import bisect
import math
from typing import Any

import numpy as np

from companion.config import build_mixer
from companion.control import AXES
from sitl.envelope import angular_accel_limits_rad_s2
from sitl.link_model import (
    DOWN,
    ID_HIGHRES_IMU,
    ID_SET_ACTUATOR_CONTROL_TARGET,
    UP,
    LinkModel,
)
from sitl.vehicle_params import GRAVITY_M_S2, VehicleParams


def input_gains(profile: Any) -> dict[str, float]:
    """Roll/pitch angular acceleration per unit normalised torque at hover, and motor lag.

    For a full-scale roll command the mixer moves motor ``i``'s command by
    ``0.5 R_i``; at the hover speed ``w_h`` its thrust moves by
    ``dT_i = 2 k_i w_h (w_max - w_idle) 0.5 R_i``, so
    ``b_roll = |sum_i -y_i dT_i| / J_xx`` (rad/s^2 per unit normalised torque; the
    PID's gains are in normalised torque per rad/s, so its loop gain scales with
    ``b``). Read from the simulator's physics: this is the "why", not the controller.
    """
    P = VehicleParams.from_profile(profile)
    roll_f, pitch_f, _ = build_mixer(profile).factors()
    w_h = math.sqrt(P.mass_kg * GRAVITY_M_S2 / sum(P.thrust_coeff))
    span = P.w_max_rad_s - P.w_idle_rad_s
    dT_roll = [2 * k * w_h * span * 0.5 * r for k, r in zip(P.thrust_coeff, roll_f, strict=True)]
    dT_pitch = [2 * k * w_h * span * 0.5 * p for k, p in zip(P.thrust_coeff, pitch_f, strict=True)]
    tau_x = -sum(a[1] * d for a, d in zip(P.arm_frd_m, dT_roll, strict=True))
    tau_y = sum(a[0] * d for a, d in zip(P.arm_frd_m, dT_pitch, strict=True))
    return {
        "b_roll_rad_s2": round(abs(tau_x) / P.inertia_kg_m2[0][0], 1),
        "b_pitch_rad_s2": round(abs(tau_y) / P.inertia_kg_m2[1][1], 1),
        "motor_tau_up_s": P.tau_up_s,
        "motor_tau_down_s": P.tau_down_s,
    }


FAST_CHANGE_DEG_S2 = 2000.0
AFTER_CHANGE_S = 0.5


def transient_split(record: Any) -> dict[str, dict[str, float | None]]:
    """How much of each axis' error follows fast stick changes.

    A sample is "after a fast change" when, within the previous
    ``AFTER_CHANGE_S`` seconds, the commanded rate on that axis changed faster
    than ``FAST_CHANGE_DEG_S2`` (flip entries and exits, reversals). Returns per
    axis the fraction of airborne time in such windows (``time_fraction``), the
    share of the absolute error accumulated there (``error_share``) and the MAE
    over the rest of the flight (``mae_elsewhere_deg_s``), all while airborne.
    """
    c = record.columns
    air = c["airborne"].astype(bool)
    out: dict[str, dict[str, float | None]] = {}
    if air.sum() < 3:
        return {
            a: {"time_fraction": None, "error_share": None, "mae_elsewhere_deg_s": None}
            for a in AXES
        }
    t = c["t_s"][air]
    ref = np.degrees(c["ref_rad_s"][air])
    err = np.abs(np.degrees(c["meas_rad_s"][air]) - ref)
    for i, a in enumerate(AXES):
        fast_t = t[np.abs(np.gradient(ref[:, i], t)) > FAST_CHANGE_DEG_S2]
        k = np.searchsorted(fast_t, t, side="right") - 1
        near = (
            (k >= 0) & (t - fast_t[np.clip(k, 0, None)] <= AFTER_CHANGE_S)
            if fast_t.size
            else np.zeros(t.size, bool)
        )
        total = float(err[:, i].sum())
        out[a] = {
            "time_fraction": round(float(near.mean()), 3),
            "error_share": round(float(err[near, i].sum()) / total, 3) if total > 0 else None,
            "mae_elsewhere_deg_s": round(float(err[~near, i].mean()), 2) if (~near).any() else None,
        }
    return out


FLOOR_GRID_RAD_S = 0.01


def acceleration_floor_deg_s(t_s: Any, ref_rad_s: Any, accel_up: float, accel_down: float) -> float:
    """A lower bound on the rate-tracking MAE that peak angular acceleration allows.

    The least mean ``|ref - w|`` over every rate trajectory ``w`` whose change
    between samples is within ``accel_up * dt`` upwards and ``accel_down * dt``
    downwards, found by dynamic programming over a grid of
    ``FLOOR_GRID_RAD_S``: motor lag, the gyro filter, noise and the other axes
    are ignored, and the trajectory may know the stick in advance, so no
    controller can do better (deg/s). The grid search allows one extra grid
    step per sample and the result is lowered by half a step, which keeps it a
    bound: a real trajectory rounded to the grid is then feasible and costs at
    most half a step more per sample.
    """
    t = np.asarray(t_s, dtype=float)
    ref = np.asarray(ref_rad_s, dtype=float)
    if ref.size == 0:
        return 0.0
    step = FLOOR_GRID_RAD_S
    grid = np.arange(ref.min() - step, ref.max() + 2 * step, step)
    cost = np.abs(ref[0] - grid)  # the start is free: a lower bound needs no initial state
    dts = np.diff(t)
    for k in range(1, ref.size):
        up = math.ceil(accel_up * dts[k - 1] / step) + 1
        down = math.ceil(accel_down * dts[k - 1] / step) + 1
        # w_k = grid[j] is reachable from grid[i] for j - up <= i <= j + down
        cost = np.minimum(_running_min(cost, up), _running_min(cost[::-1], down)[::-1])
        cost += np.abs(ref[k] - grid)
    return math.degrees(max(float(cost.min()) / ref.size - step / 2, 0.0))


def _running_min(a: Any, width: int) -> Any:
    """``out[j] = min(a[max(0, j - width)] .. a[j])``, by doubling spans."""
    out = a.copy()
    span = 1
    while span <= width:
        s = min(span, width - span + 1)
        out[s:] = np.minimum(out[s:], out[:-s])
        span += s
    return out


def ideal_tracker_rates(
    t_s: Any, ref_rad_s: Any, accel_up: float, accel_down: float, tau_s: float
) -> Any:
    r"""The rates, at the samples, of an ideal digital controller on a lagged plant.

    The plant: the angular acceleration ``a`` follows a target in
    ``[-accel_down, accel_up]`` (the command) through a first-order lag
    ``tau_s``, and ``w' = a``; nothing else acts on it. The controller runs at
    the samples and holds its command until the next one; it sees ``w`` and
    ``a`` exactly and the stick only as it comes (no preview), and it knows the
    plant. It aims the point where the vehicle would stop if it braked at full
    opposite command, :math:`w + \tau (a - A \ln(1 + a / A))` (``A`` the
    opposite limit), at the reference as seen at the end of the sample
    interval: the time-optimal switching curve of this plant, so on a stick
    step it accelerates at full command and then brakes at full command onto
    the new rate. Integrated exactly between samples; starts on the
    reference, at rest.
    """
    t = np.asarray(t_s, dtype=float)
    ref = np.asarray(ref_rad_s, dtype=float)
    w_out = np.empty_like(ref)
    if ref.size == 0:
        return w_out
    lo, hi = -accel_down, accel_up

    def advance(target: float, w: float, a: float, h: float, d: float) -> tuple[float, float]:
        """``w`` and ``a`` after ``h`` s of ``target`` (``d`` = exp(-h / tau_s))."""
        return w + target * h + (a - target) * tau_s * (1.0 - d), target + (a - target) * d

    def miss(target: float, w: float, a: float, h: float, d: float, r: float) -> float:
        """Where the vehicle would stop, braking from the end of the interval, minus ``r``."""
        w, a = advance(target, w, a, h, d)
        if a > 0.0:
            return w + tau_s * (a - accel_down * math.log1p(a / accel_down)) - r
        return w - tau_s * (-a - accel_up * math.log1p(-a / accel_up)) - r

    w = float(ref[0])
    a = 0.0
    for k in range(ref.size):
        w_out[k] = w
        if k + 1 == ref.size:
            break
        h = float(t[k + 1] - t[k])
        d = math.exp(-h / tau_s)
        r = float(ref[k])
        if miss(hi, w, a, h, d, r) <= 0.0:
            target = hi
        elif miss(lo, w, a, h, d, r) >= 0.0:
            target = lo
        else:  # the miss grows with the target: bisect
            t_lo, t_hi = lo, hi
            for _ in range(40):
                target = 0.5 * (t_lo + t_hi)
                if miss(target, w, a, h, d, r) > 0.0:
                    t_hi = target
                else:
                    t_lo = target
        w, a = advance(target, w, a, h, d)
    return w_out


def ideal_tracker_deg_s(
    t_s: Any, ref_rad_s: Any, accel_up: float, accel_down: float, tau_s: float
) -> float:
    """Mean ``|ref - w|`` of :func:`ideal_tracker_rates`, deg/s.

    Not a bound (a controller with preview, or luckier with a later stick
    change, can do better), but what motor lag alone costs a controller that
    is perfect in every other way; never below :func:`acceleration_floor_deg_s`
    for the same limits, since its acceleration stays within them.
    """
    ref = np.asarray(ref_rad_s, dtype=float)
    if ref.size == 0:
        return 0.0
    return mae_deg_s(ref, ideal_tracker_rates(t_s, ref, accel_up, accel_down, tau_s))


def mae_deg_s(ref_rad_s: Any, rates_rad_s: Any) -> float:
    return math.degrees(float(np.mean(np.abs(np.asarray(ref_rad_s) - rates_rad_s))))


def through_gyro_filter(rates: Any, weight: float) -> Any:
    """``rates`` (one per IMU sample) as the paper's first-stage filter reports them:
    ``y_k = weight * rates_k + (1 - weight) * y_(k-1)``, ``y_0 = rates_0``, as
    :class:`sitl.imu.Imu` applies it (without the noise)."""
    x = np.asarray(rates, dtype=float)
    out = np.empty_like(x)
    y = float(x[0]) if x.size else 0.0
    keep = 1.0 - weight
    for k, v in enumerate(x.tolist()):
        y = weight * v + keep * y
        out[k] = y
    return out


def command_acting(t_s: Any, link: Any, seed: int) -> Any:
    """Per IMU sample ``j`` (times ``t_s``), the index of the newest sample whose
    command acts by ``t_s[j]`` through ``link`` (a :class:`sitl.link_model.LinkSpec`),
    -1 before the first: each sample goes up, its command comes down, and the
    autopilot acts on it at its first IMU sample at or after the arrival, as
    :func:`sitl.lab.simulate.simulate_flight` flies it (the same seeded draws: the
    link's generator is keyed per stream). The ideal link acts at once (``j``)."""
    t = np.asarray(t_s, dtype=float)
    if link.ideal:
        return np.arange(t.size)
    model = LinkModel(link, seed)
    acts = np.full(t.size, -1)
    times = t.tolist()
    for k, tk in enumerate(times):
        for a in model.arrivals(UP, ID_HIGHRES_IMU, tk)[:1]:
            for b in model.arrivals(DOWN, ID_SET_ACTUATOR_CONTROL_TARGET, a)[:1]:
                j = bisect.bisect_left(times, b - 1e-12)
                if j < t.size:
                    acts[j] = max(acts[j], k)
    return np.maximum.accumulate(acts)


def ideal_tracker_through_link_deg_s(
    t_s: Any, ref_rad_s: Any, limits: tuple[float, float], tau_s: float, weight: float,
    acting: Any, airborne: Any,
) -> float:  # fmt: skip
    """:func:`ideal_tracker_deg_s` measured as the flights are (through the gyro
    filter of ``weight``), when what moves the motors at sample ``j`` can know the
    stick only up to sample ``acting[j]`` (:func:`command_acting`): a controller
    that knows the plant and predicts it perfectly still answers each stick move
    one round trip late. The error is against the reference as flown."""
    ref = np.asarray(ref_rad_s, dtype=float)
    acting = np.asarray(acting)
    known = np.where(acting >= 0, ref[np.maximum(acting, 0)], ref[0])
    w = ideal_tracker_rates(t_s, known, *limits, tau_s)
    y = through_gyro_filter(w, weight)
    air = np.asarray(airborne, dtype=bool)
    return mae_deg_s(ref[air], y[air])


MOTION_KEYS = (
    "acceleration_floor_deg_s",
    "ideal_tracker_deg_s",
    "ideal_tracker_measured_deg_s",
    "ideal_tracker_link_deg_s",
)


def motion_limits(
    record: Any, profile: Any, filter_weight: float, link: Any = None, seed: int = 0
) -> dict[str, dict[str, float]]:
    """Roll and pitch of one flight (airborne samples) against the vehicle's limits.

    ``acceleration_floor_deg_s``: :func:`acceleration_floor_deg_s` with the
    profile's peak accelerations (:func:`sitl.envelope.angular_accel_limits_rad_s2`).
    ``ideal_tracker_deg_s``: :func:`ideal_tracker_deg_s` with the same limits
    and the faster of the profile's two motor time constants (the kinder one).
    ``ideal_tracker_measured_deg_s``: the same ideal's rates as the flight's
    gyro reports them, through its first-stage filter of weight
    ``filter_weight`` (:func:`through_gyro_filter`): on the footing of the
    flight's MAE, which is against the measured rate.
    ``ideal_tracker_link_deg_s`` (a flight through a companion ``link``, seeded
    by ``seed``): the same, one round trip late (:func:`ideal_tracker_through_link_deg_s`).
    Yaw is left out: a rotor's spin-up reaction gives yaw far more than its
    steady peak for a moment, so a bound from the steady figure would not hold.
    """
    c = record.columns
    air = np.asarray(c["airborne"], dtype=bool)
    t = np.asarray(c["t_s"])[air]
    ref = np.asarray(c["ref_rad_s"])[air]
    limits = angular_accel_limits_rad_s2(profile)
    tau = min(profile.physics.motor_tau_up_s, profile.physics.motor_tau_down_s)
    through = link is not None and not link.ideal
    out: dict[str, dict[str, float]] = {
        key: {} for key in MOTION_KEYS if through or key != "ideal_tracker_link_deg_s"
    }
    if through:
        acting = command_acting(np.asarray(c["t_s"]), link, seed)
    for i, a in enumerate(AXES[:2]):
        r = ref[:, i]
        w = ideal_tracker_rates(t, r, *limits[i], tau)
        y = through_gyro_filter(w, filter_weight)
        out["acceleration_floor_deg_s"][a] = round(acceleration_floor_deg_s(t, r, *limits[i]), 2)
        out["ideal_tracker_deg_s"][a] = round(mae_deg_s(r, w), 2)
        out["ideal_tracker_measured_deg_s"][a] = round(mae_deg_s(r, y), 2)
        if through:
            late = ideal_tracker_through_link_deg_s(
                c["t_s"], np.asarray(c["ref_rad_s"])[:, i], limits[i], tau, filter_weight,
                acting, air,
            )  # fmt: skip
            out["ideal_tracker_link_deg_s"][a] = round(late, 2)
    return out
