"""The link's round trip and the autopilot's clock, measured with TIMESYNC.

The companion sends ``TIMESYNC`` with ``tc1 = 0`` and ``ts1`` its own clock in
nanoseconds; the autopilot (PX4, ArduPilot, the bundled SITL) answers with
``tc1`` its clock and ``ts1`` copied. The answer gives the round trip and,
taking each direction as half of it, the offset from our clock to the
autopilot's, which dates each IMU sample: its *age* when its command leaves
is how stale the state the law acted on was (the uplink, plus our own work).

Pure bookkeeping: the caller owns the clock and the sending
(:meth:`companion.app.Companion` sends a request every
:data:`REQUEST_PERIOD_S`).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

__all__ = ["LINK_RTT_SHOWN_MS", "REQUEST_PERIOD_S", "LinkClock", "LinkStats"]

REQUEST_PERIOD_S = 0.25
"""How often the companion asks (TIMESYNC is 24 bytes of payload each way)."""

LINK_RTT_SHOWN_MS = 20.0
"""The slowest round trip the controller's figures cover: 10 ms each way
(docs/link.md). A median beyond it is an event (``link_slow``), not a failsafe:
the envelope and divergence failsafes judge the flight itself."""

_PENDING_KEPT = 8
"""Requests that may still be answered: a reply older than 8 periods is dropped."""

_RTT_MAX_S = 5.0
"""A reply later than this is not a round trip worth a figure (a stalled link)."""


@dataclass(frozen=True)
class LinkStats:
    """The round trips over the window, in milliseconds (NaN: none yet)."""

    n: int
    """Answers in the window."""
    rtt_last_ms: float
    rtt_min_ms: float
    rtt_median_ms: float
    rtt_max_ms: float

    @property
    def jitter_ms(self) -> float:
        """The spread of the round trip: max - min over the window."""
        return self.rtt_max_ms - self.rtt_min_ms

    def as_dict(self) -> dict[str, float | int | None]:
        def num(x: float) -> float | None:
            return round(x, 3) if math.isfinite(x) else None

        return {
            "n": self.n,
            "rtt_last_ms": num(self.rtt_last_ms),
            "rtt_min_ms": num(self.rtt_min_ms),
            "rtt_median_ms": num(self.rtt_median_ms),
            "rtt_max_ms": num(self.rtt_max_ms),
            "jitter_ms": num(self.jitter_ms),
        }


class LinkClock:
    """Round trips and the clock offset from TIMESYNC exchanges.

    Parameters
    ----------
    window
        Answers kept for the statistics and the offset (at
        :data:`REQUEST_PERIOD_S`, 16 is the last 4 s: short enough to follow
        two crystals drifting apart, long enough to find a quick exchange).

    The offset comes from the quickest exchange in the window: its two halves
    can differ by at most its own round trip, so the dates it gives are off by
    at most half of it, and the quickest bounds that best.
    """

    def __init__(self, window: int = 16) -> None:
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        self._pending: deque[int] = deque(maxlen=_PENDING_KEPT)
        self._rtts: deque[float] = deque(maxlen=window)
        self._offsets: deque[tuple[float, float]] = deque(maxlen=window)
        self.offset_s = math.nan
        """The autopilot's clock minus ours, s (NaN until the first answer)."""
        self.rtt_s = math.nan
        """The last round trip, s."""
        self.n_requests = 0
        self.n_replies = 0
        self.n_unmatched = 0
        """Answers to no request of ours (another client's, or one we gave up on)."""

    def request(self, now_s: float) -> int:
        """A request sent at ``now_s`` (our clock, s): returns its ``ts1`` (ns)."""
        ts1 = round(now_s * 1e9)
        self._pending.append(ts1)
        self.n_requests += 1
        return ts1

    def reply(self, tc1_ns: int, ts1_ns: int, now_s: float) -> bool:
        """An answer (``tc1`` the autopilot's ns, ``ts1`` ours) received at ``now_s``.

        Returns False (and counts it) when it answers no pending request of
        ours or gives no usable figure."""
        if ts1_ns not in self._pending:
            self.n_unmatched += 1
            return False
        self._pending.remove(ts1_ns)
        t_sent = ts1_ns * 1e-9
        rtt = now_s - t_sent
        if not (0.0 <= rtt <= _RTT_MAX_S) or tc1_ns <= 0:
            self.n_unmatched += 1
            return False
        self.n_replies += 1
        self.rtt_s = rtt
        self._rtts.append(rtt)
        self._offsets.append((rtt, tc1_ns * 1e-9 - 0.5 * (t_sent + now_s)))
        self.offset_s = min(self._offsets)[1]
        return True

    def sample_age_s(self, sample_t_s: float, now_s: float) -> float:
        """How old a sample stamped ``sample_t_s`` (the autopilot's clock) is at
        ``now_s`` (ours); NaN before the first answer."""
        return now_s + self.offset_s - sample_t_s

    def stats(self) -> LinkStats:
        r = sorted(self._rtts)
        if not r:
            nan = math.nan
            return LinkStats(0, nan, nan, nan, nan)
        k = len(r)
        median = r[k // 2] if k % 2 else 0.5 * (r[k // 2 - 1] + r[k // 2])
        return LinkStats(k, self.rtt_s * 1e3, r[0] * 1e3, median * 1e3, r[-1] * 1e3)
