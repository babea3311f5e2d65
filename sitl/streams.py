"""Message streams in simulation time: what goes out when (``MAV_CMD_SET_MESSAGE_INTERVAL``).

Both MAVLink faces schedule their streams with :class:`MessageStreams`; the
ArduPilot face's interval rules (whole milliseconds, its own refusals) are a
subclass in ``sitl.ardupilot_face``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from sitl.personality import MavResult

__all__ = ["MessageStreams", "StreamSpec"]


@dataclass(frozen=True)
class StreamSpec:
    """A message the SITL can stream."""

    msg_id: int
    name: str
    default_interval_s: float
    imu_based: bool = False


@dataclass
class _StreamState:
    spec: StreamSpec
    interval_s: float  # <= 0: disabled
    next_due_s: float = 0.0


class MessageStreams:
    """Per-message stream intervals in simulation time (``MAV_CMD_SET_MESSAGE_INTERVAL``).

    Parameters
    ----------
    specs
        The streamable messages and their default intervals.
    imu_rate_hz
        IMU sample rate: an IMU-based stream cannot be faster (faster is DENIED).
    max_rate_hz
        Fastest any stream may go (the physics rate, 1 kHz).
    """

    def __init__(
        self, specs: Sequence[StreamSpec], *, imu_rate_hz: float, max_rate_hz: float = 1000.0
    ) -> None:
        self.imu_rate_hz = imu_rate_hz
        self.max_rate_hz = max_rate_hz
        self._streams = {s.msg_id: _StreamState(s, s.default_interval_s) for s in specs}

    def __contains__(self, msg_id: int) -> bool:
        return msg_id in self._streams

    def interval_s(self, msg_id: int) -> float:
        """Current interval, s (<= 0 when disabled)."""
        return self._streams[msg_id].interval_s

    def set_interval(self, msg_id: int, interval_us: float, *, t_s: float = 0.0) -> MavResult:
        """Apply ``MAV_CMD_SET_MESSAGE_INTERVAL`` (param2: µs, -1 off, 0 default).

        Returns
        -------
        MavResult
            ACCEPTED, or DENIED for an unknown message, a non-finite or too short
            interval (faster than ``max_rate_hz``, or than the IMU for IMU streams).
        """
        st = self._streams.get(msg_id)
        if st is None or not math.isfinite(interval_us):
            return MavResult.DENIED
        if interval_us == -1:
            st.interval_s = 0.0
            return MavResult.ACCEPTED
        if interval_us == 0:
            st.interval_s = st.spec.default_interval_s
            st.next_due_s = t_s
            return MavResult.ACCEPTED
        if interval_us < 0:
            return MavResult.DENIED
        interval_s = interval_us * 1e-6
        max_hz = min(self.max_rate_hz, self.imu_rate_hz) if st.spec.imu_based else self.max_rate_hz
        if interval_s < (1.0 / max_hz) * (1.0 - 1e-9):
            return MavResult.DENIED
        st.interval_s = interval_s
        st.next_due_s = t_s
        return MavResult.ACCEPTED

    def rephase(self, t_s: float) -> None:
        """Start every stream's schedule again at ``t_s`` (the rates are kept).

        A stream is scheduled from when it was asked for, which in a simulation
        depends on how long the client took: rephased at arming, the messages
        fall on the same steps of the flight whenever that was."""
        for st in self._streams.values():
            st.next_due_s = t_s

    def lockstep_stream(self, candidates: tuple[int, ...]) -> int | None:
        """Of the enabled ``candidates``, the one streamed fastest (ties: the first).

        The lockstep clock waits after this one: it is the stream a client
        that asked for a fast rate is running its loop on.
        """
        best: int | None = None
        best_s = math.inf
        for msg_id in candidates:
            st = self._streams.get(msg_id)
            if st is not None and 0.0 < st.interval_s < best_s * (1.0 - 1e-9):
                best, best_s = msg_id, st.interval_s
        return best

    def due(self, msg_id: int, t_s: float) -> bool:
        """True (and schedules the next one) when ``msg_id`` is due at ``t_s``.

        The schedule advances by whole intervals from the previous due time, so
        the mean rate is exact; after a long stall it restarts from ``t_s``.
        """
        st = self._streams[msg_id]
        if st.interval_s <= 0.0 or t_s + 1e-9 < st.next_due_s:
            return False
        st.next_due_s += st.interval_s
        if st.next_due_s <= t_s:
            st.next_due_s = t_s + st.interval_s
        return True
