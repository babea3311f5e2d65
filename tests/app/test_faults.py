"""Fault injection on the product path: each fault ends in a defined outcome.

Each test injects one fault into a running companion (a fake autopilot over a
MemoryTransport, see tests/app/flight.py) and checks what follows and when, in
sample time where the rule is judged in sample time. ``docs/failsafes.md``
lists them with the bounds these tests hold the app to.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import signal
import time
import tracemalloc
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any, BinaryIO

import pytest

from companion.app import Companion, RunOptions
from companion.failsafe import FailsafeConfig
from companion.link.transport import MemoryTransport
from companion.records import writer as records_writer
from tests.app.fakes import CMD_DO_SET_MODE, CMD_SET_MESSAGE_INTERVAL, PX4_OFFBOARD, settle
from tests.app.flight import (
    CONTROLLER,
    FEED_PERIOD_S,
    LOOSE,
    PROFILE,
    Flight,
    Start,
    engage_px4_auto,
    index_of,
    setpoint_times,
)

OFFBOARD = 6.0  # PX4 main mode of the engagement; any other DO_SET_MODE is a hand-back


def is_hand_back(m: Any) -> bool:
    return m.get_type() == "COMMAND_LONG" and m.command == CMD_DO_SET_MODE and m.param2 != OFFBOARD


def handed_back(f: Flight) -> bool:
    """A safe mode was accepted, or the autopilot's own mode kept (it left OFFBOARD
    for a mode the vehicle can fly)."""
    return any(
        d.endswith(("accepted", "kept (the autopilot's mode)")) for d in f.details("handed_back")
    )


def commands_after_hand_back(f: Flight) -> list[Any]:
    i = index_of(f.fake, is_hand_back)
    return [m for m in f.fake.received[i:] if m.get_type() == "SET_ACTUATOR_CONTROL_TARGET"]


def change_output(f: Flight, monkeypatch: pytest.MonkeyPatch, change: Callable[[Any], Any]) -> None:
    """From now on the law's output passes through ``change`` (a fault in the law)."""
    update = f.companion.core.controller.update
    monkeypatch.setattr(f.companion.core.controller, "update", lambda *a: change(update(*a)))


async def engaged_by_switch(start: Start) -> Flight:
    """An armed PX4 in OFFBOARD, ``--engage rc-switch --on-failsafe wait``: the
    pilot's switch low then high, engaged, five samples flown."""
    fs = replace(LOOSE, stale_imu_s=2.0, rc_timeout_s=5.0, link_timeout_s=5.0, on_failsafe="wait")
    f = await start(engage="rc-switch", output="actuator", failsafe=fs,
                    custom_mode=PX4_OFFBOARD, armed=True)  # fmt: skip
    await f.fake.wait_until(lambda: f.companion.started_up, 2.0)
    f.fake.rc(1000)
    await settle()
    f.fake.rc(2000)
    await f.feed_until(lambda: f.companion.engaged, what="engaged")
    await fly(f, 5)
    return f


