"""A pilot flying a timeline of segments (:class:`ScriptedPilot`).

A timeline is a list of :class:`Segment`; segment *i* owns ``[t_i, t_{i+1})``.
On each axis a segment either *scripts* a rate (a number, ramped linearly from
the previous scripted value over ``ramp_s``, or a chirp) or leaves the axis to
the virtual pilot (``None``, see :mod:`sitl.pilot.virtual`).

Every stick then passes a slew limiter (a thumb cannot teleport): a full
deflection from centre takes at least ``stick_slew_s`` (80 ms), a full throttle
sweep ``throttle_slew_s`` (250 ms).  Only axes scripted by a segment marked
``step`` jump (rate steps for diagnosis).

With ``free_flight=False`` (test-stand rig, attitude only) the throttle is a
constant ``hover_throttle`` and levelling still runs.
"""

from __future__ import annotations

import bisect
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

from sitl.pilot.rc import RC_HALF_SPAN_US, RC_MAX_US, RC_MID_US, RC_MIN_US, Sticks
from sitl.pilot.virtual import (
    PilotParams,
    PilotView,
    ThrottleMode,
    level_rates_rad_s,
    throttle_command,
)

__all__ = ["Chirp", "Pilot", "ScriptedPilot", "Segment"]

_DEG = math.pi / 180.0
_RAD = 180.0 / math.pi


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
