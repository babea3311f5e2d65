"""The sections of a vehicle profile the companion reads: ``frame`` and ``limits``."""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from companion.profile._bounds import (
    MOTOR_DISTANCE_MAX_M,
    RateLimitDegS,
    _Coordinate,
    _problems,
    rate_limit_validator,
)
from companion.schema import Real, StrictModel, real_number


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