async def fly(f: Flight, n: int, gyro: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
    for _ in range(n):
        f.imu(gyro)
        await settle(3)


# -------------------------------------------------------------------- RC glitch


async def test_an_rc_glitch_holds_the_last_valid_sticks_never_idle_thrust(start: Start) -> None:
    fs = replace(LOOSE, stale_imu_s=2.0, rc_timeout_s=1.0, link_timeout_s=5.0)
    f = await start(engage="auto", output="actuator", failsafe=fs)
    await engage_px4_auto(f)  # sticks centred, throttle at mid stick
    f.fake.rc(1000, sticks=(1500, 1500, 1600, 1500))
    await fly(f, 5)
    thrust_before = f.fake.setpoints()[-1].controls[3]
    assert thrust_before > 0.3

    n0 = len(f.fake.setpoints())
    f.fake.rc(1000, sticks=(1500, 1500, 0, 1500))  # throttle channel missing: a glitch
    await fly(f, 10)
    after = f.fake.setpoints()[n0:]
    assert len(after) == 10
    assert [m.controls[3] for m in after] == pytest.approx([thrust_before] * 10, abs=0.02)
    assert f.companion.counters["rc_invalid"] == 1
    assert f.companion.engaged

    # Only glitches from here: the RC-lost failsafe, after rc_timeout_s of no valid RC.
    seen_at: list[float] = []

    def rc_lost() -> bool:
        if "failsafe_rc_lost" not in f.kinds():
            return False
        seen_at.append(f.companion.core.clock())  # the clock RC's arrivals are stamped on
        return True

    await f.feed_until(
        rc_lost,
        send=lambda: (f.imu(), f.fake.rc(1000, sticks=(1500, 1500, 0, 1500))),
        timeout_s=2.0,
        what="the RC-lost failsafe",
    )
    last_valid = f.companion.core.pilot.last_valid
    assert last_valid is not None
    # Not before the timeout after the last valid frame: fired no sooner than seen.
    assert seen_at[0] - last_valid >= fs.rc_timeout_s
    assert f.details("failsafe_rc_lost")[0].startswith("no valid RC for 1.0 s")
    assert await f.finish() == 3
    assert handed_back(f)
    assert min(m.controls[3] for m in f.fake.setpoints()) > 0.3  # never idle thrust


# ------------------------------------------------------------- failing records


def full_disk(log_dir: Path, monkeypatch: pytest.MonkeyPatch, *names: str) -> Path:
    """A log folder whose records ``names`` (default: the MAVLink log and the events
    file) are written to /dev/full: every write to them fails with ENOSPC (the
    control log's header, written at start-up, goes to a real file, so the disk
    fills in flight). The records' writer opens them through its opener: files put
    in the folder beforehand would be moved aside as an earlier run's."""
    full = names or ("flight.tlog", "events.jsonl")

    def opener(path: Path) -> BinaryIO:
        return open("/dev/full" if path.name in full else path, "wb")

    monkeypatch.setattr(records_writer, "_open_binary", opener)
    return log_dir


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs Linux /dev/full")
async def test_a_full_disk_leaves_the_watchdogs_running(
    start: Start, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    fs = replace(LOOSE, stale_imu_s=0.2, rc_timeout_s=5.0, link_timeout_s=5.0)
    log_dir = full_disk(tmp_path / "r", monkeypatch)
    f = await start(engage="auto", output="actuator", failsafe=fs, log_dir=log_dir)
    await engage_px4_auto(f)
    await fly(f, 100)  # enough rows and frames for every writer to have tried
    for _ in range(40):
        f.fake.statustext(b"flood")
    await fly(f, 100)
    loop = asyncio.get_running_loop()
    t_end = loop.time() + 0.3  # past the writers' flush interval, samples flowing
    while loop.time() < t_end:
        await fly(f, 5)
        await asyncio.sleep(0.01)
    assert f.companion.engaged
    assert f.companion.counters["record_failures"] >= 1
    assert "records_failed" in f.kinds()

    # The IMU stops: the supervisor is alive and fires (the stale IMU's 0.2 s, long
    # before the radio's and the link's 5 s; the wait only bounds a hang).
    await f.fake.wait_until(lambda: "failsafe_stale_imu" in f.kinds(), 4.0)
    assert await f.finish() == 3
    assert handed_back(f)


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs Linux /dev/full")
async def test_a_full_disk_fails_safe_when_asked_to(
    start: Start, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    fs = replace(LOOSE, stale_imu_s=2.0, rc_timeout_s=5.0, link_timeout_s=5.0,
                        on_record_error="failsafe")  # fmt: skip
    log_dir = full_disk(tmp_path / "r", monkeypatch)
    f = await start(engage="auto", output="actuator", failsafe=fs, log_dir=log_dir)
    f.fake.rc(1000)
    # Commanding starts with the engagement (setpoints stream before OFFBOARD): from
    # then on, the first failed write (within a flush interval) is a failsafe.
    await f.feed_until(lambda: f.task.done(), timeout_s=3.0, what="the records failsafe")
    assert await f.finish() == 3
    assert "failsafe_records" in f.kinds()
    assert handed_back(f)


async def test_an_event_that_cannot_be_recorded_does_not_stop_a_failsafe(start: Start) -> None:
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)

    def refuse(*_: Any) -> None:
        raise OSError(28, "No space left on device")

    class Broken:
        """Telemetry whose event publishing raises (a bug: it should never)."""

        publish_event = publish_status = staticmethod(refuse)

        def publish_sample(self, *_: Any) -> None:
            pass

        async def drain(self, _timeout_s: float) -> None:
            pass

    f.companion._telemetry = Broken()
    f.fake.set_state(0x10000, armed=True)  # the autopilot leaves OFFBOARD: a failsafe
    assert await f.finish() == 3
    assert handed_back(f)
    assert f.companion.counters["event_errors"] >= 1
    f.companion._telemetry = None


# ------------------------------------------------------------ per-sample errors


async def test_a_law_that_keeps_raising_is_a_failsafe_after_three_samples(
    start: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)
    await fly(f, 5)
    n0 = len(f.fake.setpoints())

    def broken(*_: Any) -> None:
        raise ZeroDivisionError("a law with a bug")

    monkeypatch.setattr(f.companion.core.controller, "update", broken)
    f.imu()
    f.imu()
    await settle()
    assert f.companion.engaged  # two in a row: not yet
    f.imu()  # the third
    await settle()
    assert not f.companion.engaged
    assert "failsafe_sample_errors" in f.kinds()
    assert len(f.fake.setpoints()) == n0  # nothing was sent for the failed samples
    assert f.companion.counters["sample_errors"] == 3
    assert await f.finish() == 3
    assert handed_back(f)


async def test_an_occasional_error_is_counted_and_flying_goes_on(
    start: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)
    update = f.companion.core.controller.update
    calls = [0]

    def flaky(*args: Any) -> Any:
        calls[0] += 1
        if calls[0] % 3 == 0:
            raise ValueError("one in three")
        return update(*args)

    monkeypatch.setattr(f.companion.core.controller, "update", flaky)
    await fly(f, 30)
    assert f.companion.engaged
    assert f.companion.counters["sample_errors"] == 10


# --------------------------------------------------------------- the last gate


async def test_a_non_finite_law_output_never_reaches_the_wire(
    start: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)
    change_output(
        f,
        monkeypatch,
        lambda out: out._replace(torque=(math.nan, math.inf, -math.inf), thrust=math.nan),
    )
    n0 = len(f.fake.setpoints())
    await fly(f, 5)
    sent = f.fake.setpoints()[n0:]
    assert len(sent) == 5
    for m in sent:
        r, p, y, t = m.controls[:4]
        assert (r, p, y) == (0.0, 1.0, -1.0)
        assert t == pytest.approx(f.companion.core.pilot.thrust)  # the pilot's collective
    assert f.companion.counters["commands_gated"] == 10  # two NaN fields per command
    assert f.kinds().count("command_gated") == 1


async def test_rates_output_gates_nan_to_the_pilots_rate(
    start: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    f = await start(engage="auto", output="rates")
    await engage_px4_auto(f)
    change_output(f, monkeypatch, lambda out: out._replace(torque=(math.nan, 0.0, math.nan)))
    f.fake.rc(1000, sticks=(1700, 1500, 1500, 1500))  # some roll rate from the pilot
    await settle()
    n0 = len(f.fake.setpoints())
    await fly(f, 3)
    pilot = f.companion.core.pilot.rate_rad_s
    assert pilot[0] > 0.1
    for m in f.fake.setpoints()[n0:]:
        assert m.body_roll_rate == pytest.approx(pilot[0], rel=1e-6)
        assert m.body_yaw_rate == pytest.approx(pilot[2], abs=1e-6)
        assert math.isfinite(m.body_pitch_rate) and 0.0 <= m.thrust <= 1.0


# ---------------------------------------------------------- time discontinuity


async def test_an_autopilot_reboot_while_engaged_fails_safe_then_flies_on_its_new_clock(
    start: Start,
) -> None:
    f = await engaged_by_switch(start)
    streams_before = len(f.fake.commands(CMD_SET_MESSAGE_INTERVAL))

    f.t_us = 0  # the autopilot rebooted: its clock starts again
    f.imu()
    f.imu()
    await settle()
    assert f.companion.engaged  # two samples may be one corrupt stretch: not yet
    f.imu()  # the third in a row on the new clock: a reboot
    await settle()
    assert "failsafe_imu_clock" in f.kinds()
    assert "imu_clock_reset" in f.kinds()
    assert not f.companion.engaged
    assert f.companion.counters["imu_clock_resets"] == 1
    await f.fake.wait_until(lambda: handed_back(f), 1.0)

    # Not locked out: samples on the new clock are processed (no longer "late").
    n = f.companion.counters["imu_samples"]
    late = f.companion.counters["imu_duplicate_or_late"]
    await fly(f, 20)
    assert f.companion.counters["imu_samples"] == n + 20
    assert f.companion.counters["imu_duplicate_or_late"] == late
    # ... and the streams were asked for again (a rebooted autopilot forgot them).
    await f.fake.wait_until(
        lambda: len(f.fake.commands(CMD_SET_MESSAGE_INTERVAL)) > streams_before, 1.0
    )
    assert not f.task.done()


async def test_a_reboot_while_idle_is_logged_and_the_new_clock_taken(start: Start) -> None:
    f = await start(engage="none", output="actuator", failsafe=LOOSE)
    await f.fake.wait_until(lambda: f.companion.core.stack is not None, 2.0)
    await fly(f, 10)
    f.t_us = 1_000
    await fly(f, 10)
    assert "imu_clock_reset" in f.kinds()
    assert not [k for k in f.kinds() if k.startswith("failsafe")]
    assert f.companion.core.time.t_prev == pytest.approx(f.t_us * 1e-6)
    # Shadow mode's duration goes on counting on the new clock: 9 sample periods
    # before the jump, 7 after the sample that confirmed it; the jump adds nothing.
    assert f.companion.core.time.t_prev - f.companion.core.time.t_first == pytest.approx(16 * 0.004)


async def test_a_gap_the_wall_clock_also_took_is_a_gap_not_a_new_clock(start: Start) -> None:
    f = await start(engage="none", output="actuator", failsafe=LOOSE)
    await f.fake.wait_until(lambda: f.companion.core.stack is not None, 2.0)
    await fly(f, 10)
    await asyncio.sleep(1.5)  # the stream pauses (a busy link, a loaded autopilot) ...
    f.t_us += 1_500_000  # ... and its clock ran on meanwhile
    await fly(f, 10)
    assert f.companion.counters["imu_gaps"] == 1
    assert f.companion.counters["imu_clock_resets"] == 0
    assert f.companion.counters["imu_samples"] == 20


async def test_a_clock_that_jumps_ahead_and_goes_on_is_a_gap_not_a_failsafe(start: Start) -> None:
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)
    await fly(f, 5)
    f.t_us += 1_200_000  # a simulator's clock outran the wall's (lockstep)
    await fly(f, 20)
    assert f.companion.counters["imu_gaps"] == 1
    assert f.companion.counters["imu_clock_resets"] == 0
    assert f.companion.engaged
    assert "imu_gap" in f.kinds()


async def test_one_sample_stamped_10_s_ahead_is_an_outlier_not_a_new_clock(start: Start) -> None:
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)
    await fly(f, 5)
    n0 = len(f.fake.setpoints())
    f.fake.highres_imu(f.t_us + 10_000_000, (0.0, 0.0, 0.0))  # one corrupt timestamp
    await settle()
    sent = [f.imu() for _ in range(20)]
    await settle()
    assert setpoint_times(f.fake.setpoints()[n0:]) == sent  # every genuine sample flown
    assert f.companion.counters["imu_time_outliers"] == 1
    assert f.companion.counters["imu_clock_resets"] == 0
    assert f.companion.engaged
    assert not [k for k in f.kinds() if k.startswith("failsafe")]


@pytest.mark.parametrize("ahead_s", [0.06, 0.3, 0.6, 0.95])
async def test_one_sample_stamped_ahead_costs_that_sample_only(
    start: Start, ahead_s: float
) -> None:
    """A serial link, a radio modem or a glitching autopilot stamps one sample
    0.06-1 s ahead: the genuine samples after it all fly."""
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)
    await fly(f, 5)
    n0 = len(f.fake.setpoints())
    f.fake.highres_imu(f.t_us + 4000 + round(ahead_s * 1e6), (0.0, 0.0, 0.0))
    await settle()
    sent = []
    for _ in range(round(ahead_s * 250) + 20):
        sent.append(f.imu())
        await settle(3)
    await settle()
    assert setpoint_times(f.fake.setpoints()[n0:]) == sent  # every genuine sample flown
    assert f.companion.counters["imu_time_outliers"] == 1
    assert f.companion.counters["imu_duplicate_or_late"] == 0
    assert f.companion.counters["imu_gaps"] == 0
    assert f.companion.engaged


