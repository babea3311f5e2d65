"""The IMU stream's time: each sample's time step, or why it is not flown.

The autopilot stamps each sample (HIGHRES_IMU in whole microseconds, ATTITUDE
in milliseconds); the rate law differentiates over the step between two stamps,
so a stamp that is wrong costs more than one sample unless it is caught here. A
sample just after the last one is flown with its step; a late or duplicate one
is dropped; a gap the wall clock also saw is flown at once; any other jump is a
candidate, flown on only once a few samples in a row follow on from it (a gap
after all, or a new clock: the autopilot rebooted).

No I/O and no clock: each sample comes with its arrival time (the caller's
clock), and what the stream's time says is given back (:class:`ImuTimeline`).
"""

from __future__ import annotations

from companion.step import whole_us

__all__ = ["NEW_CLOCK", "ImuTimeline"]

_TIME_JUMP_S = 1.0
"""An IMU time step beyond this, either way, is a discontinuity, not a late
sample or a gap (stale IMU fires after ``stale_imu_s``, far less)."""
_NEW_CLOCK_SAMPLES = 3
"""Samples in a row that must follow on from a jump before it is real (a gap,
or a new clock: an autopilot reboot) rather than one corrupt timestamp: 12 ms
at 250 Hz."""
STEP_AHEAD_S = 0.02
"""How far one IMU step may run ahead of the wall clock between the two
samples' arrivals and still be flown at once; also the longest step by which
samples follow on from a jump. A longer step is a gap only if the wall clock
took it too, or if the next samples continue from it. 20 ms is five samples at
250 Hz (a few lost in a row pass as they come, even where a lockstep
simulator's clock outruns the wall's), the rate law's own longest time step
(``dt_max_s``), and bounds what one wrong stamp can cost: the genuine samples
it puts behind it are at most this much of the stream."""

NEW_CLOCK = -1.0
"""What :meth:`ImuTimeline.step_of` returns for the first sample of a new clock."""


class ImuTimeline:
    """The IMU stream's time as the samples come, and its counters."""

    def __init__(self) -> None:
        self.t_prev: float | None = None
        """The time of the last sample flown (None before the first)."""
        self.t_first: float | None = None
        """The time of the first sample flown, on the current clock's terms."""
        self.last_arrival: float | None = None
        """When the last sample the law processed arrived (the stale-IMU clock)."""
        self.restart = False
        """The next sample's step is 0: it primes the law, as a replay's first does."""
        self._candidate: tuple[float, int] | None = None
        self.gap_detail: str | None = None
        """Set by :meth:`step_of` when samples went on across a gap the wall did not see."""
        self.n_duplicate_or_late = 0
        self.n_time_jumps = 0
        self.n_gaps = 0
        self.n_time_outliers = 0

    def step_of(self, t_s: float, arrival: float) -> float | None:
        """The step to fly the sample stamped ``t_s`` with, :data:`NEW_CLOCK`, or
        None: not flown. Call :meth:`advance` once it is flown."""
        t_prev = self.t_prev
        if t_prev is None:
            self.t_first = t_s
            return 0.0
        dt = t_s - t_prev
        if 0.0 < dt <= STEP_AHEAD_S:
            if self._candidate is not None:
                self._candidate = None  # the old clock goes on: it was one outlier
                self.n_time_outliers += 1
            # HIGHRES_IMU's stamps are whole us, ATTITUDE's ms
            return 0.0 if self.restart else whole_us(dt)
        taken = self._anomaly(t_s, dt, arrival)
        if taken is None or taken == NEW_CLOCK:
            return taken
        return 0.0 if self.restart else taken

    def advance(self, t_s: float) -> None:
        """The sample stamped ``t_s`` is flown."""
        self.restart = False
        self.t_prev = t_s

    def _anomaly(self, t_s: float, dt: float, arrival: float) -> float | None:
        """A sample whose time is not just after the last one's: the time step to
        fly it with, :data:`NEW_CLOCK`, or None: dropped.

        A step back within ``_TIME_JUMP_S`` is a duplicate or a late sample
        (reordered on the link): dropped. A step forward that the wall clock
        also took, give or take ``STEP_AHEAD_S`` (the datagrams' arrivals are
        as far apart as the stamps), is a gap in the stream: flown at once. Any
        other step may be one corrupt timestamp, and a sample whose time is
        unknown is not flown (the law would differentiate its rate over a time
        it may have faked; a NaN sample would stretch the invalid-IMU run): it
        is dropped and becomes a candidate. Only when ``_NEW_CLOCK_SAMPLES``
        samples in a row follow on from it is the jump real: forward, a gap
        after all (a lockstep simulator's clock outruns the wall's); backward,
        a new clock (the autopilot rebooted). A sample that follows the old
        clock again makes the candidate an outlier, and nothing changes: one
        forward stamp costs that one sample, a real gap the wall did not see
        two more.
        """
        if dt != dt or -_TIME_JUMP_S <= dt <= 0.0:
            self.n_duplicate_or_late += 1
            return None
        # The step to fly a gap with: the law clamps it; beyond _TIME_JUMP_S it starts over.
        gap_dt = whole_us(dt) if dt <= _TIME_JUMP_S else 0.0
        last = self.last_arrival
        cand = self._candidate
        if dt > 0.0 and last is not None and dt <= arrival - last + STEP_AHEAD_S:
            self.n_gaps += 1
            if cand is not None:
                self._candidate = None
                self.n_time_outliers += 1  # the old clock went on, through a gap
            return gap_dt
        if cand is not None and 0.0 < t_s - cand[0] <= STEP_AHEAD_S:
            self._candidate = (t_s, cand[1] + 1)
            if cand[1] + 1 < _NEW_CLOCK_SAMPLES:
                return None
            self._candidate = None
            if dt > 0.0:
                self.n_gaps += 1
                self.gap_detail = f"IMU time went on from {self.t_prev:.6f} s to {t_s:.6f} s"
                return gap_dt
            return NEW_CLOCK
        if cand is not None:
            self.n_time_outliers += 1  # the previous candidate led nowhere
        self._candidate = (t_s, 1)
        self.n_time_jumps += 1
        return None

    def new_clock(self, t_s: float) -> str:
        """The clock restarted at ``t_s`` (a reboot): shadow mode's duration counts
        on across it; returns what happened, in words."""
        detail = f"IMU time jumped from {self.t_prev:.6f} s to {t_s:.6f} s"
        if self.t_first is not None and self.t_prev is not None:
            self.t_first = t_s - (self.t_prev - self.t_first)
        return detail
