"""Vehicle profiles: one YAML file per vehicle, validated once at the edge.

A profile holds three sections:

``frame``
    Geometry the companion needs to mix: motor positions (FRD body frame, metres,
    relative to the geometric centre) and spin directions, in output order.
``limits``
    Rate and motor limits the companion enforces.
``physics``
    What only the simulator reads (mass, inertia, rotor constants, drag, damage,
    IMU). The companion never uses these numbers: that is the point of
    model-free control.

Loading rejects unknown keys, missing keys, wrong types and non-physical values
with a :class:`~companion.errors.ConfigError` naming the file and key path.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from companion.errors import ConfigError
from companion.schema import StrictModel, load_yaml_model

__all__ = [
    "Damage",
    "Frame",
    "ImuModel",
    "Limits",
    "MotorDamage",
    "MotorSpec",
    "Physics",
    "VehicleProfile",
    "load_profile",
]


Vec3 = tuple[float, float, float]


class MotorSpec(StrictModel):
    """One rotor: where it is and which way it spins (seen from above)."""

    position_frd_m: Vec3
    spin: Literal["cw", "ccw"]

    @field_validator("position_frd_m")
    @classmethod
    def _finite(cls, v: Vec3) -> Vec3:
        if not all(math.isfinite(x) for x in v):
            raise ValueError("expected three finite numbers")
        if math.hypot(v[0], v[1]) < 0.01:
            raise ValueError("expected a motor at least 0.01 m from the centre in the x-y plane")
        return v


class Frame(StrictModel):
    """Frame geometry, in output (motor index) order."""

    layout: Literal["quad_x", "quad_plus", "custom"] = "custom"
    motors: list[MotorSpec] = Field(min_length=4, max_length=8)

    @model_validator(mode="after")
    def _spins_balance(self) -> Frame:
        n_cw = sum(1 for m in self.motors if m.spin == "cw")
        if 2 * n_cw != len(self.motors):
            raise ValueError(
                f"expected as many cw as ccw motors for yaw authority, got {n_cw} cw of "
                f"{len(self.motors)}"
            )
        return self


class Limits(StrictModel):
    """Limits the companion enforces whatever the controller asks."""

    rate_max_deg_s: Vec3 = (1080.0, 1080.0, 720.0)
    motor_idle: float = Field(0.05, ge=0.0, le=0.3)

    @field_validator("rate_max_deg_s")
    @classmethod
    def _positive(cls, v: Vec3) -> Vec3:
        if not all(0.0 < x <= 2000.0 for x in v):
            raise ValueError("expected three rates in (0, 2000] deg/s (roll, pitch, yaw)")
        return v


class MotorDamage(StrictModel):
    """Damage or asymmetry on one motor (index into ``frame.motors``)."""

    motor: int = Field(ge=0)
    thrust_efficiency: float = Field(1.0, gt=0.0, le=1.5)
    torque_efficiency: float = Field(1.0, gt=0.0, le=1.5)
    imbalance_n: float = Field(
        0.0, ge=0.0, le=50.0, description="once-per-revolution radial force amplitude at max speed"
    )
    fail_at_s: float | None = Field(None, ge=0.0, description="time the motor degrades")
    efficiency_after_fail: float = Field(0.0, ge=0.0, le=1.0)


class Damage(StrictModel):
    """Asymmetries of a damaged or oddly loaded vehicle."""

    motors: list[MotorDamage] = Field(default_factory=list)
    cg_offset_frd_m: Vec3 = (0.0, 0.0, 0.0)
    inertia_delta_kg_m2: tuple[Vec3, Vec3, Vec3] = ((0.0,) * 3, (0.0,) * 3, (0.0,) * 3)


class ImuModel(StrictModel):
    """Gyro model (and the paper's first-stage filter)."""

    rate_hz: float = Field(1000.0, gt=0.0, le=8000.0)
    gyro_noise_density_rad_s_sqrt_hz: float = Field(
        0.0, ge=0.0, description="white noise density; sigma = density * sqrt(rate_hz)"
    )
    gyro_bias_random_walk_rad_s2_sqrt_hz: float = Field(0.0, ge=0.0)
    gyro_range_deg_s: float = Field(2000.0, gt=0.0)
    latency_s: float = Field(0.0, ge=0.0, le=0.05)
    first_stage_filter_weight: float = Field(
        1.0,
        gt=0.0,
        le=1.0,
        description="paper's complementary filter: out = w*new + (1-w)*previous out; 1 disables",
    )


class Physics(StrictModel):
    """Rigid body, rotors and drag; read only by the simulator."""

    mass_kg: float = Field(gt=0.0, le=100.0)
    inertia_kg_m2: tuple[Vec3, Vec3, Vec3]
    kf_n_per_rad_s2: float = Field(gt=0.0, description="thrust = kf * w^2")
    km_m: float = Field(gt=0.0, le=0.2, description="reaction torque = km * thrust")
    motor_w_max_rad_s: float = Field(gt=0.0)
    motor_w_idle_rad_s: float = Field(ge=0.0)
    motor_tau_up_s: float = Field(gt=0.0, le=0.5)
    motor_tau_down_s: float = Field(gt=0.0, le=0.5)
    rotor_inertia_kg_m2: float = Field(0.0, ge=0.0)
    drag_linear_n_per_m_s: Vec3 = (0.0, 0.0, 0.0)
    drag_quadratic_n_per_m2_s2: Vec3 = (0.0, 0.0, 0.0)
    angular_drag_n_m_per_rad_s: Vec3 = (0.0, 0.0, 0.0)
    mixer: Literal["geometry", "paper"] = Field(
        "geometry",
        description="how the simulated autopilot allocates actuator-control torques to motors",
    )
    damage: Damage = Field(default_factory=Damage)
    imu: ImuModel = Field(default_factory=ImuModel)

    @field_validator("inertia_kg_m2")
    @classmethod
    def _inertia_physical(cls, v: tuple[Vec3, Vec3, Vec3]) -> tuple[Vec3, Vec3, Vec3]:
        J = np.array(v, dtype=float)
        if not np.all(np.isfinite(J)):
            raise ValueError("expected a finite 3x3 matrix")
        if not np.allclose(J, J.T, atol=1e-12):
            raise ValueError("expected a symmetric 3x3 matrix")
        eig = np.linalg.eigvalsh(J)
        if eig.min() <= 0.0:
            raise ValueError(f"expected a positive-definite matrix, eigenvalues {eig.tolist()}")
        # Triangle inequality of principal moments (a real body satisfies it).
        a, b, c = sorted(eig.tolist())
        if a + b < c * (1 - 1e-6):
            raise ValueError(f"principal moments {a:.4g}, {b:.4g}, {c:.4g} violate a + b >= c")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> Physics:
        if self.motor_w_idle_rad_s >= self.motor_w_max_rad_s:
            raise ValueError("motor_w_idle_rad_s must be below motor_w_max_rad_s")
        return self


class VehicleProfile(StrictModel):
    """A whole vehicle: geometry, limits, and simulator-only physics."""

    name: str = Field(min_length=1)
    frame: Frame
    limits: Limits = Field(default_factory=Limits)
    physics: Physics

    @model_validator(mode="after")
    def _damage_indices(self) -> VehicleProfile:
        n = len(self.frame.motors)
        for d in self.physics.damage.motors:
            if d.motor >= n:
                raise ValueError(
                    f"physics.damage.motors: motor index {d.motor} out of range 0..{n - 1}"
                )
        return self

    @model_validator(mode="after")
    def _damaged_inertia(self) -> VehicleProfile:
        J = np.array(self.physics.inertia_kg_m2) + np.array(self.physics.damage.inertia_delta_kg_m2)
        if not np.allclose(J, J.T, atol=1e-12) or np.linalg.eigvalsh(J).min() <= 0.0:
            raise ValueError(
                "physics.damage.inertia_delta_kg_m2: inertia plus this change must stay "
                "symmetric positive-definite"
            )
        return self

    @property
    def n_motors(self) -> int:
        return len(self.frame.motors)

    def hover_problem(self) -> str | None:
        """Why the simulator could not hover this vehicle (undamaged, on equal
        motor speeds: sitl.rotors's hover command), or None if it can."""
        p = self.physics
        w = math.sqrt(p.mass_kg * 9.80665 / (self.n_motors * p.kf_n_per_rad_s2))
        if p.motor_w_idle_rad_s <= w <= p.motor_w_max_rad_s:
            return None
        return (
            f"physics: cannot hover: mass_kg, kf_n_per_rad_s2 and {self.n_motors} motors "
            f"need {w:.4g} rad/s, outside motor_w_idle_rad_s..motor_w_max_rad_s "
            f"({p.motor_w_idle_rad_s:g}..{p.motor_w_max_rad_s:g})"
        )

    def thrust_to_weight(self) -> float:
        """Total static thrust at full speed over weight (undamaged)."""
        p = self.physics
        return self.n_motors * p.kf_n_per_rad_s2 * p.motor_w_max_rad_s**2 / (p.mass_kg * 9.80665)


def load_profile(path: str | Path, *, simulated: bool = False) -> VehicleProfile:
    """Load and validate a vehicle profile YAML file.

    ``simulated``: the vehicle is to be flown in the simulator, so its physics
    must also let it hover (:meth:`VehicleProfile.hover_problem`); the companion
    alone never reads the physics section.
    """
    prof: VehicleProfile = load_yaml_model(path, VehicleProfile)
    if simulated and (problem := prof.hover_problem()) is not None:
        raise ConfigError(str(path), [problem])
    return prof
