"""LinkClock: round trips and the autopilot's clock from TIMESYNC, against analytic answers.

Each exchange below is built from a known link: sent at ``t`` on our clock,
handled by the autopilot ``up`` later (``tc1`` = its clock then, ``AP`` ahead
of ours), back ``down`` after that. The round trip is ``up + down``; the
offset the exchange gives is ``AP + (up - down) / 2`` (each direction taken
as half the round trip), exact only for a symmetric link.
"""

from __future__ import annotations

import json
import math

import pytest

from companion.link.timesync import LINK_RTT_SHOWN_MS, REQUEST_PERIOD_S, LinkClock, LinkStats

AP = 1234.5
"""The autopilot's clock minus ours, s (it booted long before we started)."""
T0 = 5000.0
"""Our clock (perf_counter, s) at the first request."""
NS = 1e-9
EPS = 1e-7  # s: far below a link's figures, far above float and ns rounding at these clocks


def exchange(clock: LinkClock, t: float, up: float, down: float, ap: float = AP) -> bool:
    """A request at ``t``, answered through a link of ``up`` / ``down`` s."""
    ts1 = clock.request(t)
    tc1 = round((t + up + ap) * 1e9)
    return clock.reply(tc1, ts1, t + up + down)


def test_the_constants_are_those_documented() -> None:
    assert REQUEST_PERIOD_S == 0.25
    assert LINK_RTT_SHOWN_MS == 20.0


def test_a_request_is_stamped_in_ns_of_our_clock() -> None:
    clock = LinkClock()
    assert clock.request(T0) == 5_000_000_000_000
    assert clock.request(1.2345678912) == 1_234_567_891
    assert clock.n_requests == 2
    assert clock.n_replies == 0


def test_one_exchange_gives_the_round_trip_and_the_offset() -> None:
    clock = LinkClock()
    assert exchange(clock, T0, up=0.004, down=0.004)
    assert clock.rtt_s == pytest.approx(0.008, abs=EPS)
    assert clock.offset_s == pytest.approx(AP, abs=EPS)
    assert clock.n_replies == 1 and clock.n_unmatched == 0
    # An asymmetric link: the round trip is still exact; the offset is off by half
    # the difference of the two directions (here 3 ms up, 1 ms down: +1 ms).
    clock = LinkClock()
    assert exchange(clock, T0, up=0.003, down=0.001)
    assert clock.rtt_s == pytest.approx(0.004, abs=EPS)
    assert clock.offset_s == pytest.approx(AP + 0.001, abs=EPS)


def test_a_samples_age_is_dated_on_the_autopilots_clock() -> None:
    clock = LinkClock()
    assert exchange(clock, T0, up=0.005, down=0.005)
    # Stamped 7 ms before now (on the autopilot's clock): 7 ms old.
    now = T0 + 0.1
    assert clock.sample_age_s(now + AP - 0.007, now) == pytest.approx(0.007, abs=EPS)
    # A stamp on our clock would be AP "old": what the offset takes out.
    assert clock.sample_age_s(now, now) == pytest.approx(AP, abs=EPS)


def test_no_answer_yet_leaves_everything_nan() -> None:
    clock = LinkClock()
    clock.request(T0)
    assert math.isnan(clock.offset_s) and math.isnan(clock.rtt_s)
    assert math.isnan(clock.sample_age_s(AP + T0, T0 + 0.01))
    stats = clock.stats()
    assert stats.n == 0
    for x in (stats.rtt_last_ms, stats.rtt_min_ms, stats.rtt_median_ms, stats.rtt_max_ms):
        assert math.isnan(x)
    assert math.isnan(stats.jitter_ms)
    assert stats.as_dict() == {
        "n": 0,
        "rtt_last_ms": None,
        "rtt_min_ms": None,
        "rtt_median_ms": None,
        "rtt_max_ms": None,
        "jitter_ms": None,
    }
    # Only answers that are not ours: still nothing.
    assert not clock.reply(round((T0 + AP) * 1e9), 42, T0 + 0.01)
    assert math.isnan(clock.offset_s)
    assert math.isnan(clock.sample_age_s(AP + T0, T0 + 0.01))


