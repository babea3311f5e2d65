"""A vehicle profile's ``physics`` section: what only the simulator reads."""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from companion.profile._bounds import (
    ANGULAR_DRAG_MAX_N_M_PER_RAD_S,
    DRAG_LINEAR_MAX_N_PER_M_S,
    DRAG_QUADRATIC_MAX_N_PER_M2_S2,
    FLIGHT_MAX_S,
    GYRO_RANGE_MAX_DEG_S,
    GYRO_RANGE_MIN_DEG_S,
    INERTIA_MAX_KG_M2,
    KF_RANGE_N_PER_RAD_S2,
    KM_MAX_M,
    MASS_MAX_KG,
    MASS_MIN_KG,
    MOTOR_W_MAX_RANGE_RAD_S,
    ROTOR_INERTIA_MAX_KG_M2,
    FilterWeight,
    GyroBiasWalk,
    GyroNoiseDensity,
    ImuLatencyS,
    ImuRateHz,
    Vec3,
    _Coordinate,
)
from companion.schema import Count, Real, StrictModel, range_problem, real_number

_RPM_PER_RAD_S = 60.0 / (2.0 * math.pi)


class MotorDamage(StrictModel):
    """Damage or asymmetry on one motor (index into ``frame.motors``)."""

    motor: Count = Field(ge=0)
    thrust_efficiency: Real = Field(1.0, gt=0.0, le=1.5)
    torque_efficiency: Real = Field(1.0, gt=0.0, le=1.5)
    imbalance_n: Real = Field(
        0.0, ge=0.0, le=50.0, description="once-per-revolution radial force amplitude at max speed"
    )
    fail_at_s: Annotated[float, Field(ge=0.0, le=FLIGHT_MAX_S)] | None = Field(
        None, description="time the motor degrades, s from the start of the flight"
    )
    efficiency_after_fail: Real = Field(0.0, ge=0.0, le=1.0)


_InertiaEntry = Annotated[float, Field(ge=-INERTIA_MAX_KG_M2, le=INERTIA_MAX_KG_M2)]
_Inertia = tuple[_InertiaEntry, _InertiaEntry, _InertiaEntry]


class Damage(StrictModel):
    """Asymmetries of a damaged or oddly loaded vehicle."""

    motors: list[MotorDamage] = Field(default_factory=list)
    cg_offset_frd_m: tuple[_Coordinate, _Coordinate, _Coordinate] = Field(
        (0.0, 0.0, 0.0),
        description="centre of mass offset from the geometric centre, FRD, m; no farther "
        "than a motor may be",
    )
    inertia_delta_kg_m2: tuple[_Inertia, _Inertia, _Inertia] = Field(
        ((0.0,) * 3, (0.0,) * 3, (0.0,) * 3),
        description="added to physics.inertia_kg_m2, kg m^2",
    )


class ImuModel(StrictModel):
    """Gyro model (and the paper's first-stage filter)."""

    rate_hz: ImuRateHz = Field(1000.0, description="sample rate, Hz")
    gyro_noise_density_rad_s_sqrt_hz: GyroNoiseDensity = Field(
        0.0, description="white noise density, rad/s/sqrt(Hz); sigma = density * sqrt(rate_hz)"
    )
    gyro_bias_random_walk_rad_s2_sqrt_hz: GyroBiasWalk = Field(
        0.0, description="bias random walk, rad/s^2/sqrt(Hz)"
    )
    gyro_range_deg_s: Real = Field(
        2000.0, ge=GYRO_RANGE_MIN_DEG_S, le=GYRO_RANGE_MAX_DEG_S, description="full scale, deg/s"
    )
    latency_s: ImuLatencyS = Field(0.0, description="delay of each sample, s")
    first_stage_filter_weight: FilterWeight = Field(
        1.0,
        description="paper's complementary filter: out = w*new + (1-w)*previous out; 1 disables",
    )

    @field_validator("gyro_range_deg_s", mode="before")
    @classmethod
    def _gyro_range(cls, raw: Any) -> Any:
        if (v := real_number(raw)) is None:
            return raw
        problem = range_problem(
            v,
            (GYRO_RANGE_MIN_DEG_S, GYRO_RANGE_MAX_DEG_S),
            "a full scale in %s deg/s",
            f"{v:g} looks like rad/s ({math.degrees(v):.4g} deg/s)",
            "wider than any flight-controller gyro",
        )
        if problem is not None:
            raise ValueError(problem)
        return raw


_DragLinear = Annotated[float, Field(ge=0.0, le=DRAG_LINEAR_MAX_N_PER_M_S)]
_DragQuadratic = Annotated[float, Field(ge=0.0, le=DRAG_QUADRATIC_MAX_N_PER_M2_S2)]
_AngularDrag = Annotated[float, Field(ge=0.0, le=ANGULAR_DRAG_MAX_N_M_PER_RAD_S)]


