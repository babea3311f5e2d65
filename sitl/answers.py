"""Which sample a client's setpoint answers, from the setpoint's time field.

The lockstep clock waits, after each sample it gives the client, for that
sample's answer. Counting setpoints is enough while the client keeps up; a
client that fell behind (the clock did not wait before OFFBOARD, or after a
timeout, and the client stalled) still has older samples to answer, and a
count would end a wait on one of those: which setpoint the autopilot flies
would then depend on the wall clock.

A client that stamps each setpoint with the time of the sample it answers
(``SET_ACTUATOR_CONTROL_TARGET.time_usec``, ``SET_ATTITUDE_TARGET.time_boot_ms``:
the companion does) says which sample that is. It is recognised by
:data:`ECHO_RUN` setpoints in a row stamped with the times of consecutive
samples it was given (a client stamping its own clock, as MAVSDK does, does
not produce that), and forgotten at a stamp it was never given or a lockstep
timeout. Its answers to samples older than the ones waited for are handled
(as an autopilot handles any setpoint) but not counted.
"""

from __future__ import annotations

from collections import deque

__all__ = ["ECHO_RUN", "SAMPLES_KEPT", "AnswerJudge"]

ECHO_RUN = 8
"""Setpoints in a row stamped with consecutive samples' times before a client
counts as stamping its answers so."""
SAMPLES_KEPT = 16384
"""Samples remembered (16 s at 1 kHz): an answer to an older one is a stamp the
client was never given."""


class AnswerJudge:
    """Remembers the samples given to the client; judges each setpoint's stamp."""

    def __init__(self) -> None:
        self._seq = 0
        # Sample number by stamp, in microseconds and in milliseconds.
        self._by_us: dict[int, int] = {}
        self._by_ms: dict[int, int] = {}
        self._kept: deque[tuple[int, int]] = deque()
        self._last_answered: int | None = None
        self._run = 0
        self._await_t_s: float | None = None
        self.echoes_stamps = False
        """The client stamps each setpoint with the time of the sample it answers."""
        self.stale = 0
        """Setpoints that answered a sample older than the ones waited for."""

    def sample_given(self, t_s: float) -> None:
        """A clock-stream sample of time ``t_s`` reached the client's socket."""
        self._seq += 1
        us, ms = round(t_s * 1e6), round(t_s * 1e3)
        self._by_us[us] = self._by_ms[ms] = self._seq
        kept = self._kept
        kept.append((us, ms))
        if len(kept) > SAMPLES_KEPT:
            old_us, old_ms = kept.popleft()
            if self._by_us.get(old_us) == self._seq - SAMPLES_KEPT:
                del self._by_us[old_us]
            if self._by_ms.get(old_ms) == self._seq - SAMPLES_KEPT:
                del self._by_ms[old_ms]

    def await_from(self, t_s: float | None) -> None:
        """The lockstep clock waits for answers to samples from ``t_s`` on (None: not waiting)."""
        self._await_t_s = t_s

    def forget(self) -> None:
        """A lockstep timeout: count whatever the client sends again."""
        self.echoes_stamps = False
        self._run = 0
        self._last_answered = None

    def counts(self, stamp: int, unit_s: float) -> bool:
        """Whether a setpoint stamped ``stamp`` (in ``unit_s``) counts towards the wait."""
        seq = (self._by_us if unit_s < 1e-4 else self._by_ms).get(stamp)
        if seq is None:
            self.forget()  # a time the client was never given: its own clock
            return True
        last = self._last_answered
        self._last_answered = seq
        if last is not None and seq == last + 1:
            self._run += 1
            if self._run >= ECHO_RUN:
                self.echoes_stamps = True
        else:
            self._run = 0
        oldest = self._await_t_s
        if self.echoes_stamps and oldest is not None and stamp * unit_s < oldest - 0.5 * unit_s:
            self.stale += 1
            return False
        return True
