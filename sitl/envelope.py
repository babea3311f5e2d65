r"""The vehicle envelope: physically consistent quad-X profiles from a few scalars.

The envelope this project targets: quadrotors of mass 0.25-5 kg, thrust-to-weight
1.8-10 and motor time constant 5-60 ms, with arm length and inertia consistent with
those, plus damage inside that envelope. :func:`derive` turns four scalars (mass,
thrust-to-weight, motor time constant, optionally the arm) into an
:class:`EnvelopeVehicle` whose :meth:`~EnvelopeVehicle.profile` is a complete,
validated :class:`~companion.profile.VehicleProfile`; :func:`sample_envelope`
fills the envelope with a seeded Latin hypercube, :func:`corners` names its
extremes and :func:`damage_variants` damages any vehicle in three stated ways.

Every scaling law below is anchored on the DJI F450 of
``vehicle_profiles/f450.yaml`` (RflySim's F450 model,
``docs/research/profiles.md#f450``): fed the
F450's own scalars (1.5 kg, arm 0.225 m, T/W 2.569, 21 ms) the generator
returns its inertia, ``kf``, ``km``, ``w_max``, rotor inertia and drag exactly.

Size law (arm from mass)
------------------------
.. math::  L = f_L \, L_0 \, (m / m_0)^{1/2}, \qquad L_0 = 0.225\ \text{m},\ m_0 = 1.5\ \text{kg}

with the *arm factor* :math:`f_L \in [0.8, 1.25]` sampled (log-uniformly, it is
symmetric about 1). The exponent 1/2 is constant *disk loading*: hover thrust
scales with :math:`m`, disk area with :math:`r^2 \propto L^2`, and designers keep
the disk loading (hence the ideal hover power per newton,
:math:`\propto\sqrt{T/A}`) in a narrow band. It fits the reference table better
than geometric similarity (exponent 1/3): it predicts 0.26 m for the 2 kg X500
(real 0.246), 0.318 m for the 3 kg Tarot 650 (real 0.325), 0.225 m for the
1.5 kg Iris (real 0.255), and 0.092 m for a 0.25 kg 3-inch quad (real ~0.07 m).
The arm factor spreads the disk loading by :math:`1/f_L^2`, i.e. 0.64-1.56 times
the F450's 73 N/m² (an efficient camera ship to a racer-like 113 N/m²).

Propeller, rotor speed and thrust constant
------------------------------------------
Prop radius :math:`r = 0.564 L` (F450: 0.127 m on 0.225 m; the quad-X
no-overlap limit is :math:`L/\sqrt2 = 0.707 L`). One propeller family with the
F450's thrust coefficient,

.. math::  T = C_T \rho \pi r^2 (\omega r)^2, \qquad
           C_T = k_{f,0} / (\rho \pi r_0^4) = 0.0168,\ \rho = 1.225\ \text{kg/m}^3,

sets the tip speed at full thrust from the per-motor maximum
:math:`T_{max} = (T/W) m g / 4`: :math:`V_{tip} = \sqrt{T_{max} / (C_T \rho \pi r^2)}`
(F450: 95 m/s). It is capped at :data:`TIP_SPEED_MAX_M_S` = 200 m/s (Mach 0.6, what
a 5-inch racer reaches at ~30 000 rpm); above it a designer fits pitchier props,
so ``kf`` grows instead. Then

.. math::  \omega_{max} = V_{tip} / r, \qquad k_f = T_{max} / \omega_{max}^2,

so ``profile.thrust_to_weight()`` equals the requested value to rounding.
Idle speed :math:`\omega_{idle} = 0.133\,\omega_{max}` (F450: 100 of 750 rad/s).
Yaw moment constant :math:`k_m = k_{m,0}\, r / r_0` (reaction torque over thrust
is a length, :math:`r\,C_Q/C_T`; F450 0.0166 m), clipped to [0.005, 0.05] m.
Rotor inertia :math:`J_r = J_{r,0} (r / r_0)^4` (blade mass :math:`\propto r^2`
times :math:`r^2`; F450 6e-5 kg m², which the law carries to 3.0e-4 for a 15-inch
prop, the Tarot 650 estimate).

Rigid body
----------
.. math::  I_{xx} = c_x m L^2, \quad I_{yy} = c_y m L^2, \quad I_{zz} = c_z m L^2,

with :math:`(c_x, c_y, c_z) = (0.278, 0.288, 0.482)` from the F450. Across the
reference vehicles (``docs/research/profiles.md``) :math:`c_x` runs from 0.18
(X500, Tarot) to 0.30 (Iris), so the F450 sits at the heavy-arm end; the anchor
is kept because its inertia is measured, the others partly estimated. Motors sit
in the PX4 quad-X order of the bundled profiles, the prop plane :math:`0.18 L`
above the CG (the F450 cut-prop profile's 4 cm; it is what lets an imbalanced
prop shake roll and pitch, not only yaw). Drag (linear, quadratic, angular) scales with frontal
area, :math:`(L/L_0)^2` times the F450's figures. Motor lag is symmetric,
``motor_tau_up_s = motor_tau_down_s = motor_tau_s`` (as RflySim's F450), so the
sampled scalar is the lag. Limits and IMU are the F450's (scenarios override
the IMU rate and noise).

Figure of merit
---------------
:func:`peak_angular_accel_rad_s2` is the body angular acceleration, at rest, for
a full-scale normalised torque command on one axis: the motors whose mixer
factor (``-y``, ``x``, spin) is positive at full command, the others at the
idle command ``limits.motor_idle``. For roll and pitch this is exactly what the
geometry mixer's air mode delivers for a full-scale command at *any*
collective; for yaw (which only gets headroom in the mixer) it is the upper
bound. Undamaged quad-X:

.. math::  \dot p_{peak} = 2 k_f (\omega_{max}^2 - \omega_{lo}^2)\,
           (L/\sqrt2) / I_{xx} \approx \frac{(T/W)\, g}{2\sqrt2\, c_x L},

so it scales as :math:`(T/W)/L`: 5.6x in T/W times 7.0x in arm (0.073-0.513 m)
over the envelope, 38.8x between the corners ``tiny-fast`` and ``heavy-weak``.

Damage (:func:`damage_variants`)
--------------------------------
``motor60``: motor 0 (front right) at 60 % thrust and 60 % reaction torque.
``imbalance``: motor 0's prop unbalanced, ``imbalance_n = 0.3 T_max``. The
simulator scales the rotating force with :math:`\omega^2` like the thrust, so at
any speed it is 30 % of that rotor's own thrust, whatever the T/W. The bundled
cut-prop F450 has about 3x (0.4-0.7 g left on one blade); 0.3 is a tenth of
that, a chipped tip (~0.06 g at 0.09 m on the F450). At most 37 N in the
envelope (schema limit 50 N). ``cg10``: the CG moved by 10 % of the arm along
the diagonal towards motor 0 (the worst direction for a single motor: in hover
motor 0 carries 1.2 times its share, 0.3 of the weight).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from companion.profile import Damage, MotorDamage, VehicleProfile
from sitl.rotors import hover_motor_command, motor_command_to_speed
from sitl.vehicle_params import GRAVITY_M_S2, VehicleParams

__all__ = [
    "AIR_DENSITY_KG_M3",
    "ENVELOPE_BOUNDS",
    "PROP_THRUST_COEFF",
    "TIP_SPEED_MAX_M_S",
    "EnvelopeVehicle",
    "angular_accel_limits_rad_s2",
    "corners",
    "damage_variants",
    "derive",
    "latin_hypercube",
    "nominal_arm_m",
    "peak_angular_accel_rad_s2",
    "sample_envelope",
    "write_profile_yaml",
]

# --- Anchor: DJI F450, vehicle_profiles/f450.yaml (docs/research/profiles.md#f450) ---
_F450_MASS_KG = 1.5
_F450_ARM_M = 0.225
_F450_PROP_RADIUS_M = 0.127  # 10-inch prop
_F450_INERTIA_KG_M2 = (0.0211, 0.0219, 0.0366)
_F450_KF_N_PER_RAD_S2 = 1.68e-5
_F450_KM_M = 0.0166
_F450_W_MAX_RAD_S = 750.0
_F450_W_IDLE_RAD_S = 100.0
_F450_ROTOR_INERTIA_KG_M2 = 6.0e-5
_F450_DRAG_LINEAR = (0.10, 0.10, 0.15)
_F450_DRAG_QUADRATIC = (0.02, 0.02, 0.04)
_F450_DRAG_ANGULAR = (0.0005, 0.0005, 0.001)
_F450_LIMITS: dict[str, Any] = {"rate_max_deg_s": (1080.0, 1080.0, 720.0), "motor_idle": 0.05}
_F450_IMU: dict[str, Any] = {
    "rate_hz": 1000.0,
    "gyro_noise_density_rad_s_sqrt_hz": 8.7e-5,
    "gyro_bias_random_walk_rad_s2_sqrt_hz": 1.0e-5,
    "gyro_range_deg_s": 2000.0,
    "latency_s": 0.0,
    "first_stage_filter_weight": 1.0,
}

#: Sea-level ISA air density (kg/m³).
AIR_DENSITY_KG_M3 = 1.225
#: Propeller family's thrust coefficient in ``T = C_T rho pi r^2 (w r)^2`` (F450's).
PROP_THRUST_COEFF = _F450_KF_N_PER_RAD_S2 / (AIR_DENSITY_KG_M3 * math.pi * _F450_PROP_RADIUS_M**4)
#: Highest prop tip speed at full thrust (m/s); above it ``kf`` grows instead.
TIP_SPEED_MAX_M_S = 200.0

_PROP_RADIUS_PER_ARM = _F450_PROP_RADIUS_M / _F450_ARM_M
_IDLE_SPEED_FRACTION = _F450_W_IDLE_RAD_S / _F450_W_MAX_RAD_S
_KM_PER_PROP_RADIUS = _F450_KM_M / _F450_PROP_RADIUS_M
_KM_RANGE_M = (0.005, 0.05)
_INERTIA_COEFFS = tuple(i / (_F450_MASS_KG * _F450_ARM_M**2) for i in _F450_INERTIA_KG_M2)
_PROP_PLANE_ABOVE_CG_PER_ARM = 0.18
_MOTOR60_EFFICIENCY = 0.6
_IMBALANCE_PER_MAX_THRUST = 0.3
_CG_OFFSET_PER_ARM = 0.1

#: Sampled ranges: ``mass_kg``, ``thrust_to_weight``, ``motor_tau_s`` and
#: ``arm_factor`` (arm over :func:`nominal_arm_m`), each sampled log-uniformly;
#: ``arm_m`` is the range these imply, not a dimension of its own.
ENVELOPE_BOUNDS: dict[str, tuple[float, float]] = {
    "mass_kg": (0.25, 5.0),
    "thrust_to_weight": (1.8, 10.0),
    "motor_tau_s": (0.005, 0.06),
    "arm_factor": (0.8, 1.25),
}
ENVELOPE_BOUNDS["arm_m"] = (
    ENVELOPE_BOUNDS["arm_factor"][0] * _F450_ARM_M * math.sqrt(0.25 / _F450_MASS_KG),
    ENVELOPE_BOUNDS["arm_factor"][1] * _F450_ARM_M * math.sqrt(5.0 / _F450_MASS_KG),
)
_LHS_DIMS = ("mass_kg", "thrust_to_weight", "motor_tau_s", "arm_factor")


def nominal_arm_m(mass_kg: float) -> float:
    r"""Arm length (centre to motor, m) of the size law, arm factor 1.

    .. math::  L = L_0 (m / m_0)^{1/2}, \qquad L_0 = 0.225\ \text{m},\ m_0 = 1.5\ \text{kg}
    """
    return _F450_ARM_M * math.sqrt(mass_kg / _F450_MASS_KG)


def _check_range(name: str, value: float, lo: float, hi: float) -> None:
    if not (math.isfinite(value) and lo < value <= hi):
        raise ValueError(f"{name}: expected a number in ({lo}, {hi}], got {value!r}")


@dataclass(frozen=True)
class EnvelopeVehicle:
    """A quad-X described by the envelope's scalars; the rest is derived.

    Attributes
    ----------
    name : str
        Vehicle name, e.g. ``"env-07"``; becomes the profile's name.
    mass_kg : float
        Take-off mass (kg), in (0, 100].
    arm_m : float
        Centre-to-motor distance (m), in (0.02, 5].
    thrust_to_weight : float
        Total static thrust at full speed over weight, in (1, 50].
    motor_tau_s : float
        First-order rotor-speed lag (s), up and down, in (0, 0.5].

    Raises
    ------
    ValueError
        On construction, for a value outside the ranges above.
    """

    name: str
    mass_kg: float
    arm_m: float
    thrust_to_weight: float
    motor_tau_s: float

    def __post_init__(self) -> None:
        if not self.name:
            raise ValueError("name: expected a non-empty string")
        _check_range("mass_kg", self.mass_kg, 0.0, 100.0)
        _check_range("arm_m", self.arm_m, 0.02, 5.0)
        # Above ~56 the hover speed would fall below idle.
        _check_range("thrust_to_weight", self.thrust_to_weight, 1.0, 50.0)
        _check_range("motor_tau_s", self.motor_tau_s, 0.0, 0.5)

    @property
    def arm_factor(self) -> float:
        """Arm over the size law's arm for this mass (1 on the law)."""
        return self.arm_m / nominal_arm_m(self.mass_kg)

    @property
    def prop_radius_m(self) -> float:
        """Propeller radius (m), ``0.564 * arm_m``."""
        return _PROP_RADIUS_PER_ARM * self.arm_m

    @property
    def max_motor_thrust_n(self) -> float:
        """One rotor's thrust at full speed (N), ``(T/W) m g / 4``."""
        return self.thrust_to_weight * self.mass_kg * GRAVITY_M_S2 / 4.0

    @property
    def tip_speed_m_s(self) -> float:
        r"""Prop tip speed at full speed (m/s), ``sqrt(T_max / (C_T rho pi r^2))`` capped."""
        r = self.prop_radius_m
        v = math.sqrt(
            self.max_motor_thrust_n / (PROP_THRUST_COEFF * AIR_DENSITY_KG_M3 * math.pi * r * r)
        )
        return min(v, TIP_SPEED_MAX_M_S)

    @property
    def motor_w_max_rad_s(self) -> float:
        """Rotor speed at full command (rad/s), ``V_tip / r``."""
        return self.tip_speed_m_s / self.prop_radius_m

    @property
    def kf_n_per_rad_s2(self) -> float:
        """Thrust constant (N/(rad/s)²), ``T_max / w_max^2``."""
        return self.max_motor_thrust_n / self.motor_w_max_rad_s**2

    @property
    def km_m(self) -> float:
        """Reaction torque over thrust (m), ``0.1307 r`` clipped to [0.005, 0.05]."""
        lo, hi = _KM_RANGE_M
        return min(max(_KM_PER_PROP_RADIUS * self.prop_radius_m, lo), hi)

    @property
    def inertia_diag_kg_m2(self) -> tuple[float, float, float]:
        """Principal moments ``(Ixx, Iyy, Izz) = (c_x, c_y, c_z) m L^2`` (kg m²)."""
        mL2 = self.mass_kg * self.arm_m**2
        cx, cy, cz = _INERTIA_COEFFS
        return (cx * mL2, cy * mL2, cz * mL2)

    def profile(self) -> VehicleProfile:
        """The complete, validated quad-X profile (module docstring for each law)."""
        L = self.arm_m
        d = L / math.sqrt(2.0)
        z = -_PROP_PLANE_ABOVE_CG_PER_ARM * L
        s2 = (L / _F450_ARM_M) ** 2
        r_ratio = self.prop_radius_m / _F450_PROP_RADIUS_M
        w_max = self.motor_w_max_rad_s
        ixx, iyy, izz = self.inertia_diag_kg_m2
        data = {
            "name": self.name,
            "frame": {
                "layout": "quad_x",
                # PX4 quad-X order: front-right CCW, rear-left CCW, front-left CW, rear-right CW.
                "motors": [
                    {"position_frd_m": (d, d, z), "spin": "ccw"},
                    {"position_frd_m": (-d, -d, z), "spin": "ccw"},
                    {"position_frd_m": (d, -d, z), "spin": "cw"},
                    {"position_frd_m": (-d, d, z), "spin": "cw"},
                ],
            },
            "limits": dict(_F450_LIMITS),
            "physics": {
                "mass_kg": self.mass_kg,
                "inertia_kg_m2": ((ixx, 0.0, 0.0), (0.0, iyy, 0.0), (0.0, 0.0, izz)),
                "kf_n_per_rad_s2": self.kf_n_per_rad_s2,
                "km_m": self.km_m,
                "motor_w_max_rad_s": w_max,
                "motor_w_idle_rad_s": _IDLE_SPEED_FRACTION * w_max,
                "motor_tau_up_s": self.motor_tau_s,
                "motor_tau_down_s": self.motor_tau_s,
                "rotor_inertia_kg_m2": _F450_ROTOR_INERTIA_KG_M2 * r_ratio**4,
                "drag_linear_n_per_m_s": tuple(c * s2 for c in _F450_DRAG_LINEAR),
                "drag_quadratic_n_per_m2_s2": tuple(c * s2 for c in _F450_DRAG_QUADRATIC),
                "angular_drag_n_m_per_rad_s": tuple(c * s2 for c in _F450_DRAG_ANGULAR),
                "mixer": "geometry",
                "imu": dict(_F450_IMU),
            },
        }
        return VehicleProfile.model_validate(data)

    def to_dict(self) -> dict[str, float | str]:
        """The scalars and the derived figures, JSON-able (units in the keys)."""
        prof = self.profile()
        ph = prof.physics
        ixx, iyy, izz = self.inertia_diag_kg_m2
        roll, pitch, yaw = peak_angular_accel_rad_s2(prof)
        r = self.prop_radius_m
        return {
            "name": self.name,
            "mass_kg": self.mass_kg,
            "arm_m": self.arm_m,
            "thrust_to_weight": self.thrust_to_weight,
            "motor_tau_s": self.motor_tau_s,
            "arm_factor": self.arm_factor,
            "prop_radius_m": r,
            "disk_loading_n_m2": self.mass_kg * GRAVITY_M_S2 / (4.0 * math.pi * r * r),
            "max_motor_thrust_n": self.max_motor_thrust_n,
            "tip_speed_m_s": self.tip_speed_m_s,
            "motor_w_max_rad_s": ph.motor_w_max_rad_s,
            "motor_w_idle_rad_s": ph.motor_w_idle_rad_s,
            "kf_n_per_rad_s2": ph.kf_n_per_rad_s2,
            "km_m": ph.km_m,
            "rotor_inertia_kg_m2": ph.rotor_inertia_kg_m2,
            "ixx_kg_m2": ixx,
            "iyy_kg_m2": iyy,
            "izz_kg_m2": izz,
            "hover_command": hover_motor_command(prof),
            "peak_roll_accel_rad_s2": roll,
            "peak_pitch_accel_rad_s2": pitch,
            "peak_yaw_accel_rad_s2": yaw,
        }


