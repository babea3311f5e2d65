"""Physics of the SITL plant against analytic answers."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.errors import ConfigError
from companion.profile import VehicleProfile, load_profile
from sitl import frames
from sitl.frames import euler_to_quat, quat_rotate, quat_to_euler_rad
from sitl.imu import Imu
from sitl.physics import CRASH_SPEED_M_S, Quadrotor
from sitl.rotors import hover_motor_command, motor_command_to_speed
from sitl.vehicle_params import GRAVITY_M_S2, VehicleParams
from sitl.wind import Wind, WindConfig

PROFILES = Path(__file__).resolve().parents[2] / "vehicle_profiles"
G = GRAVITY_M_S2


def f450() -> VehicleProfile:
    return load_profile(PROFILES / "f450.yaml")


def modified(profile: VehicleProfile, **physics: Any) -> VehicleProfile:
    """Copy of ``profile`` with physics keys replaced, re-validated."""
    data = profile.model_dump()
    data["physics"].update(physics)
    return VehicleProfile.model_validate(data)


def frictionless(profile: VehicleProfile, **physics: Any) -> VehicleProfile:
    """No drag of any kind, so the answers are textbook ones."""
    return modified(
        profile,
        drag_linear_n_per_m_s=(0.0, 0.0, 0.0),
        drag_quadratic_n_per_m2_s2=(0.0, 0.0, 0.0),
        angular_drag_n_m_per_rad_s=(0.0, 0.0, 0.0),
        **physics,
    )


def cmd_for_speed(profile: VehicleProfile, w_rad_s: float) -> float:
    ph = profile.physics
    return (w_rad_s - ph.motor_w_idle_rad_s) / (ph.motor_w_max_rad_s - ph.motor_w_idle_rad_s)


def hover_speed(profile: VehicleProfile) -> float:
    ph = profile.physics
    return math.sqrt(ph.mass_kg * G / (profile.n_motors * ph.kf_n_per_rad_s2))


def quad(profile: VehicleProfile, seed: int = 0, **kw: Any) -> Quadrotor:
    return Quadrotor(profile, rng=np.random.default_rng(seed), **kw)


# --------------------------------------------------------------------------- motors


def test_command_mapping() -> None:
    assert motor_command_to_speed(0.0, 100.0, 700.0) == 0.0
    assert motor_command_to_speed(-0.5, 100.0, 700.0) == 0.0
    assert motor_command_to_speed(float("nan"), 100.0, 700.0) == 0.0
    assert motor_command_to_speed(float("inf"), 100.0, 700.0) == 0.0
    assert motor_command_to_speed(2.0, 100.0, 700.0) == 700.0
    np.testing.assert_allclose(motor_command_to_speed(0.5, 100.0, 700.0), 400.0, rtol=1e-15)


def test_step_rejects_wrong_command_count() -> None:
    with pytest.raises(ValueError, match="4 commands"):
        quad(f450()).step([0.5, 0.5, 0.5])


def test_motor_lag_time_constants_up_and_down() -> None:
    # x500 has asymmetric lag: tau_up 12.5 ms, tau_down 25 ms.
    prof = load_profile(PROFILES / "x500.yaml")
    ph = prof.physics
    dt = 0.0005
    q = quad(prof, dt_s=dt, test_stand=True)
    n_up = round(ph.motor_tau_up_s / dt)
    for _ in range(n_up):
        q.step([1.0] * 4)
    # 63 % of the way to w_max after one time constant (exact solution, so tight).
    np.testing.assert_allclose(
        q.state.motor_w_rad_s, [ph.motor_w_max_rad_s * (1.0 - math.exp(-1.0))] * 4, rtol=1e-12
    )
    for _ in range(400):
        q.step([1.0] * 4)
    w_top = q.state.motor_w_rad_s[0]
    n_down = round(ph.motor_tau_down_s / dt)
    for _ in range(n_down):
        q.step([0.0] * 4)
    np.testing.assert_allclose(q.state.motor_w_rad_s, [w_top * math.exp(-1.0)] * 4, rtol=1e-12)


def test_non_finite_and_out_of_range_commands() -> None:
    prof = f450()
    q = quad(prof, test_stand=True)
    for _ in range(300):
        q.step([float("nan"), float("inf"), -3.0, 7.0])
    w = q.state.motor_w_rad_s
    assert w[0] == 0.0 and w[1] == 0.0 and w[2] == 0.0
    np.testing.assert_allclose(w[3], prof.physics.motor_w_max_rad_s, rtol=1e-5)


# --------------------------------------------------------------------- translation


def test_hover_command_is_analytic() -> None:
    prof = f450()
    w = hover_speed(prof)
    np.testing.assert_allclose(hover_motor_command(prof), cmd_for_speed(prof, w), rtol=1e-12)


def test_hover_equilibrium() -> None:
    prof = f450()
    w = hover_speed(prof)
    q = quad(prof)
    q.set_state(pos_ned_m=(1.0, -2.0, -10.0), motor_w_rad_s=[w] * 4)
    assert not q.state.landed
    cmd = [cmd_for_speed(prof, w)] * 4
    for _ in range(2000):
        q.step(cmd)
    s = q.state
    np.testing.assert_allclose(s.pos_ned_m, (1.0, -2.0, -10.0), atol=1e-9)
    np.testing.assert_allclose(s.vel_ned_m_s, (0.0, 0.0, 0.0), atol=1e-9)
    np.testing.assert_allclose(s.rate_frd_rad_s, (0.0, 0.0, 0.0), atol=1e-12)
    np.testing.assert_allclose(s.specific_force_frd_m_s2, (0.0, 0.0, -G), atol=1e-9)
    np.testing.assert_allclose(s.t_s, 2.0, rtol=1e-12)


def test_free_fall_from_rest() -> None:
    q = quad(frictionless(f450()))
    q.set_state(pos_ned_m=(0.0, 0.0, -100.0))
    for _ in range(1000):
        q.step([0.0] * 4)
    s = q.state
    np.testing.assert_allclose(s.vel_ned_m_s, (0.0, 0.0, G * 1.0), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(s.pos_ned_m, (0.0, 0.0, -100.0 + 0.5 * G), rtol=1e-9)
    # A falling accelerometer reads nothing.
    np.testing.assert_allclose(s.specific_force_frd_m_s2, (0.0, 0.0, 0.0), atol=1e-12)


def test_drag_gives_terminal_velocity() -> None:
    # Falling flat: m g = c1 v + c2 v^2 along body z.
    prof = modified(
        f450(), drag_linear_n_per_m_s=(0.1, 0.1, 0.2), drag_quadratic_n_per_m2_s2=(0.02, 0.02, 0.05)
    )
    q = quad(prof)
    q.set_state(pos_ned_m=(0.0, 0.0, -5000.0))
    for _ in range(30000):
        q.step([0.0] * 4)
    c1, c2, m = 0.2, 0.05, prof.physics.mass_kg
    v_term = (-c1 + math.sqrt(c1 * c1 + 4 * c2 * m * G)) / (2 * c2)
    np.testing.assert_allclose(q.state.vel_ned_m_s[2], v_term, rtol=1e-4)


def test_drag_is_relative_to_the_air() -> None:
    # A vehicle at rest in a steady 5 m/s east wind is pushed east.
    prof = f450()
    w = hover_speed(prof)
    wind = Wind(WindConfig(steady_ned_m_s=(0.0, 5.0, 0.0)), rng=np.random.default_rng(1))
    q = quad(prof, wind=wind)
    q.set_state(pos_ned_m=(0.0, 0.0, -10.0), motor_w_rad_s=[w] * 4)
    q.step([cmd_for_speed(prof, w)] * 4)
    cl, cq = prof.physics.drag_linear_n_per_m_s[1], prof.physics.drag_quadratic_n_per_m2_s2[1]
    expected_f_y = (cl * 5.0 + cq * 25.0) / prof.physics.mass_kg
    np.testing.assert_allclose(q.state.specific_force_frd_m_s2[1], expected_f_y, rtol=1e-3)
    assert q.wind_ned_m_s == (0.0, 5.0, 0.0)


# ------------------------------------------------------------------------ rotation


def steady_test_stand(prof: VehicleProfile, w: list[float], **kw: Any) -> tuple[Quadrotor, list]:
    """Test-stand vehicle with rotors already at ``w`` and the matching commands."""
    q = quad(prof, test_stand=True, **kw)
    q.set_state(motor_w_rad_s=w)
    return q, [cmd_for_speed(prof, x) for x in w]


def test_pure_roll_torque_gives_tau_over_ixx() -> None:
    prof = frictionless(f450())
    ph = prof.physics
    w_lo, w_hi = 400.0, 500.0
    # Motors 1 (rear-left) and 2 (front-left) are on the left (y < 0): lifting them
    # rolls right. One CCW and one CW per side, so yaw torques cancel.
    w = [w_lo, w_hi, w_hi, w_lo]
    q, cmd = steady_test_stand(prof, w)
    t = 0.005
    for _ in range(round(t / q.dt_s)):
        q.step(cmd)
    arm_y = 0.159
    tau_x = 2 * arm_y * ph.kf_n_per_rad_s2 * (w_hi**2 - w_lo**2)
    p_expected = tau_x / ph.inertia_kg_m2[0][0] * t
    s = q.state
    assert s.rate_frd_rad_s[0] > 0.0
    np.testing.assert_allclose(s.rate_frd_rad_s, (p_expected, 0.0, 0.0), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(quat_to_euler_rad(s.q_wxyz)[0], 0.5 * p_expected * t, rtol=1e-6)


def test_ccw_rotors_yaw_the_nose_right() -> None:
    prof = frictionless(f450(), rotor_inertia_kg_m2=0.0)
    ph = prof.physics
    spins = [m.spin for m in prof.frame.motors]
    assert spins == ["ccw", "ccw", "cw", "cw"]
    w_lo, w_hi = 400.0, 500.0
    q, cmd = steady_test_stand(prof, [w_hi, w_hi, w_lo, w_lo])
    t = 0.01
    for _ in range(round(t / q.dt_s)):
        q.step(cmd)
    tau_z = 2 * ph.km_m * ph.kf_n_per_rad_s2 * (w_hi**2 - w_lo**2)
    s = q.state
    assert s.rate_frd_rad_s[2] > 0.0  # CW reaction on the frame = positive yaw in FRD
    np.testing.assert_allclose(
        s.rate_frd_rad_s, (0.0, 0.0, tau_z / ph.inertia_kg_m2[2][2] * t), rtol=1e-9, atol=1e-12
    )
    assert quat_to_euler_rad(s.q_wxyz)[2] > 0.0


def test_rotor_spin_up_reaction_torque() -> None:
    # Spinning up a CCW rotor pushes the frame the other way: CW from above, +yaw.
    prof = frictionless(f450(), km_m=1e-9)
    jr, izz = prof.physics.rotor_inertia_kg_m2, prof.physics.inertia_kg_m2[2][2]
    q = quad(prof, test_stand=True)
    for _ in range(50):
        q.step([0.8, 0.0, 0.0, 0.0])
    s = q.state
    # Angular momentum about z: Izz r + h_rotor_z = 0 with h_rotor_z = -J_r w (CCW).
    np.testing.assert_allclose(izz * s.rate_frd_rad_s[2], jr * s.motor_w_rad_s[0], rtol=1e-3)


def test_rotor_gyroscopic_precession() -> None:
    prof = frictionless(f450(), km_m=1e-9)
    ph = prof.physics
    w_ccw, w_cw = 600.0, 300.0
    q, cmd = steady_test_stand(prof, [w_ccw, w_ccw, w_cw, w_cw])
    p0 = 1.0
    q.set_state(rate_frd_rad_s=(p0, 0.0, 0.0))
    q.step(cmd)
    # J dw/dt = -w x h_r with h_r = (0, 0, -J_r sum(sigma w)): q_dot = p h_z / Iyy.
    h_z = -ph.rotor_inertia_kg_m2 * (2 * w_ccw - 2 * w_cw)
    q_dot = p0 * h_z / ph.inertia_kg_m2[1][1]
    np.testing.assert_allclose(q.state.rate_frd_rad_s[1] / q.dt_s, q_dot, rtol=2e-3)


def test_torque_free_spin_conserves_angular_momentum_and_energy() -> None:
    J = ((0.02, 0.001, 0.0), (0.001, 0.03, -0.002), (0.0, -0.002, 0.045))
    prof = frictionless(f450(), inertia_kg_m2=J)
    q = quad(prof, test_stand=True)
    q.set_state(rate_frd_rad_s=(4.0, 0.5, -2.0), q_wxyz=euler_to_quat(0.3, -0.2, 1.0))
    Jm = np.array(J)

    def momentum_and_energy() -> tuple[np.ndarray, float]:
        s = q.state
        om = np.array(s.rate_frd_rad_s)
        L_b = Jm @ om
        return np.array(quat_rotate(s.q_wxyz, tuple(L_b))), 0.5 * float(om @ L_b)

    L0, E0 = momentum_and_energy()
    max_norm_err = 0.0
    for _ in range(3000):
        q.step([0.0] * 4)
        qq = q.state.q_wxyz
        max_norm_err = max(max_norm_err, abs(math.fsum(x * x for x in qq) - 1.0))
    L1, E1 = momentum_and_energy()
    np.testing.assert_allclose(L1, L0, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(E1, E0, rtol=1e-7)
    assert not np.allclose(q.state.rate_frd_rad_s, (4.0, 0.5, -2.0), atol=1e-2)  # it precessed
    assert max_norm_err < 1e-12


def test_quaternion_stays_unit_in_aggressive_flight() -> None:
    prof = f450()
    q = quad(prof)
    q.set_state(pos_ned_m=(0.0, 0.0, -500.0))
    rng = np.random.default_rng(3)
    for k in range(3000):
        if k % 50 == 0:
            cmd = rng.uniform(0.0, 1.0, 4).tolist()
        q.step(cmd)
        qq = q.state.q_wxyz
        assert abs(math.fsum(x * x for x in qq) - 1.0) < 1e-12
    assert not q.state.crashed


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=4, max_size=4))
def test_state_stays_finite_for_any_command(cmd: list[float]) -> None:
    q = quad(load_profile(PROFILES / "f450_cut_props.yaml"))
    q.set_state(pos_ned_m=(0.0, 0.0, -100.0))
    for _ in range(200):
        q.step(cmd)
    s = q.state
    flat = [*s.pos_ned_m, *s.vel_ned_m_s, *s.q_wxyz, *s.rate_frd_rad_s, *s.motor_w_rad_s]
    assert all(math.isfinite(x) for x in flat)


# -------------------------------------------------------------------------- ground


def test_starts_landed_and_does_not_sink() -> None:
    prof = f450()
    q = quad(prof)
    s = q.state
    assert s.landed and not s.crashed
    assert s.pos_ned_m == (0.0, 0.0, 0.0) and s.q_wxyz == (1.0, 0.0, 0.0, 0.0)
    below_hover = 0.9 * hover_motor_command(prof)
    for _ in range(2000):
        q.step([below_hover, 0.05, below_hover, 0.3])  # uneven: still no tipping or sliding
    s = q.state
    assert s.landed
    assert s.pos_ned_m == (0.0, 0.0, 0.0)
    assert s.vel_ned_m_s == (0.0, 0.0, 0.0)
    assert s.rate_frd_rad_s == (0.0, 0.0, 0.0)
    np.testing.assert_allclose(s.specific_force_frd_m_s2, (0.0, 0.0, -G), atol=1e-12)
    assert s.motor_w_rad_s[0] > 0.0  # motors spin while sitting on the ground


def test_takeoff_and_gentle_landing() -> None:
    prof = f450()
    q = quad(prof)
    for _ in range(500):
        q.step([0.8] * 4)
    assert not q.state.landed
    assert q.state.pos_ned_m[2] < -0.1
    # Cut power: from ~0.2 m the vehicle is slow enough to land, not crash.
    q.set_state(pos_ned_m=(0.0, 0.0, -0.2), vel_ned_m_s=(0.0, 0.0, 0.0))
    for _ in range(1000):
        q.step([0.0] * 4)
    s = q.state
    assert s.landed and not s.crashed
    assert s.pos_ned_m[2] == 0.0 and s.vel_ned_m_s == (0.0, 0.0, 0.0)


def test_hard_impact_crashes_and_freezes() -> None:
    prof = f450()
    q = quad(prof)
    h = 1.0  # impact at sqrt(2 g h) = 4.4 m/s > 3 m/s
    assert math.sqrt(2 * G * h) > CRASH_SPEED_M_S
    q.set_state(pos_ned_m=(0.0, 0.0, -h))
    for _ in range(1000):
        q.step([0.0] * 4)
    s = q.state
    assert s.crashed and not s.landed
    assert s.pos_ned_m[2] == 0.0
    q.step([1.0] * 4)
    assert q.state == s  # frozen, time included


def test_tilted_touchdown_at_speed_crashes() -> None:
    q = quad(frictionless(f450()))
    q.set_state(pos_ned_m=(0.0, 0.0, -0.2), q_wxyz=euler_to_quat(math.radians(70), 0.0, 0.0))
    for _ in range(1000):
        q.step([0.0] * 4)
    assert q.state.crashed


def test_test_stand_holds_position() -> None:
    prof = f450()
    q = quad(prof, test_stand=True)
    assert not q.state.landed
    for _ in range(1000):
        q.step([1.0, 1.0, 0.2, 0.2])  # CCW rotors fast: yaws
    s = q.state
    assert s.pos_ned_m == (0.0, 0.0, 0.0) and s.vel_ned_m_s == (0.0, 0.0, 0.0)
    assert not s.landed and not s.crashed
    assert abs(s.rate_frd_rad_s[2]) > 0.1  # but it turns
    # Held still: the accelerometer reads gravity only, rotated into the body.
    g_body = quat_rotate((s.q_wxyz[0], -s.q_wxyz[1], -s.q_wxyz[2], -s.q_wxyz[3]), (0.0, 0.0, -G))
    np.testing.assert_allclose(s.specific_force_frd_m_s2, g_body, atol=1e-12)


# -------------------------------------------------------------------------- damage


def with_damage(profile: VehicleProfile, **damage: Any) -> VehicleProfile:
    data = profile.model_dump()
    data["physics"]["damage"].update(damage)
    return VehicleProfile.model_validate(data)


def fit_sinusoid(t: np.ndarray, y: np.ndarray, omega: float) -> float:
    """Amplitude of the ``omega`` component, with an offset and a trend removed."""
    A = np.column_stack([np.cos(omega * t), np.sin(omega * t), np.ones_like(t), t])
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    return float(math.hypot(coef[0], coef[1]))


def test_imbalance_shows_in_gyro_at_rotor_frequency() -> None:
    base = frictionless(f450())
    data = base.model_dump()
    for m in data["frame"]["motors"]:
        m["position_frd_m"] = (m["position_frd_m"][0], m["position_frd_m"][1], -0.03)
    data["physics"]["damage"]["motors"] = [{"motor": 0, "imbalance_n": 10.0}]
    prof = VehicleProfile.model_validate(data)
    ph = prof.physics
    w = hover_speed(prof)
    q, cmd = steady_test_stand(prof, [w] * 4)
    imu = Imu(ph.imu, rng=np.random.default_rng(5), dt_s=q.dt_s)
    ts, gyro = [], []
    for _ in range(2000):
        q.step(cmd)
        sample = imu.update(q.t_s, q.rate_frd_rad_s, q.specific_force_frd_m_s2)
        assert sample is not None
        ts.append(sample.time_s)
        gyro.append(sample.gyro_frd_rad_s)
    t = np.array(ts)
    g = np.array(gyro)
    f_rotor_hz = w / (2 * math.pi)
    for axis in (0, 2):
        y = g[:, axis] - np.polyval(np.polyfit(t, g[:, axis], 2), t)
        spec = np.abs(np.fft.rfft(y * np.hanning(len(y))))
        freqs = np.fft.rfftfreq(len(y), d=q.dt_s)
        band = freqs > 5.0
        f_peak = freqs[band][np.argmax(spec[band])]
        np.testing.assert_allclose(f_peak, f_rotor_hz, atol=1.0)  # 0.5 Hz bins
    # Amplitudes: yaw torque |r_xy| F, roll torque |r_z| F, rate = torque / (I Omega).
    F = 10.0 * (w / ph.motor_w_max_rad_s) ** 2
    r_xy = math.hypot(0.159, 0.159)
    amp_r = fit_sinusoid(t, g[:, 2], w)
    amp_p = fit_sinusoid(t, g[:, 0], w)
    np.testing.assert_allclose(amp_r, r_xy * F / (ph.inertia_kg_m2[2][2] * w), rtol=0.05)
    np.testing.assert_allclose(amp_p, 0.03 * F / (ph.inertia_kg_m2[0][0] * w), rtol=0.1)


def test_cut_props_vibrate_far_above_sensor_noise() -> None:
    prof = load_profile(PROFILES / "f450_cut_props.yaml")
    ph = prof.physics
    intact = hover_motor_command(prof, include_damage=False)
    q, _ = steady_test_stand(prof, [hover_speed(prof)] * 4)
    imu = Imu(ph.imu, rng=np.random.default_rng(2), dt_s=q.dt_s)
    g = []
    for _ in range(1000):
        q.step([intact] * 4)
        s = imu.update(q.t_s, q.rate_frd_rad_s, q.specific_force_frd_m_s2)
        assert s is not None
        g.append(s.gyro_frd_rad_s)
    gyro = np.array(g)
    t = np.arange(len(gyro)) * q.dt_s
    # Unequal cut props also tip the stand slowly: remove that before measuring shake.
    shake = [np.std(gyro[:, i] - np.polyval(np.polyfit(t, gyro[:, i], 3), t)) for i in range(3)]
    sensor = ph.imu.gyro_noise_density_rad_s_sqrt_hz * math.sqrt(ph.imu.rate_hz)
    assert min(shake) > 5 * sensor
    assert max(shake) > math.radians(5.0)  # "began to vibrate badly"


def test_cut_props_reduce_thrust() -> None:
    prof = frictionless(load_profile(PROFILES / "f450_cut_props.yaml"))
    effs = [d.thrust_efficiency for d in prof.physics.damage.motors]
    w = hover_speed(prof)
    q = quad(prof)
    q.set_state(pos_ned_m=(0.0, 0.0, -50.0), motor_w_rad_s=[w] * 4)
    q.step([cmd_for_speed(prof, w)] * 4)
    # Same rotor speeds as the intact hover, so thrust is mean(eff) of the weight.
    np.testing.assert_allclose(q.state.specific_force_frd_m_s2[2], -G * np.mean(effs), rtol=1e-6)
    assert prof.thrust_to_weight() * min(effs) > 1.3
    assert hover_motor_command(prof) > hover_motor_command(prof, include_damage=False)


def test_cg_offset_produces_the_expected_torques() -> None:
    dx, dy = 0.02, 0.03
    d_ixx = 0.004
    base = frictionless(f450(), rotor_inertia_kg_m2=0.0)
    prof = with_damage(
        base,
        cg_offset_frd_m=(dx, dy, 0.0),
        inertia_delta_kg_m2=((d_ixx, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
    )
    ph = prof.physics
    w = hover_speed(prof)
    q, cmd = steady_test_stand(prof, [w] * 4)
    t = 0.005
    for _ in range(round(t / q.dt_s)):
        q.step(cmd)
    thrust = ph.mass_kg * G  # equal rotors at hover speed
    # Motor arms shrink on the heavy side: CG right rolls right, CG forward noses down.
    p_dot = dy * thrust / (ph.inertia_kg_m2[0][0] + d_ixx)
    q_dot = -dx * thrust / ph.inertia_kg_m2[1][1]
    np.testing.assert_allclose(
        q.state.rate_frd_rad_s, (p_dot * t, q_dot * t, 0.0), rtol=1e-3, atol=1e-5
    )  # atol: Euler coupling r_dot = (Ixx - Iyy) p q / Izz is second order


def test_inertia_delta_must_keep_inertia_positive_definite(tmp_path: Path) -> None:
    # The profile schema rejects it at load time, naming the file and the key.
    data = f450().model_dump(mode="json")
    data["physics"]["damage"]["inertia_delta_kg_m2"] = [[-0.03, 0, 0], [0, 0, 0], [0, 0, 0]]
    bad = tmp_path / "bad_inertia.yaml"
    bad.write_text(yaml.safe_dump(data), encoding="utf-8")
    with pytest.raises(ConfigError, match="inertia_delta_kg_m2") as info:
        load_profile(bad)
    assert "bad_inertia.yaml" in str(info.value)


def test_motor_fails_at_fail_at_s() -> None:
    prof = with_damage(
        f450(),
        motors=[
            {"motor": 2, "fail_at_s": 0.5, "efficiency_after_fail": 0.0},
            {"motor": 3, "fail_at_s": 0.5, "efficiency_after_fail": 0.5},
        ],
    )
    w = hover_speed(prof)
    q, cmd = steady_test_stand(prof, [w] * 4)
    for _ in range(500):
        q.step(cmd)
    np.testing.assert_allclose(q.state.motor_w_rad_s, [w] * 4, rtol=1e-9)
    for _ in range(300):  # > 10 time constants
        q.step(cmd)
    ws = q.state.motor_w_rad_s
    np.testing.assert_allclose(ws[:2], [w, w], rtol=1e-9)
    assert ws[2] < 1e-3 * w
    # Half the thrust: speed scaled by sqrt(0.5).
    np.testing.assert_allclose(ws[3] ** 2, 0.5 * w**2, rtol=1e-6)


def test_set_motor_failure_now() -> None:
    prof = f450()
    w = hover_speed(prof)
    q, cmd = steady_test_stand(prof, [w] * 4)
    q.set_motor_failure(1, efficiency=0.25)
    for _ in range(500):
        q.step(cmd)
    np.testing.assert_allclose(q.state.motor_w_rad_s[1], 0.5 * w, rtol=1e-6)
    with pytest.raises(ValueError):
        q.set_motor_failure(4)


def test_params_apply_damage_per_motor() -> None:
    prof = load_profile(PROFILES / "f450_cut_props.yaml")
    P = VehicleParams.from_profile(prof)
    kf = prof.physics.kf_n_per_rad_s2
    np.testing.assert_allclose(P.thrust_coeff, [kf * 0.686, kf * 0.656, kf * 0.627, kf * 0.656])
    assert P.spin_sign == (1.0, 1.0, -1.0, -1.0)


# ------------------------------------------------------------------- determinism


def run_flight(seed: int) -> list:
    prof = load_profile(PROFILES / "f450_cut_props.yaml")
    rng = np.random.default_rng(seed)
    wind = Wind(WindConfig(steady_ned_m_s=(1.0, 2.0, 0.0), gust_sigma_m_s=1.5), rng=rng)
    q = Quadrotor(prof, rng=rng, wind=wind)
    q.set_state(pos_ned_m=(0.0, 0.0, -50.0))
    imu = Imu(prof.physics.imu, rng=rng, dt_s=q.dt_s)
    out = []
    for k in range(1000):
        c = 0.8 if k < 500 else 0.72
        q.step([c, c, c + 0.01, c - 0.01])
        sample = imu.update(q.t_s, q.rate_frd_rad_s, q.specific_force_frd_m_s2)
        out.append((q.state, sample))
    return out


def test_same_seed_gives_bit_identical_flight() -> None:
    a, b = run_flight(7), run_flight(7)
    assert a == b
    assert not a[-1][0].landed and not a[-1][0].crashed


def test_different_seed_gives_different_noise() -> None:
    a, b = run_flight(7), run_flight(8)
    assert a[-1][1] is not None and b[-1][1] is not None
    assert a[-1][1] != b[-1][1]
    assert a[-1][0].pos_ned_m != b[-1][0].pos_ned_m


# ---------------------------------------------------------------- frames (sitl.frames)


def test_quat_mul_composes_rotations() -> None:
    qz = euler_to_quat(0.0, 0.0, math.pi / 2)  # yaw 90 deg
    qx = euler_to_quat(math.pi / 2, 0.0, 0.0)  # roll 90 deg
    # Body x after yaw 90 points east; then q = qz * qx: roll first (body), then yaw.
    q = frames.quat_mul(qz, qx)
    np.testing.assert_allclose(quat_rotate(q, (0.0, 1.0, 0.0)), (0.0, 0.0, 1.0), atol=1e-15)
    np.testing.assert_allclose(quat_rotate(q, (1.0, 0.0, 0.0)), (0.0, 1.0, 0.0), atol=1e-15)
    ident = frames.quat_mul(q, frames.quat_conj(q))
    np.testing.assert_allclose(ident, (1.0, 0.0, 0.0, 0.0), atol=1e-15)


def test_normalise() -> None:
    np.testing.assert_allclose(frames.normalise((2.0, 0.0, 0.0, 0.0)), (1.0, 0.0, 0.0, 0.0))
    q = frames.normalise((1.0, 2.0, -3.0, 4.0))
    np.testing.assert_allclose(sum(x * x for x in q), 1.0, rtol=1e-15)
    with pytest.raises(ValueError):
        frames.normalise((0.0, 0.0, 0.0, 0.0))


def test_rotation_conventions_ned_frd() -> None:
    # Nose up 30 deg: the body x axis points north and up (negative down).
    q = euler_to_quat(0.0, math.radians(30), 0.0)
    np.testing.assert_allclose(
        quat_rotate(q, (1.0, 0.0, 0.0)), (math.cos(math.pi / 6), 0.0, -0.5), atol=1e-15
    )
    # Right wing down 30 deg: body y points east and down.
    q = euler_to_quat(math.radians(30), 0.0, 0.0)
    np.testing.assert_allclose(
        quat_rotate(q, (0.0, 1.0, 0.0)), (0.0, math.cos(math.pi / 6), 0.5), atol=1e-15
    )
    v = (0.3, -1.2, 2.0)
    np.testing.assert_allclose(frames.quat_rotate_inv(q, quat_rotate(q, v)), v, atol=1e-15)
    R = np.array(frames.quat_to_dcm(q))
    np.testing.assert_allclose(R @ np.array(v), quat_rotate(q, v), atol=1e-15)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)


@given(
    st.floats(-3.1, 3.1),
    st.floats(-1.5, 1.5),
    st.floats(-3.1, 3.1),
)
def test_euler_round_trip(roll: float, pitch: float, yaw: float) -> None:
    q = euler_to_quat(roll, pitch, yaw)
    np.testing.assert_allclose(quat_to_euler_rad(q), (roll, pitch, yaw), atol=1e-9)
    np.testing.assert_allclose(
        frames.tilt_rad(q), math.acos(math.cos(roll) * math.cos(pitch)), atol=1e-7
    )


def test_frame_and_order_conversions() -> None:
    assert frames.ned_to_enu((1.0, 2.0, 3.0)) == (2.0, 1.0, -3.0)
    assert frames.frd_to_flu((1.0, 2.0, 3.0)) == (1.0, -2.0, -3.0)
    q = (0.5, 0.1, 0.2, 0.3)
    assert frames.q_wxyz_to_xyzw(q) == (0.1, 0.2, 0.3, 0.5)
    assert frames.q_xyzw_to_wxyz(frames.q_wxyz_to_xyzw(q)) == q
