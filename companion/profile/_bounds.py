"""The bounds a vehicle profile is checked against, and the field types that carry them.

Errors: what is impossible for a 0.1-100 kg multirotor, or a number in the wrong
unit. Warnings (:func:`~companion.profile.profile_warnings`): what is possible but
unlike any multirotor. Each bound says where it comes from.
"""

from __future__ import annotations

import math
from typing import Annotated, Any

from pydantic import Field, ValidationError, field_validator
from pydantic_core import InitErrorDetails, PydanticCustomError

from companion.schema import Real, range_problem, real_number

# --- Bounds: errors (impossible for a 0.1-100 kg multirotor, or a unit mistake) ---

RATE_LIMIT_MAX_DEG_S = 2000.0
"""Highest body-rate limit: the full scale flight controllers set on their gyros (±2000 deg/s)."""

RATE_LIMIT_MIN_DEG_S = 35.0
"""Lowest body-rate limit: :data:`RATE_LIMIT_MAX_DEG_S` is 34.9 rad/s, so any allowed
limit written in rad/s falls below it (1080 deg/s reads 18.8)."""

GYRO_RANGE_MIN_DEG_S = 100.0
"""Narrowest gyro full scale: flight controllers run their gyros at ±2000 deg/s and a
multirotor turns faster than 100 deg/s; the widest MEMS gyros' ±4000 deg/s is 69.8 rad/s,
so a range written in rad/s falls below."""

GYRO_RANGE_MAX_DEG_S = 8000.0
"""Widest gyro full scale: twice the widest of flight-controller MEMS gyros (±4000 deg/s)."""

MOTOR_DISTANCE_MAX_M = 2.0
"""Farthest a motor may be from the centre: 100 kg agricultural octocopters, some 2.2 m
across, have arms near 1.1 m; in millimetres even a 100 g quad's 50 mm arm reads 50."""

MASS_MAX_KG = 100.0
"""Heaviest vehicle: the top of the 0.1-100 kg multirotors the bounds here are derived for."""

MASS_MIN_KG = 0.1
"""Lightest vehicle: the bottom of those 0.1-100 kg (the envelope's lightest is 0.25 kg)."""

KF_RANGE_N_PER_RAD_S2 = (1e-9, 0.1)
"""Thrust constant ``kf = C_T rho pi r^4`` for C_T 0.01-0.03 (F450: 0.0168) and props of
1.6 to 60 inches (r 0.02-0.75 m): 6e-9 to 0.037 N/(rad/s)^2, with margin either side."""

KM_MAX_M = 0.2
"""Largest reaction torque over thrust, ``r C_Q / C_T`` ~ 0.13 r (F450: 0.0166 m on a
0.127 m prop): 0.2 m would take a 1.5 m prop radius, twice the largest."""

MOTOR_W_MAX_RANGE_RAD_S = (50.0, 10_000.0)
"""Full rotor speed: 60-inch props need ~90 rad/s to lift a 100 kg octocopter's share at
T/W 1.5; the fastest small motors turn ~60 000 rpm (6300 rad/s). In rpm, 10 000 is 95 000."""

THRUST_TO_WEIGHT_MAX = 30.0
"""Highest thrust over weight: the lightest racing quads reach ~20; a speed in rpm for rad/s
gives 91 times the thrust, a kf exponent missing its minus sign far more."""

INERTIA_RANGE_PER_M_ARM2 = (0.0025, 4.0)
"""Each diagonal inertia over ``m L^2`` (``L`` mean motor distance): below, all the mass within
0.05 L of the axis, though the motors alone (>= 5 % of it, at L) give >= 0.025; above,
a radius of gyration beyond 2 L, past the prop tips (<= 1.7 L). A g m^2 or kg cm^2
unit is 1000 or 10 000 times too big."""

INERTIA_MAX_KG_M2 = MASS_MAX_KG * MOTOR_DISTANCE_MAX_M**2 * INERTIA_RANGE_PER_M_ARM2[1]
"""Largest inertia entry (1600 kg m^2): the heaviest vehicle with motors at the farthest, at
the top of :data:`INERTIA_RANGE_PER_M_ARM2`."""

ROTOR_INERTIA_MAX_KG_M2 = 1.0
"""Largest rotor inertia: a 60-inch prop of 1 kg taken as a rod, ``m r^2 / 3``, is 0.2
kg m^2 (the bundled 10-15 inch props 6e-5 to 3e-4)."""

DRAG_LINEAR_MAX_N_PER_M_S = 100.0
"""Largest linear (rotor) drag per axis: the bundled ones 0.07-0.08 N/(m/s) per kg of
vehicle, 7 for 100 kg."""

DRAG_QUADRATIC_MAX_N_PER_M2_S2 = 10.0
"""Largest quadratic drag per axis, ``rho Cd A / 2``: 1.2 for a 100 kg octocopter's 2 m^2
frontal area at Cd 1 (the bundled ones 0.02-0.08)."""