def derive(
    name: str,
    mass_kg: float,
    thrust_to_weight: float,
    motor_tau_s: float,
    arm_m: float | None = None,
) -> EnvelopeVehicle:
    """A vehicle from its scalars; the arm from the size law when not given.

    Parameters
    ----------
    name : str
        Vehicle (and profile) name.
    mass_kg : float
        Take-off mass (kg).
    thrust_to_weight : float
        Full-speed static thrust over weight, > 1.
    motor_tau_s : float
        Motor lag (s).
    arm_m : float or None
        Centre-to-motor distance (m); ``None`` is :func:`nominal_arm_m` ``(mass_kg)``.

    Raises
    ------
    ValueError
        For a value outside :class:`EnvelopeVehicle`'s ranges. Values outside
        :data:`ENVELOPE_BOUNDS` are allowed (the F450 anchor, extrapolation).
    """
    arm = nominal_arm_m(mass_kg) if arm_m is None else arm_m
    return EnvelopeVehicle(
        name=name,
        mass_kg=float(mass_kg),
        arm_m=float(arm),
        thrust_to_weight=float(thrust_to_weight),
        motor_tau_s=float(motor_tau_s),
    )


def latin_hypercube(n: int, n_dims: int, rng: np.random.Generator) -> np.ndarray:
    """A Latin hypercube sample on the unit cube.

    Each dimension is cut into ``n`` equal strata; every stratum holds exactly
    one point, at a uniform position inside it, and the strata are matched
    across dimensions by independent random permutations:
    ``u[i, j] = (pi_j(i) + U[i, j]) / n``.

    Parameters
    ----------
    n : int
        Number of points, >= 1.
    n_dims : int
        Number of dimensions, >= 1.
    rng : numpy.random.Generator
        Source of the permutations and the offsets.

    Returns
    -------
    numpy.ndarray, shape (n, n_dims)
        Points in ``[0, 1)``.
    """
    if n < 1 or n_dims < 1:
        raise ValueError(f"expected n >= 1 and n_dims >= 1, got {n} and {n_dims}")
    strata = np.column_stack([rng.permutation(n) for _ in range(n_dims)])
    return (strata + rng.random((n, n_dims))) / n


