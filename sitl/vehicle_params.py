"""The plant's constants, read once from a vehicle profile (damage folded in)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.profile import VehicleProfile
from sitl.linalg import inverse

__all__ = ["GRAVITY_M_S2", "VehicleParams"]

#: Standard gravity (m/s²), as in ``VehicleProfile.thrust_to_weight``.
GRAVITY_M_S2 = 9.80665


@dataclass(frozen=True)
class VehicleParams:
    """Profile numbers turned into what the integrators use (SI units throughout).

    Built once by :meth:`from_profile`; shared by :class:`sitl.physics.Quadrotor` and
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
        J_inv = np.array(inverse(J.tolist()))  # the same bits on every machine

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
