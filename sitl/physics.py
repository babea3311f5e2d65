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

The rotor forces and torques (``k_T,i``, ``k_Q,i``, the imbalance forces
``F_imb,i``, the motor lag and damage) are modelled in :mod:`sitl.rotors`, the
constants read from the profile in :mod:`sitl.vehicle_params`.

Integration
-----------
The rigid body is integrated with classic fixed-step RK4. Because the rotor
wrench does not depend on the rigid-body state, it is evaluated once at the
three RK4 nodes ``s = 0, dt/2, dt`` (the motor lag is solved exactly over the
step).

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
from sitl.rotors import Rotors
from sitl.vehicle_params import GRAVITY_M_S2, VehicleParams
from sitl.wind import Wind

__all__ = [
    "CRASH_SPEED_M_S",
    "CRASH_TILT_RAD",
    "CRASH_TILT_SPEED_M_S",
    "Quadrotor",
    "VehicleState",
]

_log = logging.getLogger(__name__)

#: Vertical touchdown speed above which the vehicle is wrecked (m/s).
CRASH_SPEED_M_S = 3.0
#: Tilt at touchdown beyond which a moving vehicle tips over and breaks props (rad).
CRASH_TILT_RAD = math.radians(60.0)
#: Speed above which a touchdown beyond :data:`CRASH_TILT_RAD` counts as a crash (m/s).
CRASH_TILT_SPEED_M_S = 0.5


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


def _rigid_body_rates(
    x: Sequence[float], wrench: Sequence[float], c: Sequence[float]
) -> tuple[float, ...]:
    """Time derivative of ``x = (p, v, q, omega)`` (13 floats), plus specific force.

    ``wrench = (Fx, Fy, Fz, tau_x, tau_y, tau_z, h_rz)``: rotor forces and torques
    in FRD about the CG (spin-up reaction included) and rotor angular momentum.
    ``c`` packs mass, gravity, wind and drag, inertia and its inverse (see
    :meth:`Quadrotor.step`). Returns 16 floats: the 13 derivatives then the
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
        self._n = P.n_motors
        self._rotors = Rotors(P, self.dt_s, rng)
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
        self._wind_ned = (0.0, 0.0, 0.0)
        self._k = 0  # steps taken: t = k dt, free of accumulated rounding
        self._t_s = 0.0
        self._x: list[float] = [0.0] * 13
        self._x[6] = 1.0
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
    def steps(self) -> int:
        """Steps taken since the start: ``t_s == steps * dt_s``."""
        return self._k

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
        return tuple(self._rotors.phase_rad)

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
            motor_w_rad_s=tuple(self._rotors.speed_rad_s),
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
            self._rotors.speed_rad_s = ws
        if rotor_phase_rad is not None:
            ph = [float(a) for a in rotor_phase_rad]
            if len(ph) != self._n or not all(math.isfinite(a) for a in ph):
                raise ValueError(f"rotor_phase_rad: expected {self._n} angles, got {ph!r}")
            self._rotors.phase_rad = ph
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
        self._rotors.fail(motor, efficiency)

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
        w_cmd = self._rotors.targets(motor_cmd, self._t_s)
        wr0, wr1, wr2 = self._rotors.advance(w_cmd)
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