def sample_envelope(n: int, seed: int) -> list[EnvelopeVehicle]:
    """``n`` vehicles filling the envelope, named ``env-00`` .. ``env-(n-1)``.

    A Latin hypercube (:func:`latin_hypercube`, generator
    ``numpy.random.default_rng(seed)``) over ``log mass_kg``,
    ``log thrust_to_weight``, ``log motor_tau_s`` and ``log arm_factor`` within
    :data:`ENVELOPE_BOUNDS`: ``x = lo (hi / lo)^u``. Same seed, same list.

    Raises
    ------
    ValueError
        If ``n < 1``.
    """
    u = latin_hypercube(n, len(_LHS_DIMS), np.random.default_rng(seed))
    lo = np.array([ENVELOPE_BOUNDS[k][0] for k in _LHS_DIMS])
    hi = np.array([ENVELOPE_BOUNDS[k][1] for k in _LHS_DIMS])
    x = lo * (hi / lo) ** u
    width = max(2, len(str(n - 1)))
    return [
        derive(
            f"env-{i:0{width}d}",
            mass_kg=float(m),
            thrust_to_weight=float(tw),
            motor_tau_s=float(tau),
            arm_m=float(af) * nominal_arm_m(float(m)),
        )
        for i, (m, tw, tau, af) in enumerate(x)
    ]


