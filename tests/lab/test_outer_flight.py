"""The outer loops flown in the lab (sitl/lab/outer_flight.py) and the estimator model
(sitl/estimator_model.py) they fly on.

Flights are short (8-20 s of the bundled scenarios) to keep this file well under
30 s on a loaded 2-core machine; the full-length figures are in
``docs/research/outer.md`` ("Flown in the lab").
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
from pathlib import Path

import numpy as np
import pytest

from companion.config import MfcConfig, PidConfig, load_controller
from companion.control.quaternion import quat_conj, quat_log, quat_mul
from companion.profile import VehicleProfile, load_profile
from sitl.estimator_model import EKF_GPS, EstimatorModel, EstimatorSpec, estimator_seed_sequence
from sitl.frames import euler_to_quat
from sitl.lab.outer_flight import (
    SCENARIOS,
    OuterFlight,
    main,
    outer_metrics,
    simulate_outer_flight,
)
from sitl.physics import VehicleState

ROOT = Path(__file__).resolve().parents[2]


@functools.cache
def _f450() -> VehicleProfile:
    return load_profile(ROOT / "vehicle_profiles" / "f450.yaml", simulated=True)


@functools.cache
def _rate_cfg() -> MfcConfig | PidConfig:
    return load_controller()


# --- the estimator model ---------------------------------------------------------------

STATS_T_S = 3000.0
STATS_DT_S = 0.02


def _tolerance(tau_s: float) -> float:
    """Relative, on a component's sample standard deviation: for a Gauss-Markov
    process observed over T the sample standard deviation has a relative standard
    error of about sqrt(tau / (2 T)): 2.4 % for tau 3.5 s over 3000 s, 10 % for the
    heading's 60 s. Four of them, and at least 15 %: a wrong sigma (or a sigma
    applied per step instead of stationary: smaller by a factor of up to 10) fails;
    seeded, the run is fixed anyway."""
    return max(0.15, 4.0 * math.sqrt(tau_s / (2.0 * STATS_T_S)))


def _truth(t_s: float, q: tuple[float, float, float, float]) -> VehicleState:
    return VehicleState(
        t_s, (1.0, -2.0, -5.0), (0.5, 0.0, -0.2), q, (0.0, 0.0, 0.0), (), (0.0, 0.0, -9.8),
        False, False,
    )  # fmt: skip


def _model(spec: EstimatorSpec, seed: int, dt_s: float = STATS_DT_S) -> EstimatorModel:
    return EstimatorModel(
        spec,
        rng=np.random.default_rng(estimator_seed_sequence(seed)),
        dt_s=dt_s,
        imu_rate_hz=1.0 / dt_s,
    )


def _estimator_errors(
    spec: EstimatorSpec, seed: int, t_end_s: float = STATS_T_S, dt_s: float = STATS_DT_S
) -> tuple[np.ndarray, ...]:
    """Run the model against a still truth (tilted, turned) on a ``dt_s`` grid; the
    errors of every delivered estimate, and the delivery times against the stamps."""
    q_true = euler_to_quat(0.2, -0.1, 1.0)
    est = _model(spec, seed, dt_s)
    att, pos, vel, lag_att, lag_pos = [], [], [], [], []
    for k in range(round(t_end_s / dt_s)):
        t = k * dt_s
        new_att, new_pos = est.update(_truth(t, q_true))
        if new_att and est.attitude is not None:
            # The error rotation, in the world frame: q_est = exp(e/2) q_true.
            err = quat_mul(est.attitude.q_wxyz, quat_conj(q_true))
            att.append(quat_log(err))
            lag_att.append(t - est.attitude.time_s)
        if new_pos and est.position is not None:
            pos.append(np.subtract(est.position.position_ned_m, (1.0, -2.0, -5.0)))
            vel.append(np.subtract(est.position.velocity_ned_m_s, (0.5, 0.0, -0.2)))
            lag_pos.append(t - est.position.time_s)
    return tuple(np.asarray(x) for x in (att, pos, vel, lag_att, lag_pos))


def test_estimator_noise_matches_its_documented_figures() -> None:
    """Each error component's spread is the documented sigma (within
    :func:`_tolerance`), its mean this flight's attitude bias (zero for position and
    velocity). (Latencies on this 20 ms grid: whole steps, so the 10 and 30 ms of
    the figures are not asked here; the next test flies them on 1 ms.)"""
    spec = dataclasses.replace(EKF_GPS, attitude_latency_s=0.02, position_latency_s=0.04)
    att, pos, vel, _, _ = _estimator_errors(spec, seed=12)
    bias = np.asarray(_model(spec, seed=12).attitude_bias_rad)
    zero = np.zeros(3)
    for name, err, sigma, tau, mean in (
        ("attitude", att, spec.attitude_sigma_rad, spec.attitude_tau_s, bias),
        ("position", pos, spec.position_sigma_m, spec.position_tau_s, zero),
        ("velocity", vel, spec.velocity_sigma_m_s, spec.velocity_tau_s, zero),
    ):
        for i in range(3):
            tol = _tolerance(tau[i])
            assert err[:, i].std() == pytest.approx(sigma[i], rel=tol), (name, i)
        # The mean of a Gauss-Markov process over T has a standard error of
        # sigma sqrt(2 tau / T): allow 4 of them.
        bound = 4.0 * np.asarray(sigma) * np.sqrt(2.0 * np.asarray(tau) / STATS_T_S)
        assert np.all(np.abs(err.mean(axis=0) - mean) < bound), name
    # One position estimate per 20 ms, none lost.
    assert len(pos) == pytest.approx(STATS_T_S * spec.position_rate_hz, abs=3)


@pytest.mark.long
def test_the_velocity_error_moves_with_the_position_error() -> None:
    """The two share a driver (an EKF's position and velocity errors are one
    error): their correlation is ``shared`` times sqrt(tau / (tau + smoothing))
    per axis (0.84 north and east, 0.76 down); with ``shared`` 0 they are
    independent."""
    _, pos, vel, _, _ = _estimator_errors(EKF_GPS, seed=4)
    s = EKF_GPS
    for i in range(3):
        tau, tf = s.position_tau_s[i], s.position_smoothing_s[i]
        expected = s.shared[i] * math.sqrt(tau / (tau + tf))
        got = float(np.corrcoef(pos[:, i], vel[:, i])[0, 1])
        assert got == pytest.approx(expected, abs=0.05), i
    apart = dataclasses.replace(EKF_GPS, shared=(0.0, 0.0, 0.0))
    _, pos, vel, _, _ = _estimator_errors(apart, seed=4)
    for i in range(3):
        assert abs(float(np.corrcoef(pos[:, i], vel[:, i])[0, 1])) < 0.1


def test_estimator_rates_and_latencies_on_the_physics_step() -> None:
    """On the lab's 1 ms step: attitude at the IMU rate (here 250 Hz) 10 ms late,
    position and velocity at 50 Hz 30 ms late."""
    q = euler_to_quat(0.0, 0.0, 0.0)
    est = EstimatorModel(EKF_GPS, rng=np.random.default_rng(1), dt_s=0.001, imu_rate_hz=250.0)
    n_att = n_pos = 0
    for k in range(2000):
        t = k * 0.001
        new_att, new_pos = est.update(_truth(t, q))
        if new_att and est.attitude is not None:
            n_att += 1
            assert t - est.attitude.time_s == pytest.approx(0.010, abs=1e-9)
        if new_pos and est.position is not None:
            n_pos += 1
            assert t - est.position.time_s == pytest.approx(0.030, abs=1e-9)
    assert n_att == pytest.approx(2.0 * 250.0, abs=3)
    assert n_pos == pytest.approx(2.0 * 50.0, abs=2)


def test_estimator_is_seeded_and_perfect_is_the_truth() -> None:
    a = _estimator_errors(EKF_GPS, seed=3, t_end_s=20.0)
    b = _estimator_errors(EKF_GPS, seed=3, t_end_s=20.0)
    for x, y in zip(a, b, strict=True):
        assert np.array_equal(x, y)
    c = _estimator_errors(EKF_GPS, seed=4, t_end_s=20.0)
    assert not np.array_equal(a[1], c[1])
    zero = EstimatorSpec(
        attitude_sigma_rad=(0.0, 0.0, 0.0),
        attitude_bias_sigma_rad=(0.0, 0.0, 0.0),
        position_sigma_m=(0.0, 0.0, 0.0),
        velocity_sigma_m_s=(0.0, 0.0, 0.0),
    )
    att, pos, vel, _, _ = _estimator_errors(zero, seed=3, t_end_s=20.0)
    assert np.abs(att).max() < 1e-12
    assert np.abs(pos).max() < 1e-12
    assert np.abs(vel).max() < 1e-12


@pytest.mark.parametrize(
    "bad",
    [
        {"position_sigma_m": (-0.1, 0.1, 0.1)},
        {"velocity_tau_s": (0.0, 1.0, 1.0)},
        {"position_latency_s": 2.0},
        {"position_rate_hz": 0.0},
        {"shared": (1.1, 0.0, 0.0)},
        {"position_smoothing_s": (-1.0, 1.0, 1.0)},
        {"attitude_bias_sigma_rad": (math.nan, 0.0, 0.0)},
    ],
)
def test_estimator_spec_rejects_bad_figures(bad: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        EstimatorSpec(**bad)  # type: ignore[arg-type]


# --- flights ---------------------------------------------------------------------------


def test_same_seed_same_flight_bit_for_bit() -> None:
    sc = SCENARIOS["position-hold"].with_duration(6.0)
    a = simulate_outer_flight(_f450(), _rate_cfg(), sc, seed=5)
    b = simulate_outer_flight(_f450(), _rate_cfg(), sc, seed=5)
    assert a.columns.keys() == b.columns.keys()
    for k in a.columns:
        assert np.array_equal(a.columns[k], b.columns[k], equal_nan=True), k
    ma, mb = outer_metrics(a, sc), outer_metrics(b, sc)
    assert json.dumps(ma, sort_keys=True) == json.dumps(mb, sort_keys=True)
    c = simulate_outer_flight(_f450(), _rate_cfg(), sc, seed=6)
    assert not np.array_equal(a.columns["pos_ned_m"], c.columns["pos_ned_m"])


def _estimate_error_at(flight: OuterFlight, t_s: np.ndarray) -> np.ndarray:
    i = np.minimum(np.searchsorted(flight.columns["t_s"], t_s), len(flight.columns["t_s"]) - 1)
    c = flight.columns
    return np.asarray(c["est_pos_ned_m"][i] - c["pos_ned_m"][i])


def test_on_px4s_gyro_the_core_flies_means_at_that_rate_on_the_same_estimate() -> None:
    """``gyro_hz`` changes what the core gets, not the autopilot's estimate: the
    estimator keeps its rate and its errors (what another seed would change)."""
    sc = SCENARIOS["position-hold"].with_duration(3.0)
    every = simulate_outer_flight(_f450(), _rate_cfg(), sc, seed=5)
    means = simulate_outer_flight(_f450(), _rate_cfg(), sc, seed=5, gyro_hz=250.0)
    other = simulate_outer_flight(_f450(), _rate_cfg(), sc, seed=6)
    assert (every.meta["gyro_hz"], means.meta["gyro_hz"]) == (1000.0, 250.0)
    assert len(means.columns["t_s"]) == len(every.columns["t_s"]) // 4
    np.testing.assert_allclose(np.diff(means.columns["t_s"]), 0.004, atol=1e-9)
    t = means.columns["t_s"][means.columns["t_s"] > 1.0]
    err = _estimate_error_at(every, t)
    moved = np.nanmax(np.abs(_estimate_error_at(means, t) - err))
    reseeded = np.nanmax(np.abs(_estimate_error_at(other, t) - err))
    assert moved < 0.05 * reseeded, (moved, reseeded)


POSITION_HOLD_S = 20.0
POSITION_RMS_BOUND_M = 0.9
ESTIMATE_RMS_BOUND_M = 0.5
ALTITUDE_RMS_BOUND_M = 0.5
"""Regression check. Measured over 14-20 s, seed 20200318, 2026-11-29: 0.45 m
horizontal RMS of the true position, 0.26 m of the estimate the loops flew on, 0.23 m
vertical (``python -m sitl.lab.outer_flight --profile f450 --mode position
--duration 20``). The estimate's own errors are most of it (EKF_GPS: 0.15 m, its
velocity 0.2 m/s, moving together, as the real EKF2's). The bounds are about
twice the figures, not specifications: a limit cycle (tens of degrees of tilt) or
a loop that does not hold gives metres."""


@pytest.mark.long
def test_f450_holds_position_in_the_papers_gusty_wind() -> None:
    sc = SCENARIOS["position-hold"].with_duration(POSITION_HOLD_S)
    fl = simulate_outer_flight(_f450(), _rate_cfg(), sc)
    m = outer_metrics(fl, sc)
    assert not m["crashed"]
    assert m["lift_off_s"] is not None and m["lift_off_s"] < 3.0
    assert m["pos_rms_h_m"] < POSITION_RMS_BOUND_M
    assert m["est_rms_h_m"] < ESTIMATE_RMS_BOUND_M
    assert m["pos_rms_v_m"] < ALTITUDE_RMS_BOUND_M
    # It really took off and climbed to the hold altitude (5 m; the truth within
    # the estimate's height error of it).
    assert -fl.columns["est_pos_ned_m"][-1, 2] == pytest.approx(5.0, abs=0.5)
    assert -fl.columns["pos_ned_m"][-1, 2] == pytest.approx(5.0, abs=1.0)
    # The F450 has authority to spare: its gains never back off.
    assert m["gain_scale_min"] == 1.0 and m["backed_off_s"] == 0.0


STEP_REACH_BOUND_S = 6.0
"""Measured 2.6 s for the 5 -> 8 m step (the estimated altitude within 10 % of its
3 m, seed 20200318, 2026-11-29): ``python -m sitl.lab.outer_flight --profile f450
--mode altitude --duration 18``. The altitude loop's 0.69 1/s is a 1.45 s time
constant: ln(10) x 1.45 = 3.3 s to 10 % on an ideal climb-rate loop; the climb
rate fed forward shortens it."""


def test_f450_altitude_step_reaches_the_new_altitude_in_time() -> None:
    sc = SCENARIOS["altitude-steps"].with_duration(18.0)
    fl = simulate_outer_flight(_f450(), _rate_cfg(), sc)
    m = outer_metrics(fl, sc)
    assert not m["crashed"]
    reach = m["step_reach_s"][0]
    assert reach is not None and reach < STEP_REACH_BOUND_S
    t = fl.columns["t_s"]
    est_up = -fl.columns["est_pos_ned_m"][:, 2]
    assert np.all(np.abs(est_up[t > 17.0] - 8.0) < 0.4)
    up = -fl.columns["pos_ned_m"][:, 2]
    assert np.all(np.abs(up[t > 17.0] - 8.0) < 1.0)  # the estimate's height error


def test_entry_prints_metrics_as_json(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--profile", "f450", "--mode", "angle", "--duration", "3", "--seed", "1"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["mode"] == "angle"
    assert out["crashed"] is False
    assert out["pos_rms_h_m"] is None  # nothing holds the position in angle mode


def test_a_vehicle_hovering_near_0_7_lifts_off() -> None:
    """The X500 hovers at 0.69: with the attitude loop left running on the ground it
    never lifted off (the mixer cut the collective to 0.525 for the torques an
    attitude error on its legs asked); held level with no rates while landed, it
    does (measured: lift-off at 2.0 s, ``python -m sitl.lab.outer_flight --profile
    x500 --duration 6 --seed 1``)."""
    x500 = load_profile(ROOT / "vehicle_profiles" / "x500.yaml", simulated=True)
    sc = SCENARIOS["position-hold"].with_duration(6.0)
    fl = simulate_outer_flight(x500, _rate_cfg(), sc, seed=1)
    m = outer_metrics(fl, sc)
    assert not m["crashed"]
    assert m["lift_off_s"] is not None and m["lift_off_s"] < 3.0
    assert -fl.columns["pos_ned_m"][-1, 2] > 1.5


# --- the baseline (PX4's default cascade, sitl/lab/cascade_pid.py) ----------------------


def test_entry_flies_the_px4_baseline(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--outer", "px4", "--profile", "f450", "--duration", "3", "--seed", "1"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["outer_law"] == "px4"
    assert out["crashed"] is False
    assert out["lift_off_s"] is not None


@pytest.mark.long
def test_table_with_the_baseline_prints_both_and_their_ratio(
    capsys: pytest.CaptureFixture[str],
) -> None:
    argv = ["--table", "--baseline", "px4", "--profiles", "f450", "--duration", "2", "--seed", "1"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "### MFC outer loops" in out and "### Baseline: PX4 default cascade" in out
    assert "### MFC / baseline" in out
    ratio_rows = out.split("### MFC / baseline")[1].strip().splitlines()[4:]
    assert len(ratio_rows) == len(SCENARIOS)
    assert all(r.startswith("| DJI F450 |") for r in ratio_rows)


# --- paths: the figure eight, the fast square, the path error ---------------------------


@pytest.mark.parametrize("name", ["figure-eight", "figure-eight-fast"])
def test_the_figure_eight_is_a_lemniscate_flown_at_its_speed(name: str) -> None:
    sc = SCENARIOS[name]
    top = 2.0 if name == "figure-eight" else 5.0
    t = np.arange(0.0, sc.duration_s - sc.start_s, 0.01)
    sps = [sc.setpoints(x) for x in t]
    pos = np.array([s.position_ne_m for s in sps])
    vel = np.array([s.velocity_ne_m_s for s in sps])
    moving = np.hypot(*vel.T) > 0.0
    # Gerono's lemniscate: e = n * sqrt(1 - (n / size)^2), here size 8 m.
    n, e = pos[moving].T
    np.testing.assert_allclose(e**2, n**2 * (1.0 - (n / 8.0) ** 2), atol=1e-9)
    assert np.hypot(*vel[moving].T).max() == pytest.approx(top, rel=1e-3)
    # The velocity and acceleration fed forward are the path's own (central differences).
    dpos = np.gradient(pos[moving], 0.01, axis=0)
    np.testing.assert_allclose(dpos[1:-1], vel[moving][1:-1], atol=1e-3)
    acc = np.array([s.accel_ne_m_s2 for s in sps])[moving]
    np.testing.assert_allclose(np.gradient(vel[moving], 0.01, axis=0)[1:-1], acc[1:-1], atol=1e-3)
    assert np.abs(acc).max() > 0.4
    # It starts and ends at the origin and then holds there.
    np.testing.assert_allclose(pos[0], (0.0, 0.0), atol=1e-12)
    assert not moving[-1] and tuple(pos[-1]) == (0.0, 0.0)


@pytest.mark.long
def test_a_path_scenario_reports_its_path_error() -> None:
    sc = SCENARIOS["square-fast"].with_duration(16.0)  # 6 s of its first legs
    out = outer_metrics(simulate_outer_flight(_f450(), _rate_cfg(), sc), sc)
    assert not out["crashed"]
    # The vehicle lags behind the moving setpoint more than it strays from the path.
    assert 0.0 < out["path_rms_m"] < out["pos_rms_h_m"]
    assert out["path_max_m"] >= out["path_rms_m"]
    hold = SCENARIOS["position-hold"].with_duration(2.0)
    assert (
        outer_metrics(simulate_outer_flight(_f450(), _rate_cfg(), hold), hold)["path_rms_m"] is None
    )


def test_a_damaged_vehicle_that_hops_at_take_off_still_climbs() -> None:
    """The cut-prop F450 with motor 0 at 80 %: it hops, touches down, and lifts off
    again (the rate law starts afresh on its legs); it hovered on the ground,
    collective cut by a saturated mixer, when the law kept its F from the hop."""
    from sitl.lab.campaign import damaged_profile
    from sitl.lab.outer_flight import _profile

    plant = damaged_profile(_profile("f450_cut_props"), 0.8)
    sc = SCENARIOS["position-hold"].with_duration(16.0)
    out = outer_metrics(simulate_outer_flight(plant, _rate_cfg(), sc), sc)
    assert not out["crashed"]
    assert out["pos_rms_v_m"] < 0.5  # 5.0 (the hold altitude) when it stayed down


@pytest.mark.long
def test_a_vehicle_tipped_at_lift_off_by_a_weak_motor_is_flown_and_backs_off() -> None:
    """The cut-prop F450 with motor 0 at 65 %: the weak motor tips it at lift-off,
    before the 4 Hz landed state clears. A rate law restarted on every sample of that
    state hopped for the whole flight, the vertical error the hold altitude (4.99 m
    in the paper vehicles' sweep); flown once the gyro shows the legs do not hold it
    (``MfcController.held_on_ground``), it climbs.

    Regression pin. Measured over 20 s with this test's flight, 2026-11-29, on the
    EKF_GPS estimate as measured on the real EKF2: it hops at 2 s and 6 s and sits on
    its legs, the rate loop saturated, until 16 s, then climbs (4.01 m up at 20 s;
    vertical RMS 3.85 m); the outer gains backed off to their floor (0.55) for 6.0 s.
    On the earlier estimate (errors a third the size, no tilt offset) it climbed at
    once and held at 0.42 m vertical RMS; PX4's default cascade climbs at once on
    either (4.67 m up at 20 s). Why the damaged vehicle stays on its legs so long
    on the realistic estimate is open (docs/research/outer.md, open problems)."""
    from sitl.lab.campaign import damaged_profile
    from sitl.lab.outer_flight import _profile

    plant = damaged_profile(_profile("f450_cut_props"), 0.65)
    sc = SCENARIOS["position-hold"].with_duration(20.0)
    fl = simulate_outer_flight(plant, _rate_cfg(), sc)
    out = outer_metrics(fl, sc)
    assert not out["crashed"]
    assert -fl.columns["pos_ned_m"][-1, 2] > 3.5 and fl.columns["airborne"][-2000:].all()
    assert out["gain_scale_min"] == pytest.approx(0.55) and out["backed_off_s"] > 1.0


@pytest.mark.long
def test_a_vehicle_losing_its_heading_to_yaw_saturation_is_given_a_yaw_share() -> None:
    """The cut-prop F450 with motor 0 at 60 % holding position: with roll and pitch
    always first, the weak motor leaves yaw no room, the vehicle turns where yaw
    drives it and drifts off (20.4 m horizontal RMS, 4.8 m vertical, heading 14.3 deg
    MAE: measured, this flight); the shipped rate loop gives yaw a share of roll and
    pitch once the heading is being lost (companion/control/yaw_share.py) and holds
    the position (0.85 m, heading 11.5 deg).

    Regression pin, measured 2026-11-29 with this flight (the outer sweep's seed); on
    seeds 1 and 2: 0.78 and 0.87 m, 14.2 and 9.5 deg, against 1.28 and 4.74 m, 70.9
    and 87.0 deg without the share (docs/research/mixer.md, "Yaw's share on demand")."""
    from sitl.lab.campaign import damaged_profile
    from sitl.lab.outer_flight import _profile

    plant = damaged_profile(_profile("f450_cut_props"), 0.6)
    sc = SCENARIOS["position-hold"]
    shipped = _rate_cfg()
    assert isinstance(shipped, MfcConfig) and shipped.yaw_share_max == 0.5
    fl = simulate_outer_flight(plant, shipped, sc)
    out = outer_metrics(fl, sc)
    assert not out["crashed"] and out["yaw_mae_deg"] < 15.0 and out["pos_rms_h_m"] < 1.5
    assert out["yaw_share_s"] > 5.0 and fl.columns["yaw_share"].max() == 0.5
    first = shipped.model_copy(update={"yaw_share_max": 0.0})
    lost = outer_metrics(simulate_outer_flight(plant, first, sc), sc)
    assert lost["yaw_share_s"] == 0.0
    assert lost["crashed"] or lost["pos_rms_h_m"] > 5.0