class Physics(StrictModel):
    """Rigid body, rotors and drag; read only by the simulator."""

    mass_kg: Real = Field(ge=MASS_MIN_KG, le=MASS_MAX_KG, description="take-off mass, kg")
    inertia_kg_m2: tuple[_Inertia, _Inertia, _Inertia] = Field(
        description="3x3 inertia about the centre of mass, FRD, kg m^2"
    )
    kf_n_per_rad_s2: Real = Field(
        ge=KF_RANGE_N_PER_RAD_S2[0],
        le=KF_RANGE_N_PER_RAD_S2[1],
        description="thrust = kf * w^2, N/(rad/s)^2",
    )
    km_m: Real = Field(gt=0.0, le=KM_MAX_M, description="reaction torque = km * thrust, m")
    motor_w_max_rad_s: Real = Field(
        ge=MOTOR_W_MAX_RANGE_RAD_S[0],
        le=MOTOR_W_MAX_RANGE_RAD_S[1],
        description="rotor speed at full command, rad/s",
    )
    motor_w_idle_rad_s: Real = Field(
        ge=0.0, le=MOTOR_W_MAX_RANGE_RAD_S[1], description="rotor speed at idle, rad/s"
    )
    motor_tau_up_s: Real = Field(gt=0.0, le=0.5)
    motor_tau_down_s: Real = Field(gt=0.0, le=0.5)
    rotor_inertia_kg_m2: Real = Field(
        0.0,
        ge=0.0,
        le=ROTOR_INERTIA_MAX_KG_M2,
        description="one rotor's inertia (spin-up reaction torque), kg m^2",
    )
    drag_linear_n_per_m_s: tuple[_DragLinear, _DragLinear, _DragLinear] = Field(
        (0.0, 0.0, 0.0), description="linear drag per body axis, N/(m/s)"
    )
    drag_quadratic_n_per_m2_s2: tuple[_DragQuadratic, _DragQuadratic, _DragQuadratic] = Field(
        (0.0, 0.0, 0.0), description="quadratic drag per body axis, N/(m/s)^2"
    )
    angular_drag_n_m_per_rad_s: tuple[_AngularDrag, _AngularDrag, _AngularDrag] = Field(
        (0.0, 0.0, 0.0), description="angular damping per body axis, N m/(rad/s)"
    )
    mixer: Literal["geometry", "paper"] = Field(
        "geometry",
        description="how the simulated autopilot allocates actuator-control torques to motors",
    )
    damage: Damage = Field(default_factory=Damage)
    imu: ImuModel = Field(default_factory=ImuModel)

    # The checks below run before pydantic's range, to name the likely mistake.

    @field_validator("mass_kg", mode="before")
    @classmethod
    def _mass(cls, raw: Any) -> Any:
        if (v := real_number(raw)) is not None and v > MASS_MAX_KG:
            raise ValueError(
                f"{v:g} looks like grams ({v / 1000:g} kg): expected kg, at most {MASS_MAX_KG:g}"
            )
        return raw

    @field_validator("kf_n_per_rad_s2", mode="before")
    @classmethod
    def _kf(cls, raw: Any) -> Any:
        if (v := real_number(raw)) is None or v <= 0.0:
            return raw
        problem = range_problem(
            v,
            KF_RANGE_N_PER_RAD_S2,
            "a thrust constant in %s N/(rad/s)^2 (props of 1.6 to 60 inches)",
            f"no propeller has this kf (per rpm^2? per (rad/s)^2 is 91.2 times it, "
            f"{v * _RPM_PER_RAD_S**2:.3g})",
            "no propeller has this kf (a minus sign missing from the exponent?)",
        )
        if problem is not None:
            raise ValueError(problem)
        return raw

    @field_validator("km_m", mode="before")
    @classmethod
    def _km(cls, raw: Any) -> Any:
        if (v := real_number(raw)) is not None and v > KM_MAX_M:
            raise ValueError(
                f"{v:g} looks like millimetres ({v / 1000:g} m): expected metres, at most "
                f"{KM_MAX_M:g} (reaction torque over thrust, ~0.13 prop radius)"
            )
        return raw

    @field_validator("motor_w_max_rad_s", mode="before")
    @classmethod
    def _w_max(cls, raw: Any) -> Any:
        if (v := real_number(raw)) is None or v <= 0.0:
            return raw
        problem = range_problem(
            v,
            MOTOR_W_MAX_RANGE_RAD_S,
            "a full speed in %s rad/s",
            f"{v:g} looks like rev/s ({v * 2.0 * math.pi:.4g} rad/s)",
            f"{v:g} looks like rpm ({v / _RPM_PER_RAD_S:.4g} rad/s)",
        )
        if problem is not None:
            raise ValueError(problem)
        return raw

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