async def test_a_sample_stamped_300_ms_ahead_in_real_time_is_no_stale_imu(start: Start) -> None:
    """In real time, with the stale-IMU bound at its default (0.1 s): the stream
    the forward stamp would have blanked for 0.3 s flies on."""
    fs = replace(LOOSE, stale_imu_s=0.1)
    f = await start(engage="auto", output="actuator", failsafe=fs)
    await engage_px4_auto(f)
    await f.feed_until(lambda: len(f.fake.setpoints()) >= 30)
    n0 = len(f.fake.setpoints())
    f.fake.highres_imu(f.t_us + 4000 + 300_000, (0.0, 0.0, 0.0))
    sent: list[int] = []
    for _ in range(round(0.6 / FEED_PERIOD_S)):  # 0.6 s of samples, as they come
        sent.append(f.imu())
        await asyncio.sleep(FEED_PERIOD_S)
    await settle()
    assert "failsafe_stale_imu" not in f.kinds()
    assert f.companion.engaged
    assert setpoint_times(f.fake.setpoints()[n0:]) == sent
    assert f.companion.counters["imu_time_outliers"] == 1


async def test_two_nan_samples_the_second_stamped_ahead_are_no_invalid_imu(start: Start) -> None:
    """The second NaN sample, stamped 60 ms ahead, must not stretch the run of
    invalid samples past ``invalid_imu_s`` (0.05 s)."""
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)
    await fly(f, 5)
    f.imu((math.nan, 0.0, 0.0))
    await settle()
    f.fake.highres_imu(f.t_us + 4000 + 60_000, (math.nan, math.nan, math.nan))
    await settle()
    await fly(f, 30, (0.1, 0.0, 0.0))
    assert "failsafe_invalid_imu" not in f.kinds()
    assert f.companion.engaged
    assert f.companion.counters["imu_invalid"] == 1
    assert f.companion.counters["imu_time_outliers"] == 1


