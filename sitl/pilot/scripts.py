"""Stick-script YAML files, loaded into a :class:`~sitl.pilot.scripted.ScriptedPilot`.

Format
------
::

    duration_s: 20                          # required, > 0
    rate_full_scale_deg_s: [720, 720, 360]  # optional, stick full scale per axis
    altitude_m: 10                          # optional, altitude-hold target (m, up)
    aux_us: [1000]                          # optional, initial ch5.. (us)
    segments:                               # required, t_s strictly increasing, first 0
      - {t_s: 0.0, level: true}             # take-off: level + altitude hold
      - {t_s: 4.0, level: true, throttle: climb, climb_m_s: 5}
      - {t_s: 4.6, rate_deg_s: [720, null, null], ramp_s: 0.1, throttle: coast}
      - {t_s: 5.0, rate_deg_s: [0, null, null], ramp_s: 0.1, throttle: coast}
      - {t_s: 5.1, level: true, aux_us: [2000]}
      - {t_s: 8.0, chirp: {axis: roll, amplitude_deg_s: 100, f0_hz: 1, f1_hz: 8}}
      - {t_s: 18.0, rate_deg_s: [90, null, null], step: true}

Segment keys: exactly one of ``level: true``, ``rate_deg_s: [p, q, r]``
(``null`` = virtual pilot on that axis) or ``chirp: {axis, amplitude_deg_s,
f0_hz, f1_hz, taper_s}``; optional ``ramp_s`` (s, default 0.1), ``step``
(bool), ``throttle`` (hold | climb | coast, default hold), ``climb_m_s``
(m/s, default 5), ``altitude_m`` (new hold target, persists) and ``aux_us``
(persists).  Unknown keys and out-of-range values raise
:class:`companion.errors.ConfigError` naming the file and the key path.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, ValidationError, model_validator

from companion.errors import ConfigError
from companion.profile import (
    FLIGHT_MAX_S,
    RATE_LIMIT_MAX_DEG_S,
    RateLimitDegS,
    rate_limit_validator,
)
from companion.schema import StrictModel, format_validation_error, read_yaml
from sitl.pilot.rc import DEFAULT_RATE_FULL_SCALE_DEG_S, RC_MAX_US, RC_MIN_US
from sitl.pilot.scripted import Chirp, ScriptedPilot, Segment
from sitl.pilot.virtual import PilotParams

_AXES = ("roll", "pitch", "yaw")
"""A chirp's axis names, in the order of the pilot's rate channels."""

__all__ = ["load_stick_script"]

_RateDegS = Annotated[float, Field(ge=-RATE_LIMIT_MAX_DEG_S, le=RATE_LIMIT_MAX_DEG_S)]
_AuxUs = Annotated[int, Field(ge=RC_MIN_US, le=RC_MAX_US)]


class _ChirpModel(StrictModel):
    axis: Literal["roll", "pitch", "yaw"]
    amplitude_deg_s: float = Field(gt=0.0, le=RATE_LIMIT_MAX_DEG_S)
    f0_hz: float = Field(gt=0.0, le=100.0)
    f1_hz: float = Field(gt=0.0, le=100.0)
    taper_s: float = Field(default=0.5, ge=0.0, le=10.0)


class _SegmentModel(StrictModel):
    t_s: float = Field(ge=0.0, le=FLIGHT_MAX_S)
    level: bool = False
    rate_deg_s: tuple[_RateDegS | None, _RateDegS | None, _RateDegS | None] | None = None
    chirp: _ChirpModel | None = None
    ramp_s: float = Field(default=0.1, ge=0.0, le=10.0)
    step: bool = False
    throttle: Literal["hold", "climb", "coast"] = "hold"
    climb_m_s: float = Field(default=5.0, ge=-10.0, le=10.0)
    altitude_m: float | None = Field(default=None, gt=0.0, le=500.0)
    aux_us: tuple[_AuxUs, ...] | None = None

    @model_validator(mode="after")
    def _one_kind(self) -> _SegmentModel:
        kinds = int(self.level) + int(self.rate_deg_s is not None) + int(self.chirp is not None)
        if kinds != 1:
            raise ValueError("exactly one of level: true, rate_deg_s or chirp is required")
        return self


class _ScriptModel(StrictModel):
    duration_s: float = Field(gt=0.0, le=FLIGHT_MAX_S)
    rate_full_scale_deg_s: tuple[RateLimitDegS, RateLimitDegS, RateLimitDegS] = (
        DEFAULT_RATE_FULL_SCALE_DEG_S
    )
    altitude_m: float = Field(default=10.0, gt=0.0, le=500.0)
    aux_us: tuple[_AuxUs, ...] = ()
    segments: list[_SegmentModel] = Field(min_length=1)

    _full_scale = rate_limit_validator(
        "rate_full_scale_deg_s", "three rates at full stick (roll, pitch, yaw) in %s deg/s"
    )

    @model_validator(mode="after")
    def _check(self) -> _ScriptModel:
        if self.segments[0].t_s != 0.0:
            raise ValueError("segments.0.t_s must be 0")
        for k in range(1, len(self.segments)):
            if not self.segments[k].t_s > self.segments[k - 1].t_s:
                raise ValueError(f"segments.{k}.t_s must be greater than segments.{k - 1}.t_s")
        return self


def _to_segment(m: _SegmentModel) -> Segment:
    rates: tuple[float | None, float | None, float | None] = (
        m.rate_deg_s if m.rate_deg_s is not None else (None, None, None)
    )
    chirp = None
    if m.chirp is not None:
        c = m.chirp
        chirp = Chirp(_AXES.index(c.axis), c.amplitude_deg_s, c.f0_hz, c.f1_hz, c.taper_s)
    return Segment(
        t_s=m.t_s,
        rate_deg_s=rates,
        ramp_s=m.ramp_s,
        step=m.step,
        chirp=chirp,
        throttle=m.throttle,
        climb_m_s=m.climb_m_s,
        altitude_m=m.altitude_m,
        aux_us=m.aux_us,
    )


def load_stick_script(
    path: str | Path, *, free_flight: bool = True, params: PilotParams | None = None
) -> ScriptedPilot:
    """Load a stick-script YAML file (format in the module docstring) into a pilot.

    Parameters
    ----------
    path : str or Path
        The YAML file.
    free_flight : bool
        See :class:`ScriptedPilot`.
    params : PilotParams, optional
        Base gains; the file's ``rate_full_scale_deg_s`` and ``altitude_m``
        override them.

    Returns
    -------
    ScriptedPilot

    Raises
    ------
    companion.errors.ConfigError
        Unreadable file, bad YAML, unknown key or out-of-range value; the
        message names the file and the key path (e.g. ``segments.2.ramp_s``).
    """
    p = Path(path)
    raw = read_yaml(p)
    if not isinstance(raw, dict):
        raise ConfigError(str(p), ["top level: expected a mapping"])
    try:
        model = _ScriptModel.model_validate(raw)
    except ValidationError as exc:
        raise ConfigError(str(p), format_validation_error(exc)) from exc
    base = params if params is not None else PilotParams()
    prm = PilotParams(
        **{
            **base.__dict__,
            "rate_full_scale_deg_s": model.rate_full_scale_deg_s,
            "altitude_m": model.altitude_m,
        }
    )
    return ScriptedPilot(
        [_to_segment(s) for s in model.segments],
        model.duration_s,
        params=prm,
        free_flight=free_flight,
        aux_us=model.aux_us,
        name=p.name,
    )
