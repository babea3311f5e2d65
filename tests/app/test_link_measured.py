"""The companion measures its link in flight: TIMESYNC round trips and each sample's age.

The fake autopilot keeps its own clock, ``AP_AHEAD_S`` ahead of the
companion's (perf_counter), answers TIMESYNC with it (as PX4 and ArduPilot
do) and stamps its IMU samples on it, each ``STALE_S`` before it sends it.
The companion knows neither: it must find the offset from the answers, and
date each sample with it (``control.mcap``'s ``sample_age_ms``).

An answer stamped anywhere between the request's sending and the answer's
arrival gives an offset within half the round trip of the true one: the
bounds below are that, not tolerances. Round trips and ages are the wall's (a
loaded machine lengthens them): each is held between what the test itself saw
on the same clock, never under a fixed figure.
"""

from __future__ import annotations

import asyncio
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import companion.watchdogs as watchdogs_module
from companion.link.timesync import LINK_RTT_SHOWN_MS
from companion.records import read_control_log
from tests.app.fakes import CMD_ARM, PX4_OFFBOARD, FakeAutopilot, settle
from tests.app.flight import Flight, Start, engage_px4_auto, streams_requested

AP_AHEAD_S = 1000.0
"""The autopilot's clock minus the companion's, s."""
STALE_S = 0.030
"""How old each IMU sample is when the fake autopilot sends it (on its clock), s."""

FIGURES = {
    "n",
    "rtt_last_ms",
    "rtt_min_ms",
    "rtt_median_ms",
    "rtt_max_ms",
    "jitter_ms",
    "sample_age_p50_ms",
    "sample_age_p99_ms",
}


def ap_clock() -> float:
    """The fake autopilot's clock, s."""
    return time.perf_counter() + AP_AHEAD_S


class StampedImu:
    """HIGHRES_IMU stamped on the autopilot's clock, ``STALE_S`` before it is sent."""

    def __init__(self, fake: FakeAutopilot) -> None:
        self.fake = fake
        self.last_us = 0

    def __call__(self) -> int:
        t_us = max(round((ap_clock() - STALE_S) * 1e6), self.last_us + 1)
        self.last_us = t_us
        self.fake.highres_imu(t_us, (0.0, 0.0, 0.0))
        return t_us


class TelemetryRecorder:
    """Stands in for MqttTelemetry: keeps what it is offered (``offered``: both
    kinds in the order they came)."""

    def __init__(self) -> None:
        self.links: list[dict[str, Any]] = []
        self.events: list[str] = []
        self.offered: list[dict[str, Any] | str] = []

    def publish_link(self, figures: dict[str, Any]) -> None:
        self.links.append(dict(figures))
        self.offered.append(dict(figures))

    def publish_event(self, kind: str, detail: str, t_s: float) -> None:
        self.events.append(kind)
        self.offered.append(kind)

    def publish_status(self, status: dict[str, Any]) -> None:
        pass

    def publish_sample(self, *_: Any) -> None:
        pass

    async def drain(self, timeout_s: float = 1.0) -> bool:
        return True


async def engage_stamped(f: Flight, send: StampedImu) -> None:
    """:func:`tests.app.flight.engage_px4_auto` with samples on the autopilot's clock."""
    await streams_requested(f)
    f.fake.rc(1000, sticks=(1500, 1500, 1500, 1500))
    await f.feed_until(lambda: f.fake.commands(CMD_ARM), send=send, what="ARM")
    f.fake.set_state(PX4_OFFBOARD, armed=True)
    await f.feed_until(lambda: f.companion.engaged, send=send, what="engaged")


def requests(f: Flight) -> list[Any]:
    return f.fake.of_type("TIMESYNC")


class Exchange:
    """One answer as the companion took it: our ``ts1`` sent (s), the fake's
    ``tc1`` (s, its clock), the arrival the companion stamped (s) and when it
    handled it (s, the same clock)."""

    def __init__(self, ts1_ns: int, tc1_ns: int, arrival_s: float) -> None:
        self.sent_s = ts1_ns * 1e-9
        self.answered_s = tc1_ns * 1e-9 - AP_AHEAD_S  # when the fake stamped it, our clock
        self.arrival_s = arrival_s
        self.handled_s = time.perf_counter()

    @property
    def rtt_ms(self) -> float:
        return (self.arrival_s - self.sent_s) * 1e3


