"""The maneuver library: named timelines of flips, rolls, spins, steps and sweeps."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from sitl.pilot.scripted import Chirp, Segment
from sitl.pilot.virtual import ThrottleMode

__all__ = ["MANEUVERS", "acro_random_timeline"]


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


def _acro_mixed(rng: np.random.Generator) -> tuple[list[Segment], float]:
    """About 25 s that work every axis, each maneuver's size and order seeded: a
    roll and a pitch reversal, a yaw turn each way, a roll and a pitch flip, and
    stick stirring on all three (what a pilot does in a short acro session)."""
    tl = _Timeline(takeoff_s=1.0)

    def u(lo: float, hi: float) -> float:
        return float(rng.uniform(lo, hi))

    def sign() -> float:
        return 1.0 if rng.random() < 0.5 else -1.0

    def flip(axis: int) -> None:
        tl.punch()
        tl.spin(axis, sign() * u(450.0, 650.0), 1.0)

    for i in rng.permutation(7):
        k = int(i)
        if k < 2:
            tl.reversal(k, sign() * u(250.0, 400.0), u(30.0, 45.0))
        elif k < 4:
            tl.spin(2, sign() * u(150.0, 300.0), 1.0, 0.15, "hold")
        elif k < 6:
            flip(k - 4)
        else:
            tl.wiggle(rng, u(2.0, 3.0), u(90.0, 150.0))
        tl.level(u(1.2, 2.0))
    return tl.finish()


MANEUVERS: dict[str, Callable[[np.random.Generator], tuple[list[Segment], float]]] = {
    "acro-mixed": _acro_mixed,
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