def test_the_offset_comes_from_the_quickest_exchange_in_the_window() -> None:
    clock = LinkClock()
    # 20 ms, lopsided (15 up, 5 down): this one alone says AP + 5 ms.
    assert exchange(clock, T0, up=0.015, down=0.005)
    assert clock.offset_s == pytest.approx(AP + 0.005, abs=EPS)
    # 2 ms, symmetric: the quickest, so its (exact) offset is taken.
    assert exchange(clock, T0 + 0.25, up=0.001, down=0.001)
    assert clock.offset_s == pytest.approx(AP, abs=EPS)
    # Later, slower and lopsided (8 up, 2 down): the last, but not the quickest.
    assert exchange(clock, T0 + 0.5, up=0.008, down=0.002)
    assert clock.rtt_s == pytest.approx(0.010, abs=EPS)  # the last round trip
    assert clock.offset_s == pytest.approx(AP, abs=EPS)  # still the quickest's
    # Each exchange's offset is bounded by half its round trip: the quickest bounds it best.
    assert abs(clock.offset_s - AP) <= 0.5 * clock.stats().rtt_min_ms * 1e-3 + EPS


def test_the_window_bounds_the_figures_and_the_quickest_ages_out() -> None:
    clock = LinkClock(window=3)
    t = T0
    # The quickest first (1 ms, 1 ms of asymmetry), then three slower, symmetric ones.
    assert exchange(clock, t, up=0.001, down=0.0)
    assert clock.offset_s == pytest.approx(AP + 0.0005, abs=EPS)
    for rtt_ms in (6.0, 4.0, 8.0):
        t += REQUEST_PERIOD_S
        assert exchange(clock, t, up=rtt_ms * 5e-4, down=rtt_ms * 5e-4, ap=AP + 0.1)
    # The 1 ms one has left the window: the quickest now is the 4 ms one.
    stats = clock.stats()
    assert stats.n == 3
    assert stats.rtt_min_ms == pytest.approx(4.0, abs=1e-4)
    assert stats.rtt_max_ms == pytest.approx(8.0, abs=1e-4)
    assert stats.rtt_median_ms == pytest.approx(6.0, abs=1e-4)
    assert clock.offset_s == pytest.approx(AP + 0.1, abs=EPS)
    assert clock.n_replies == 4
    # The default window: 16 answers (4 s at the request period).
    clock = LinkClock()
    for i in range(1, 21):
        assert exchange(clock, T0 + i * REQUEST_PERIOD_S, up=0.001 * i, down=0.001 * i)
    stats = clock.stats()
    assert stats.n == 16
    assert stats.rtt_min_ms == pytest.approx(10.0, abs=1e-4)  # i = 5: the first 4 have gone
    assert stats.rtt_max_ms == pytest.approx(40.0, abs=1e-4)


def test_a_window_below_one_is_refused() -> None:
    with pytest.raises(ValueError, match="window"):
        LinkClock(window=0)


def test_stats_median_min_max_last_and_jitter() -> None:
    clock = LinkClock()
    t = T0
    for rtt_ms in (10.0, 2.0, 6.0, 30.0):
        assert exchange(clock, t, up=rtt_ms * 5e-4, down=rtt_ms * 5e-4)
        t += REQUEST_PERIOD_S
    stats = clock.stats()
    assert isinstance(stats, LinkStats)
    assert stats.n == 4
    assert stats.rtt_last_ms == pytest.approx(30.0, abs=1e-4)
    assert stats.rtt_min_ms == pytest.approx(2.0, abs=1e-4)
    assert stats.rtt_median_ms == pytest.approx(8.0, abs=1e-4)  # even: (6 + 10) / 2
    assert stats.rtt_max_ms == pytest.approx(30.0, abs=1e-4)
    assert stats.jitter_ms == pytest.approx(28.0, abs=1e-4)
    assert exchange(clock, t, up=0.002, down=0.002)  # 4 ms: odd, the middle one
    stats = clock.stats()
    assert stats.n == 5
    assert stats.rtt_median_ms == pytest.approx(6.0, abs=1e-4)
    assert stats.rtt_last_ms == pytest.approx(4.0, abs=1e-4)
    d = stats.as_dict()
    assert d == {
        "n": 5,
        "rtt_last_ms": 4.0,
        "rtt_min_ms": 2.0,
        "rtt_median_ms": 6.0,
        "rtt_max_ms": 30.0,
        "jitter_ms": 28.0,
    }
    json.dumps(d, allow_nan=False)  # as telemetry sends it