def exchanges(f: Flight, monkeypatch: pytest.MonkeyPatch) -> list[Exchange]:
    """Every answer the companion's link clock is given, as it is given."""
    clock = f.companion.core.link_clock
    reply = clock.reply
    seen: list[Exchange] = []

    def noted(tc1_ns: int, ts1_ns: int, now_s: float) -> bool:
        seen.append(Exchange(ts1_ns, tc1_ns, now_s))
        return reply(tc1_ns, ts1_ns, now_s)

    monkeypatch.setattr(clock, "reply", noted)
    return seen


def waits_of(task_name: str, monkeypatch: pytest.MonkeyPatch) -> list[float]:
    """Every wait (s) the task named ``task_name`` asks ``asyncio.sleep`` for."""
    sleep = asyncio.sleep
    waits: list[float] = []

    async def noted(delay: float, result: Any = None) -> Any:
        task = asyncio.current_task()
        if task is not None and task.get_name() == task_name:
            waits.append(delay)
        return await sleep(delay, result)

    monkeypatch.setattr(asyncio, "sleep", noted)
    return waits


def counted(f: Flight) -> dict[str, str]:
    """The last ``counters`` event's ``name=value`` pairs."""
    return dict(kv.split("=", 1) for kv in f.details("counters")[-1].split())


async def quick_shadow(
    start: Start, monkeypatch: pytest.MonkeyPatch, delay_s: float
) -> tuple[Flight, TelemetryRecorder]:
    """A shadow run whose autopilot answers TIMESYNC ``delay_s`` each way, asked and
    judged quicker than in flight so that the window (16 answers) turns over
    within a test."""
    monkeypatch.setattr(watchdogs_module, "REQUEST_PERIOD_S", 0.02)
    monkeypatch.setattr(watchdogs_module, "_LINK_REPORT_PERIOD_S", 0.1)
    f = await start(engage="none", output="actuator")
    f.fake.timesync_clock = ap_clock
    f.fake.timesync_delay_s = delay_s
    tel = TelemetryRecorder()
    f.companion._telemetry = tel
    return f, tel


# ------------------------------------------------------------------- requests