def corners() -> list[EnvelopeVehicle]:
    """Named extremes of the envelope (and its centre).

    ``tiny-fast`` (0.25 kg, T/W 10, 5 ms, shortest arm: the highest angular
    acceleration), ``tiny-slow-motor`` (same airframe, 60 ms motors),
    ``heavy-weak`` (5 kg, T/W 1.8, 60 ms, longest arm: the lowest),
    ``heavy-strong`` (5 kg, T/W 10, 60 ms, nominal arm) and ``mid`` (geometric
    centre of every range: 1.12 kg, T/W 4.24, 17 ms, nominal arm).
    """
    m_lo, m_hi = ENVELOPE_BOUNDS["mass_kg"]
    tw_lo, tw_hi = ENVELOPE_BOUNDS["thrust_to_weight"]
    tau_lo, tau_hi = ENVELOPE_BOUNDS["motor_tau_s"]
    af_lo, af_hi = ENVELOPE_BOUNDS["arm_factor"]
    return [
        derive("tiny-fast", m_lo, tw_hi, tau_lo, af_lo * nominal_arm_m(m_lo)),
        derive("tiny-slow-motor", m_lo, tw_hi, tau_hi, af_lo * nominal_arm_m(m_lo)),
        derive("heavy-weak", m_hi, tw_lo, tau_hi, af_hi * nominal_arm_m(m_hi)),
        derive("heavy-strong", m_hi, tw_hi, tau_hi),
        derive("mid", math.sqrt(m_lo * m_hi), math.sqrt(tw_lo * tw_hi), math.sqrt(tau_lo * tau_hi)),
    ]


