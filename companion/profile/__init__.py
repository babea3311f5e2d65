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

Loading rejects unknown keys, missing keys, wrong types (``true`` or ``"1.5"``
where a number belongs among them: YAML reads ``true``, ``yes`` and ``on`` as
booleans and a quoted number as text, which pydantic would pass as 1 and 1.5)
and non-physical values with a :class:`~companion.errors.ConfigError` naming the
file and key path.

Plausibility
------------
A profile must describe a multirotor of some 100 g to 100 kg, so every number with
a unit has a range (in the field, shown in ``docs/reference/config.md``) and a
number of the wrong unit is refused by its magnitude, the message naming the
likely mistake: rate limits or a gyro range in rad/s, motor positions in
millimetres, a mass in grams, ``kf`` or rotor speeds no propeller has. The
sections must also agree:
thrust-to-weight at most :data:`THRUST_TO_WEIGHT_MAX`, each inertia within
:data:`INERTIA_RANGE_PER_M_ARM2` of ``m L^2`` (``L`` the mean motor distance
from the centre), a ``layout`` matching the motors. Each bound is a module
constant saying where it comes from. What is unusual but possible (a vehicle
that cannot hover: a real vehicle's profile may carry placeholder physics) is
not an error: :func:`profile_warnings` lists it.

Layout
------
``_bounds`` holds the bounds and the field types other models share (a rate limit,
the IMU model's fields), ``_frame`` the ``frame`` and ``limits`` sections,
``_physics`` the ``physics`` section and ``_vehicle`` the whole profile, its
warnings and its loading. Import them from here.
"""

from companion.profile._bounds import (
    ANGULAR_DRAG_MAX_N_M_PER_RAD_S,
    DRAG_LINEAR_MAX_N_PER_M_S,
    DRAG_QUADRATIC_MAX_N_PER_M2_S2,
    FLIGHT_MAX_S,
    GYRO_BIAS_WALK_MAX_RAD_S2_SQRT_HZ,
    GYRO_NOISE_DENSITY_MAX_RAD_S_SQRT_HZ,
    GYRO_RANGE_MAX_DEG_S,
    GYRO_RANGE_MIN_DEG_S,
    INERTIA_MAX_KG_M2,
    INERTIA_RANGE_PER_M_ARM2,
    INERTIA_TYPICAL_PER_M_ARM2,
    KF_RANGE_N_PER_RAD_S2,
    KM_MAX_M,
    KM_MIN_TYPICAL_M,
    MASS_MAX_KG,
    MASS_MIN_KG,
    MOTOR_DISTANCE_MAX_M,
    MOTOR_W_MAX_RANGE_RAD_S,
    RATE_LIMIT_MAX_DEG_S,
    RATE_LIMIT_MIN_DEG_S,
    ROTOR_INERTIA_MAX_KG_M2,
    THRUST_TO_WEIGHT_MAX,
    THRUST_TO_WEIGHT_TYPICAL,
    FilterWeight,
    GyroBiasWalk,
    GyroNoiseDensity,
    ImuLatencyS,
    ImuRateHz,
    RateLimitDegS,
    rate_limit_problem,
    rate_limit_validator,
)
from companion.profile._frame import Frame, Limits, MotorSpec
from companion.profile._physics import Damage, ImuModel, MotorDamage, Physics
from companion.profile._vehicle import VehicleProfile, load_profile, profile_warnings

__all__ = [
    "ANGULAR_DRAG_MAX_N_M_PER_RAD_S",
    "DRAG_LINEAR_MAX_N_PER_M_S",
    "DRAG_QUADRATIC_MAX_N_PER_M2_S2",
    "FLIGHT_MAX_S",
    "GYRO_BIAS_WALK_MAX_RAD_S2_SQRT_HZ",
    "GYRO_NOISE_DENSITY_MAX_RAD_S_SQRT_HZ",
    "GYRO_RANGE_MAX_DEG_S",
    "GYRO_RANGE_MIN_DEG_S",
    "INERTIA_MAX_KG_M2",
    "INERTIA_RANGE_PER_M_ARM2",
    "INERTIA_TYPICAL_PER_M_ARM2",
    "KF_RANGE_N_PER_RAD_S2",
    "KM_MAX_M",
    "KM_MIN_TYPICAL_M",
    "MASS_MAX_KG",
    "MASS_MIN_KG",
    "MOTOR_DISTANCE_MAX_M",
    "MOTOR_W_MAX_RANGE_RAD_S",
    "RATE_LIMIT_MAX_DEG_S",
    "RATE_LIMIT_MIN_DEG_S",
    "ROTOR_INERTIA_MAX_KG_M2",
    "THRUST_TO_WEIGHT_MAX",
    "THRUST_TO_WEIGHT_TYPICAL",
    "Damage",
    "FilterWeight",
    "Frame",
    "GyroBiasWalk",
    "GyroNoiseDensity",
    "ImuLatencyS",
    "ImuModel",
    "ImuRateHz",
    "Limits",
    "MotorDamage",
    "MotorSpec",
    "Physics",
    "RateLimitDegS",
    "VehicleProfile",
    "load_profile",
    "profile_warnings",
    "rate_limit_problem",
    "rate_limit_validator",
]