async def test_requests_go_out_every_quarter_second_and_the_figures_to_telemetry(
    start: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    waits = waits_of("timesync", monkeypatch)
    t_before = time.perf_counter()
    f = await start(engage="none", output="actuator")
    answers = exchanges(f, monkeypatch)
    f.fake.timesync_clock = ap_clock
    f.fake.timesync_delay_s = 0.005  # 5 ms each way: a 10 ms round trip
    tel = TelemetryRecorder()
    f.companion._telemetry = tel
    send = StampedImu(f.fake)
    await f.feed_until(lambda: tel.links, send=send, timeout_s=3.0, what="the link's figures")
    await settle()  # the request sent just after the figures reaches the fake
    t_after = time.perf_counter()

    # Requests: tc1 = 0, ts1 our clock in ns, one every REQUEST_PERIOD_S: each
    # followed by a wait of just that (the wall may stretch it, never shorten it).
    asked = requests(f)
    assert len(asked) >= 2
    assert all(m.tc1 == 0 for m in asked)
    ts1_s = np.array([m.ts1 for m in asked]) * 1e-9
    assert t_before <= ts1_s[0] and ts1_s[-1] <= t_after
    assert (np.diff(ts1_s) >= watchdogs_module.REQUEST_PERIOD_S - 1e-3).all(), np.diff(ts1_s)
    assert waits == [watchdogs_module.REQUEST_PERIOD_S] * len(waits)
    assert len(waits) - 1 <= len(asked) <= len(waits)  # one request before each wait
    assert f.companion.core.link_clock.n_requests == len(waits)

    # Telemetry is offered the figures (about once a second), as MQTT sends them.
    figures = tel.links[0]
    assert set(figures) == FIGURES
    json.dumps(figures, allow_nan=False)
    assert figures["n"] >= 1
    # Each round trip is its own request's, stamped when its answer arrived: after
    # the fake answered, 5 ms after it was asked, and 5 ms more on the way back;
    # before the companion handled it. So never quicker than the link.
    for a in answers:
        assert a.sent_s + 0.005 - 1e-6 <= a.answered_s
        assert a.answered_s + 0.005 - 1e-6 <= a.arrival_s <= a.handled_s
    window = sorted(a.rtt_ms for a in answers[: figures["n"]])  # the figures' window
    assert figures["rtt_min_ms"] == pytest.approx(window[0], abs=1e-3)
    assert figures["rtt_max_ms"] == pytest.approx(window[-1], abs=1e-3)
    assert figures["rtt_min_ms"] >= 10.0 - 1e-3
    assert window[0] - 1e-3 <= figures["rtt_median_ms"] <= window[-1] + 1e-3
    # Samples STALE_S old when sent, then dated within half a round trip (and
    # never older than the whole test).
    age = figures["sample_age_p50_ms"]
    assert STALE_S * 1e3 - 0.5 * figures["rtt_max_ms"] - 1e-3 <= age
    assert age <= STALE_S * 1e3 + 0.5 * figures["rtt_max_ms"] + (t_after - t_before) * 1e3
    assert figures["sample_age_p99_ms"] >= age
    # Said to be slow exactly when a figure offered says so: a 10 ms round trip is
    # within what the controller is shown to fly (a loaded machine may stretch it).
    slow = [x for x in tel.links if x["rtt_median_ms"] > LINK_RTT_SHOWN_MS]
    assert ("link_slow" in f.kinds()) == bool(slow)


async def test_answers_date_every_sample_in_control_bin(
    start: Start, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    t_before = time.perf_counter()
    f = await start(engage="auto", output="actuator", log_dir=tmp_path)
    answers = exchanges(f, monkeypatch)
    f.fake.timesync_clock = ap_clock  # answered at once
    send = StampedImu(f.fake)
    await engage_stamped(f, send)
    n0 = f.companion.core.n_imu
    await f.feed_until(lambda: f.companion.core.n_imu >= n0 + 60, send=send, what="60 samples")
    clock = f.companion.core.link_clock
    assert clock.n_replies >= 1 and clock.n_unmatched == 0
    # The offset found is the fake's, within half the quickest round trip.
    assert abs(clock.offset_s - AP_AHEAD_S) <= 0.5 * clock.stats().rtt_min_ms * 1e-3 + 1e-6
    f.companion._stop.set()
    assert await f.finish() == 0
    run_ms = (time.perf_counter() - t_before) * 1e3

    cols, _ = read_control_log(tmp_path / "control.mcap")
    engaged = cols["engaged"] > 0.5
    assert engaged.sum() >= 60
    rtt_ms = cols["link_rtt_ms"][engaged]
    age_ms = cols["sample_age_ms"][engaged]
    assert np.isfinite(rtt_ms).all() and np.isfinite(age_ms).all()
    # Each row's round trip is one the companion measured, stamped as it arrived:
    # after the fake answered its own request, before the companion handled it.
    measured = np.array([a.rtt_ms for a in answers])
    assert all(np.abs(measured - x).min() < 1e-3 for x in set(rtt_ms.tolist()))
    for a in answers:
        assert a.sent_s - 1e-6 <= a.answered_s <= a.arrival_s + 1e-6
        assert a.arrival_s <= a.handled_s
    # Each sample was STALE_S old when sent, and older still when its command left;
    # the offset that dates it is within half a round trip of the true one (and no
    # sample is older than the whole run).
    assert (age_ms >= STALE_S * 1e3 - 0.5 * rtt_ms - 1e-3).all(), age_ms.min()
    assert (age_ms <= STALE_S * 1e3 + 0.5 * rtt_ms + run_ms).all(), age_ms.max()
    assert float(np.median(age_ms)) >= STALE_S * 1e3 - 1.0
    # The run's last counters carry the link's figures.
    last = counted(f)
    assert float(last["timesync.n"]) >= 1
    rtts = [a.rtt_ms for a in answers]
    assert min(rtts) - 1e-3 <= float(last["timesync.rtt_median_ms"]) <= max(rtts) + 1e-3
    assert float(last["timesync.sample_age_p50_ms"]) >= STALE_S * 1e3 - 1.0


async def test_without_answers_the_columns_stay_nan(start: Start, tmp_path: Path) -> None:
    f = await start(engage="auto", output="actuator", log_dir=tmp_path)
    await engage_px4_auto(f)
    await f.fake.wait_until(lambda: bool(requests(f)), 2.0)  # asked, never answered
    for _ in range(20):
        f.imu()
        await settle()
    figures = watchdogs_module.link_figures(f.companion.core)
    assert figures["n"] == 0
    assert figures["rtt_median_ms"] is None and figures["sample_age_p50_ms"] is None
    f.companion._stop.set()
    assert await f.finish() == 0
    cols, _ = read_control_log(tmp_path / "control.mcap")
    assert len(cols["t_s"]) >= 20
    assert np.isnan(cols["link_rtt_ms"]).all() and np.isnan(cols["sample_age_ms"]).all()
    assert "imu_samples" in counted(f)
    assert not [k for k in counted(f) if k.startswith("timesync.")]  # no figures to give


async def test_the_autopilots_own_request_is_not_an_answer(start: Start) -> None:
    f = await start(engage="none", output="actuator")  # the fake answers nothing itself
    await f.fake.wait_until(lambda: bool(requests(f)), 2.0)
    ours = requests(f)[0]
    assert ours.tc1 == 0
    clock = f.companion.core.link_clock
    # The autopilot asks us the time (tc1 = 0), even with the ts1 we wait on.
    f.fake.timesync(0, ours.ts1)
    f.fake.timesync(0, round(time.perf_counter() * 1e9))
    await settle()
    assert clock.n_replies == 0 and clock.n_unmatched == 0
    assert math.isnan(clock.offset_s) and clock.stats().n == 0
    # Our request still waits for its answer, which counts when it comes.
    f.fake.timesync(round(ap_clock() * 1e9), ours.ts1)
    await settle()
    assert clock.n_replies == 1 and clock.n_unmatched == 0
    assert abs(clock.offset_s - AP_AHEAD_S) <= 0.5 * clock.rtt_s + 1e-6
    # An answer to someone else's request is counted, and changes nothing.
    offset = clock.offset_s
    f.fake.timesync(round(ap_clock() * 1e9), 12345)
    await settle()
    assert clock.n_replies == 1 and clock.n_unmatched == 1
    assert clock.offset_s == offset


# --------------------------------------------------------------- a slow link


async def test_a_slow_link_is_one_link_slow_event_and_one_link_ok_after(
    start: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    f, tel = await quick_shadow(start, monkeypatch, 0.015)  # 30 ms: beyond the 20 ms shown
    await f.fake.wait_until(lambda: len(tel.links) >= 6, 5.0)
    assert f.kinds().count("link_slow") == 1  # said once, not at every report
    assert "link_ok" not in f.kinds()
    detail = f.details("link_slow")[0]
    assert detail.startswith("round trip ") and "beyond the 20 ms" in detail, detail
    assert tel.events.count("link_slow") == 1  # telemetry has the event too
    slow = [x["rtt_median_ms"] for x in tel.links if x["n"]]
    assert slow and min(slow) >= 30.0 - 1e-3

    # Quick again: once the window's median is under 0.8 x 20 ms, link_ok, once.
    f.fake.timesync_delay_s = 0.0
    await f.fake.wait_until(lambda: "link_ok" in f.kinds(), 5.0)
    ok = tel.offered.index("link_ok")
    judged = tel.offered[ok - 1]  # the figures offered in the report that said so
    assert isinstance(judged, dict) and judged["rtt_median_ms"] < 0.8 * LINK_RTT_SHOWN_MS
    n = len(tel.links)
    await f.fake.wait_until(lambda: len(tel.links) >= n + 3, 3.0)
    assert f.kinds().count("link_slow") == 1 and f.kinds().count("link_ok") == 1
    assert f.kinds().index("link_slow") < f.kinds().index("link_ok")
    f.companion._stop.set()
    assert await f.finish() == 0


async def test_a_link_within_the_shown_round_trip_is_not_slow(
    start: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    f, tel = await quick_shadow(start, monkeypatch, 0.007)  # 14 ms round trips
    await f.fake.wait_until(lambda: sum(1 for x in tel.links if x["n"]) >= 4, 5.0)
    medians = [x["rtt_median_ms"] for x in tel.links if x["n"]]
    assert min(medians) >= 14.0 - 1e-3
    if max(medians) <= 20.0:  # a loaded machine may slow the answers beyond it
        assert "link_slow" not in f.kinds()


async def test_telemetry_that_refuses_the_figures_is_no_failsafe(
    start: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(watchdogs_module, "REQUEST_PERIOD_S", 0.02)
    monkeypatch.setattr(watchdogs_module, "_LINK_REPORT_PERIOD_S", 0.1)
    f = await start(engage="auto", output="actuator")
    f.fake.timesync_clock = ap_clock
    send = StampedImu(f.fake)
    await engage_stamped(f, send)

    class Refusing(TelemetryRecorder):
        """Telemetry whose link publishing raises (a bug: it should never)."""

        def publish_link(self, figures: dict[str, Any]) -> None:
            raise RuntimeError("broken")

    f.companion._telemetry = Refusing()
    await f.feed_until(
        lambda: f.companion.counters["event_errors"] >= 2, send=send, what="two refusals"
    )
    assert f.companion.engaged  # flying on: the measuring task lives
    assert not [k for k in f.kinds() if k.startswith("failsafe")]
    assert any(t.get_name() == "timesync" for t in f.companion._tasks)
    f.companion._stop.set()
    assert await f.finish() == 0