def _with_damage(base: VehicleProfile, suffix: str, damage: Damage) -> VehicleProfile:
    data = base.model_dump()
    data["name"] = f"{base.name}+{suffix}"
    data["physics"]["damage"] = damage.model_dump()
    return VehicleProfile.model_validate(data)


def damage_variants(vehicle: EnvelopeVehicle) -> dict[str, VehicleProfile]:
    """The vehicle's profile damaged three ways, each alone.

    Returns
    -------
    dict of str to VehicleProfile
        ``"motor60"``: motor 0 with ``thrust_efficiency = torque_efficiency = 0.6``;
        ``"imbalance"``: motor 0 with ``imbalance_n = 0.3 * max_motor_thrust_n``;
        ``"cg10"``: ``cg_offset_frd_m`` of ``0.1 * arm_m`` along the diagonal
        towards motor 0 (front right). Names are ``"<name>+<key>"``.
    """
    base = vehicle.profile()
    x0, y0, _ = base.frame.motors[0].position_frd_m
    imbalance_n = _IMBALANCE_PER_MAX_THRUST * vehicle.max_motor_thrust_n
    return {
        "motor60": _with_damage(
            base,
            "motor60",
            Damage(
                motors=[
                    MotorDamage(
                        motor=0,
                        thrust_efficiency=_MOTOR60_EFFICIENCY,
                        torque_efficiency=_MOTOR60_EFFICIENCY,
                    )
                ]
            ),
        ),
        "imbalance": _with_damage(
            base, "imbalance", Damage(motors=[MotorDamage(motor=0, imbalance_n=imbalance_n)])
        ),
        "cg10": _with_damage(
            base,
            "cg10",
            Damage(cg_offset_frd_m=(_CG_OFFSET_PER_ARM * x0, _CG_OFFSET_PER_ARM * y0, 0.0)),
        ),
    }


