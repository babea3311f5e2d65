"""Many vehicles stepped at once with numpy, for Monte Carlo work.

:class:`BatchQuadrotor` integrates the same equations as
:class:`sitl.physics.Quadrotor` (see that module's docstring): exact first-order
motor lag with asymmetric time constants, rotor wrench (thrust, reaction and
spin-up torque, gyroscopic momentum, rotating imbalance), damage including
``fail_at_s``, CG offset and inertia delta, linear, quadratic and angular drag,
and classic RK4 for the rigid body. Each vehicle may have its own profile (same
motor count), so parameters can be drawn per vehicle.

Simplified compared with :class:`~sitl.physics.Quadrotor`:

* no ground: vehicles fly through ``z = 0``; no ``landed``/``crashed`` logic and
  no test-stand mode;
* wind is a constant air velocity per vehicle (no turbulence);
* a non-finite state is not trapped: that vehicle simply carries NaN on.

Use it for statistics over many vehicles started in the air; use
:class:`~sitl.physics.Quadrotor` for single flights with take-off and landing.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from companion.profile import VehicleProfile
from sitl.vehicle_params import GRAVITY_M_S2, VehicleParams

__all__ = ["BatchQuadrotor"]

F64 = NDArray[np.float64]


class BatchQuadrotor:
    """``N`` multirotors in lockstep, vectorised over the first axis.

    Parameters
    ----------
    profiles : VehicleProfile or sequence of VehicleProfile
        One profile for every vehicle, or one per vehicle (same motor count).
    n_vehicles : int, optional
        Number of vehicles when a single profile is given.
    rng : numpy.random.Generator, optional
        Draws the initial rotor phases (as :class:`~sitl.physics.Quadrotor`
        does); without it every phase starts at 0.
    dt_s : float
        Physics step (s).
    wind_ned_m_s : array_like, shape (3,) or (N, 3)
        Constant air velocity (NED, m/s).

    Notes
    -----
    All vehicles start at the NED origin, at rest, level, motors stopped; place
    them with :meth:`set_state`. State arrays are exposed read-only-by-convention
    as attributes: ``pos_ned_m`` (N, 3), ``vel_ned_m_s`` (N, 3), ``q_wxyz`` (N, 4),
    ``rate_frd_rad_s`` (N, 3), ``motor_w_rad_s`` (N, M), ``rotor_phase_rad``
    (N, M) and ``specific_force_frd_m_s2`` (N, 3).
    """

    def __init__(
        self,
        profiles: VehicleProfile | Sequence[VehicleProfile],
        n_vehicles: int | None = None,
        *,
        rng: np.random.Generator | None = None,
        dt_s: float = 0.001,
        wind_ned_m_s: ArrayLike = (0.0, 0.0, 0.0),
    ) -> None:
        if isinstance(profiles, VehicleProfile):
            if n_vehicles is None or n_vehicles < 1:
                raise ValueError("n_vehicles: expected >= 1 with a single profile")
            params = [VehicleParams.from_profile(profiles)] * n_vehicles
        else:
            params = [VehicleParams.from_profile(p) for p in profiles]
            if not params:
                raise ValueError("profiles: expected at least one profile")
            if n_vehicles is not None and n_vehicles != len(params):
                raise ValueError(f"n_vehicles={n_vehicles} but {len(params)} profiles given")
        n_motors = {p.n_motors for p in params}
        if len(n_motors) != 1:
            raise ValueError(f"profiles: expected one motor count, got {sorted(n_motors)}")
        if not dt_s > 0.0:
            raise ValueError(f"dt_s: expected > 0, got {dt_s!r}")
        self.n_vehicles = N = len(params)
        self.n_motors = M = n_motors.pop()
        self.dt_s = float(dt_s)

        def arr(get: Callable[[VehicleParams], object]) -> F64:
            return np.asarray([get(p) for p in params], dtype=np.float64)

        self._mass = arr(lambda p: p.mass_kg)
        self._J = arr(lambda p: p.inertia_kg_m2)  # (N, 3, 3)
        self._J_inv = arr(lambda p: p.inertia_inv)
        arm = arr(lambda p: p.arm_frd_m)  # (N, M, 3)
        self._rx, self._ry, self._rz = arm[..., 0], arm[..., 1], arm[..., 2]
        self._sigma = arr(lambda p: p.spin_sign)
        self._kt = arr(lambda p: p.thrust_coeff)
        self._kq = arr(lambda p: p.torque_coeff)
        self._imb = arr(lambda p: p.imbalance_coeff)
        self._has_imbalance = bool(np.any(self._imb > 0.0))
        self._fail_at = arr(lambda p: [np.inf if t is None else t for t in p.fail_at_s])
        self._after = arr(lambda p: p.speed_scale_after_fail)
        self._w_idle = arr(lambda p: p.w_idle_rad_s)[:, None]
        self._w_max = arr(lambda p: p.w_max_rad_s)[:, None]
        self._tau_up = arr(lambda p: p.tau_up_s)[:, None]
        self._tau_down = arr(lambda p: p.tau_down_s)[:, None]
        self._sigma_jr = self._sigma * arr(lambda p: p.rotor_inertia_kg_m2)[:, None]
        self._c_lin = arr(lambda p: p.drag_linear)
        self._c_quad = arr(lambda p: p.drag_quadratic)
        self._c_ang = arr(lambda p: p.drag_angular)
        self.wind_ned_m_s = np.broadcast_to(np.asarray(wind_ned_m_s, dtype=float), (N, 3)).copy()

        self._k = 0
        self.pos_ned_m = np.zeros((N, 3))
        self.vel_ned_m_s = np.zeros((N, 3))
        self.q_wxyz = np.zeros((N, 4))
        self.q_wxyz[:, 0] = 1.0
        self.rate_frd_rad_s = np.zeros((N, 3))
        self.motor_w_rad_s = np.zeros((N, M))
        self.rotor_phase_rad = (
            rng.uniform(0.0, 2.0 * np.pi, size=(N, M)) if rng is not None else np.zeros((N, M))
        )
        self.specific_force_frd_m_s2 = np.zeros((N, 3))
        self.specific_force_frd_m_s2[:, 2] = -GRAVITY_M_S2

    @property
    def t_s(self) -> float:
        """Simulation time (s), common to all vehicles."""
        return self._k * self.dt_s

    def set_state(
        self,
        *,
        pos_ned_m: ArrayLike | None = None,
        vel_ned_m_s: ArrayLike | None = None,
        q_wxyz: ArrayLike | None = None,
        rate_frd_rad_s: ArrayLike | None = None,
        motor_w_rad_s: ArrayLike | None = None,
        rotor_phase_rad: ArrayLike | None = None,
    ) -> None:
        """Set parts of the state, broadcast to every vehicle (omitted parts kept)."""
        N, M = self.n_vehicles, self.n_motors
        if pos_ned_m is not None:
            self.pos_ned_m = np.broadcast_to(np.asarray(pos_ned_m, float), (N, 3)).copy()
        if vel_ned_m_s is not None:
            self.vel_ned_m_s = np.broadcast_to(np.asarray(vel_ned_m_s, float), (N, 3)).copy()
        if q_wxyz is not None:
            q = np.broadcast_to(np.asarray(q_wxyz, float), (N, 4))
            self.q_wxyz = q / np.linalg.norm(q, axis=1, keepdims=True)
        if rate_frd_rad_s is not None:
            self.rate_frd_rad_s = np.broadcast_to(np.asarray(rate_frd_rad_s, float), (N, 3)).copy()
        if motor_w_rad_s is not None:
            self.motor_w_rad_s = np.broadcast_to(np.asarray(motor_w_rad_s, float), (N, M)).copy()
        if rotor_phase_rad is not None:
            self.rotor_phase_rad = np.broadcast_to(
                np.asarray(rotor_phase_rad, float), (N, M)
            ).copy()

    def _wrench(self, w: F64, w_dot: F64, phase: F64) -> tuple[F64, F64, F64]:
        """Rotor force (N, 3), torque about the CG (N, 3) and rotor momentum h_z (N,)."""
        N = self.n_vehicles
        T = self._kt * w * w  # (N, M) thrust
        force = np.zeros((N, 3))
        torque = np.zeros((N, 3))
        force[:, 2] = -T.sum(axis=1)
        # r x (0, 0, -T) = (-ry T, rx T, 0)
        torque[:, 0] = -(self._ry * T).sum(axis=1)
        torque[:, 1] = (self._rx * T).sum(axis=1)
        torque[:, 2] = (self._sigma * self._kq * w * w + self._sigma_jr * w_dot).sum(axis=1)
        if self._has_imbalance:
            amp = self._imb * w * w
            Fx = amp * np.cos(phase)
            Fy = amp * np.sin(phase)
            force[:, 0] = Fx.sum(axis=1)
            force[:, 1] = Fy.sum(axis=1)
            torque[:, 0] -= (self._rz * Fy).sum(axis=1)
            torque[:, 1] += (self._rz * Fx).sum(axis=1)
            torque[:, 2] += (self._rx * Fy - self._ry * Fx).sum(axis=1)
        h_z = -(self._sigma_jr * w).sum(axis=1)
        return force, torque, h_z

    def _rates(self, x: F64, force_b: F64, torque_b: F64, h_z: F64) -> tuple[F64, F64]:
        """Derivative of ``x`` (N, 13) = (p, v, q, omega), and the specific force (N, 3)."""
        v = x[:, 3:6]
        qw, qx, qy, qz = x[:, 6], x[:, 7], x[:, 8], x[:, 9]
        om = x[:, 10:13]
        R = np.empty((x.shape[0], 3, 3))
        R[:, 0, 0] = 1.0 - 2.0 * (qy * qy + qz * qz)
        R[:, 0, 1] = 2.0 * (qx * qy - qw * qz)
        R[:, 0, 2] = 2.0 * (qx * qz + qw * qy)
        R[:, 1, 0] = 2.0 * (qx * qy + qw * qz)
        R[:, 1, 1] = 1.0 - 2.0 * (qx * qx + qz * qz)
        R[:, 1, 2] = 2.0 * (qy * qz - qw * qx)
        R[:, 2, 0] = 2.0 * (qx * qz - qw * qy)
        R[:, 2, 1] = 2.0 * (qy * qz + qw * qx)
        R[:, 2, 2] = 1.0 - 2.0 * (qx * qx + qy * qy)
        u_b = np.einsum("nji,nj->ni", R, v - self.wind_ned_m_s)  # R^T (v - wind)
        f_b = force_b - self._c_lin * u_b - self._c_quad * u_b * np.abs(u_b)
        sf = f_b / self._mass[:, None]
        acc = np.einsum("nij,nj->ni", R, sf)
        acc[:, 2] += GRAVITY_M_S2
        L = np.einsum("nij,nj->ni", self._J, om)
        L[:, 2] += h_z
        M = torque_b - self._c_ang * om - np.cross(om, L)
        om_dot = np.einsum("nij,nj->ni", self._J_inv, M)
        p, q, r = om[:, 0], om[:, 1], om[:, 2]
        dx = np.empty_like(x)
        dx[:, 0:3] = v
        dx[:, 3:6] = acc
        dx[:, 6] = -0.5 * (qx * p + qy * q + qz * r)
        dx[:, 7] = 0.5 * (qw * p + qy * r - qz * q)
        dx[:, 8] = 0.5 * (qw * q - qx * r + qz * p)
        dx[:, 9] = 0.5 * (qw * r + qx * q - qy * p)
        dx[:, 10:13] = om_dot
        return dx, sf

    def step(self, motor_cmd: ArrayLike) -> None:
        """Advance every vehicle by ``dt_s``.

        Parameters
        ----------
        motor_cmd : array_like, shape (N, M) or (M,)
            Normalised commands, clamped to ``[0, 1]``; 0 or non-finite -> stopped.
        """
        N, M = self.n_vehicles, self.n_motors
        dt = self.dt_s
        h = 0.5 * dt
        cmd = np.broadcast_to(np.asarray(motor_cmd, dtype=float), (N, M))
        ok = np.isfinite(cmd) & (cmd > 0.0)
        c = np.clip(np.where(ok, cmd, 0.0), 0.0, 1.0)
        scale = np.where(self.t_s >= self._fail_at - 1e-9, self._after, 1.0)
        w_cmd = np.where(ok, self._w_idle + c * (self._w_max - self._w_idle), 0.0) * scale
        w0 = self.motor_w_rad_s
        tau = np.where(w_cmd >= w0, self._tau_up, self._tau_down)
        d = w0 - w_cmd
        e_half = np.exp(-h / tau)
        e_full = np.exp(-dt / tau)
        w1 = w_cmd + d * e_half
        w2 = w_cmd + d * e_full
        ph0 = self.rotor_phase_rad
        sig = self._sigma
        # Exact phase: integral of w(s) = w_cmd s + tau (d - (w(s) - w_cmd)).
        ph1 = ph0 - sig * (w_cmd * h + tau * (d - (w1 - w_cmd)))
        ph2 = ph0 - sig * (w_cmd * dt + tau * (d - (w2 - w_cmd)))
        wr0 = self._wrench(w0, -d / tau, ph0)
        wr1 = self._wrench(w1, (w_cmd - w1) / tau, ph1)
        wr2 = self._wrench(w2, (w_cmd - w2) / tau, ph2)

        x = np.concatenate(
            (self.pos_ned_m, self.vel_ned_m_s, self.q_wxyz, self.rate_frd_rad_s), axis=1
        )
        k1, s1 = self._rates(x, *wr0)
        k2, s2 = self._rates(x + h * k1, *wr1)
        k3, s3 = self._rates(x + h * k2, *wr1)
        k4, s4 = self._rates(x + dt * k3, *wr2)
        xn = x + (dt / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)
        q = xn[:, 6:10]
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        self.pos_ned_m = xn[:, 0:3]
        self.vel_ned_m_s = xn[:, 3:6]
        self.q_wxyz = xn[:, 6:10]
        self.rate_frd_rad_s = xn[:, 10:13]
        self.specific_force_frd_m_s2 = (s1 + 2.0 * (s2 + s3) + s4) / 6.0
        self.motor_w_rad_s = w2
        self.rotor_phase_rad = np.fmod(ph2, 2.0 * np.pi)
        self._k += 1