async def test_a_gap_in_real_time_is_taken_at_once(start: Start) -> None:
    """The link lost 50 ms of datagrams; the samples resume with stamps matching
    the wall time that passed: the first one after the gap flies."""
    fs = replace(LOOSE, stale_imu_s=0.1)
    f = await start(engage="auto", output="actuator", failsafe=fs)
    await engage_px4_auto(f)
    await f.feed_until(lambda: len(f.fake.setpoints()) >= 30)
    n0 = len(f.fake.setpoints())
    await asyncio.sleep(0.05)
    f.t_us += 50_000
    sent: list[int] = []
    for _ in range(round(0.1 / FEED_PERIOD_S)):  # 0.1 s of samples, as they come
        sent.append(f.imu())
        await asyncio.sleep(FEED_PERIOD_S)
    await settle()
    assert setpoint_times(f.fake.setpoints()[n0:]) == sent
    assert f.companion.counters["imu_gaps"] == 1
    assert f.companion.counters["imu_time_outliers"] == 0
    assert "failsafe_stale_imu" not in f.kinds()


async def test_a_gap_faster_than_the_wall_costs_two_samples(start: Start) -> None:
    """In lockstep the simulator's clock outruns the wall's: a 50 ms gap arrives
    at once, is a candidate, and is taken when two more samples follow on."""
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)
    await fly(f, 5)
    n0 = len(f.fake.setpoints())
    f.t_us += 50_000
    sent = [f.imu() for _ in range(20)]
    await settle()
    assert setpoint_times(f.fake.setpoints()[n0:]) == sent[2:]
    assert f.companion.counters["imu_gaps"] == 1
    assert f.companion.counters["imu_time_outliers"] == 0
    assert f.companion.engaged