def test_unmatched_duplicate_and_late_answers_are_counted_and_ignored() -> None:
    clock = LinkClock()
    assert exchange(clock, T0, up=0.002, down=0.002)
    good = (clock.rtt_s, clock.offset_s)

    # An answer to no request of ours (another client's request, say).
    assert not clock.reply(round((T0 + AP) * 1e9), round((T0 - 3.0) * 1e9), T0 + 0.3)
    assert clock.n_unmatched == 1

    # The same answer twice: the second matches nothing any more.
    ts1 = clock.request(T0 + 0.5)
    tc1 = round((T0 + 0.5 + 0.001 + AP) * 1e9)
    assert clock.reply(tc1, ts1, T0 + 0.502)
    good = (clock.rtt_s, clock.offset_s)
    assert not clock.reply(tc1, ts1, T0 + 0.6)
    assert clock.n_unmatched == 2

    # Later than 5 s: no round trip worth a figure (and the request is spent).
    ts1 = clock.request(T0 + 1.0)
    assert not clock.reply(round((T0 + 1.0 + AP) * 1e9), ts1, T0 + 6.5)
    assert clock.n_unmatched == 3
    assert not clock.reply(round((T0 + 1.0 + AP) * 1e9), ts1, T0 + 6.6)
    assert clock.n_unmatched == 4

    # Received before it was sent (a clock gone wrong), and a tc1 that is no clock.
    ts1 = clock.request(T0 + 7.0)
    assert not clock.reply(round((T0 + 7.0 + AP) * 1e9), ts1, T0 + 6.9)
    ts1 = clock.request(T0 + 8.0)
    assert not clock.reply(0, ts1, T0 + 8.001)
    ts1 = clock.request(T0 + 9.0)
    assert not clock.reply(-5, ts1, T0 + 9.001)
    assert clock.n_unmatched == 7

    # None of them moved a figure.
    assert clock.n_replies == 2
    assert (clock.rtt_s, clock.offset_s) == good
    assert clock.stats().n == 2

    # A slow answer within 5 s is a round trip like any other (3 s up, 1 s down:
    # alone it would say AP + 1 s), but not the quickest: the offset stays.
    assert exchange(clock, T0 + 10.0, up=3.0, down=1.0)
    assert clock.rtt_s == pytest.approx(4.0, abs=EPS)
    assert clock.stats().n == 3
    assert clock.offset_s == pytest.approx(good[1], abs=EPS)


def test_at_most_8_requests_wait_for_their_answer() -> None:
    clock = LinkClock()
    sent = [clock.request(T0 + 0.25 * i) for i in range(9)]
    t_rx = T0 + 3.0
    # The oldest was given up on when the ninth went out.
    assert not clock.reply(round((t_rx + AP) * 1e9), sent[0], t_rx)
    assert clock.n_unmatched == 1
    # The other eight are still answered, in any order.
    for ts1 in reversed(sent[1:]):
        assert clock.reply(round((t_rx + AP) * 1e9), ts1, t_rx)
    assert clock.n_replies == 8
    assert clock.n_requests == 9
    # The quickest of them (the last sent) gives the offset and the minimum.
    assert clock.stats().rtt_min_ms == pytest.approx(1000.0, abs=1e-3)
    assert clock.stats().rtt_max_ms == pytest.approx(2750.0, abs=1e-3)
    assert clock.offset_s == pytest.approx(AP + 0.5, abs=EPS)
