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
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, ValidationError, field_validator, model_validator
from pydantic_core import InitErrorDetails, PydanticCustomError

from companion.errors import ConfigError
from companion.schema import (
    Count,
    Real,
    StrictModel,
    load_yaml_model,
    range_problem,
    real_number,
)

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
    "Frame",
    "ImuModel",
    "Limits",
    "MotorDamage",
    "MotorSpec",
    "Physics",
    "VehicleProfile",
    "load_profile",
    "profile_warnings",
    "rate_limit_problem",
    "rate_limit_validator",
]

_G_M_S2 = 9.80665  # standard gravity
_RPM_PER_RAD_S = 60.0 / (2.0 * math.pi)

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


class MotorSpec(StrictModel):
    """One rotor: where it is and which way it spins (seen from above)."""

    position_frd_m: tuple[_Coordinate, _Coordinate, _Coordinate] = Field(
        description="x forward, y right, z down from the geometric centre, m; at most "
        f"{MOTOR_DISTANCE_MAX_M:g} m from it"
    )
    spin: Literal["cw", "ccw"]

    @field_validator("position_frd_m", mode="before")
    @classmethod
    def _distance(cls, raw: Any) -> Any:
        # Before pydantic's range: a motor in millimetres is named as such.
        given = [real_number(x) for x in raw] if isinstance(raw, (list, tuple)) else []
        v = [x for x in given if x is not None]
        if len(given) != 3 or len(v) != 3:
            return raw  # pydantic says what is wrong
        if math.hypot(v[0], v[1]) < 0.01:
            raise ValueError("expected a motor at least 0.01 m from the centre in the x-y plane")
        d = math.sqrt(sum(x * x for x in v))
        if d > MOTOR_DISTANCE_MAX_M:
            raise ValueError(
                f"{d:.4g} m from the centre looks like millimetres ({d / 1000:.4g} m) or "
                f"centimetres ({d / 100:.4g} m): expected metres, a motor at most "
                f"{MOTOR_DISTANCE_MAX_M:g} m from the centre"
            )
        return raw


def _layout_problem(layout: str, motors: list[MotorSpec]) -> str | None:
    """Why ``motors`` contradict a named ``layout``, or None (always None for ``custom``).

    ``quad_x``: four motors, one in each quadrant clear of the axes (more than ~6 deg
    off them: H and dead-cat frames are X too), diagonal ones spinning the same way.
    ``quad_plus``: four motors, one on each half-axis (within 30 deg of it), opposite
    ones spinning the same way. Same-spin neighbours would tie yaw to roll or pitch.
    """
    if layout == "custom":
        return None
    if len(motors) != 4:
        return f"expected layout: custom for {len(motors)} motors ({layout} has 4)"
    xy = [(m.position_frd_m[0], m.position_frd_m[1]) for m in motors]
    slots: list[tuple[bool, bool]]
    if layout == "quad_x":
        # Slot (front, right); opposite corners flip both.
        slots = [(x > 0, y > 0) for x, y in xy if min(abs(x), abs(y)) > 0.1 * math.hypot(x, y)]
        pairs = [((True, True), (False, False)), ((True, False), (False, True))]
        where = "one motor in each quadrant, clear of the x and y axes"
    else:
        # Slot (on the x axis, on its positive side); opposite ends flip the second.
        slots = [
            (abs(x) > abs(y), (x if abs(x) > abs(y) else y) > 0)
            for x, y in xy
            if min(abs(x), abs(y)) < 0.5 * math.hypot(x, y)
        ]
        pairs = [((True, True), (True, False)), ((False, True), (False, False))]
        where = "one motor on each half-axis (front, right, back, left)"
    if len(set(slots)) != 4:
        return f"frame.motors are not a {layout}: expected {where}, or layout: custom"
    spin = dict(zip(slots, (m.spin for m in motors), strict=True))
    if any(spin[a] != spin[b] for a, b in pairs):
        return (
            f"frame.motors spin as no {layout} does: expected opposite motors to spin the "
            "same way (else yaw is tied to roll or pitch), or layout: custom"
        )
    return None


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

    @model_validator(mode="after")
    def _layout_matches(self) -> Frame:
        if (problem := _layout_problem(self.layout, self.motors)) is not None:
            raise _problems("Frame", [(("layout",), problem, self.layout)])
        return self


class Limits(StrictModel):
    """Limits the companion enforces whatever the controller asks."""

    rate_max_deg_s: tuple[RateLimitDegS, RateLimitDegS, RateLimitDegS] = Field(
        (1080.0, 1080.0, 720.0),
        description="roll, pitch, yaw rate limits, deg/s: the envelope failsafe's",
    )
    motor_idle: Real = Field(0.05, ge=0.0, le=0.3)

    _rates = rate_limit_validator("rate_max_deg_s", "three rates (roll, pitch, yaw) in %s deg/s")


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