# ---------------------------------------------------------- intermittent gyro


async def test_a_gyro_invalid_every_other_sample_trips_the_invalid_imu_failsafe(
    start: Start,
) -> None:
    fs = replace(LOOSE, stale_imu_s=2.0, rc_timeout_s=5.0, link_timeout_s=5.0)
    f = await start(engage="auto", output="actuator", failsafe=fs)
    await engage_px4_auto(f)
    t_start = f.t_us
    flip = [False]

    def half_nan() -> None:
        flip[0] = not flip[0]
        f.imu((math.nan, 0.0, 0.0) if flip[0] else (0.1, 0.0, 0.0))

    await f.feed_until(lambda: f.task.done() or "failsafe_invalid_imu" in f.kinds(),
                       send=half_nan, timeout_s=3.0, what="the invalid-IMU failsafe")  # fmt: skip
    # A 50 % share passes 20 % after about 0.5 s of samples (first order, 1 s):
    # -ln(1 - 0.2/0.5) * 1 s = 0.51 s.
    t_fired = (f.t_us - t_start) * 1e-6
    assert 0.4 < t_fired < 0.7
    assert await f.finish() == 3
    assert handed_back(f)
    assert not commands_after_hand_back(f)


async def test_rare_invalid_samples_do_not_trip_it(start: Start) -> None:
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)
    for i in range(400):  # 1 in 10 invalid, 1.6 s of samples
        f.imu((math.nan, 0.0, 0.0) if i % 10 == 0 else (0.1, 0.0, 0.0))
        await settle(2)
    assert f.companion.engaged
    assert f.companion.counters["imu_invalid"] == 40


