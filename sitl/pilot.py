"""The simulated RC pilot: stick scripts, a maneuver library and a virtual outer loop.

A pilot turns a *timeline* of desired body rates (deg/s) into RC frames, like a
person flying a quadrotor in acro (body-rate) mode, which is what the companion's
MFC rate controller must track (paper Section IV: "the reference trajectories are
arbitrary and are generated in real time" by the pilot).

Conventions (fixed by the project)
----------------------------------
* RC channels are pulse widths in microseconds, 1000..2000, centre 1500, AETR map:
  ch1 roll, ch2 pitch, ch3 throttle, ch4 yaw, ch5.. auxiliary switches.
* Body frame FRD; signs follow the rates they command:

  - ch1 > 1500 (stick right)  -> +p, roll right;
  - ch2 > 1500                -> +q, nose up.  **Project convention**: a high ch2
    pulse is "stick back".  This is the ArduPilot default (its wiki: the pitch bar
    moves opposite to the physical stick), and the opposite sign of MAVLink
    ``MANUAL_CONTROL.x`` (positive = stick forward = nose down);
  - ch4 > 1500 (stick right)  -> +r, nose right;
  - ch3 throttle: 1000 -> 0, 2000 -> 1 (normalised collective thrust).

* Stick-to-rate is linear (no expo): ``rate = (us - 1500) / 500 * full_scale``,
  full scale 720 deg/s on roll and pitch and 360 deg/s on yaw by default.  The
  companion has its own mapping; this one is only for authoring.

How a pilot flies
-----------------
A timeline is a list of :class:`Segment`; segment *i* owns ``[t_i, t_{i+1})``.
On each axis a segment either *scripts* a rate (a number, ramped linearly from
the previous scripted value over ``ramp_s``, or a chirp) or leaves the axis to
the *virtual pilot* (``None``): roll and pitch are levelled with a P law on
attitude (:func:`level_rates_rad_s`), yaw is centred.  Throttle always comes
from the virtual pilot (:func:`throttle_command`):

* ``hold``  -- altitude hold, a saturated PD on altitude with ``hover_throttle``
  as feed-forward and tilt compensation;
* ``climb`` -- climb at ``climb_m_s`` (a "punch-out" before a flip);
* ``coast`` -- feed-forward only (what a pilot holds through a flip or roll).

Every stick then passes a slew limiter (a thumb cannot teleport): a full
deflection from centre takes at least ``stick_slew_s`` (80 ms), a full throttle
sweep ``throttle_slew_s`` (250 ms).  Only axes scripted by a segment marked
``step`` jump (rate steps for diagnosis).

With ``free_flight=False`` (test-stand rig, attitude only) the throttle is a
constant ``hover_throttle`` and levelling still runs.

Stick-script YAML format
------------------------
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

import bisect
import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Protocol

import numpy as np
from pydantic import Field, ValidationError, model_validator

from companion._schema import StrictModel, read_yaml
from companion.errors import ConfigError

__all__ = [
    "DEFAULT_RATE_FULL_SCALE_DEG_S",
    "MANEUVERS",
    "Chirp",
    "Pilot",
    "PilotParams",
    "PilotView",
    "ScriptedPilot",
    "Segment",
    "Sticks",
    "acro_random_timeline",
    "level_rates_rad_s",
    "load_stick_script",
    "make_pilot",
    "rate_to_stick_us",
    "stick_us_to_rate",
    "stick_us_to_throttle",
    "throttle_command",
    "throttle_to_stick_us",
]

RC_MIN_US = 1000
RC_MID_US = 1500
RC_MAX_US = 2000
RC_HALF_SPAN_US = 500.0
DEFAULT_RATE_FULL_SCALE_DEG_S: tuple[float, float, float] = (720.0, 720.0, 360.0)
GRAVITY_M_S2 = 9.80665

_DEG = math.pi / 180.0
_RAD = 180.0 / math.pi
ThrottleMode = Literal["hold", "climb", "coast"]
AXES = ("roll", "pitch", "yaw")


# --------------------------------------------------------------------------- mapping


def rate_to_stick_us(rate_deg_s: float, full_scale_deg_s: float) -> int:
    """Map a body rate to a stick pulse, linear and clamped.

    ``us = clamp(round(1500 + 500 * rate / full_scale), 1000, 2000)``

    Parameters
    ----------
    rate_deg_s : float
        Desired body rate, deg/s (FRD sign: + roll right, nose up, nose right).
    full_scale_deg_s : float
        Rate at full deflection (500 us from centre), deg/s, > 0.

    Returns
    -------
    int
        Pulse width, us, in 1000..2000.
    """
    us = RC_MID_US + RC_HALF_SPAN_US * rate_deg_s / full_scale_deg_s
    if us <= RC_MIN_US:
        return RC_MIN_US
    if us >= RC_MAX_US:
        return RC_MAX_US
    return math.floor(us + 0.5)


def stick_us_to_rate(us: float, full_scale_deg_s: float) -> float:
    """Map a stick pulse to a body rate, the inverse of :func:`rate_to_stick_us`.

    ``rate = (clamp(us, 1000, 2000) - 1500) / 500 * full_scale``

    Parameters
    ----------
    us : float
        Pulse width, us; values outside 1000..2000 are clamped.
    full_scale_deg_s : float
        Rate at full deflection, deg/s.

    Returns
    -------
    float
        Body rate, deg/s.
    """
    us = min(max(float(us), RC_MIN_US), RC_MAX_US)
    return (us - RC_MID_US) / RC_HALF_SPAN_US * full_scale_deg_s


def throttle_to_stick_us(throttle: float) -> int:
    """Map a normalised throttle (0..1, clamped) to ch3, 1000..2000 us."""
    us = RC_MIN_US + 1000.0 * min(max(throttle, 0.0), 1.0)
    return math.floor(us + 0.5)


def stick_us_to_throttle(us: float) -> float:
    """Map ch3 (us, clamped to 1000..2000) to a normalised throttle, 0..1."""
    return (min(max(float(us), RC_MIN_US), RC_MAX_US) - RC_MIN_US) / 1000.0


# --------------------------------------------------------------------------- API types


@dataclass(frozen=True)
class Sticks:
    """One RC frame, pulse widths in us (1000..2000), AETR.

    Attributes
    ----------
    roll_us, pitch_us, throttle_us, yaw_us : int
        ch1..ch4.
    aux_us : tuple of int
        ch5 onwards (e.g. an engage switch), may be empty.
    """

    roll_us: int
    pitch_us: int
    throttle_us: int
    yaw_us: int
    aux_us: tuple[int, ...] = ()

    def channels(self) -> tuple[int, ...]:
        """Return ``(ch1, ch2, ch3, ch4, *aux)`` in AETR order, us."""
        return (self.roll_us, self.pitch_us, self.throttle_us, self.yaw_us, *self.aux_us)


@dataclass(frozen=True)
class PilotView:
    """What the virtual pilot may see of the true vehicle (filled by the simulator).

    Attributes
    ----------
    t_s : float
        Simulation time, s (monotonic within a flight).
    roll_rad, pitch_rad, yaw_rad : float
        ZYX Euler angles of FRD body w.r.t. NED, rad.
    rate_frd_rad_s : tuple of float
        Body rates (p, q, r), rad/s.
    altitude_m : float
        Height above ground, m, up positive.
    climb_rate_m_s : float
        Vertical speed, m/s, up positive.
    hover_throttle : float
        Normalised throttle that roughly hovers the vehicle (a human learns it).
    """

    t_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    rate_frd_rad_s: tuple[float, float, float]
    altitude_m: float
    climb_rate_m_s: float
    hover_throttle: float


class Pilot(Protocol):
    """Anything that produces RC frames from a view of the vehicle."""

    duration_s: float

    def sticks(self, view: PilotView) -> Sticks:
        """Return the RC frame for this instant."""
        ...


@dataclass(frozen=True)
class Chirp:
    """A linear frequency sweep on one axis, scripted rate in deg/s.

    ``rate(tau) = A * w(tau) * sin(2 pi (f0 tau + (f1 - f0) tau^2 / (2 T)))``
    with ``T`` the segment length and ``w`` a linear taper of ``taper_s`` at both
    ends, so the stick starts and ends at centre.

    Attributes
    ----------
    axis : int
        0 roll, 1 pitch, 2 yaw.
    amplitude_deg_s : float
        Peak rate A, deg/s.
    f0_hz, f1_hz : float
        Start and end frequencies, Hz.
    taper_s : float
        Fade-in and fade-out time, s.
    """

    axis: int
    amplitude_deg_s: float
    f0_hz: float
    f1_hz: float
    taper_s: float = 0.5


@dataclass(frozen=True)
class Segment:
    """One piece of a pilot timeline, active from ``t_s`` to the next segment.

    Attributes
    ----------
    t_s : float
        Start time, s.
    rate_deg_s : tuple of (float or None)
        Scripted (p, q, r) in deg/s; ``None`` leaves the axis to the virtual pilot
        (roll/pitch levelling, yaw centred).
    ramp_s : float
        Time to ramp linearly from the previous segment's scripted rate on that
        axis (0 if it was not scripted) to this one, s.
    step : bool
        Scripted axes jump (no slew limit); for diagnosis only.
    chirp : Chirp or None
        A sweep on ``chirp.axis`` (that axis's ``rate_deg_s`` is ignored).
    throttle : {"hold", "climb", "coast"}
        Throttle mode of the virtual pilot.
    climb_m_s : float
        Climb rate for ``throttle="climb"``, m/s, up positive.
    altitude_m : float or None
        New altitude-hold target from here on, m; ``None`` keeps the current one.
    aux_us : tuple of int or None
        New ch5.. values from here on, us; ``None`` keeps the current ones.
    """

    t_s: float
    rate_deg_s: tuple[float | None, float | None, float | None] = (None, None, None)
    ramp_s: float = 0.1
    step: bool = False
    chirp: Chirp | None = None
    throttle: ThrottleMode = "hold"
    climb_m_s: float = 5.0
    altitude_m: float | None = None
    aux_us: tuple[int, ...] | None = None


@dataclass(frozen=True)
class PilotParams:
    """Gains and limits of the virtual pilot.

    Attributes
    ----------
    rate_full_scale_deg_s : tuple of float
        Stick full scale (roll, pitch, yaw), deg/s.
    level_gain_1_s : float
        Attitude P gain k of :func:`level_rates_rad_s`, 1/s.
    level_rate_max_deg_s : float
        Limit of the levelling rate command, deg/s.
    altitude_m : float
        Default altitude-hold target, m above ground.
    altitude_gain_1_s : float
        Altitude P gain to a climb-rate command, 1/s.
    climb_max_m_s, descent_max_m_s : float
        Limits of the commanded climb and descent rate, m/s (both > 0).
    climb_gain_1_s : float
        Climb-rate P gain to a vertical acceleration command, 1/s.
    accel_max_g : float
        Limit of the vertical acceleration command, in g.
    tilt_comp_min_cos : float
        Tilt compensation ``1/(cos roll cos pitch)`` is used down to this cosine
        and blended to ``inverted_throttle_frac`` at 90 deg of tilt and beyond.
    inverted_throttle_frac : float
        Throttle kept when on the side or inverted, fraction of the upright value.
    throttle_min, throttle_max : float
        Throttle clamp, normalised.
    stick_slew_s : float
        Minimum time for a full deflection from centre (500 us) on ch1/2/4, s.
    throttle_slew_s : float
        Minimum time for a full throttle sweep (1000 us), s.
    """

    rate_full_scale_deg_s: tuple[float, float, float] = DEFAULT_RATE_FULL_SCALE_DEG_S
    level_gain_1_s: float = 5.0
    level_rate_max_deg_s: float = 300.0
    altitude_m: float = 10.0
    altitude_gain_1_s: float = 1.2
    climb_max_m_s: float = 4.0
    descent_max_m_s: float = 3.0
    climb_gain_1_s: float = 3.0
    accel_max_g: float = 0.8
    tilt_comp_min_cos: float = 0.7
    inverted_throttle_frac: float = 0.5
    throttle_min: float = 0.05
    throttle_max: float = 1.0
    stick_slew_s: float = 0.08
    throttle_slew_s: float = 0.25


# --------------------------------------------------------------------------- virtual pilot


def level_rates_rad_s(
    roll_rad: float,
    pitch_rad: float,
    gain_1_s: float,
    rate_max_rad_s: float,
    *,
    both_axes: bool = True,
) -> tuple[float, float]:
    """Body rates (p, q) that bring the vehicle back to level, a P law on tilt.

    With ``g_b = (-sin(theta), sin(phi) cos(theta), cos(phi) cos(theta))`` the
    gravity direction in FRD body axes, the shortest rotation to level is about
    ``(-g_y, g_x)`` by the tilt angle ``a = atan2(|(g_x, g_y)|, g_z)``:

    ``(p, q) = k * a / sin(a) * (-g_y, g_x)``   (``both_axes=True``)

    which is ``(-k phi, -k theta)`` for small angles and rolls upright when
    inverted.  When another axis is scripted (``both_axes=False``) the
    component ``k * (-g_y, g_x)`` is used without the ``a/sin(a)`` factor, so
    levelling stays small while a flip on the other axis goes through
    inverted.  The result is scaled down to at most ``rate_max`` in norm.

    Parameters
    ----------
    roll_rad, pitch_rad : float
        ZYX Euler roll and pitch, rad.
    gain_1_s : float
        P gain k, 1/s.
    rate_max_rad_s : float
        Limit of the command's norm, rad/s.
    both_axes : bool
        Whether both roll and pitch are being levelled.

    Returns
    -------
    tuple of float
        (p, q) in rad/s, FRD.
    """
    cp = math.cos(pitch_rad)
    gx = -math.sin(pitch_rad)
    gy = math.sin(roll_rad) * cp
    if both_axes:
        gz = math.cos(roll_rad) * cp
        s = math.hypot(gx, gy)
        if s < 1e-6:
            if gz > 0.0:
                return (0.0, 0.0)
            return (rate_max_rad_s, 0.0)  # exactly inverted: roll upright
        scale = gain_1_s * math.atan2(s, gz) / s
    else:
        scale = gain_1_s
    p = -scale * gy
    q = scale * gx
    norm = math.hypot(p, q)
    if norm > rate_max_rad_s:
        k = rate_max_rad_s / norm
        p *= k
        q *= k
    return (p, q)


def throttle_command(
    mode: ThrottleMode,
    *,
    altitude_m: float,
    climb_rate_m_s: float,
    target_altitude_m: float,
    climb_target_m_s: float,
    hover_throttle: float,
    cos_tilt: float,
    params: PilotParams,
) -> float:
    """Normalised throttle of the virtual pilot's altitude loop.

    ``v_cmd = clamp(k_z (z_ref - z), -v_down, v_up)`` (``hold``) or
    ``climb_m_s`` (``climb``); ``a_cmd = clamp(k_v (v_cmd - v), +-a_max)``
    (0 in ``coast``); then

    ``T = clamp(T_hover (1 + a_cmd / g) f(c), T_min, T_max)``

    where ``c = cos(roll) cos(pitch)`` and ``f(c) = 1/c`` when nearly upright
    (``c >= tilt_comp_min_cos``), blending linearly to ``inverted_throttle_frac``
    at ``c = 0`` and constant beyond (on the side or inverted).

    Parameters
    ----------
    mode : {"hold", "climb", "coast"}
        Throttle mode.
    altitude_m, climb_rate_m_s : float
        Measured height above ground (m) and vertical speed (m/s), up positive.
    target_altitude_m : float
        Hold target, m.
    climb_target_m_s : float
        Climb-rate target in ``climb`` mode, m/s.
    hover_throttle : float
        Feed-forward, normalised.
    cos_tilt : float
        ``cos(roll) cos(pitch)``.
    params : PilotParams
        Gains and limits.

    Returns
    -------
    float
        Throttle in ``[throttle_min, throttle_max]``.
    """
    if mode == "coast":
        accel = 0.0
    else:
        if mode == "hold":
            v_cmd = params.altitude_gain_1_s * (target_altitude_m - altitude_m)
            v_cmd = min(max(v_cmd, -params.descent_max_m_s), params.climb_max_m_s)
        else:
            v_cmd = climb_target_m_s
        a_max = params.accel_max_g * GRAVITY_M_S2
        accel = min(max(params.climb_gain_1_s * (v_cmd - climb_rate_m_s), -a_max), a_max)
    c_min = params.tilt_comp_min_cos
    if cos_tilt >= c_min:
        factor = 1.0 / cos_tilt
    elif cos_tilt > 0.0:
        frac = cos_tilt / c_min
        factor = params.inverted_throttle_frac + frac * (
            1.0 / c_min - params.inverted_throttle_frac
        )
    else:
        factor = params.inverted_throttle_frac
    thr = hover_throttle * (1.0 + accel / GRAVITY_M_S2) * factor
    return min(max(thr, params.throttle_min), params.throttle_max)


# --------------------------------------------------------------------------- the pilot


@dataclass(frozen=True)
class _Piece:
    """A segment resolved for fast evaluation (private)."""

    t_s: float
    t_end_s: float
    start_deg_s: tuple[float, float, float]
    rate_deg_s: tuple[float | None, float | None, float | None]
    ramp_s: float
    step: bool
    chirp: Chirp | None
    throttle: ThrottleMode
    climb_m_s: float
    altitude_m: float
    aux_us: tuple[int, ...]


class ScriptedPilot:
    """A pilot flying a timeline of segments with a virtual outer loop.

    Stateful only through its stick slew limiter (last output and time); all
    randomness was spent when the timeline was built.  Call :meth:`sticks`
    with non-decreasing ``view.t_s``; going back in time resets the limiter.

    Parameters
    ----------
    segments : sequence of Segment
        Timeline, ``t_s`` strictly increasing, the first at 0.
    duration_s : float
        Length of the flight, s; after it the last segment continues.
    params : PilotParams
        Virtual-pilot gains and stick limits.
    free_flight : bool
        ``False`` on a test stand: throttle is ``hover_throttle``, no altitude loop.
    aux_us : tuple of int
        Initial ch5.. values, us.
    name : str
        Label for logs.
    """

    def __init__(
        self,
        segments: Sequence[Segment],
        duration_s: float,
        *,
        params: PilotParams | None = None,
        free_flight: bool = True,
        aux_us: tuple[int, ...] = (),
        name: str = "script",
    ) -> None:
        if not segments:
            raise ValueError("a pilot timeline needs at least one segment")
        if segments[0].t_s != 0.0:
            raise ValueError("the first segment must start at t_s = 0")
        for a, b in itertools.pairwise(segments):
            if not b.t_s > a.t_s:
                raise ValueError(f"segment times must increase: {a.t_s} then {b.t_s}")
        if not duration_s > 0.0:
            raise ValueError(f"duration_s must be > 0, got {duration_s}")
        self.params = params if params is not None else PilotParams()
        self.duration_s = float(duration_s)
        self.free_flight = free_flight
        self.name = name
        self.segments: tuple[Segment, ...] = tuple(segments)
        self._pieces = self._resolve(self.segments, aux_us, self.duration_s)
        self._starts = [p.t_s for p in self._pieces]
        fs = self.params.rate_full_scale_deg_s
        self._us_per_deg_s = tuple(RC_HALF_SPAN_US / f for f in fs)
        self._stick_slew_us_s = RC_HALF_SPAN_US / self.params.stick_slew_s
        self._thr_slew_us_s = 1000.0 / self.params.throttle_slew_s
        self._level_max_rad_s = self.params.level_rate_max_deg_s * _DEG
        self._i = 0
        self._t_last: float | None = None
        self._state = [float(RC_MID_US), float(RC_MID_US), float(RC_MIN_US), float(RC_MID_US)]

    def _resolve(
        self, segs: tuple[Segment, ...], aux0: tuple[int, ...], duration_s: float
    ) -> list[_Piece]:
        pieces: list[_Piece] = []
        prev = [0.0, 0.0, 0.0]
        alt = self.params.altitude_m
        aux = tuple(aux0)
        for k, s in enumerate(segs):
            if k + 1 < len(segs):
                t_end = segs[k + 1].t_s
            else:  # a chirp in the last segment sweeps until duration_s
                t_end = duration_s if duration_s > s.t_s else math.inf
            rates = list(s.rate_deg_s)
            if s.chirp is not None:
                rates[s.chirp.axis] = None
            alt = s.altitude_m if s.altitude_m is not None else alt
            aux = s.aux_us if s.aux_us is not None else aux
            pieces.append(
                _Piece(
                    t_s=s.t_s,
                    t_end_s=t_end,
                    start_deg_s=(prev[0], prev[1], prev[2]),
                    rate_deg_s=s.rate_deg_s,
                    ramp_s=s.ramp_s,
                    step=s.step,
                    chirp=s.chirp,
                    throttle=s.throttle,
                    climb_m_s=s.climb_m_s,
                    altitude_m=alt,
                    aux_us=aux,
                )
            )
            prev = [0.0 if r is None else float(r) for r in rates]
        return pieces

    def scripted_rate_deg_s(self, t_s: float) -> tuple[float | None, float | None, float | None]:
        """The timeline's scripted rates at ``t_s`` (deg/s; ``None`` = virtual pilot).

        Pure in ``t_s``; handy for plots and for the tests' reference signal.
        """
        i = bisect.bisect_right(self._starts, t_s) - 1
        pc = self._pieces[max(i, 0)]
        return (
            self._axis_rate(pc, 0, t_s),
            self._axis_rate(pc, 1, t_s),
            self._axis_rate(pc, 2, t_s),
        )

    @staticmethod
    def _axis_rate(pc: _Piece, axis: int, t: float) -> float | None:
        ch = pc.chirp
        if ch is not None and ch.axis == axis:
            tau = t - pc.t_s
            span = pc.t_end_s - pc.t_s
            if not math.isfinite(span):
                span = 10.0
            tau = min(max(tau, 0.0), span)
            w = 1.0
            if ch.taper_s > 0.0:
                w = min(1.0, tau / ch.taper_s, (span - tau) / ch.taper_s)
            phase = (
                2.0 * math.pi * (ch.f0_hz * tau + 0.5 * (ch.f1_hz - ch.f0_hz) * tau * tau / span)
            )
            return ch.amplitude_deg_s * w * math.sin(phase)
        r = pc.rate_deg_s[axis]
        if r is None:
            return None
        if pc.step or pc.ramp_s <= 0.0:
            return r
        x = (t - pc.t_s) / pc.ramp_s
        if x >= 1.0:
            return r
        r0 = pc.start_deg_s[axis]
        return r0 + (r - r0) * x

    def sticks(self, view: PilotView) -> Sticks:
        """Return the RC frame for ``view`` (about 3 us of pure-Python float math).

        Parameters
        ----------
        view : PilotView
            The vehicle as the pilot sees it.

        Returns
        -------
        Sticks
            Channels in us, 1000..2000.
        """
        t = view.t_s
        pieces = self._pieces
        i = self._i
        if t < pieces[i].t_s:
            i = max(bisect.bisect_right(self._starts, t) - 1, 0)
        n = len(pieces)
        while i + 1 < n and t >= pieces[i + 1].t_s:
            i += 1
        self._i = i
        pc = pieces[i]
        prm = self.params

        # Rates: scripted axes from the timeline, the rest from the virtual pilot.
        r_roll = self._axis_rate(pc, 0, t)
        r_pitch = self._axis_rate(pc, 1, t)
        r_yaw = self._axis_rate(pc, 2, t)
        if r_roll is None or r_pitch is None:
            p, q = level_rates_rad_s(
                view.roll_rad,
                view.pitch_rad,
                prm.level_gain_1_s,
                self._level_max_rad_s,
                both_axes=r_roll is None and r_pitch is None,
            )
            if r_roll is None:
                r_roll = p * _RAD
            if r_pitch is None:
                r_pitch = q * _RAD
        if r_yaw is None:
            r_yaw = 0.0

        # Throttle.
        if self.free_flight:
            cos_tilt = math.cos(view.roll_rad) * math.cos(view.pitch_rad)
            thr = throttle_command(
                pc.throttle,
                altitude_m=view.altitude_m,
                climb_rate_m_s=view.climb_rate_m_s,
                target_altitude_m=pc.altitude_m,
                climb_target_m_s=pc.climb_m_s,
                hover_throttle=view.hover_throttle,
                cos_tilt=cos_tilt,
                params=prm,
            )
        else:
            thr = min(max(view.hover_throttle, 0.0), 1.0)

        k = self._us_per_deg_s
        target = (
            RC_MID_US + k[0] * r_roll,
            RC_MID_US + k[1] * r_pitch,
            RC_MIN_US + 1000.0 * thr,
            RC_MID_US + k[2] * r_yaw,
        )
        st = self._state
        t_last = self._t_last
        if t_last is None or t < t_last:
            # First frame (or time went back): the pilot picks up the sticks where
            # they should be, except on the ground where the throttle starts at idle.
            st[0], st[1], st[2], st[3] = target
            if self.free_flight and view.altitude_m <= 0.5:
                st[2] = float(RC_MIN_US)
        else:
            dt = t - t_last
            step_move = self._stick_slew_us_s * dt
            thr_move = self._thr_slew_us_s * dt
            jump = pc.step
            for ax in (0, 1, 3):
                goal = target[ax]
                if jump and pc.rate_deg_s[2 if ax == 3 else ax] is not None:
                    st[ax] = goal
                    continue
                cur = st[ax]
                if goal > cur + step_move:
                    goal = cur + step_move
                elif goal < cur - step_move:
                    goal = cur - step_move
                st[ax] = goal
            cur = st[2]
            goal = target[2]
            if goal > cur + thr_move:
                goal = cur + thr_move
            elif goal < cur - thr_move:
                goal = cur - thr_move
            st[2] = goal
        self._t_last = t
        return Sticks(_to_us(st[0]), _to_us(st[1]), _to_us(st[2]), _to_us(st[3]), pc.aux_us)


def _to_us(x: float) -> int:
    if x <= RC_MIN_US:
        return RC_MIN_US
    if x >= RC_MAX_US:
        return RC_MAX_US
    return int(x + 0.5)


# --------------------------------------------------------------------------- library


class _Timeline:
    """A small builder of segments that keeps the clock (private)."""

    def __init__(self, takeoff_s: float = 4.0) -> None:
        self.t = 0.0
        self.segs: list[Segment] = []
        # Take-off: level, altitude hold from the ground to the target.
        self.level(takeoff_s)

    def add(self, dur_s: float, **kw: object) -> None:
        self.segs.append(Segment(t_s=round(self.t, 6), **kw))  # type: ignore[arg-type]
        self.t += dur_s

    def level(self, dur_s: float, throttle: ThrottleMode = "hold") -> None:
        self.add(dur_s, throttle=throttle)

    def punch(self, dur_s: float = 0.8, climb_m_s: float = 5.0) -> None:
        self.add(dur_s, throttle="climb", climb_m_s=climb_m_s)

    def spin(
        self,
        axis: int,
        rate_deg_s: float,
        turns: float,
        ramp_s: float = 0.1,
        throttle: ThrottleMode = "coast",
    ) -> None:
        """Rotate ``turns`` x 360 deg on one axis: ramp up, hold, ramp down, level."""
        hold = turns * 360.0 / abs(rate_deg_s) - ramp_s
        if hold < 0.0:
            raise ValueError("spin too short for its ramp")
        self.add(ramp_s + hold, rate_deg_s=_on(axis, rate_deg_s), ramp_s=ramp_s, throttle=throttle)
        self.add(ramp_s, rate_deg_s=_on(axis, 0.0), ramp_s=ramp_s, throttle=throttle)

    def reversal(
        self, axis: int, rate_deg_s: float, angle_deg: float, ramp_s: float = 0.08
    ) -> None:
        """Bank ``angle`` one way, snap through to the other side and back (net 0)."""
        d = angle_deg / abs(rate_deg_s) + ramp_s / 2.0
        self.add(d, rate_deg_s=_on(axis, rate_deg_s), ramp_s=ramp_s)
        self.add(2.0 * d, rate_deg_s=_on(axis, -rate_deg_s), ramp_s=ramp_s)
        self.add(d, rate_deg_s=_on(axis, rate_deg_s), ramp_s=ramp_s)
        self.add(ramp_s, rate_deg_s=_on(axis, 0.0), ramp_s=ramp_s)

    def steps(self, axis: int, amps_deg_s: Sequence[float], hold_s: float, gap_s: float) -> None:
        """Rate doublets +A, -A (net angle 0) with a level gap after each."""
        for a in amps_deg_s:
            self.add(hold_s, rate_deg_s=_on(axis, a), step=True)
            self.add(hold_s, rate_deg_s=_on(axis, -a), step=True)
            self.add(0.2, rate_deg_s=_on(axis, 0.0), step=True)
            self.level(gap_s)

    def wiggle(self, rng: np.random.Generator, dur_s: float, amp_deg_s: float) -> None:
        """Smooth random stick stirring on all axes, then centre.

        Rates come in +r / -r pairs of equal length so the attitude wanders by at
        most about ``amp * 0.35 s`` and comes back, like a pilot stirring the
        sticks around level, instead of random-walking into a dive.
        """
        t_end = self.t + dur_s
        while self.t < t_end - 0.5:
            hold = float(rng.uniform(0.15, 0.35))
            ramp = float(rng.uniform(0.08, 0.15))
            r = rng.uniform(-amp_deg_s, amp_deg_s, size=3)
            rates = (float(r[0]), float(r[1]), 0.5 * float(r[2]))
            self.add(hold, rate_deg_s=rates, ramp_s=ramp)
            self.add(hold, rate_deg_s=(-rates[0], -rates[1], -rates[2]), ramp_s=ramp)
        self.add(0.15, rate_deg_s=(0.0, 0.0, 0.0), ramp_s=0.15)

    def finish(self, duration_s: float | None = None) -> tuple[list[Segment], float]:
        dur = self.t if duration_s is None else max(duration_s, self.t)
        return self.segs, round(dur, 6)


def _on(axis: int, rate: float) -> tuple[float | None, float | None, float | None]:
    r: list[float | None] = [None, None, None]
    r[axis] = rate
    return (r[0], r[1], r[2])


def _hover(rng: np.random.Generator) -> tuple[list[Segment], float]:
    tl = _Timeline()
    tl.level(16.0)
    return tl.finish()


def _flip(axis: int) -> Callable[[np.random.Generator], tuple[list[Segment], float]]:
    def build(rng: np.random.Generator) -> tuple[list[Segment], float]:
        tl = _Timeline()
        for sign in (1.0, -1.0, 1.0):
            tl.level(2.0)
            tl.punch()
            tl.spin(axis, sign * 720.0, 1.0)
        tl.level(3.0)
        return tl.finish()

    return build


def _rolls(rng: np.random.Generator) -> tuple[list[Segment], float]:
    tl = _Timeline()
    for rate, turns in ((540.0, 2.0), (-720.0, 3.0), (360.0, 1.0), (-450.0, 2.0)):
        tl.level(2.5)
        tl.punch(1.0, 6.0)
        tl.spin(0, rate, turns)
    tl.level(3.0)
    return tl.finish()


def _yaw_spin(rng: np.random.Generator) -> tuple[list[Segment], float]:
    tl = _Timeline()
    for rate, turns in ((360.0, 3.0), (-360.0, 3.0), (180.0, 1.0), (-270.0, 2.0)):
        tl.level(1.5)
        tl.spin(2, rate, turns, ramp_s=0.15, throttle="hold")
    tl.level(2.0)
    return tl.finish()


def _steps(axis: int) -> Callable[[np.random.Generator], tuple[list[Segment], float]]:
    amps = (90.0, 180.0, 360.0) if axis < 2 else (90.0, 180.0, 270.0)
    hold = 0.4 if axis < 2 else 1.0

    def build(rng: np.random.Generator) -> tuple[list[Segment], float]:
        tl = _Timeline()
        tl.level(1.0)
        tl.steps(axis, amps, hold, 2.0)
        return tl.finish()

    return build


def _chirp_roll(rng: np.random.Generator) -> tuple[list[Segment], float]:
    tl = _Timeline()
    tl.level(1.0)
    tl.add(20.0, chirp=Chirp(axis=0, amplitude_deg_s=100.0, f0_hz=1.0, f1_hz=8.0, taper_s=0.5))
    tl.level(3.0)
    return tl.finish()


def _random_maneuver(tl: _Timeline, rng: np.random.Generator) -> None:
    kind = int(rng.integers(0, 5))
    sign = 1.0 if rng.random() < 0.5 else -1.0
    if kind == 0:  # flip, roll or pitch
        tl.punch(float(rng.uniform(0.6, 1.0)), float(rng.uniform(4.0, 6.0)))
        tl.spin(int(rng.integers(0, 2)), sign * float(rng.uniform(450.0, 720.0)), 1.0)
    elif kind == 1:  # continuous rolls, at most ~1.5 s of rotation
        rate = float(rng.uniform(360.0, 720.0))
        turns = float(min(int(rng.integers(2, 4)), max(1, int(1.5 * rate / 360.0))))
        tl.punch(1.0, 6.0)
        tl.spin(0, sign * rate, turns)
    elif kind == 2:  # yaw spin
        tl.spin(2, sign * float(rng.uniform(180.0, 360.0)), float(rng.integers(1, 4)), 0.15, "hold")
    elif kind == 3:  # quick reversal
        tl.reversal(
            int(rng.integers(0, 2)),
            sign * float(rng.uniform(250.0, 500.0)),
            float(rng.uniform(30.0, 70.0)),
        )
    else:
        tl.wiggle(rng, float(rng.uniform(2.0, 4.0)), float(rng.uniform(60.0, 180.0)))


def acro_random_timeline(
    rng: np.random.Generator, duration_s: float = 60.0
) -> tuple[list[Segment], float]:
    """A seeded random acro session: maneuvers separated by level gaps.

    Parameters
    ----------
    rng : numpy.random.Generator
        The only source of randomness; consumed here, at build time.
    duration_s : float
        Approximate length, s (the last maneuver is allowed to finish).

    Returns
    -------
    segments, duration_s
    """
    tl = _Timeline()
    while tl.t < duration_s - 6.0:
        tl.level(float(rng.uniform(1.5, 3.0)))
        _random_maneuver(tl, rng)
    tl.level(max(3.0, duration_s - tl.t))
    return tl.finish()


def _acro_random(rng: np.random.Generator) -> tuple[list[Segment], float]:
    return acro_random_timeline(rng, 60.0)


def _paper_acro(rng: np.random.Generator) -> tuple[list[Segment], float]:
    """About 60 s of pilot-like acro, a fixed programme with seeded variations."""
    tl = _Timeline()

    def gap() -> None:
        tl.level(float(rng.uniform(1.5, 2.5)))

    def u(lo: float, hi: float) -> float:
        return float(rng.uniform(lo, hi))

    tl.wiggle(rng, 3.0, 90.0)
    gap()
    tl.punch()
    tl.spin(0, 720.0, 1.0)  # roll flip right, full stick
    gap()
    tl.reversal(0, u(350.0, 450.0), u(45.0, 60.0))
    gap()
    tl.punch()
    tl.spin(1, 720.0, 1.0)  # back flip, full stick
    gap()
    tl.spin(2, 360.0, 2.0, 0.15, "hold")  # yaw spin right
    gap()
    tl.punch(1.0, 6.0)
    tl.spin(0, -u(600.0, 720.0), 2.0)  # double roll left
    gap()
    tl.reversal(1, -u(300.0, 400.0), u(30.0, 45.0))
    gap()
    tl.punch()
    tl.spin(1, -u(600.0, 720.0), 1.0)  # front flip
    gap()
    tl.spin(2, -u(270.0, 360.0), 2.0, 0.15, "hold")  # yaw spin left
    gap()
    tl.wiggle(rng, 3.0, 150.0)
    gap()
    tl.punch()
    tl.spin(0, -720.0, 1.0)  # roll flip left
    gap()
    tl.reversal(0, -u(400.0, 500.0), u(50.0, 70.0))
    gap()
    tl.spin(2, u(300.0, 360.0), 1.0, 0.15, "hold")
    tl.reversal(1, u(300.0, 400.0), u(30.0, 45.0))
    gap()
    tl.punch()
    tl.spin(1, u(650.0, 720.0), 1.0)
    tl.level(max(2.0, 60.0 - tl.t))
    return tl.finish()


MANEUVERS: dict[str, Callable[[np.random.Generator], tuple[list[Segment], float]]] = {
    "hover": _hover,
    "roll-flip": _flip(0),
    "pitch-flip": _flip(1),
    "rolls": _rolls,
    "yaw-spin": _yaw_spin,
    "step-roll": _steps(0),
    "step-pitch": _steps(1),
    "step-yaw": _steps(2),
    "chirp-roll": _chirp_roll,
    "acro-random": _acro_random,
    "paper-acro": _paper_acro,
}
"""Maneuver library: name -> builder ``(rng) -> (segments, duration_s)``."""


# --------------------------------------------------------------------------- YAML loader


class _ChirpModel(StrictModel):
    axis: Literal["roll", "pitch", "yaw"]
    amplitude_deg_s: float = Field(gt=0.0, le=2000.0)
    f0_hz: float = Field(gt=0.0, le=100.0)
    f1_hz: float = Field(gt=0.0, le=100.0)
    taper_s: float = Field(default=0.5, ge=0.0, le=10.0)


class _SegmentModel(StrictModel):
    t_s: float = Field(ge=0.0)
    level: bool = False
    rate_deg_s: tuple[float | None, float | None, float | None] | None = None
    chirp: _ChirpModel | None = None
    ramp_s: float = Field(default=0.1, ge=0.0, le=10.0)
    step: bool = False
    throttle: Literal["hold", "climb", "coast"] = "hold"
    climb_m_s: float = Field(default=5.0, ge=-10.0, le=10.0)
    altitude_m: float | None = Field(default=None, gt=0.0, le=500.0)
    aux_us: tuple[int, ...] | None = None

    @model_validator(mode="after")
    def _one_kind(self) -> _SegmentModel:
        kinds = int(self.level) + int(self.rate_deg_s is not None) + int(self.chirp is not None)
        if kinds != 1:
            raise ValueError("exactly one of level: true, rate_deg_s or chirp is required")
        if self.rate_deg_s is not None:
            for r in self.rate_deg_s:
                if r is not None and not abs(r) <= 2000.0:
                    raise ValueError(f"rates must be within +-2000 deg/s, got {r}")
        if self.aux_us is not None:
            for a in self.aux_us:
                if not RC_MIN_US <= a <= RC_MAX_US:
                    raise ValueError(f"aux_us values must be in 1000..2000, got {a}")
        return self


class _ScriptModel(StrictModel):
    duration_s: float = Field(gt=0.0, le=36000.0)
    rate_full_scale_deg_s: tuple[float, float, float] = DEFAULT_RATE_FULL_SCALE_DEG_S
    altitude_m: float = Field(default=10.0, gt=0.0, le=500.0)
    aux_us: tuple[int, ...] = ()
    segments: list[_SegmentModel] = Field(min_length=1)

    @model_validator(mode="after")
    def _check(self) -> _ScriptModel:
        for v in self.rate_full_scale_deg_s:
            if not 0.0 < v <= 2000.0:
                raise ValueError(f"rate_full_scale_deg_s must be in (0, 2000], got {v}")
        for a in self.aux_us:
            if not RC_MIN_US <= a <= RC_MAX_US:
                raise ValueError(f"aux_us values must be in 1000..2000, got {a}")
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
        chirp = Chirp(AXES.index(c.axis), c.amplitude_deg_s, c.f0_hz, c.f1_hz, c.taper_s)
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
        problems = []
        for e in exc.errors():
            loc = ".".join(str(x) for x in e["loc"]) or "top level"
            problems.append(f"{loc}: {e['msg']}")
        raise ConfigError(str(p), problems) from exc
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


# --------------------------------------------------------------------------- factory


def make_pilot(
    spec: str,
    *,
    rng: np.random.Generator,
    free_flight: bool = True,
    aux_us: tuple[int, ...] = (),
) -> Pilot:
    """Build a pilot from a maneuver name or a stick-script file.

    Parameters
    ----------
    spec : str
        A key of :data:`MANEUVERS` (``"paper-acro"``, ``"roll-flip"``, ...) or a
        path to a stick-script YAML file.
    rng : numpy.random.Generator
        Randomness for the library's random details (all drawn here).
    free_flight : bool
        ``False`` for a test-stand rig: constant hover throttle, no altitude loop.
    aux_us : tuple of int
        ch5.. values for library maneuvers (e.g. ``(2000,)`` to hold an engage
        switch on); stick scripts set their own.

    Returns
    -------
    Pilot
        A :class:`ScriptedPilot`.

    Raises
    ------
    ValueError
        Unknown maneuver name that is not an existing file.
    companion.errors.ConfigError
        The stick-script file is invalid.
    """
    builder = MANEUVERS.get(spec)
    if builder is not None:
        segments, duration_s = builder(rng)
        return ScriptedPilot(
            segments, duration_s, free_flight=free_flight, aux_us=aux_us, name=spec
        )
    p = Path(spec)
    if p.suffix in (".yaml", ".yml") or p.exists():
        return load_stick_script(p, free_flight=free_flight)
    raise ValueError(
        f"unknown pilot {spec!r}: expected one of {sorted(MANEUVERS)} or a stick-script file"
    )
