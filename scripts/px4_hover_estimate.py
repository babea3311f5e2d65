#!/usr/bin/env python3
"""The real PX4 v1.16 SIH's estimate in a hover against the truth, and the model's.

``px4``
    Boots the real PX4 SITL (``sitl.lab.realstack``: the launcher in
    ``../shared/stacks``), takes off its own way (arm, ``MAV_CMD_NAV_TAKEOFF``)
    and hovers in AUTO.LOITER (Hold) with the pilot's sticks centred
    (``MANUAL_CONTROL`` on the ground station's link). It records, as the
    ground station receives them, the estimate (``LOCAL_POSITION_NED`` at 50 Hz,
    ``ATTITUDE_QUATERNION`` at 100 Hz) and the truth (``HIL_STATE_QUATERNION`` at
    100 Hz: PX4 v1.16 streams SIH's ``vehicle_*_groundtruth`` topics in it), then
    lands and stops the stack. ``--save`` keeps the recording (``.npz``).
``model``
    The same figures for :class:`sitl.estimator_model.EstimatorModel` with
    ``EKF_GPS`` fed a vehicle hovering still (constant position, zero velocity,
    level), at the physics step of the lab's flights.
``analyse FILE``
    The figures of a saved recording.
``compare FILE... [--seeds N]``
    The figures compared: the median over the saved recordings, the median over
    the model's seeds ``0..N-1``, and their ratio (model over real) where both
    are spreads or times.

Each prints one JSON object. The figures, per NED axis: the error's mean and
standard deviation (estimate minus truth) of position and velocity; the lag at
which the error's autocorrelation (about its mean) first falls below 1/e; over
windows of :data:`WINDOW_S`, the position error's rate of change (standard
deviation), the correlation coefficient between its change and the velocity
error's integral and the regression slope of the one on the other (1: the
velocity error is all of the position error's motion); the correlation
coefficient between the velocity error and the position error; the attitude
error's mean, standard deviation and correlation time in roll, pitch and yaw
(deg, Euler angles of the estimate minus those of the truth). For PX4 also the
GPS fixes' error (``GPS_RAW_INT`` against the truth), the delay of the
estimated position behind the truth that correlates them best, and which
attitude, the truth's or the estimate's, explains the truth's horizontal motion
(:func:`tilt_check`).

The truth and the estimate are paired by the time the ground station received
them (the stream's source, as read, leaves ``HIL_STATE_QUATERNION.time_usec``
at 0), the truth interpolated to each estimate: the error is what a client
of the link sees, the stream's lag included. The truth's position is its
latitude, longitude (1e-7 deg) and altitude (mm) taken to NED about the EKF's
origin (``GPS_GLOBAL_ORIGIN``); its velocity is in cm/s (the message's units).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from sitl.estimator_model import EKF_GPS, EstimatorModel, estimator_seed_sequence
from sitl.lab.realstack.flights import Session
from sitl.physics import VehicleState

AXES = ("n", "e", "d")
EARTH_RADIUS_M = 6_371_000.0
"""PX4's ``CONSTANTS_RADIUS_OF_EARTH`` (its map projection's sphere)."""

_ID_ATTITUDE_QUATERNION = 31
_ID_LOCAL_POSITION_NED = 32
_ID_GPS_GLOBAL_ORIGIN = 49
_ID_HIL_STATE_QUATERNION = 115
_ID_GPS_RAW_INT = 24
_RATES_HZ = {
    _ID_LOCAL_POSITION_NED: 50.0,
    _ID_ATTITUDE_QUATERNION: 100.0,
    _ID_HIL_STATE_QUATERNION: 100.0,
    _ID_GPS_RAW_INT: 20.0,
}
_RECORDED = (
    "LOCAL_POSITION_NED",
    "ATTITUDE_QUATERNION",
    "HIL_STATE_QUATERNION",
    "GPS_GLOBAL_ORIGIN",
    "GPS_RAW_INT",
)
EKF2_PARAMS = (
    "EKF2_GPS_P_NOISE",
    "EKF2_GPS_V_NOISE",
    "EKF2_BARO_NOISE",
    "EKF2_GPS_DELAY",
    "EKF2_ACC_NOISE",
    "EKF2_GYR_NOISE",
    "EKF2_HEAD_NOISE",
    "EKF2_MAG_NOISE",
    "EKF2_HGT_REF",
    "EKF2_TAU_POS",
    "EKF2_TAU_VEL",
    "SIM_GPS_USED",
)
"""Read back from the running PX4 (the values in force, the airframe's included)."""
WINDOW_S = 0.5
"""The window over which the position error's change is set against the velocity
error's integral (:func:`window_changes`): the truth's position comes in 1e-7 deg
steps (about 1 cm) 10 ms apart, too coarse for a sample-to-sample derivative."""
SIH_DRAG_PER_S = 1.0
"""SIH's linear drag over its mass: ``SIH_KDV`` 1 N/(m/s) over ``SIH_MASS`` 1 kg
(v1.16 defaults, ``etc/extras/parameters.json.xz``)."""
GRAVITY_M_S2 = 9.81
MODEL_DT_S = 0.001
"""The model's step: the outer sweep's physics step (``OuterScenario.physics_dt_s``),
one model update per step as ``sitl/lab/outer_flight.py`` makes them."""
MODEL_IMU_HZ = 1000.0
"""The outer sweep's IMU rate (the profiles' 1 kHz): the attitude stream's rate."""


# ---------------------------------------------------------------- the real PX4
def record_px4(hover_s: float, altitude_m: float, settle_s: float, workdir: Path) -> dict[str, Any]:
    """Fly the real PX4 SIH into a hover and record ``hover_s`` of it (module docstring)."""
    session = Session("px4", workdir)
    try:
        g = session.connect(90.0)
        g.record_types.update(_RECORDED)
        session.take_off(altitude_m)
        session.hold()
        for msg_id, hz in _RATES_HZ.items():
            g.send("command_long_send", g.target, 1, 511, 0, msg_id, 1e6 / hz, 0, 0, 0, 0, 0)
        g.send("command_long_send", g.target, 1, 512, 0, _ID_GPS_GLOBAL_ORIGIN, 0, 0, 0, 0, 0, 0)
        time.sleep(settle_s)
        t0 = g.clock()
        time.sleep(hover_s)
        t1 = g.clock()
        said = g.texts_since(t0)
        mode = g.now.mode
        params = {}
        for name in EKF2_PARAMS:
            got = g.param_get(name)
            params[name] = None if got is None else round(got[0], 6)
        session.land()
    finally:
        session.close()
    return _arrays(g.records, t0, t1) | {"said": said, "mode": mode, "params": params}


def _arrays(records: dict[str, Any], t0: float, t1: float) -> dict[str, Any]:
    def rows(mtype: str, *names: str) -> np.ndarray:
        got = [[s.t_s, *(s.fields[n] for n in names)] for s in records.get(mtype, [])]
        a = np.array(got, dtype=float).reshape(-1, 1 + len(names))
        return a[(a[:, 0] >= t0) & (a[:, 0] <= t1)]

    origin = records.get("GPS_GLOBAL_ORIGIN", [])
    if not origin:
        raise RuntimeError("no GPS_GLOBAL_ORIGIN from PX4: the truth cannot be put in its frame")
    o = origin[-1].fields
    return {
        "origin": np.array([o["latitude"] * 1e-7, o["longitude"] * 1e-7, o["altitude"] * 1e-3]),
        "lpos": rows("LOCAL_POSITION_NED", "time_boot_ms", "x", "y", "z", "vx", "vy", "vz"),
        "att": rows("ATTITUDE_QUATERNION", "time_boot_ms", "q1", "q2", "q3", "q4"),
        "truth": _truth_rows(records.get("HIL_STATE_QUATERNION", []), t0, t1),
        "gps": rows("GPS_RAW_INT", "time_usec", "lat", "lon", "alt"),
    }


def _truth_rows(samples: list[Any], t0: float, t1: float) -> np.ndarray:
    """(t, lat deg, lon deg, alt m, vn, ve, vd m/s, qw, qx, qy, qz) per HIL_STATE_QUATERNION."""
    out = []
    for s in samples:
        if not t0 <= s.t_s <= t1:
            continue
        f = s.fields
        q = f["attitude_quaternion"]
        out.append([s.t_s, f["lat"] * 1e-7, f["lon"] * 1e-7, f["alt"] * 1e-3,
                    f["vx"] * 1e-2, f["vy"] * 1e-2, f["vz"] * 1e-2, *q])  # fmt: skip
    return np.array(out, dtype=float).reshape(-1, 11)


def geo_ned(lat_lon_alt: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Rows of (latitude deg, longitude deg, altitude m) as NED (m) about ``origin``
    (PX4's azimuthal equidistant projection, ``MapProjection::project``)."""
    lat0, lon0 = np.radians(origin[0]), np.radians(origin[1])
    lat, lon = np.radians(lat_lon_alt[:, 0]), np.radians(lat_lon_alt[:, 1])
    cos_c = np.sin(lat0) * np.sin(lat) + np.cos(lat0) * np.cos(lat) * np.cos(lon - lon0)
    c = np.arccos(np.clip(cos_c, -1.0, 1.0))
    k = np.where(c > 0.0, c / np.maximum(np.sin(c), 1e-300), 1.0)
    n = k * (np.cos(lat0) * np.sin(lat) - np.sin(lat0) * np.cos(lat) * np.cos(lon - lon0))
    e = k * np.cos(lat) * np.sin(lon - lon0)
    d = -(lat_lon_alt[:, 2] - origin[2])
    return np.column_stack([n * EARTH_RADIUS_M, e * EARTH_RADIUS_M, d])


def gps_errors(rec: dict[str, Any], tt: np.ndarray, p_true: np.ndarray) -> dict[str, np.ndarray]:
    """The GPS fixes PX4 streams (``GPS_RAW_INT``, each new fix once) minus the truth."""
    gps = rec.get("gps")
    if gps is None or len(gps) < 2:
        return {}
    new = np.concatenate([[True], np.diff(gps[:, 1]) != 0.0])
    gps = gps[new & (gps[:, 0] >= tt[0]) & (gps[:, 0] <= tt[-1])]
    p = geo_ned(np.column_stack([gps[:, 2] * 1e-7, gps[:, 3] * 1e-7, gps[:, 4] * 1e-3]),
                rec["origin"])  # fmt: skip
    err = np.column_stack([p[:, i] - np.interp(gps[:, 0], tt, p_true[:, i]) for i in range(3)])
    return {"t_gps": gps[:, 0], "gps_err": err, "gps_period_s": np.diff(gps[:, 1] * 1e-6)}


def px4_errors(rec: dict[str, Any]) -> dict[str, np.ndarray]:
    """Estimate minus truth, the truth interpolated at each estimate's arrival."""
    lpos, att, truth = rec["lpos"], rec["att"], rec["truth"]
    if len(truth) < 2 or len(lpos) < 2 or len(att) < 2:
        raise RuntimeError(
            f"too few samples: {len(lpos)} LOCAL_POSITION_NED, {len(att)} ATTITUDE_QUATERNION, "
            f"{len(truth)} HIL_STATE_QUATERNION"
        )
    tt = truth[:, 0]
    p_true = geo_ned(truth[:, 1:4], rec["origin"])
    t = lpos[:, 0]
    keep = (t >= tt[0]) & (t <= tt[-1])
    t = t[keep]
    pos_err = np.column_stack(
        [lpos[keep, 2 + i] - np.interp(t, tt, p_true[:, i]) for i in range(3)]
    )
    vel_err = np.column_stack(
        [lpos[keep, 5 + i] - np.interp(t, tt, truth[:, 4 + i]) for i in range(3)]
    )
    ta = att[:, 0]
    keep_a = (ta >= tt[0]) & (ta <= tt[-1])
    ta = ta[keep_a]
    q_true = _interp_quat(ta, tt, truth[:, 7:11])
    att_err = euler_deg(att[keep_a, 2:6]) - euler_deg(q_true)
    return {
        "t_pos": t,
        "pos_err": pos_err,
        "vel_err": vel_err,
        "t_att": ta,
        "att_err": _wrap_deg(att_err),
        "pos_period_s": np.diff(lpos[:, 1] * 1e-3),
        **gps_errors(rec, tt, p_true),
    }


def estimate_lag_s(rec: dict[str, Any], max_s: float = 1.0) -> dict[str, float]:
    """Per axis, the delay (s) of the estimated position behind the truth that
    correlates them best (positive: the estimate lags), in 10 ms steps."""
    lpos, truth = rec["lpos"], rec["truth"]
    tt, p_true = truth[:, 0], geo_ned(truth[:, 1:4], rec["origin"])
    t = lpos[:, 0]
    keep = (t >= tt[0] + max_s) & (t <= tt[-1] - max_s)
    lags = np.arange(-max_s, max_s + 1e-9, 0.01)
    out = {}
    for i, ax in enumerate(AXES):
        est = lpos[keep, 2 + i]
        corr = [_corr(est, np.interp(t[keep] - lag, tt, p_true[:, i])) for lag in lags]
        out[f"pos_{ax}_lag_s"] = round(float(lags[int(np.nanargmax(corr))]), 2)
    return out


def tilt_check(rec: dict[str, Any], window_s: float = 0.3) -> dict[str, float]:
    """Which attitude explains the truth's horizontal motion: SIH's quadrotor is
    pushed only by its thrust (about ``g`` along the body's up axis in a hover)
    and its linear drag, so ``dv/dt + kdv/m v`` should equal ``-g`` times the
    body's down axis in NED. Per axis N, E: the correlation of the two with the
    truth's attitude and with the estimate's, and the mean horizontal push
    each attitude implies (m/s^2) beside the one the truth's motion shows."""
    truth, att = rec["truth"], rec["att"]
    tt = truth[:, 0]
    grid = np.arange(tt[0] + 1.0, tt[-1] - 1.0, 0.05)
    lo, hi = grid - 0.5 * window_s, grid + 0.5 * window_s
    out: dict[str, float] = {}
    attitudes = {
        "truth": _interp_quat(grid, tt, truth[:, 7:11]),
        "est": _interp_quat(grid, att[:, 0], att[:, 2:6]),
    }
    for i, ax in enumerate(AXES[:2]):
        v = truth[:, 4 + i]
        push = (np.interp(hi, tt, v) - np.interp(lo, tt, v)) / window_s
        push = push + SIH_DRAG_PER_S * np.interp(grid, tt, v)
        out[f"push_{ax}_mean_m_s2"] = round(float(push.mean()), 3)
        for name, q in attitudes.items():
            w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
            down = (2 * (x * z + w * y), 2 * (y * z - w * x))[i]
            implied = -GRAVITY_M_S2 * down
            out[f"{name}_tilt_corr_{ax}"] = round(_corr(push, implied), 3)
            out[f"{name}_tilt_push_{ax}_mean_m_s2"] = round(float(implied.mean()), 3)
    return out


def _interp_quat(t: np.ndarray, tt: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Componentwise interpolation, renormalised (the samples are 10 ms apart)."""
    q = q.copy()
    for i in range(1, len(q)):  # one hemisphere
        if np.dot(q[i], q[i - 1]) < 0.0:
            q[i] = -q[i]
    out = np.column_stack([np.interp(t, tt, q[:, j]) for j in range(4)])
    unit: np.ndarray = out / np.linalg.norm(out, axis=1, keepdims=True)
    return unit


def euler_deg(q: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw (deg, ZYX) of unit quaternions (w, x, y, z) per row."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    roll = np.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2.0 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    deg: np.ndarray = np.degrees(np.column_stack([roll, pitch, yaw]))
    return deg


def _wrap_deg(a: np.ndarray) -> np.ndarray:
    return (a + 180.0) % 360.0 - 180.0


# ---------------------------------------------------------------- the model
def model_errors(duration_s: float, seed: int) -> dict[str, np.ndarray]:
    """The model's errors on a vehicle hovering still, as its streams deliver them."""
    model = EstimatorModel(
        EKF_GPS,
        rng=np.random.default_rng(estimator_seed_sequence(seed)),
        dt_s=MODEL_DT_S,
        imu_rate_hz=MODEL_IMU_HZ,
    )
    level = (1.0, 0.0, 0.0, 0.0)
    truth_p = (0.0, 0.0, -15.0)

    def state(t: float) -> VehicleState:
        return VehicleState(t, truth_p, (0.0, 0.0, 0.0), level, (0.0, 0.0, 0.0),
                            (0.0,) * 4, (0.0, 0.0, -9.81), False, False)  # fmt: skip

    model.begin(state(0.0))
    t_pos, pos, vel, t_att, att = [], [], [], [], []
    for k in range(1, round(duration_s / MODEL_DT_S) + 1):
        t = k * MODEL_DT_S
        new_att, new_pos = model.update(state(t))
        if new_pos and model.position is not None:
            t_pos.append(t)
            pos.append(model.position.position_ned_m)
            vel.append(model.position.velocity_ned_m_s)
        if new_att and model.attitude is not None and k % 10 == 0:  # at 100 Hz, as recorded
            t_att.append(t)
            att.append(model.attitude.q_wxyz)
    p = np.array(pos) - np.array(truth_p)
    return {
        "t_pos": np.array(t_pos),
        "pos_err": p,
        "vel_err": np.array(vel),
        "t_att": np.array(t_att),
        "att_err": _wrap_deg(euler_deg(np.array(att))),
    }


# ---------------------------------------------------------------- the figures
def correlation_time_s(t: np.ndarray, x: np.ndarray) -> float:
    """The first lag at which the autocorrelation of ``x`` (about its mean, on
    the samples' median period) falls below 1/e; NaN if it never does."""
    dt = float(np.median(np.diff(t)))
    grid = np.arange(t[0], t[-1], dt)
    y = np.interp(grid, t, x)
    y = y - y.mean()
    n = len(y)
    if n < 4 or not np.any(y):
        return math.nan
    f = np.fft.rfft(y, 2 * n)
    acf = np.fft.irfft(f * np.conj(f))[:n]
    acf = acf / acf[0]
    below = np.nonzero(acf < 1.0 / math.e)[0]
    return float(below[0] * dt) if below.size else math.nan


def window_changes(
    t: np.ndarray, pos_err: np.ndarray, vel_err: np.ndarray, window_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Over windows of ``window_s`` (every half window): the position error's change
    and the velocity error's integral (trapezoid). A velocity error that integrates
    into the position error makes them equal."""
    grid = np.arange(t[0] + window_s, t[-1] - window_s, 0.5 * window_s)
    lo, hi = grid - 0.5 * window_s, grid + 0.5 * window_s
    dp = np.interp(hi, t, pos_err) - np.interp(lo, t, pos_err)
    area = np.concatenate([[0.0], np.cumsum(0.5 * (vel_err[1:] + vel_err[:-1]) * np.diff(t))])
    return dp, np.interp(hi, t, area) - np.interp(lo, t, area)


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    if a.std() == 0.0 or b.std() == 0.0:
        return math.nan
    return float(np.corrcoef(a, b)[0, 1])


def figures(err: dict[str, np.ndarray]) -> dict[str, Any]:
    """The figures of a recording's errors (module docstring)."""
    t, pe, ve = err["t_pos"], err["pos_err"], err["vel_err"]
    out: dict[str, Any] = {
        "duration_s": round(float(t[-1] - t[0]), 1),
        "n_position": len(t),
        "n_attitude": len(err["t_att"]),
    }
    for i, ax in enumerate(AXES):
        out[f"pos_{ax}_mean_m"] = round(float(pe[:, i].mean()), 4)
        out[f"pos_{ax}_std_m"] = round(float(pe[:, i].std()), 4)
        out[f"pos_{ax}_tau_s"] = round(correlation_time_s(t, pe[:, i]), 2)
        out[f"vel_{ax}_mean_m_s"] = round(float(ve[:, i].mean()), 4)
        out[f"vel_{ax}_std_m_s"] = round(float(ve[:, i].std()), 4)
        out[f"vel_{ax}_tau_s"] = round(correlation_time_s(t, ve[:, i]), 2)
        dp, iv = window_changes(t, pe[:, i], ve[:, i], WINDOW_S)
        out[f"pos_{ax}_rate_m_s"] = round(float(dp.std()) / WINDOW_S, 4)
        out[f"corr_vel_dpos_{ax}"] = round(_corr(iv, dp), 3)
        out[f"dpos_per_int_vel_{ax}"] = round(float(np.dot(dp, iv) / np.dot(iv, iv)), 3)
        out[f"corr_vel_pos_{ax}"] = round(_corr(ve[:, i], pe[:, i]), 3)
    if "gps_err" in err:
        tg, ge = err["t_gps"], err["gps_err"]
        out["gps_n_fixes"] = len(tg)
        out["gps_period_ms_median"] = round(float(np.median(err["gps_period_s"])) * 1e3, 1)
        for i, ax in enumerate(AXES):
            out[f"gps_{ax}_mean_m"] = round(float(ge[:, i].mean()), 4)
            out[f"gps_{ax}_std_m"] = round(float(ge[:, i].std()), 4)
            out[f"gps_{ax}_tau_s"] = round(correlation_time_s(tg, ge[:, i]), 2)
    ae = err["att_err"]
    for i, name in enumerate(("roll", "pitch", "yaw")):
        out[f"{name}_mean_deg"] = round(float(ae[:, i].mean()), 3)
        out[f"{name}_std_deg"] = round(float(ae[:, i].std()), 3)
        out[f"{name}_tau_s"] = round(correlation_time_s(err["t_att"], ae[:, i]), 2)
    return out


_SPREADS = ("_std_", "_tau_s", "_rate_")


def compare(real: list[dict[str, Any]], model: list[dict[str, Any]]) -> dict[str, Any]:
    """Per figure both share: the real runs' values and their median, the model's
    median over its seeds, and (spreads and times) the ratio of the medians,
    model / real."""
    out: dict[str, Any] = {"real_runs": len(real), "model_seeds": len(model)}
    for key in model[0]:
        if key.startswith(("duration", "n_")) or key not in real[0]:
            continue
        r = [float(f[key]) for f in real]
        r_mid = float(np.median(r))
        m_mid = float(np.median([f[key] for f in model]))
        row: dict[str, Any] = {"real": r, "real_median": round(r_mid, 4)}
        row["model_median"] = round(m_mid, 4)
        if any(tag in key for tag in _SPREADS):
            row["ratio"] = round(m_mid / r_mid, 2)
        out[key] = row
    return out


def _save(path: Path, rec: dict[str, Any]) -> None:
    arrays = {k: v for k, v in rec.items() if isinstance(v, np.ndarray)}
    np.savez_compressed(path, allow_pickle=False, **arrays)


def _load(path: Path) -> dict[str, Any]:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    p = sub.add_parser("px4", help="fly the real PX4 SIH and measure its estimate")
    p.add_argument("--hover-s", type=float, default=150.0, help="recorded hover (s)")
    p.add_argument("--altitude-m", type=float, default=15.0)
    p.add_argument("--settle-s", type=float, default=10.0, help="hover before recording (s)")
    p.add_argument("--workdir", type=Path, help="PX4's work folder (default: a new temporary one)")
    p.add_argument("--save", type=Path, help="keep the recording here (.npz)")
    m = sub.add_parser("model", help="the same figures for the estimator model (EKF_GPS)")
    m.add_argument("--duration-s", type=float, default=150.0)
    m.add_argument("--seed", type=int, default=0)
    a = sub.add_parser("analyse", help="the figures of a saved PX4 recording")
    a.add_argument("file", type=Path)
    c = sub.add_parser("compare", help="saved PX4 recordings against the model's seeds")
    c.add_argument("files", type=Path, nargs="+")
    c.add_argument("--seeds", type=int, default=5)
    c.add_argument("--duration-s", type=float, default=150.0)
    args = ap.parse_args(argv)

    if args.what == "compare":
        real = [figures(px4_errors(_load(f))) for f in args.files]
        model = [figures(model_errors(args.duration_s, s)) for s in range(args.seeds)]
        out = compare(real, model)
    elif args.what == "model":
        out = {
            "source": "model EKF_GPS",
            "seed": args.seed,
            **figures(model_errors(args.duration_s, args.seed)),
        }
    else:
        if args.what == "px4":
            workdir = args.workdir or Path(tempfile.mkdtemp(prefix="px4-hover-"))
            rec = record_px4(args.hover_s, args.altitude_m, args.settle_s, workdir)
            if args.save:
                _save(args.save, rec)
            extra = {
                "px4_mode_at_end": rec["mode"],
                "px4_said": rec["said"][:10],
                "px4_params": rec["params"],
            }
        else:
            rec, extra = _load(args.file), {}
        err = px4_errors(rec)
        per = err["pos_period_s"]
        out = {
            "source": "PX4 v1.16 SIH, estimate minus HIL_STATE_QUATERNION truth",
            **figures(err),
            "lpos_period_ms_median": round(float(np.median(per)) * 1e3, 1),
            **estimate_lag_s(rec),
            **tilt_check(rec),
            **extra,
        }
    rows = (f" {json.dumps(k)}: {json.dumps(v)}" for k, v in out.items())
    print("{\n" + ",\n".join(rows) + "\n}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