# --------------------------------------------------------------- crashed tasks


async def test_a_crashed_supervisor_is_a_failsafe_and_ends_the_run(
    start: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    fs = replace(LOOSE, stale_imu_s=2.0, rc_timeout_s=5.0, link_timeout_s=5.0, on_failsafe="wait")
    f = await start(engage="auto", output="actuator", failsafe=fs)
    await engage_px4_auto(f)

    def crash() -> None:
        raise RuntimeError("a bug in a watchdog")

    monkeypatch.setattr(f.companion.watchdogs, "check_records", crash)
    assert await f.finish() == 3  # exits even with on_failsafe=wait: nobody would watch
    assert "failsafe_task_failed" in f.kinds()
    assert "supervise" in f.details("failsafe_task_failed")[0]
    assert handed_back(f)
    assert f.companion.counters["task_failures"] == 1


async def test_a_crashed_background_task_while_idle_is_an_event(start: Start) -> None:
    f = await start(engage="none", output="actuator")
    await f.fake.wait_until(lambda: f.companion.core.stack is not None, 2.0)

    async def boom() -> None:
        raise RuntimeError("telemetry bug")

    f.companion._spawn(boom(), "mqtt")
    await settle()
    assert "task_failed" in f.kinds()
    assert not f.task.done()  # not engaged, not the supervisor: the run goes on


async def test_a_task_that_ignores_its_cancellation_does_not_keep_the_run_from_ending(
    start: Start, caplog: pytest.LogCaptureFixture
) -> None:
    # On Python 3.11 asyncio.wait_for (in aiomqtt's publish) can lose a
    # cancellation; a task that then carries on must not hang the run's end.
    f = await start(engage="none", output="actuator")
    await f.fake.wait_until(lambda: f.companion.core.stack is not None, 2.0)
    release = asyncio.Event()

    async def deaf() -> None:
        while not release.is_set():
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.sleep(3600.0)

    f.companion._spawn(deaf(), "mqtt")
    await settle()
    f.companion._on_signal(signal.SIGTERM)
    assert await f.finish(timeout_s=5.0) == 0  # the run waited 2 s for it, not for ever
    assert any("task mqtt did not stop" in r.getMessage() for r in caplog.records)
    release.set()


# ---------------------------------------------------------------- lost heartbeats


async def test_two_lost_heartbeats_are_not_a_lost_link(start: Start) -> None:
    default_link_timeout_s = FailsafeConfig().link_timeout_s
    fs = replace(LOOSE, stale_imu_s=5.0, rc_timeout_s=10.0, link_timeout_s=default_link_timeout_s)
    f = await start(engage="auto", output="actuator", failsafe=fs)
    await engage_px4_auto(f)
    f.fake.heartbeat_period_s = 3600.0  # the background heartbeat stops
    if f.fake._hb_task is not None:
        f.fake._hb_task.cancel()
    f.fake.heartbeat()
    # 1 Hz heartbeats, two lost, the third 30 ms late: a 3.03 s gap.
    loop = asyncio.get_running_loop()
    t_end = loop.time() + 3.03
    while loop.time() < t_end:
        f.imu()
        await asyncio.sleep(0.02)
    f.fake.heartbeat()
    await fly(f, 5)
    assert f.companion.engaged
    assert "failsafe_link_lost" not in f.kinds()


# ------------------------------------------------------------ bounded memory


@pytest.mark.long
async def test_a_long_flight_and_a_statustext_flood_keep_memory_bounded(
    start: Start, tmp_path: Path
) -> None:
    f = await start(engage="auto", output="actuator", log_dir=tmp_path / "r")
    await engage_px4_auto(f)

    async def burst(n: int) -> None:
        for i in range(n):
            f.imu((0.1, -0.1, 0.0))
            f.fake.statustext(b"flood %d" % i)
            if i % 50 == 0:
                f.fake.rc(1000)
                await settle(3)
                f.fake.received.clear()  # the fake's own record is not the companion's
        await settle()

    await burst(2_000)
    tracemalloc.start()
    await burst(2_000)
    base, _ = tracemalloc.get_traced_memory()
    await burst(6_000)
    now, _ = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert len(f.companion.events) <= 1000
    assert f.companion.counters["events"] > 10_000
    # Three times more samples and events, and no more than ~2 MB of growth (the
    # records' buffers between flushes, the caches): nothing grows per event.
    assert now - base < 2_000_000


# ------------------------------------------------------- conflicting autopilot state


async def test_a_mode_that_flips_back_and_forth_ends_in_one_clean_hand_back(start: Start) -> None:
    f = await engaged_by_switch(start)

    for i in range(20):  # the one true autopilot, undecided: POSCTL, OFFBOARD, POSCTL, ...
        f.fake.set_state(0x30000 if i % 2 == 0 else PX4_OFFBOARD)
        f.fake.rc(2000)  # the pilot's switch stays high
        await fly(f, 2)
    await f.fake.wait_until(lambda: handed_back(f), 1.0)
    assert f.kinds().count("failsafe_autopilot_took_over") == 1
    assert not f.companion.engaged and not f.companion.commanding
    # The pilot (valid RC) has it in POSCTL: kept, and nothing that fights the autopilot.
    assert f.details("handed_back")[-1].endswith("POSCTL kept (the autopilot's mode)")
    n = len(f.fake.setpoints())
    await fly(f, 20)
    assert len(f.fake.setpoints()) == n
    assert not [m for m in f.fake.commands(CMD_DO_SET_MODE) if m.param2 == 6.0]
    assert not f.task.done()  # waiting for the pilot's switch, low then high


# ------------------------------------------------------------ a diverging loop


def pinned_motors(
    f: Flight, monkeypatch: pytest.MonkeyPatch, every: int, error_deg_s: float = 50.0
) -> None:
    """The law's output from now on: motors at full and at idle together on one
    sample in ``every``, and a steady tracking error."""
    idle = f.companion.opts.profile.limits.motor_idle
    n = [0]
    e = math.radians(error_deg_s)

    def oscillating(out: Any) -> Any:
        n[0] += 1
        motors = (1.0, idle, 1.0, idle) if n[0] % every == 0 else (0.5, 0.5, 0.5, 0.5)
        return out._replace(motors=motors, error=(e, -e, 0.0))

    change_output(f, monkeypatch, oscillating)


async def test_motors_at_both_ends_most_of_the_time_is_a_diverging_failsafe(
    start: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)
    pinned_motors(f, monkeypatch, every=1)
    t0 = f.t_us

    def sample_and_rc() -> None:  # the radio streams too (25 Hz), however long it takes
        if f.imu() // 4000 % 10 == 0:
            f.fake.rc(1000)

    await f.feed_until(
        lambda: f.task.done() or "failsafe_diverging" in f.kinds(),
        send=sample_and_rc,
        timeout_s=5.0,
        what="the diverging failsafe",
    )
    # First order over 2 s from 0 to 0.8: -2 s * ln(0.2) = 3.2 s of samples.
    assert (f.t_us - t0) * 1e-6 == pytest.approx(3.22, abs=0.05)
    assert await f.finish() == 3
    assert handed_back(f)
    assert "failsafe_envelope" not in f.kinds()  # 50 deg/s: the envelope alone never fires


async def test_motors_at_both_ends_a_third_of_the_time_is_a_normal_flight(
    start: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)
    pinned_motors(f, monkeypatch, every=3, error_deg_s=200.0)
    for _ in range(5):  # 10 s of samples
        await fly(f, 500)
        f.fake.rc(1000)
    assert f.companion.engaged
    assert f.companion.core.watch.pinned_fraction == pytest.approx(1 / 3, abs=0.05)


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs Linux /dev/full")
async def test_records_that_cannot_be_opened_stop_the_run_before_anything_is_sent(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    log_dir = full_disk(tmp_path / "r", monkeypatch, "control.mcap")  # no room for its header
    ours, _theirs = MemoryTransport.pair()
    opts = RunOptions(connect="memory", profile=PROFILE, controller=CONTROLLER, log_dir=log_dir)
    assert await asyncio.wait_for(Companion(opts, transport=ours).run(), 2.0) == 1
    assert not ours.is_open  # the link was never opened: nothing was sent
    assert ours.counters["chunks_out"] == 0


async def test_a_heartbeat_that_comes_back_gets_the_streams_asked_for_again(start: Start) -> None:
    fs = replace(LOOSE, stale_imu_s=2.0, rc_timeout_s=5.0, link_timeout_s=0.3)
    f = await start(engage="rc-switch", output="actuator", failsafe=fs)
    await f.fake.wait_until(lambda: f.companion.core.modes.imu_rate_hz is not None, 2.0)
    asked = len(f.fake.commands(CMD_SET_MESSAGE_INTERVAL))
    if f.fake._hb_task is not None:
        f.fake._hb_task.cancel()  # the autopilot goes quiet (a reboot) ...
    await f.fake.wait_until(lambda: "link_lost" in f.kinds(), 1.0)
    f.fake.heartbeat()  # ... and comes back, having forgotten what it was asked
    await f.fake.wait_until(lambda: "link_restored" in f.kinds(), 1.0)
    await f.fake.wait_until(lambda: len(f.fake.commands(CMD_SET_MESSAGE_INTERVAL)) > asked, 1.0)
    assert not f.task.done()  # rc-switch: idle, it waits for the pilot


async def test_a_companion_held_off_the_cpu_reads_what_waits_before_calling_the_imu_stale(
    start: Start,
) -> None:
    """Measured against the real PX4 with both cores busy: the companion saw gaps up to
    152 ms between IMU samples that were all there, queued in its socket while it was
    not running. The watchdog reads what waits before it judges."""
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)
    c = f.companion
    c.core.time.last_arrival = time.perf_counter() - 1.0  # as if held off the CPU for a second
    f.imu()  # a sample came meanwhile: it waits to be read
    assert await c.watchdogs.still_stale(0.25) is False
    c.core.time.last_arrival = time.perf_counter() - 1.0  # and with nothing waiting, it is stale
    assert await c.watchdogs.still_stale(0.25) is True