def peak_angular_accel_rad_s2(profile: VehicleProfile) -> tuple[float, float, float]:
    """Angular acceleration for a full-scale torque command on each axis (rad/s²): the
    smaller of the two directions of :func:`angular_accel_limits_rad_s2`, the
    authority available both ways.

    Returns
    -------
    tuple of 3 float
        Roll, pitch, yaw (rad/s²).
    """
    roll, pitch, yaw = angular_accel_limits_rad_s2(profile)
    return (min(roll), min(pitch), min(yaw))


def angular_accel_limits_rad_s2(
    profile: VehicleProfile,
) -> tuple[tuple[float, float], tuple[float, float], tuple[float, float]]:
    r"""Angular acceleration for a full-scale torque command, each axis, each way (rad/s²).

    For axis ``a`` and direction ``s = +/-1``, motor ``i`` runs at full command
    (``w_max``) when ``s`` times its mixer factor is positive, at the idle
    command ``limits.motor_idle`` (``w_lo``) when negative, and at the equal
    hover speed when zero. Factors as the geometry mixer's: ``-y_i`` (roll),
    ``x_i`` (pitch), ``+1`` CCW / ``-1`` CW (yaw). With the damaged coefficients
    and the lever arms about the CG (:class:`sitl.vehicle_params.VehicleParams`),

    .. math::  \tau = \sum_i r_i \times (0, 0, -k_{T,i} w_i^2) + (0, 0, \sigma_i k_{Q,i} w_i^2),
               \qquad \dot\omega = J^{-1} \tau,

    at zero body rate (no gyroscopic or drag terms, and no rotor spin-up reaction).

    Returns
    -------
    tuple of 3 (float, float)
        Roll, pitch, yaw: ``s * dot omega_a`` for ``s = +1`` and ``s = -1`` (rad/s²).
    """
    P = VehicleParams.from_profile(profile)
    w_hi = P.w_max_rad_s
    w_lo = motor_command_to_speed(profile.limits.motor_idle, P.w_idle_rad_s, P.w_max_rad_s)
    w_hover = math.sqrt(P.mass_kg * GRAVITY_M_S2 / sum(P.thrust_coeff))
    J_inv = np.array(P.inertia_inv)
    geom = [m.position_frd_m for m in profile.frame.motors]
    factors = (
        [-p[1] for p in geom],
        [p[0] for p in geom],
        list(P.spin_sign),
    )
    limits = []
    for axis, fac in enumerate(factors):
        both = []
        for s in (1.0, -1.0):
            tau = np.zeros(3)
            for i, f in enumerate(fac):
                w = w_hi if s * f > 1e-12 else (w_lo if s * f < -1e-12 else w_hover)
                thrust = P.thrust_coeff[i] * w * w
                rx, ry, _ = P.arm_frd_m[i]
                tau += (-ry * thrust, rx * thrust, P.spin_sign[i] * P.torque_coeff[i] * w * w)
            both.append(s * float((J_inv @ tau)[axis]))
        limits.append((both[0], both[1]))
    return (limits[0], limits[1], limits[2])


def write_profile_yaml(profile: VehicleProfile, path: Path) -> None:
    """Write ``profile`` as YAML that :func:`companion.profile.load_profile` reads back equal.

    Floats are written with ``repr`` (shortest round-tripping form), so the
    loaded profile compares equal to ``profile``.
    """
    header = "# Generated by sitl.envelope (see its module docstring for every law).\n"
    body = yaml.safe_dump(profile.model_dump(mode="json"), sort_keys=False, default_flow_style=None)
    Path(path).write_text(header + body, encoding="utf-8")
