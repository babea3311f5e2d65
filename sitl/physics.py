"""Quadrotor (multirotor) rigid-body physics for the SITL.

Conventions: world NED, body FRD, ``q_wxyz`` rotates body to world (see
:mod:`sitl.frames`). State ``x = (p, v, q, omega)`` plus per-motor rotor speed
``w_i`` and rotor phase ``phi_i``.

Equations of motion
-------------------
Translational (world), with ``R = R(q)`` and body force ``F_b``:

.. math::

    \\dot p = v, \\qquad m \\dot v = R F_b + m g e_z,

    F_b = \\sum_i \\left(-k_{T,i} w_i^2 e_z + F_{imb,i}\\right)
          - C_1 u_b - C_2 u_b |u_b|, \\qquad u_b = R^T (v - v_{wind}),

with ``k_T,i = kf * thrust_efficiency_i`` and the drag terms per body axis.

Rotational (body, about the CG), with ``J`` the inertia (profile inertia plus
``damage.inertia_delta_kg_m2``) and ``h_r`` the rotor angular momentum:

.. math::

    \\dot q = \\tfrac12 q \\otimes (0, \\omega), \\qquad
    J \\dot\\omega = \\tau - \\omega \\times (J\\omega + h_r) - \\dot h_r - D\\omega,

    \\tau = \\sum_i r_i \\times (-k_{T,i} w_i^2 e_z + F_{imb,i})
            + \\sigma_i k_{Q,i} w_i^2 e_z,
    \\qquad h_r = -J_r \\sum_i \\sigma_i w_i\\, e_z,

where ``r_i`` is motor ``i``'s position relative to the CG
(``position_frd_m - damage.cg_offset_frd_m``), ``k_Q,i = km * kf *
torque_efficiency_i`` and ``sigma_i = +1`` for a CCW rotor (seen from above),
``-1`` for CW. Sign check: a CCW rotor spins about ``-z`` (up), its air drag
torque on it is CW from above, so the motor drives it CCW and the reaction on the
frame is CW from above, i.e. about ``+z`` in FRD: positive yaw (nose right). That
is why PX4 raises its CCW motors to yaw right. Gravity acts at the CG, so it
produces no torque.

Rotor imbalance (a cut or damaged prop) is a radial force rotating with the
rotor at its position: ``F_imb,i = A_i (w_i / w_max)^2 (cos phi_i, sin phi_i, 0)``
with ``dphi_i/dt = -sigma_i w_i`` (a CCW rotor turns from +y towards +x in FRD).
It excites the airframe at the rotor frequency ``w_i / 2pi``: through the yaw arm
and, when the rotor plane is above or below the CG, in roll and pitch.

Motors
------
Commands are normalised, clamped to ``[0, 1]`` (non-finite reads as 0). A
command of exactly 0 means "stopped" (disarmed): ``w_cmd = 0``. Any positive
command maps linearly onto speed,
``w_cmd = w_idle + cmd (w_max - w_idle)``, so thrust is quadratic in the command
as on a real ESC. Rotor speed follows a first-order lag with ``tau_up`` when
speeding up and ``tau_down`` when slowing down. With the command held over a step
this ODE is solved exactly, ``w(s) = w_cmd + (w_0 - w_cmd) e^{-s/tau}`` (it never
crosses ``w_cmd``, so the choice of tau is fixed within a step), as is the phase
integral; the rigid body is integrated with classic fixed-step RK4. Because the
motor wrench does not depend on the rigid-body state, it is evaluated once at the
three RK4 nodes ``s = 0, dt/2, dt``.

Damage: after ``fail_at_s`` a motor delivers ``efficiency_after_fail`` of its
thrust and torque, modelled as a loss of motor power: its commanded speed is
scaled by ``sqrt(efficiency_after_fail)`` (0: the rotor spins down and stops).

Ground and test stand
---------------------
Flat ground at ``z = 0``. A landed vehicle stays level (yaw kept), still, and at
``z = 0`` until thrust exceeds its weight. Touching down faster than
:data:`CRASH_SPEED_M_S` vertically, or tilted beyond :data:`CRASH_TILT_RAD` while
moving faster than :data:`CRASH_TILT_SPEED_M_S`, is a crash: the simulation
freezes. In test-stand mode the vehicle sits on a gimbal pivoting at its CG:
position and velocity are held, only the attitude moves; it never lands or
crashes.

Simplifications: no blade flapping, induced drag or ground effect; the motor
speed reached does not depend on the prop load (a cut prop spins no faster);
drag acts at the CG (no drag torque other than the angular term ``D omega``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from companion.profile import VehicleProfile
from sitl.frames import euler_to_quat, quat_to_euler_rad
from sitl.wind import Wind

__all__ = [
    "CRASH_SPEED_M_S",
    "CRASH_TILT_RAD",
    "CRASH_TILT_SPEED_M_S",
    "GRAVITY_M_S2",
    "Quadrotor",
    "VehicleParams",
    "VehicleState",
    "hover_motor_command",
    "motor_command_to_speed",
]

_log = logging.getLogger(__name__)

#: Standard gravity (m/s²), as in ``VehicleProfile.thrust_to_weight``.
GRAVITY_M_S2 = 9.80665
#: Vertical touchdown speed above which the vehicle is wrecked (m/s).
CRASH_SPEED_M_S = 3.0
#: Tilt at touchdown beyond which a moving vehicle tips over and breaks props (rad).
CRASH_TILT_RAD = math.radians(60.0)
#: Speed above which a touchdown beyond :data:`CRASH_TILT_RAD` counts as a crash (m/s).
CRASH_TILT_SPEED_M_S = 0.5

_TWO_PI = 2.0 * math.pi


@dataclass(frozen=True)
class VehicleState:
    """A snapshot of the simulated vehicle.

    Attributes
    ----------
    t_s : float
        Simulation time (s).
    pos_ned_m : tuple of 3 float
        CG position in NED (m); the ground is ``z = 0``.
    vel_ned_m_s : tuple of 3 float
        CG velocity in NED (m/s).
    q_wxyz : tuple of 4 float
        Unit quaternion rotating body FRD into world NED.
    rate_frd_rad_s : tuple of 3 float
        Body angular rate (FRD, rad/s).
    motor_w_rad_s : tuple of float
        Rotor speeds (rad/s), in motor output order.
    specific_force_frd_m_s2 : tuple of 3 float
        Non-gravitational force per unit mass in FRD (m/s²), what a noise-free
        accelerometer at the CG reads (``(0, 0, -g)`` level at rest), averaged
        over the last step.
    landed : bool
        Resting on the ground.
    crashed : bool
        Hit the ground too hard; the simulation is frozen.
    """

    t_s: float
    pos_ned_m: tuple[float, float, float]
    vel_ned_m_s: tuple[float, float, float]
    q_wxyz: tuple[float, float, float, float]
    rate_frd_rad_s: tuple[float, float, float]
    motor_w_rad_s: tuple[float, ...]
    specific_force_frd_m_s2: tuple[float, float, float]
    landed: bool
    crashed: bool


@dataclass(frozen=True)
class VehicleParams:
    """Profile numbers turned into what the integrators use (SI units throughout).

    Built once by :meth:`from_profile`; shared by :class:`Quadrotor` and
    :class:`sitl.batch.BatchQuadrotor` so both read a profile the same way.
    """

    n_motors: int
    mass_kg: float
    inertia_kg_m2: tuple[tuple[float, float, float], ...]
    inertia_inv: tuple[tuple[float, float, float], ...]
    arm_frd_m: tuple[tuple[float, float, float], ...]  # motor positions relative to the CG
    spin_sign: tuple[float, ...]  # +1 CCW (positive yaw reaction), -1 CW
    thrust_coeff: tuple[float, ...]  # N/(rad/s)^2, kf * thrust_efficiency
    torque_coeff: tuple[float, ...]  # N m/(rad/s)^2, km * kf * torque_efficiency
    imbalance_coeff: tuple[float, ...]  # N/(rad/s)^2, imbalance_n / w_max^2
    fail_at_s: tuple[float | None, ...]
    speed_scale_after_fail: tuple[float, ...]  # sqrt(efficiency_after_fail)
    w_idle_rad_s: float
    w_max_rad_s: float
    tau_up_s: float
    tau_down_s: float
    rotor_inertia_kg_m2: float
    drag_linear: tuple[float, float, float]
    drag_quadratic: tuple[float, float, float]
    drag_angular: tuple[float, float, float]

    @classmethod
    def from_profile(cls, profile: VehicleProfile) -> VehicleParams:
        """Derive integrator constants from a validated profile.

        Raises
        ------
        ValueError
            If the inertia plus ``damage.inertia_delta_kg_m2`` is not symmetric
            positive definite (the profile schema checks only the undamaged one).
        """
        ph = profile.physics
        dmg = ph.damage
        n = profile.n_motors
        J = np.array(ph.inertia_kg_m2, dtype=float) + np.array(dmg.inertia_delta_kg_m2, dtype=float)
        if not np.allclose(J, J.T, atol=1e-12) or np.linalg.eigvalsh(J).min() <= 0.0:
            raise ValueError(
                "physics.inertia_kg_m2 + physics.damage.inertia_delta_kg_m2: expected a "
                f"symmetric positive-definite matrix, got {J.tolist()}"
            )
        J_inv = np.linalg.inv(J)

        def rows(a: np.ndarray) -> tuple[tuple[float, float, float], ...]:
            return tuple((float(r[0]), float(r[1]), float(r[2])) for r in a)

        cg = dmg.cg_offset_frd_m
        arms = tuple(
            (m.position_frd_m[0] - cg[0], m.position_frd_m[1] - cg[1], m.position_frd_m[2] - cg[2])
            for m in profile.frame.motors
        )
        thrust_eff = [1.0] * n
        torque_eff = [1.0] * n
        imbalance = [0.0] * n
        fail_at: list[float | None] = [None] * n
        after = [1.0] * n
        for d in dmg.motors:
            thrust_eff[d.motor] *= d.thrust_efficiency
            torque_eff[d.motor] *= d.torque_efficiency
            imbalance[d.motor] += d.imbalance_n
            if d.fail_at_s is not None:
                fail_at[d.motor] = d.fail_at_s
                after[d.motor] = math.sqrt(d.efficiency_after_fail)
        kf = ph.kf_n_per_rad_s2
        w_max = ph.motor_w_max_rad_s
        return cls(
            n_motors=n,
            mass_kg=ph.mass_kg,
            inertia_kg_m2=rows(J),
            inertia_inv=rows(J_inv),
            arm_frd_m=arms,
            spin_sign=tuple(1.0 if m.spin == "ccw" else -1.0 for m in profile.frame.motors),
            thrust_coeff=tuple(kf * e for e in thrust_eff),
            torque_coeff=tuple(ph.km_m * kf * e for e in torque_eff),
            imbalance_coeff=tuple(a / (w_max * w_max) for a in imbalance),
            fail_at_s=tuple(fail_at),
            speed_scale_after_fail=tuple(after),
            w_idle_rad_s=ph.motor_w_idle_rad_s,
            w_max_rad_s=w_max,
            tau_up_s=ph.motor_tau_up_s,
            tau_down_s=ph.motor_tau_down_s,
            rotor_inertia_kg_m2=ph.rotor_inertia_kg_m2,
            drag_linear=ph.drag_linear_n_per_m_s,
            drag_quadratic=ph.drag_quadratic_n_per_m2_s2,
            drag_angular=ph.angular_drag_n_m_per_rad_s,
        )


def motor_command_to_speed(cmd: float, w_idle_rad_s: float, w_max_rad_s: float) -> float:
    """Commanded rotor speed (rad/s) for a normalised command.

    ``0`` (or below, or non-finite) -> 0 (stopped); ``cmd in (0, 1]`` ->
    ``w_idle + cmd (w_max - w_idle)``; above 1 is clamped to ``w_max``.
    """
    if not 0.0 < cmd < math.inf:  # also catches NaN
        return 0.0
    if cmd >= 1.0:
        return w_max_rad_s
    return w_idle_rad_s + cmd * (w_max_rad_s - w_idle_rad_s)


def hover_motor_command(profile: VehicleProfile, *, include_damage: bool = True) -> float:
    """Equal motor command whose total steady thrust equals the weight.

    ``sum_i k_T,i w^2 = m g``  ->  ``w = sqrt(m g / sum_i k_T,i)``,
    ``cmd = (w - w_idle) / (w_max - w_idle)``.

    With ``include_damage`` the per-motor thrust efficiencies are used (failures
    are not). Equal commands balance torques only for a symmetric, undamaged
    vehicle with the CG at the centre.

    Raises
    ------
    ValueError
        If that speed is outside ``[w_idle, w_max]`` (cannot hover on equal commands).
    """
    ph = profile.physics
    if include_damage:
        kt_sum = sum(VehicleParams.from_profile(profile).thrust_coeff)
    else:
        kt_sum = profile.n_motors * ph.kf_n_per_rad_s2
    w = math.sqrt(ph.mass_kg * GRAVITY_M_S2 / kt_sum)
    w_idle, w_max = ph.motor_w_idle_rad_s, ph.motor_w_max_rad_s
    if not w_idle <= w <= w_max:
        raise ValueError(f"hover speed {w:.1f} rad/s outside [{w_idle}, {w_max}] rad/s")
    return (w - w_idle) / (w_max - w_idle)


def _rigid_body_rates(
    x: Sequence[float], wrench: Sequence[float], c: Sequence[float]
) -> tuple[float, ...]:
    """Time derivative of ``x = (p, v, q, omega)`` (13 floats), plus specific force.

    ``wrench = (Fx, Fy, Fz, tau_x, tau_y, tau_z, h_rz)``: rotor forces and torques
    in FRD about the CG (spin-up reaction included) and rotor angular momentum.
    ``c`` packs mass, gravity, wind and drag, inertia and its inverse (see
    :meth:`Quadrotor._constants`). Returns 16 floats: the 13 derivatives then the
    specific force ``F_b / m`` in FRD. Plain floats on purpose: this runs four
    times per physics step.
    """
    _px, _py, _pz, vx, vy, vz, qw, qx, qy, qz, p, q, r = x
    fx, fy, fz, tx, ty, tz, hz = wrench
    (
        m_inv, g, wnx, wny, wnz,
        cl0, cl1, cl2, cq0, cq1, cq2, ca0, ca1, ca2,
        J00, J01, J02, J10, J11, J12, J20, J21, J22,
        K00, K01, K02, K10, K11, K12, K20, K21, K22,
    ) = c  # fmt: skip
    xx, yy, zz = qx * qx, qy * qy, qz * qz
    xy, xz, yz = qx * qy, qx * qz, qy * qz
    wx, wy, wz = qw * qx, qw * qy, qw * qz
    R00 = 1.0 - 2.0 * (yy + zz)
    R01 = 2.0 * (xy - wz)
    R02 = 2.0 * (xz + wy)
    R10 = 2.0 * (xy + wz)
    R11 = 1.0 - 2.0 * (xx + zz)
    R12 = 2.0 * (yz - wx)
    R20 = 2.0 * (xz - wy)
    R21 = 2.0 * (yz + wx)
    R22 = 1.0 - 2.0 * (xx + yy)
    # Drag sees the velocity relative to the air, expressed in the body.
    ax_ = vx - wnx
    ay_ = vy - wny
    az_ = vz - wnz
    ub = R00 * ax_ + R10 * ay_ + R20 * az_
    vb = R01 * ax_ + R11 * ay_ + R21 * az_
    wb = R02 * ax_ + R12 * ay_ + R22 * az_
    sfx = (fx - cl0 * ub - cq0 * ub * abs(ub)) * m_inv
    sfy = (fy - cl1 * vb - cq1 * vb * abs(vb)) * m_inv
    sfz = (fz - cl2 * wb - cq2 * wb * abs(wb)) * m_inv
    # Angular momentum about the CG, body plus rotors.
    Lx = J00 * p + J01 * q + J02 * r
    Ly = J10 * p + J11 * q + J12 * r
    Lz = J20 * p + J21 * q + J22 * r + hz
    Mx = tx - ca0 * p - (q * Lz - r * Ly)
    My = ty - ca1 * q - (r * Lx - p * Lz)
    Mz = tz - ca2 * r - (p * Ly - q * Lx)
    return (
        vx,
        vy,
        vz,
        R00 * sfx + R01 * sfy + R02 * sfz,
        R10 * sfx + R11 * sfy + R12 * sfz,
        R20 * sfx + R21 * sfy + R22 * sfz + g,
        -0.5 * (qx * p + qy * q + qz * r),
        0.5 * (qw * p + qy * r - qz * q),
        0.5 * (qw * q - qx * r + qz * p),
        0.5 * (qw * r + qx * q - qy * p),
        K00 * Mx + K01 * My + K02 * Mz,
        K10 * Mx + K11 * My + K12 * Mz,
        K20 * Mx + K21 * My + K22 * Mz,
        sfx,
        sfy,
        sfz,
    )


class Quadrotor:
    """One simulated multirotor, stepped at a fixed ``dt_s``.

    Parameters
    ----------
    profile : VehicleProfile
        Vehicle geometry, physics and damage (``profile.physics.damage`` is
        applied automatically, including ``fail_at_s``).
    rng : numpy.random.Generator
        Randomness of the plant: the initial rotor phases (where imbalanced props
        start). Sensor noise lives in :class:`sitl.imu.Imu`, gusts in
        :class:`sitl.wind.Wind`, each with its own generator.
    dt_s : float
        Physics step (s); 1 kHz by default.
    test_stand : bool
        Mount the vehicle on a gimbal at its CG: position held, attitude free.
    wind : Wind or None
        Air velocity source; ``None`` is still air.

    Notes
    -----
    Starts on the ground at the origin, level, heading north, motors stopped
    (in test-stand mode: at the origin, not landed).
    """

    def __init__(
        self,
        profile: VehicleProfile,
        *,
        rng: np.random.Generator,
        dt_s: float = 0.001,
        test_stand: bool = False,
        wind: Wind | None = None,
    ) -> None:
        if not (dt_s > 0.0 and math.isfinite(dt_s)):
            raise ValueError(f"dt_s: expected a finite step > 0 s, got {dt_s!r}")
        self.profile = profile
        self.params = VehicleParams.from_profile(profile)
        self.dt_s = float(dt_s)
        self.test_stand = bool(test_stand)
        self._wind = wind
        self._rng = rng
        P = self.params
        n = P.n_motors
        self._n = n
        # Per-motor linear coefficients of the wrench in w^2 and in w:
        # (Fz, tau_x, tau_y, tau_z) per unit w^2, and sigma * J_r for the rotor terms.
        self._coef_w2 = tuple(
            (
                -P.thrust_coeff[i],
                -P.arm_frd_m[i][1] * P.thrust_coeff[i],
                P.arm_frd_m[i][0] * P.thrust_coeff[i],
                P.spin_sign[i] * P.torque_coeff[i],
            )
            for i in range(n)
        )
        self._sigma_jr = tuple(s * P.rotor_inertia_kg_m2 for s in P.spin_sign)
        self._has_imbalance = any(a > 0.0 for a in P.imbalance_coeff)
        h = 0.5 * self.dt_s
        self._exp_up = (math.exp(-h / P.tau_up_s), math.exp(-self.dt_s / P.tau_up_s))
        self._exp_down = (math.exp(-h / P.tau_down_s), math.exp(-self.dt_s / P.tau_down_s))
        J, K = P.inertia_kg_m2, P.inertia_inv
        self._c_mass = (1.0 / P.mass_kg, GRAVITY_M_S2)
        self._c_rest = (
            *P.drag_linear,
            *P.drag_quadratic,
            *P.drag_angular,
            *J[0],
            *J[1],
            *J[2],
            *K[0],
            *K[1],
            *K[2],
        )
        self._speed_scale = [1.0] * n
        self._failed = [False] * n
        self._wind_ned = (0.0, 0.0, 0.0)
        # Where each imbalanced prop starts: the plant's only randomness.
        self._phase = [float(v) for v in rng.uniform(0.0, _TWO_PI, size=n)]
        self._k = 0  # steps taken: t = k dt, free of accumulated rounding
        self._t_s = 0.0
        self._x: list[float] = [0.0] * 13
        self._x[6] = 1.0
        self._w = [0.0] * n
        self._sf = (0.0, 0.0, -GRAVITY_M_S2)
        self._landed = not self.test_stand
        self._crashed = False
        self._hold_pos: tuple[float, float, float] = (0.0, 0.0, 0.0)

    # ----------------------------------------------------------------- accessors
    @property
    def t_s(self) -> float:
        """Simulation time (s)."""
        return self._t_s

    @property
    def landed(self) -> bool:
        """Resting on the ground."""
        return self._landed

    @property
    def crashed(self) -> bool:
        """Crashed; :meth:`step` does nothing any more."""
        return self._crashed

    @property
    def rate_frd_rad_s(self) -> tuple[float, float, float]:
        """Body rate (FRD, rad/s), cheaper than building :attr:`state`."""
        x = self._x
        return (x[10], x[11], x[12])

    @property
    def specific_force_frd_m_s2(self) -> tuple[float, float, float]:
        """Specific force over the last step (FRD, m/s²)."""
        return self._sf

    @property
    def rotor_phase_rad(self) -> tuple[float, ...]:
        """Rotor angles (rad) that orient each imbalance force in the rotor plane."""
        return tuple(self._phase)

    @property
    def wind_ned_m_s(self) -> tuple[float, float, float]:
        """Air velocity used in the last step (NED, m/s)."""
        return self._wind_ned

    @property
    def state(self) -> VehicleState:
        """A snapshot of the vehicle."""
        x = self._x
        return VehicleState(
            t_s=self._t_s,
            pos_ned_m=(x[0], x[1], x[2]),
            vel_ned_m_s=(x[3], x[4], x[5]),
            q_wxyz=(x[6], x[7], x[8], x[9]),
            rate_frd_rad_s=(x[10], x[11], x[12]),
            motor_w_rad_s=tuple(self._w),
            specific_force_frd_m_s2=self._sf,
            landed=self._landed,
            crashed=self._crashed,
        )

    # ------------------------------------------------------------------ setters
    def set_state(
        self,
        *,
        pos_ned_m: Sequence[float] | None = None,
        vel_ned_m_s: Sequence[float] | None = None,
        q_wxyz: Sequence[float] | None = None,
        rate_frd_rad_s: Sequence[float] | None = None,
        motor_w_rad_s: Sequence[float] | None = None,
        rotor_phase_rad: Sequence[float] | None = None,
    ) -> None:
        """Place the vehicle (scenario start, tests); omitted parts are kept.

        Clears ``crashed``. The vehicle is ``landed`` if its position is on or
        below the ground (it is then put at ``z = 0``, still and level), and in the
        air otherwise. In test-stand mode the position becomes the held position.
        """
        x = self._x
        for sl, v, n in (
            (slice(0, 3), pos_ned_m, 3),
            (slice(3, 6), vel_ned_m_s, 3),
            (slice(6, 10), q_wxyz, 4),
            (slice(10, 13), rate_frd_rad_s, 3),
        ):
            if v is not None:
                vals = [float(a) for a in v]
                if len(vals) != n or not all(math.isfinite(a) for a in vals):
                    raise ValueError(f"expected {n} finite numbers, got {v!r}")
                x[sl] = vals
        qn = math.sqrt(sum(a * a for a in x[6:10]))
        if not qn > 0.0:
            raise ValueError("q_wxyz: zero quaternion")
        x[6:10] = [a / qn for a in x[6:10]]
        if motor_w_rad_s is not None:
            ws = [float(a) for a in motor_w_rad_s]
            if len(ws) != self._n or not all(math.isfinite(a) and a >= 0.0 for a in ws):
                raise ValueError(f"motor_w_rad_s: expected {self._n} speeds >= 0, got {ws!r}")
            self._w = ws
        if rotor_phase_rad is not None:
            ph = [float(a) for a in rotor_phase_rad]
            if len(ph) != self._n or not all(math.isfinite(a) for a in ph):
                raise ValueError(f"rotor_phase_rad: expected {self._n} angles, got {ph!r}")
            self._phase = ph
        self._crashed = False
        if self.test_stand:
            self._hold_pos = (x[0], x[1], x[2])
            x[3:6] = [0.0, 0.0, 0.0]
            self._landed = False
        else:
            self._landed = x[2] >= 0.0
            if self._landed:
                self._settle_on_ground()
        self._sf = self._static_specific_force()

    def set_wind(self, wind: Wind | None) -> None:
        """Replace the air the vehicle flies in (``None``: still air)."""
        self._wind = wind
        self._wind_ned = (0.0, 0.0, 0.0)

    def set_motor_failure(self, motor: int, efficiency: float = 0.0) -> None:
        """Degrade ``motor`` now to ``efficiency`` of its thrust and torque.

        Same model as ``damage.motors[].fail_at_s``: commanded speed scaled by
        ``sqrt(efficiency)``.
        """
        if not 0 <= motor < self._n:
            raise ValueError(f"motor: expected 0..{self._n - 1}, got {motor}")
        if not 0.0 <= efficiency <= 1.0:
            raise ValueError(f"efficiency: expected in [0, 1], got {efficiency}")
        self._failed[motor] = True
        self._speed_scale[motor] = math.sqrt(efficiency)

    # -------------------------------------------------------------------- step
    def _settle_on_ground(self) -> None:
        x = self._x
        yaw = quat_to_euler_rad((x[6], x[7], x[8], x[9]))[2]
        x[2] = 0.0
        x[3:6] = [0.0, 0.0, 0.0]
        x[6:10] = list(euler_to_quat(0.0, 0.0, yaw))
        x[10:13] = [0.0, 0.0, 0.0]

    def _static_specific_force(self) -> tuple[float, float, float]:
        """Specific force of a vehicle held still: ``-R^T g e_z``."""
        qw, qx, qy, qz = self._x[6:10]
        g = GRAVITY_M_S2
        return (
            -g * 2.0 * (qx * qz - qw * qy),
            -g * 2.0 * (qy * qz + qw * qx),
            -g * (1.0 - 2.0 * (qx * qx + qy * qy)),
        )

    def _motor_targets(self, motor_cmd: Sequence[float]) -> list[float]:
        P = self.params
        n = self._n
        if len(motor_cmd) != n:
            raise ValueError(f"motor_cmd: expected {n} commands, got {len(motor_cmd)}")
        t = self._t_s
        for i, t_fail in enumerate(P.fail_at_s):
            if t_fail is not None and not self._failed[i] and t >= t_fail - 1e-9:
                self._failed[i] = True
                self._speed_scale[i] = P.speed_scale_after_fail[i]
                _log.info("motor %d degraded at t=%.3f s", i, t)
        w_idle, w_max = P.w_idle_rad_s, P.w_max_rad_s
        scale = self._speed_scale
        out = [0.0] * n
        for i in range(n):
            c = motor_cmd[i]
            if 0.0 < c < math.inf:  # NaN, inf and negatives stay stopped
                w = w_max if c >= 1.0 else w_idle + c * (w_max - w_idle)
                out[i] = w * scale[i]
        return out

    def _advance_motors(
        self, w_cmd: list[float]
    ) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
        """Exact motor lag over one step; the rotor wrench at ``s = 0, dt/2, dt``.

        Updates rotor speeds and phases to the end of the step.
        """
        P = self.params
        dt = self.dt_s
        w = self._w
        coef = self._coef_w2
        sjr = self._sigma_jr
        fz0 = tx0 = ty0 = tz0 = hz0 = 0.0
        fz1 = tx1 = ty1 = tz1 = hz1 = 0.0
        fz2 = tx2 = ty2 = tz2 = hz2 = 0.0
        w_mid = [0.0] * self._n
        w_end = [0.0] * self._n
        taus = [0.0] * self._n
        for i in range(self._n):
            w0 = w[i]
            wc = w_cmd[i]
            if wc >= w0:
                tau = P.tau_up_s
                eh, ef = self._exp_up
            else:
                tau = P.tau_down_s
                eh, ef = self._exp_down
            taus[i] = tau
            d = w0 - wc
            wh = wc + d * eh
            wf = wc + d * ef
            w_mid[i] = wh
            w_end[i] = wf
            a_f, a_x, a_y, a_z = coef[i]
            s = sjr[i]  # sigma J_r
            # Rotor speed-up reaction on the frame: +sigma J_r dw/dt about z,
            # dw/dt = (w_cmd - w) / tau; rotor momentum h_z = -sigma J_r w.
            inv_tau = s / tau
            w2 = w0 * w0
            fz0 += a_f * w2
            tx0 += a_x * w2
            ty0 += a_y * w2
            tz0 += a_z * w2 - inv_tau * d
            hz0 -= s * w0
            w2 = wh * wh
            fz1 += a_f * w2
            tx1 += a_x * w2
            ty1 += a_y * w2
            tz1 += a_z * w2 - inv_tau * (wh - wc)
            hz1 -= s * wh
            w2 = wf * wf
            fz2 += a_f * w2
            tx2 += a_x * w2
            ty2 += a_y * w2
            tz2 += a_z * w2 - inv_tau * (wf - wc)
            hz2 -= s * wf
        fx0 = fy0 = fx1 = fy1 = fx2 = fy2 = 0.0
        if self._has_imbalance:
            h = 0.5 * dt
            for i in range(self._n):
                a = P.imbalance_coeff[i]
                if a <= 0.0:
                    continue
                rx, ry, rz = P.arm_frd_m[i]
                sgn = P.spin_sign[i]
                tau = taus[i]
                w0, wc = w[i], w_cmd[i]
                d = w0 - wc
                ph0 = self._phase[i]
                # Phase = phase0 - sigma * integral of w(s) ds, integrated exactly.
                ph1 = ph0 - sgn * (wc * h + tau * (d - (w_mid[i] - wc)))
                ph2 = ph0 - sgn * (wc * dt + tau * (d - (w_end[i] - wc)))
                self._phase[i] = math.fmod(ph2, _TWO_PI)
                for k, (wk, ph) in enumerate(((w0, ph0), (w_mid[i], ph1), (w_end[i], ph2))):
                    amp = a * wk * wk
                    Fx = amp * math.cos(ph)
                    Fy = amp * math.sin(ph)
                    # r x F for F in the rotor plane.
                    dtx, dty, dtz = -rz * Fy, rz * Fx, rx * Fy - ry * Fx
                    if k == 0:
                        fx0 += Fx
                        fy0 += Fy
                        tx0 += dtx
                        ty0 += dty
                        tz0 += dtz
                    elif k == 1:
                        fx1 += Fx
                        fy1 += Fy
                        tx1 += dtx
                        ty1 += dty
                        tz1 += dtz
                    else:
                        fx2 += Fx
                        fy2 += Fy
                        tx2 += dtx
                        ty2 += dty
                        tz2 += dtz
        self._w = w_end
        return (
            (fx0, fy0, fz0, tx0, ty0, tz0, hz0),
            (fx1, fy1, fz1, tx1, ty1, tz1, hz1),
            (fx2, fy2, fz2, tx2, ty2, tz2, hz2),
        )

    def step(self, motor_cmd: Sequence[float]) -> None:
        """Advance one ``dt_s`` with normalised motor commands (see module docs).

        Parameters
        ----------
        motor_cmd : sequence of float
            One command per motor in output order, clamped to ``[0, 1]``;
            non-finite values read as 0 (stopped). Ignored once crashed.
        """
        if self._crashed:
            return
        dt = self.dt_s
        x = self._x
        w_cmd = self._motor_targets(motor_cmd)
        wr0, wr1, wr2 = self._advance_motors(w_cmd)
        if self._wind is not None:
            wn = self._wind_ned
            airspeed = math.sqrt((x[3] - wn[0]) ** 2 + (x[4] - wn[1]) ** 2 + (x[5] - wn[2]) ** 2)
            self._wind_ned = self._wind.velocity_ned(self._t_s, dt, airspeed)
        if self._landed:
            # Level on the ground: lift off once thrust (end of step) beats weight.
            if wr2[2] + self.params.mass_kg * GRAVITY_M_S2 >= 0.0:
                self._k += 1
                self._t_s = self._k * dt
                self._sf = self._static_specific_force()
                return
            self._landed = False
        c = (*self._c_mass, *self._wind_ned, *self._c_rest)
        h = 0.5 * dt
        k1 = _rigid_body_rates(x, wr0, c)
        k2 = _rigid_body_rates([a + h * b for a, b in zip(x, k1)], wr1, c)
        k3 = _rigid_body_rates([a + h * b for a, b in zip(x, k2)], wr1, c)
        k4 = _rigid_body_rates([a + dt * b for a, b in zip(x, k3)], wr2, c)
        s = dt / 6.0
        xn = [a + s * (b1 + 2.0 * (b2 + b3) + b4) for a, b1, b2, b3, b4 in zip(x, k1, k2, k3, k4)]
        qn = math.sqrt(xn[6] * xn[6] + xn[7] * xn[7] + xn[8] * xn[8] + xn[9] * xn[9])
        if not (qn > 0.0 and math.isfinite(qn) and math.isfinite(sum(xn))):
            _log.warning("non-finite state at t=%.3f s; treating as a crash", self._t_s)
            self._crashed = True
            return
        xn[6] /= qn
        xn[7] /= qn
        xn[8] /= qn
        xn[9] /= qn
        self._x = xn
        self._k += 1
        self._t_s = self._k * dt
        if self.test_stand:
            xn[0:3] = self._hold_pos
            xn[3:6] = [0.0, 0.0, 0.0]
            self._sf = self._static_specific_force()
            return
        # Accelerometer: RK4-weighted mean of the specific force over the step.
        self._sf = (
            (k1[13] + 2.0 * (k2[13] + k3[13]) + k4[13]) / 6.0,
            (k1[14] + 2.0 * (k2[14] + k3[14]) + k4[14]) / 6.0,
            (k1[15] + 2.0 * (k2[15] + k3[15]) + k4[15]) / 6.0,
        )
        if xn[2] >= 0.0:
            self._touch_ground()

    def _touch_ground(self) -> None:
        x = self._x
        vz = x[5]
        if vz < 0.0:
            # Below the surface but already climbing (lift-off step): stay on it.
            x[2] = 0.0
            return
        speed = math.sqrt(x[3] * x[3] + x[4] * x[4] + vz * vz)
        cos_tilt = 1.0 - 2.0 * (x[7] * x[7] + x[8] * x[8])
        tilted = cos_tilt < math.cos(CRASH_TILT_RAD)
        if vz > CRASH_SPEED_M_S or (tilted and speed > CRASH_TILT_SPEED_M_S):
            x[2] = 0.0
            self._crashed = True
            _log.info(
                "crash at t=%.3f s: vertical %.2f m/s, speed %.2f m/s, tilt %.0f deg",
                self._t_s,
                vz,
                speed,
                math.degrees(math.acos(max(-1.0, min(1.0, cos_tilt)))),
            )
            return
        self._landed = True
        self._settle_on_ground()
        self._sf = self._static_specific_force()
