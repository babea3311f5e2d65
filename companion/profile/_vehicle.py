"""A whole vehicle profile: its sections checked against each other, its doubts, its loading."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field, model_validator

from companion.errors import ConfigError
from companion.profile._bounds import (
    INERTIA_RANGE_PER_M_ARM2,
    INERTIA_TYPICAL_PER_M_ARM2,
    KM_MIN_TYPICAL_M,
    THRUST_TO_WEIGHT_MAX,
    THRUST_TO_WEIGHT_TYPICAL,
    _problems,
)
from companion.profile._frame import Frame, Limits
from companion.profile._physics import Physics
from companion.schema import StrictModel, load_yaml_model

_G_M_S2 = 9.80665  # standard gravity
_AXES = ("xx", "yy", "zz")


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

    @model_validator(mode="after")
    def _plausible(self) -> VehicleProfile:
        """Thrust-to-weight and inertia against mass and arm (module constants)."""
        p = self.physics
        problems: list[tuple[tuple[str | int, ...], str, Any]] = []
        tw = self.thrust_to_weight()
        if tw > THRUST_TO_WEIGHT_MAX:
            problems.append(
                (
                    ("physics",),
                    f"thrust-to-weight {tw:.3g} ({self.n_motors} motors * kf_n_per_rad_s2 "
                    f"{p.kf_n_per_rad_s2:g} * motor_w_max_rad_s {p.motor_w_max_rad_s:g}^2 / "
                    f"(mass_kg {p.mass_kg:g} * g)) is above {THRUST_TO_WEIGHT_MAX:g}, more than "
                    "any multirotor: is one of them in another unit (motor_w_max_rad_s in rpm "
                    "makes it 91 times too high)?",
                    p.model_dump(),
                )
            )
        lo, hi = INERTIA_RANGE_PER_M_ARM2
        for axis, per_m_l2, value in self._inertia_per_m_arm2():
            if not lo <= per_m_l2 <= hi:
                hint = " (g m^2 or kg cm^2 for kg m^2?)" if per_m_l2 > hi else ""
                problems.append(
                    (
                        ("physics", "inertia_kg_m2"),
                        f"I{axis} is {per_m_l2:.3g} m L^2 for mass_kg {p.mass_kg:g} and motors "
                        f"L = {self.mean_arm_m():.3g} m from the centre{hint}: expected "
                        f"{lo:g} to {hi:g} m L^2, a radius of gyration of "
                        f"{math.sqrt(lo):g} to {math.sqrt(hi):g} L",
                        value,
                    )
                )
        if problems:
            raise _problems("VehicleProfile", problems)
        return self

    @property
    def n_motors(self) -> int:
        return len(self.frame.motors)

    def mean_arm_m(self) -> float:
        """Mean distance of the motors from the centre in the x-y plane (m)."""
        return (
            sum(math.hypot(m.position_frd_m[0], m.position_frd_m[1]) for m in self.frame.motors)
            / self.n_motors
        )

    def _inertia_per_m_arm2(self) -> list[tuple[str, float, float]]:
        """``(axis, I / (m L^2), I)`` for each diagonal inertia (undamaged)."""
        m_l2 = self.physics.mass_kg * self.mean_arm_m() ** 2
        J = self.physics.inertia_kg_m2
        return [(axis, J[i][i] / m_l2, J[i][i]) for i, axis in enumerate(_AXES)]

    def hover_problem(self) -> str | None:
        """Why the simulator could not hover this vehicle (undamaged, on equal
        motor speeds: sitl.rotors's hover command), or None if it can."""
        p = self.physics
        w = math.sqrt(p.mass_kg * _G_M_S2 / (self.n_motors * p.kf_n_per_rad_s2))
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
        return self.n_motors * p.kf_n_per_rad_s2 * p.motor_w_max_rad_s**2 / (p.mass_kg * _G_M_S2)


def profile_warnings(profile: VehicleProfile) -> list[str]:
    """What in ``profile`` is possible but unlike a multirotor, one ``key.path: why`` line each.

    Doubts, not errors (those :func:`load_profile` raises): a vehicle that cannot
    hover (an error only for the simulator), thrust-to-weight outside
    :data:`THRUST_TO_WEIGHT_TYPICAL`, an inertia outside
    :data:`INERTIA_TYPICAL_PER_M_ARM2` times ``m L^2``, ``km_m`` below
    :data:`KM_MIN_TYPICAL_M`, a rate limit beyond the gyro's range. Empty for
    the bundled profiles and the envelope's vehicles.
    """
    p = profile.physics
    out: list[str] = []
    tw = profile.thrust_to_weight()
    tw_lo, tw_hi = THRUST_TO_WEIGHT_TYPICAL
    if (hover := profile.hover_problem()) is not None:
        out.append(f"{hover}: the simulator refuses this profile")
    elif tw < tw_lo:
        out.append(
            f"physics: thrust-to-weight {tw:.3g} is below {tw_lo:g}: hover takes "
            f"{100.0 / tw:.0f} % of full thrust, little is left to steer"
        )
    elif tw > tw_hi:
        out.append(
            f"physics: thrust-to-weight {tw:.3g} is above {tw_hi:g}, which only the lightest "
            "racing quads reach"
        )
    i_lo, i_hi = INERTIA_TYPICAL_PER_M_ARM2
    for axis, per_m_l2, _ in profile._inertia_per_m_arm2():
        if not i_lo <= per_m_l2 <= i_hi:
            out.append(
                f"physics.inertia_kg_m2: I{axis} is {per_m_l2:.3g} m L^2 for mass_kg "
                f"{p.mass_kg:g} and motors L = {profile.mean_arm_m():.3g} m from the centre; "
                f"multirotors have {i_lo:g} to {i_hi:g} (the bundled ones 0.18 to 0.48)"
            )
    if p.km_m < KM_MIN_TYPICAL_M:
        out.append(
            f"physics.km_m: {p.km_m:g} m leaves yaw next to no authority (usually ~0.13 times "
            f"the prop radius, at least 0.003 m): a torque constant kf * km given as km?"
        )
    rate = max(profile.limits.rate_max_deg_s)
    if rate > p.imu.gyro_range_deg_s:
        out.append(
            f"limits.rate_max_deg_s: {rate:g} deg/s is beyond physics.imu.gyro_range_deg_s "
            f"({p.imu.gyro_range_deg_s:g}): the gyro saturates before the limit"
        )
    return out


def load_profile(path: str | Path, *, simulated: bool = False) -> VehicleProfile:
    """Load and validate a vehicle profile YAML file.

    ``simulated``: the vehicle is to be flown in the simulator, so its physics
    must also let it hover (:meth:`VehicleProfile.hover_problem`); the companion
    alone never reads the physics section. Doubts that are not errors:
    :func:`profile_warnings`.
    """
    prof: VehicleProfile = load_yaml_model(path, VehicleProfile)
    if simulated and (problem := prof.hover_problem()) is not None:
        raise ConfigError(str(path), [problem])
    return prof