ANGULAR_DRAG_MAX_N_M_PER_RAD_S = 10.0
"""Largest angular damping per axis: the F450's 5e-4 scaled by ``m L^2`` to 100 kg and
1.1 m arms is 0.8."""

GYRO_NOISE_DENSITY_MAX_RAD_S_SQRT_HZ = 0.1
"""Noisiest gyro: at 1 kHz, 0.1 rad/s/sqrt(Hz) is a 180 deg/s sigma, beyond any frame's
vibration (MEMS datasheets: 6e-5 to 9e-5; the vibrating scenarios: 1e-3)."""

GYRO_BIAS_WALK_MAX_RAD_S2_SQRT_HZ = 0.1
"""Fastest bias random walk: 0.1 rad/s^2/sqrt(Hz) wanders 1 rad/s in 100 s, a broken gyro
(the bundled profiles: 1e-5)."""

FLIGHT_MAX_S = 36_000.0
"""Latest time into a flight a file may name (a motor's failure, a stick script's end, a
reference's row): ten hours, longer than any multirotor flies."""

# --- Bounds: warnings (possible, but unlike any multirotor) ---

THRUST_TO_WEIGHT_TYPICAL = (1.5, 15.0)
"""Usual thrust over weight: below 1.5 hover takes 2/3 of full thrust, little left to
steer (bundled profiles 1.9-2.6, envelope 1.8-10); above 15 only the lightest racers."""

INERTIA_TYPICAL_PER_M_ARM2 = (0.05, 1.0)
"""Usual diagonal inertia over ``m L^2``: bundled profiles and envelope 0.18-0.48; all the
mass on the rotor circle gives 0.5 (roll, pitch) and 1 (yaw); the motors alone 0.025-0.05."""

KM_MIN_TYPICAL_M = 1e-3
"""Smallest usual reaction torque over thrust: ~0.13 r is 0.003 m for a 2-inch prop; below
1e-3 m yaw has next to no authority (or a torque constant ``kf * km`` was given)."""


Vec3 = tuple[Real, Real, Real]

RateLimitDegS = Annotated[float, Field(ge=RATE_LIMIT_MIN_DEG_S, le=RATE_LIMIT_MAX_DEG_S)]
"""A body-rate limit or a full-stick rate, deg/s; :func:`rate_limit_validator` says why one
is refused."""

# The IMU model's fields, shared with a scenario's override of them.
GyroNoiseDensity = Annotated[float, Field(ge=0.0, le=GYRO_NOISE_DENSITY_MAX_RAD_S_SQRT_HZ)]
GyroBiasWalk = Annotated[float, Field(ge=0.0, le=GYRO_BIAS_WALK_MAX_RAD_S2_SQRT_HZ)]
ImuRateHz = Annotated[float, Field(gt=0.0, le=8000.0)]
ImuLatencyS = Annotated[float, Field(ge=0.0, le=0.05)]
FilterWeight = Annotated[float, Field(gt=0.0, le=1.0)]


def rate_limit_problem(value: Any, what: str) -> str | None:
    """Why ``value`` (a field's input, a number or a list of them) is no rate limit in
    deg/s (:data:`RATE_LIMIT_MIN_DEG_S` to :data:`RATE_LIMIT_MAX_DEG_S`), or None.

    Run before pydantic's range check, so a rate written in rad/s is named as such
    (below the range, every allowed rate in rad/s falls). ``what`` is as in
    :func:`~companion.schema.range_problem`. Anything but a finite number is left to
    pydantic.
    """
    for v in value if isinstance(value, (list, tuple)) else (value,):
        x = real_number(v)
        if x is None:
            continue
        hint = f"{x:g} looks like rad/s ({math.degrees(x):.4g} deg/s)" if x > 0.0 else ""
        problem = range_problem(x, (RATE_LIMIT_MIN_DEG_S, RATE_LIMIT_MAX_DEG_S), what, hint, "")
        if problem is not None:
            return problem
    return None


def rate_limit_validator(field: str, what: str) -> Any:
    """A validator of a model's ``field`` (a :data:`RateLimitDegS` or a tuple of them),
    raising :func:`rate_limit_problem`'s ``what`` before pydantic's range check, so a
    rate written in rad/s is named as such: ``_rates = rate_limit_validator(...)`` in
    the class body."""

    def check(cls: type, v: Any) -> Any:
        if (problem := rate_limit_problem(v, what)) is not None:
            raise ValueError(problem)
        return v

    return field_validator(field, mode="before")(classmethod(check))


def _problems(title: str, items: list[tuple[tuple[str | int, ...], str, Any]]) -> ValidationError:
    """A validation error of several ``(key path, message, value)`` problems, so a check
    across fields names each field, as a field's own check would."""
    return ValidationError.from_exception_data(
        title,
        [
            InitErrorDetails(
                type=PydanticCustomError("value_error", "{message}", {"message": message}),
                loc=loc,
                input=value,
            )
            for loc, message, value in items
        ],
    )


_Coordinate = Annotated[float, Field(ge=-MOTOR_DISTANCE_MAX_M, le=MOTOR_DISTANCE_MAX_M)]
