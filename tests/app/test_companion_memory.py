"""The companion app driven over a MemoryTransport by a fake autopilot (pymavlink).

The middle tier of the tests (STYLE.md habit 12): the whole ``Companion.run()``
start-up, engagement, hot path, failsafes and hand-back, with the autopilot
played by :class:`tests.app.fakes.FakeAutopilot`, in one event loop, no
sockets. Every wait is bounded; the whole file runs in a few seconds.
"""

from __future__ import annotations

import asyncio
import json
import math
import signal
import socket
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from click.testing import CliRunner

from companion.app import Companion, RunOptions
from companion.cli import cli
from companion.records import read_control_log
from companion.reference import ReferenceScript
from tests.app.fakes import (
    APM_ALT_HOLD,
    APM_GUIDED_NOGPS,
    APM_STABILIZE,
    CMD_ARM,
    CMD_DO_SET_MODE,
    CMD_SET_MESSAGE_INTERVAL,
    PX4_MANUAL,
    PX4_OFFBOARD,
    PX4_POSCTL,
    mavlink2,
    settle,
)
from tests.app.flight import (
    ACCEPTED,
    ARDUPILOT,
    DENIED,
    LOOSE,
    MSG_ATTITUDE,
    MSG_EXTENDED_SYS_STATE,
    MSG_HIGHRES_IMU,
    MSG_RC_CHANNELS,
    PROFILE,
    PROFILE_PATH,
    ROOT,
    Start,
    engage_px4_auto,
    index_of,
    is_mode,
    setpoint_times,
    started_up,
    streams_requested,
    switch_flicked_high,
)

# --------------------------------------------------------------------- 1. auto PX4


async def test_auto_engagement_on_px4_then_one_command_per_sample(start: Start) -> None:
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)
    fake = f.fake

    intervals = fake.commands(CMD_SET_MESSAGE_INTERVAL)
    by_id = {int(m.param1): m.param2 for m in intervals}
    assert by_id[MSG_HIGHRES_IMU] == pytest.approx(1e6 / 250.0)
    assert by_id[MSG_RC_CHANNELS] == pytest.approx(1e6 / 50.0)

    # Order: streams, setpoints already flowing (PX4 demands it), OFFBOARD, then ARM.
    i_streams = max(fake.received.index(m) for m in intervals)
    i_setpoint = index_of(fake, lambda m: m.get_type() == "SET_ACTUATOR_CONTROL_TARGET")
    i_mode = index_of(fake, lambda m: is_mode(m, 6.0))
    i_arm = index_of(fake, lambda m: m.get_type() == "COMMAND_LONG" and m.command == CMD_ARM)
    assert i_streams < i_setpoint < i_mode < i_arm
    assert fake.received[i_mode].param1 == 1.0  # MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert fake.received[i_arm].param1 == 1.0
    assert f.kinds().count("engaged") == 1

    # Engaged: every sample, one at a time, makes exactly one command stamped with it.
    n0 = len(fake.setpoints())
    sent = []
    for _ in range(40):
        sent.append(f.imu((0.1, -0.2, 0.05)))
        await settle()
    # ... and so does a burst of samples arriving in one chunk.
    with fake.bundle():
        for _ in range(20):
            sent.append(f.imu())
    await settle()
    new = fake.setpoints()[n0:]
    assert [m.get_type() for m in new] == ["SET_ACTUATOR_CONTROL_TARGET"] * len(sent)
    assert setpoint_times(new) == sent
    assert all(math.isfinite(c) for m in new for c in m.controls)
    assert f.companion.counters["imu_duplicate_or_late"] == 0

    f.companion._stop.set()
    assert await f.finish() == 0
    assert is_mode(fake.commands(CMD_DO_SET_MODE)[-1], 3.0)  # handed back to POSCTL


async def test_the_autopilots_landed_state_stops_identification_on_the_ground(
    start: Start,
) -> None:
    """EXTENDED_SYS_STATE ON_GROUND stops the identifiers whatever the collective; an
    engagement (which resets the controller) keeps it; IN_AIR lets them learn again."""
    f = await start(engage="auto", output="actuator")
    assert not f.companion.core.controller.on_ground  # nothing said yet: the collective decides
    f.fake.extended_sys_state(mavlink2.MAV_LANDED_STATE_ON_GROUND)
    await f.fake.wait_until(lambda: f.companion.core.controller.on_ground, 1.0)
    await engage_px4_auto(f)
    asked = {int(m.param1): m.param2 for m in f.fake.commands(CMD_SET_MESSAGE_INTERVAL)}
    assert asked[MSG_EXTENDED_SYS_STATE] == pytest.approx(250_000.0)  # 4 Hz
    assert f.companion.core.controller.on_ground
    f.fake.extended_sys_state(mavlink2.MAV_LANDED_STATE_IN_AIR)
    await f.fake.wait_until(lambda: not f.companion.core.controller.on_ground, 1.0)
    assert f.details("landed_state") == ["on the ground", "in the air (2)"]
    f.companion._stop.set()
    assert await f.finish() == 0


async def test_a_refused_landed_state_stream_is_logged_and_flying_goes_on(start: Start) -> None:
    def interval(msg: Any) -> int:
        return DENIED if int(msg.param1) == MSG_EXTENDED_SYS_STATE else ACCEPTED

    f = await start(engage="auto", output="actuator", results={CMD_SET_MESSAGE_INTERVAL: interval})
    await engage_px4_auto(f)
    assert f.details("landed_state_refused") == [
        "EXTENDED_SYS_STATE at 4 Hz refused (MAV_RESULT 2): identification is gated by the "
        "collective alone unless the autopilot sends it"
    ]
    assert not f.companion.core.controller.on_ground
    f.companion._stop.set()
    assert await f.finish() == 0


async def test_records_hold_every_frame_and_one_row_per_sample(
    start: Start, tmp_path: Path
) -> None:
    from pymavlink import mavutil

    from companion.records import read_control_log

    f = await start(engage="auto", output="actuator", log_dir=tmp_path)
    await engage_px4_auto(f)
    fake = f.fake
    for _ in range(30):
        f.imu((0.1, -0.2, 0.05))
        await settle()
    with fake.bundle():  # several samples in one datagram
        for _ in range(5):
            f.imu()
    await settle()
    f.companion._stop.set()
    assert await f.finish() == 0

    # The .tlog: every IMU frame received and every command sent, readable by mavutil.
    log = mavutil.mavlink_connection(str(tmp_path / "flight.tlog"))
    seen: dict[str, list[Any]] = {}
    try:
        while (m := log.recv_match()) is not None:
            seen.setdefault(m.get_type(), []).append(m)
    finally:
        log.close()
    assert [m.time_usec for m in seen["HIGHRES_IMU"]] == fake.imu_sent
    assert setpoint_times(seen["SET_ACTUATOR_CONTROL_TARGET"]) == setpoint_times(fake.setpoints())

    # The control log: one row per processed sample, the latency measured to the send.
    cols, _ = read_control_log(tmp_path / "control.mcap")
    assert len(cols["t_s"]) == f.companion.counters["imu_samples"] == len(fake.imu_sent)
    assert [round(t * 1e6) for t in cols["t_s"]] == fake.imu_sent
    engaged = cols["engaged"] > 0.5
    assert engaged.sum() >= 35
    lat = cols["latency_us"][engaged]
    assert ((lat > 0.0) & (lat < 1e5)).all()
    assert (cols["wall_s"][1:] >= cols["wall_s"][:-1]).all()


# ------------------------------------------------------------- 2. duplicate / late


async def test_duplicate_and_late_samples_make_no_command_and_are_counted(start: Start) -> None:
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)
    fake = f.fake
    n_cmd, n_imu = len(fake.setpoints()), f.companion.counters["imu_samples"]

    t1 = f.imu()
    fake.highres_imu(t1, (0.0, 0.0, 0.0))  # duplicate
    fake.highres_imu(t1 - 1000, (0.0, 0.0, 0.0))  # late
    fake.highres_imu(t1 - 4000, (0.0, 0.0, 0.0))  # the one before t1: late too
    t2 = f.imu()
    await settle()

    assert setpoint_times(fake.setpoints()[n_cmd:]) == [t1, t2]
    assert f.companion.counters["imu_duplicate_or_late"] == 3
    assert f.companion.counters["imu_samples"] == n_imu + 2


# ------------------------------------------------------------------- 3. NaN gyro


async def test_nan_gyro_holds_output_then_invalid_imu_failsafe(start: Start) -> None:
    fs = replace(LOOSE, stale_imu_s=2.0, rc_timeout_s=5.0, link_timeout_s=5.0, invalid_imu_s=0.05)
    f = await start(engage="auto", output="actuator", failsafe=fs)
    await engage_px4_auto(f)
    fake = f.fake
    nan3 = (math.nan, math.nan, math.nan)

    for _ in range(5):
        f.imu((0.2, -0.1, 0.05))
        await settle()
    before = fake.setpoints()[-1]
    t_nan = f.imu((math.nan, 0.0, 0.0))
    await settle()
    held = fake.setpoints()[-1]
    assert held.time_usec == t_nan
    assert all(math.isfinite(c) for c in held.controls)
    assert list(held.controls) == list(before.controls)  # the last output, held
    assert f.companion.counters["imu_invalid"] == 1
    assert f.companion.engaged  # one bad sample is not yet a failsafe

    # NaN persisting beyond invalid_imu_s: failsafe, hand-back to POSCTL, exit 3.
    await f.feed_until(lambda: f.task.done() or "failsafe_invalid_imu" in f.kinds(),
                       send=lambda: f.imu(nan3), timeout_s=1.0, what="the failsafe")  # fmt: skip
    assert await f.finish() == 3
    assert "failsafe_invalid_imu" in f.kinds()
    assert f.companion.counters["imu_invalid"] > 1
    assert all(math.isfinite(c) for m in fake.setpoints() for c in m.controls)
    i_back = index_of(fake, lambda m: is_mode(m, 3.0))
    after = fake.received[i_back:]
    assert not [m for m in after if m.get_type() == "SET_ACTUATOR_CONTROL_TARGET"]


# ---------------------------------------------------------------------- 4. shadow


async def test_shadow_mode_sends_no_setpoint_mode_or_arm(start: Start) -> None:
    f = await start(engage="none", output="actuator", armed=True)
    await streams_requested(f)
    fake = f.fake
    fake.rc(2000)  # even a high engage switch means nothing in shadow mode
    for _ in range(20):
        with fake.bundle():
            for _ in range(10):
                f.imu((0.3, 0.0, -0.1))
        await settle()
    fake.set_state(PX4_OFFBOARD, armed=True)  # nor does the autopilot being in OFFBOARD
    await asyncio.sleep(0.4)  # longer than any engagement delay
    for _ in range(5):
        f.imu()
    await settle()

    assert f.companion.counters["imu_samples"] == 205  # the law ran on every sample
    assert f.companion.counters["commands_sent"] == 0
    assert not f.companion.engaged
    f.companion._stop.set()
    assert await f.finish() == 0
    # Asking the autopilot's time (TIMESYNC) measures the link; it commands nothing.
    assert {m.get_type() for m in fake.received} == {"HEARTBEAT", "COMMAND_LONG", "TIMESYNC"}
    assert {m.command for m in fake.of_type("COMMAND_LONG")} == {CMD_SET_MESSAGE_INTERVAL}


# ------------------------------------------------------------------- 5. rc-switch


async def test_rc_switch_engages_hands_back_and_reengages(start: Start) -> None:
    f = await start(
        engage="rc-switch", output="actuator", custom_mode=PX4_MANUAL, armed=True,
        follow_modes=False,  # the test says when the autopilot really switched
    )  # fmt: skip
    await streams_requested(f)
    await started_up(f)
    fake = f.fake

    # Switch low: nothing commanded, however long we wait.
    fake.rc(1000)
    await f.feed_until(lambda: f.companion.counters["imu_samples"] >= 80, what="samples")
    assert not fake.setpoints() and not fake.commands(CMD_DO_SET_MODE)

    # Switch high: setpoints, then OFFBOARD; no ARM (the pilot arms).
    fake.rc(2000)
    await f.feed_until(lambda: fake.commands(CMD_DO_SET_MODE), what="OFFBOARD")
    assert is_mode(fake.commands(CMD_DO_SET_MODE)[0], 6.0)
    assert fake.setpoints()
    assert not f.companion.engaged
    fake.set_state(PX4_OFFBOARD, armed=True)
    await f.feed_until(lambda: f.companion.engaged, what="engaged")

    # Switch low: hand back to the safe mode; the run goes on.
    fake.rc(1000)
    await f.feed_until(lambda: len(fake.commands(CMD_DO_SET_MODE)) >= 2, what="hand-back")
    assert is_mode(fake.commands(CMD_DO_SET_MODE)[1], 3.0)
    assert not f.companion.engaged
    fake.set_state(PX4_POSCTL, armed=True)
    await settle()
    n = len(fake.setpoints())
    for _ in range(20):
        f.imu()
        await asyncio.sleep(0.004)
    assert len(fake.setpoints()) == n, "commands after the hand-back"
    assert not f.task.done()

    # Switch high again: re-engages.
    fake.rc(2000)
    await f.feed_until(lambda: len(fake.commands(CMD_DO_SET_MODE)) >= 3, what="OFFBOARD again")
    assert is_mode(fake.commands(CMD_DO_SET_MODE)[2], 6.0)
    fake.set_state(PX4_OFFBOARD, armed=True)
    await f.feed_until(lambda: f.companion.engaged, what="engaged again")
    assert f.kinds().count("engaged") == 2
    assert not fake.commands(CMD_ARM)

    f.companion._stop.set()
    assert await f.finish() == 0


async def test_a_switch_already_high_at_start_engages_nothing_until_it_has_been_low(
    start: Start,
) -> None:
    """A companion started (or restarted by its service) with the pilot's switch
    high must not take over at once: only a low-to-high flick engages."""
    f = await start(
        engage="rc-switch", output="actuator", custom_mode=PX4_MANUAL, armed=True,
        follow_modes=False,
    )  # fmt: skip
    fake = f.fake
    fake.rc(2000)  # high before and through start-up
    await streams_requested(f)
    await started_up(f)
    fake.rc(2000)
    await f.feed_until(lambda: f.companion.counters["imu_samples"] >= 50, what="samples",
                       send=lambda: (f.imu(), fake.rc(2000)))  # fmt: skip
    assert not fake.setpoints() and not fake.commands(CMD_DO_SET_MODE)
    assert f.kinds().count("rc_switch_high_at_start") == 1
    assert "rc_switch" not in f.kinds()
    fake.rc(1000)
    await settle()
    fake.rc(2000)
    await f.feed_until(lambda: fake.commands(CMD_DO_SET_MODE), what="OFFBOARD")
    assert is_mode(fake.commands(CMD_DO_SET_MODE)[0], 6.0)


async def test_rc_switch_flicked_back_low_leaves_the_autopilot_in_the_safe_mode(
    start: Start,
) -> None:
    """The pilot flicks the switch high and back low within the engage delay:
    the last mode the companion asks for must be the safe mode, not OFFBOARD."""
    f = await switch_flicked_high(start)
    fake = f.fake
    for _ in range(10):
        f.imu()
        await asyncio.sleep(0.004)
    fake.rc(1000)  # back low ~40 ms later
    await f.feed_until(lambda: fake.commands(CMD_DO_SET_MODE), what="hand-back")
    t_end = asyncio.get_running_loop().time() + 0.6  # past the 0.3 s engage delay
    await f.feed_until(lambda: asyncio.get_running_loop().time() > t_end, what="time")

    modes = [m.param2 for m in fake.commands(CMD_DO_SET_MODE)]
    # POSCTL (3), then, on a machine slow enough that the hand-back watch expires
    # with the fake never showing it, the next safe mode (AUTO, 4): never OFFBOARD (6).
    assert modes[0] == 3.0 and 6.0 not in modes, f"DO_SET_MODE sequence {modes}"
    assert not f.companion.commanding


# ------------------------------------------------------------------- 6. ArduPilot


async def test_ardupilot_refuses_actuator_output_before_sending_anything(start: Start) -> None:
    f = await start(autopilot=ARDUPILOT, custom_mode=APM_STABILIZE, engage="auto",
                    output="actuator")  # fmt: skip
    assert await f.finish() == 1
    assert any("actuator" in d for d in f.details("error"))
    assert not f.fake.setpoints()
    assert not f.fake.of_type("COMMAND_LONG")


@pytest.mark.parametrize("engage", ["auto", "rc-switch"])
async def test_ardupilot_rates_refused_without_guid_options_thrust_bit(
    start: Start, engage: str
) -> None:
    f = await start(autopilot=ARDUPILOT, custom_mode=APM_STABILIZE, engage=engage,
                    output="rates", params={"GUID_OPTIONS": 0.0})  # fmt: skip
    assert await f.finish() == 1
    assert any("GUID_OPTIONS" in d for d in f.details("error")), f.companion.events
    assert f.fake.of_type("PARAM_REQUEST_READ")
    assert not f.fake.setpoints()
    assert not f.fake.of_type("COMMAND_LONG")


async def test_ardupilot_rates_engage_guided_nogps_and_send_attitude_targets(
    start: Start,
) -> None:
    f = await start(autopilot=ARDUPILOT, custom_mode=APM_STABILIZE, engage="auto",
                    output="rates", params={"GUID_OPTIONS": 8.0})  # fmt: skip
    fake = f.fake
    await streams_requested(f, MSG_ATTITUDE)
    assert f.companion.core.modes.imu_rate_hz == 250.0
    fake.rc(1000, sticks=(1500, 1500, 1500, 1500))
    await f.feed_until(lambda: fake.commands(CMD_ARM), send=f.att, what="ARM")
    i_mode = index_of(fake, lambda m: is_mode(m, 20.0))
    i_arm = index_of(fake, lambda m: m.get_type() == "COMMAND_LONG" and m.command == CMD_ARM)
    assert i_mode < i_arm
    assert not fake.of_type("SET_ACTUATOR_CONTROL_TARGET")
    fake.set_state(APM_GUIDED_NOGPS, armed=True)
    await f.feed_until(lambda: f.companion.engaged, send=f.att, what="engaged")

    n0 = len(fake.setpoints())
    sent = []
    for _ in range(30):
        sent.append(f.att((0.1, 0.0, -0.05)))
        await settle()
    new = fake.setpoints()[n0:]
    assert [m.get_type() for m in new] == ["SET_ATTITUDE_TARGET"] * len(sent)
    assert setpoint_times(new) == sent
    assert {m.type_mask for m in new} == {128}
    assert all(
        math.isfinite(v)
        for m in new
        for v in (m.body_roll_rate, m.body_pitch_rate, m.body_yaw_rate)
    )
    assert {m.thrust for m in new} == {0.5}  # the pilot's collective, half stick

    f.companion._stop.set()
    assert await f.finish() == 0
    assert is_mode(fake.commands(CMD_DO_SET_MODE)[-1], float(APM_ALT_HOLD))


async def test_rates_output_sends_the_reference_files_thrust_and_logs_the_rates(
    start: Start, tmp_path: Path
) -> None:
    script = ReferenceScript(
        t_s=(0.0, 10.0), rates_rad_s=((0.2, 0.0, 0.0),) * 2, thrust=(0.62, 0.62)
    )
    f = await start(autopilot=ARDUPILOT, custom_mode=APM_STABILIZE, engage="auto",
                    output="rates", params={"GUID_OPTIONS": 8.0}, reference=script,
                    log_dir=tmp_path)  # fmt: skip
    fake = f.fake
    await streams_requested(f, MSG_ATTITUDE)
    fake.rc(1000, sticks=(1500, 1500, 1500, 1500))  # the pilot's collective: 0.5
    await f.feed_until(lambda: fake.commands(CMD_ARM), send=f.att, what="ARM")
    fake.set_state(APM_GUIDED_NOGPS, armed=True)
    await f.feed_until(lambda: f.companion.engaged, send=f.att, what="engaged")
    n0 = len(fake.setpoints())
    for _ in range(20):
        f.att()
        await settle()
    new = fake.setpoints()[n0:]
    assert len(new) == 20
    assert {round(m.thrust, 5) for m in new} == {0.62}  # the script's, not the stick's
    f.companion._stop.set()
    assert await f.finish() == 0
    cols, _ = read_control_log(tmp_path / "control.mcap")
    sent = cols["engaged"] == 1.0
    assert sent.sum() >= 20
    # What went out is in the log, as sent (float32 on the wire).
    assert np.allclose(cols["sent_roll_rad_s"][sent][-20:], [m.body_roll_rate for m in new],
                       atol=1e-6)  # fmt: skip
    assert np.isfinite(cols["sent_roll_rad_s"][sent]).all()
    assert np.isnan(cols["sent_roll_rad_s"][0])  # before the setpoint stream began


async def test_ardupilot_denied_400_hz_falls_back_to_333_hz(start: Start) -> None:
    def interval(msg: Any) -> int:
        if int(msg.param1) == MSG_ATTITUDE and msg.param2 < 1e6 / 350.0:
            return DENIED  # ArduPilot: shorter than its loop period / 0.8
        return ACCEPTED

    f = await start(autopilot=ARDUPILOT, custom_mode=APM_STABILIZE, engage="none",
                    output="rates", loop_rate_hz=1000.0,
                    results={CMD_SET_MESSAGE_INTERVAL: interval})  # fmt: skip
    await streams_requested(f, MSG_ATTITUDE)
    imu_reqs = [m.param2 for m in f.fake.commands(CMD_SET_MESSAGE_INTERVAL) if m.param1 == 30]
    assert imu_reqs == [pytest.approx(1e6 / 400.0), pytest.approx(1e6 / 333.0)]
    assert f.companion.core.modes.imu_rate_hz == 333.0
    assert f.details("imu_rate_denied") == ["message 30 at 400 Hz denied"]
    f.companion._stop.set()
    assert await f.finish() == 0


# --------------------------------------------------------- 7. autopilot took over


async def test_autopilot_leaving_offboard_is_a_failsafe_and_ends_commands(start: Start) -> None:
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)
    fake = f.fake
    for _ in range(5):
        f.imu()
        await settle()
    fake.set_state(PX4_POSCTL, armed=True)  # e.g. the pilot flipped the mode switch
    await settle()
    n = len(fake.setpoints())
    assert not f.companion.engaged
    assert "failsafe_autopilot_took_over" in f.kinds()
    for _ in range(10):
        f.imu()
        await asyncio.sleep(0.002)
    assert await f.finish() == 3
    assert len(fake.setpoints()) == n, "commands after the autopilot took over"
    # The pilot (valid RC) chose POSCTL: kept, not overridden (no DO_SET_MODE after OFFBOARD).
    assert fake.commands(CMD_DO_SET_MODE)[-1].param2 == 6.0
    assert f.details("handed_back")[-1].endswith("POSCTL kept (the autopilot's mode)")


async def test_sample_in_the_same_datagram_as_the_takeover_heartbeat_is_not_commanded(
    start: Start,
) -> None:
    """PX4 packs several messages into one UDP datagram: a HIGHRES_IMU right after
    the HEARTBEAT that says "not OFFBOARD any more" must not be answered."""
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)
    fake = f.fake
    f.imu()
    await settle()
    n = len(fake.setpoints())
    with fake.bundle():
        fake.set_state(PX4_POSCTL, armed=True)
        t_after = f.imu()
    await settle()
    assert "failsafe_autopilot_took_over" in f.kinds()
    late = [m.time_usec for m in fake.setpoints()[n:]]
    assert late == [], f"sample {t_after} sent after the takeover heartbeat was commanded"


# ----------------------------------------------------------------------- 8. signal


async def test_sigterm_while_engaged_hands_back_and_exits_0(start: Start) -> None:
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)
    n_modes = len(f.fake.commands(CMD_DO_SET_MODE))
    f.imu()
    await settle()
    f.companion._on_signal(signal.SIGTERM)
    assert await f.finish() == 0
    modes = f.fake.commands(CMD_DO_SET_MODE)[n_modes:]
    assert [m.param2 for m in modes] == [3.0]
    assert f.details("signal") == ["SIGTERM"]
    assert any("POSCTL accepted" in d for d in f.details("handed_back"))


async def test_sigterm_before_the_autopilot_answers_exits_0_at_once_sending_nothing(
    start: Start,
) -> None:
    f = await start(engage="auto", heartbeat=False)  # a silent autopilot
    await asyncio.sleep(0.1)
    f.companion._on_signal(signal.SIGTERM)
    assert await f.finish(timeout_s=1.0) == 0  # not after the 10 s heartbeat timeout
    assert f.kinds()[-2:] == ["stopped", "counters"]
    assert not f.fake.of_type("COMMAND_LONG", "SET_ACTUATOR_CONTROL_TARGET", "SET_ATTITUDE_TARGET")


async def test_a_signal_during_a_failsafe_hand_back_lets_it_finish(start: Start) -> None:
    tries: list[float] = []

    def first_mode_switch_lost(m: Any) -> int | None:
        if m.param2 == 3.0:  # POSCTL: the hand-back
            tries.append(m.param2)
            return None if len(tries) == 1 else ACCEPTED
        return ACCEPTED

    f = await start(engage="auto", output="actuator",
                    results={CMD_DO_SET_MODE: first_mode_switch_lost})  # fmt: skip
    await engage_px4_auto(f)
    f.companion.core.failsafe("failsafe_envelope", "test")
    await settle()
    f.companion._on_signal(signal.SIGTERM)  # while the first try waits for its ACK
    assert await f.finish(timeout_s=3.0) == 3  # the failsafe came first
    assert len(tries) == 2  # retried, not cancelled with the run's tasks
    assert any("POSCTL accepted" in d for d in f.details("handed_back"))


async def test_a_pinned_autopilot_ignores_others_and_the_counters_say_so(start: Start) -> None:
    f = await start(engage="none", autopilot_sysid=9, heartbeat_timeout_s=0.5)
    f.fake.heartbeat()  # from system 1: not ours
    # No heartbeat from system 9: start-up fails as a link error (exit 1) ...
    assert await f.finish(timeout_s=2.0) == 1
    assert f.companion.link.target is None
    assert any("no HEARTBEAT" in d for d in f.details("error"))
    # ... and the last event says what was received and ignored.
    assert f.kinds()[-1] == "counters"
    detail = f.details("counters")[-1]
    assert "link.foreign_ignored=" in detail and "transport.chunks_in=" in detail


async def test_a_signal_while_the_pilots_hand_back_retries_leaves_the_safe_mode_last(
    start: Start,
) -> None:
    """Switch low (the POSCTL goes unanswered twice), high again, then SIGTERM: the
    engagement waiting behind the hand-back must not send OFFBOARD after the signal,
    and the last mode asked is the safe one (found by review; failed before)."""
    tries: list[float] = []

    def first_posctl_lost(m: Any) -> int | None:
        if m.param2 == 3.0:
            tries.append(m.param2)
            return None if len(tries) <= 2 else ACCEPTED
        return ACCEPTED

    f = await start(
        engage="rc-switch",
        output="actuator",
        custom_mode=PX4_MANUAL,
        armed=True,
        results={CMD_DO_SET_MODE: first_posctl_lost},
    )
    await streams_requested(f)
    await started_up(f)
    fake = f.fake
    fake.rc(1000)
    await settle()
    fake.rc(2000)
    await f.feed_until(lambda: fake.commands(CMD_DO_SET_MODE), what="OFFBOARD")
    fake.set_state(PX4_OFFBOARD, armed=True)
    await f.feed_until(lambda: f.companion.engaged, what="engaged")
    fake.rc(1000)  # pilot: hand back (first POSCTL will go unanswered)
    await f.feed_until(lambda: len(fake.commands(CMD_DO_SET_MODE)) >= 2, what="hand-back")
    fake.rc(2000)  # pilot: take over again while the hand-back is under way
    for _ in range(5):
        f.imu()
        await asyncio.sleep(0.004)
    assert f.companion.commanding
    f.companion._on_signal(signal.SIGTERM)
    for _ in range(30):
        f.imu()
        await asyncio.sleep(0.004)
    rc = await f.finish(timeout_s=3.0)
    await asyncio.sleep(0.2)
    modes = [m.param2 for m in fake.commands(CMD_DO_SET_MODE)]
    assert modes[-1] == 3.0, f"last mode asked is not the safe mode: {modes}"
    assert rc == 0
    i_signal = f.kinds().index("signal")
    assert "engaged" not in f.kinds()[i_signal:]


async def test_a_heartbeat_between_the_signal_and_the_hand_back_does_not_engage(
    start: Start,
) -> None:
    """The autopilot reports OFFBOARD in the loop turns between SIGTERM and the run's
    hand-back: that must not start an engagement (it did, about once in ten CI runs
    of the test above: 'engaged' logged after 'signal'). The hand-back still ends
    in the safe mode."""
    f = await switch_flicked_high(start)
    fake = f.fake
    await f.feed_until(lambda: fake.commands(CMD_DO_SET_MODE), what="OFFBOARD")
    assert f.companion.commanding and not f.companion.engaged
    f.companion._on_signal(signal.SIGTERM)
    # The heartbeat handled before the run's task wakes from its stop event.
    f.companion.core.on_heartbeat(
        SimpleNamespace(
            custom_mode=PX4_OFFBOARD, base_mode=mavlink2.MAV_MODE_FLAG_SAFETY_ARMED, system_status=4
        )
    )
    assert not f.companion.engaged
    rc = await f.finish(timeout_s=3.0)
    assert rc == 0
    i_signal = f.kinds().index("signal")
    assert "engaged" not in f.kinds()[i_signal:]
    assert [m.param2 for m in fake.commands(CMD_DO_SET_MODE)][-1] == 3.0


async def test_an_unanswered_hand_back_is_tried_again_by_the_runs_own(start: Start) -> None:
    tries: list[float] = []

    def posctl_lost(m: Any) -> int | None:
        if m.param2 == 3.0:
            tries.append(m.param2)
            return None
        return ACCEPTED

    f = await start(engage="auto", output="actuator", results={CMD_DO_SET_MODE: posctl_lost})
    await engage_px4_auto(f)
    f.companion.core.failsafe("failsafe_envelope", "test")
    await settle()
    f.companion._on_signal(signal.SIGTERM)
    assert await f.finish(timeout_s=5.0) == 3
    assert len(tries) == 6  # the failsafe's 3 tries, then the run's 3: the autopilot
    # still showed OFFBOARD after the first went unanswered
    assert len(f.details("handed_back")) == 2
    assert all("unanswered" in d for d in f.details("handed_back"))


# -------------------------------------------------------------------------- 9. CLI


@pytest.fixture
def held_udp() -> Any:
    """A UDP socket bound by the test: whatever the CLI would send there, we see."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        s.setblocking(False)
        yield s


def nothing_arrived(s: socket.socket) -> bool:
    try:
        s.recv(65535)
    except BlockingIOError:
        return True
    return False


@pytest.mark.parametrize("kind", ["udpin", "udpout"])
def test_cli_run_with_a_bad_profile_exits_2_before_opening_anything(
    tmp_path: Path, held_udp: socket.socket, kind: str
) -> None:
    text = PROFILE_PATH.read_text(encoding="utf-8")
    assert "mass_kg: 1.5" in text
    bad = tmp_path / "bad_profile.yaml"
    bad.write_text(text.replace("mass_kg: 1.5", "mass_kg: -1"), encoding="utf-8")
    port = held_udp.getsockname()[1]
    res = CliRunner().invoke(
        cli, ["run", "--connect", f"{kind}:127.0.0.1:{port}", "--profile", str(bad),
              "--engage", "none", "--heartbeat-timeout-s", "0.5"],
    )  # fmt: skip
    assert res.exit_code == 2, res.output
    assert str(bad) in res.output
    assert "physics.mass_kg" in res.output
    assert nothing_arrived(held_udp)


def test_cli_run_moves_an_earlier_runs_records_aside_and_refuses_an_unusable_log_dir(
    tmp_path: Path, held_udp: socket.socket
) -> None:
    logs = tmp_path / "logs"
    logs.mkdir()
    (logs / "control.mcap").write_bytes(b"the last flight")
    (logs / "events.jsonl").write_text('{"kind": "failsafe_link_lost"}\n')
    port = held_udp.getsockname()[1]
    # A config error first: nothing moved, nothing sent.
    res = CliRunner().invoke(
        cli, ["run", "--connect", f"udpout:127.0.0.1:{port}", "--profile", str(PROFILE_PATH),
              "--engage", "none", "--log-dir", str(logs), "--autopilot-compid", "1"],
    )  # fmt: skip
    assert res.exit_code == 2, res.output
    assert (logs / "control.mcap").read_bytes() == b"the last flight"
    # A run that starts: the earlier records are moved, untouched, not overwritten.
    res = CliRunner().invoke(
        cli, ["run", "--connect", "udpin:127.0.0.1:0", "--profile", str(PROFILE_PATH),
              "--engage", "none", "--log-dir", str(logs), "--heartbeat-timeout-s", "0.2"],
    )  # fmt: skip
    assert res.exit_code == 1, res.output  # no autopilot: a link error, after the move
    (earlier,) = logs.glob("earlier-*")
    assert (earlier / "control.mcap").read_bytes() == b"the last flight"
    assert "failsafe_link_lost" in (earlier / "events.jsonl").read_text()
    events = (logs / "events.jsonl").read_text()  # this run's own
    assert f"moved to {earlier}" in events
    assert "no HEARTBEAT" in events
    # The same again (a service restarting): a second folder, nothing lost.
    res = CliRunner().invoke(
        cli, ["run", "--connect", "udpin:127.0.0.1:0", "--profile", str(PROFILE_PATH),
              "--engage", "none", "--log-dir", str(logs), "--heartbeat-timeout-s", "0.2"],
    )  # fmt: skip
    assert res.exit_code == 1, res.output
    assert len(list(logs.glob("earlier-*"))) == 2
    # A path that cannot be a folder: exit 2, no traceback.
    res = CliRunner().invoke(
        cli, ["run", "--connect", f"udpout:127.0.0.1:{port}", "--profile", str(PROFILE_PATH),
              "--engage", "none", "--log-dir", str(logs / "events.jsonl" / "x")],
    )  # fmt: skip
    assert res.exit_code == 2, res.output
    assert "cannot create the folder" in res.output
    assert nothing_arrived(held_udp)


def test_cli_run_refuses_a_component_pin_without_a_system(held_udp: socket.socket) -> None:
    port = held_udp.getsockname()[1]
    res = CliRunner().invoke(
        cli, ["run", "--connect", f"udpout:127.0.0.1:{port}", "--profile", str(PROFILE_PATH),
              "--engage", "none", "--autopilot-compid", "1"],
    )  # fmt: skip
    assert res.exit_code == 2, res.output
    assert "--autopilot-compid" in res.output and "--autopilot-sysid" in res.output
    assert nothing_arrived(held_udp)


def test_cli_run_refuses_to_wait_after_a_failsafe_when_nothing_could_engage_again(
    held_udp: socket.socket,
) -> None:
    port = held_udp.getsockname()[1]
    res = CliRunner().invoke(
        cli, ["run", "--connect", f"udpout:127.0.0.1:{port}", "--profile", str(PROFILE_PATH),
              "--engage", "auto", "--on-failsafe", "wait"],
    )  # fmt: skip
    assert res.exit_code == 2, res.output
    assert "--on-failsafe wait: needs --engage rc-switch" in res.output
    assert nothing_arrived(held_udp)


def test_cli_run_logs_absolute_paths_so_replay_works_from_anywhere(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The run's options, as the command line gives them: _open_records writes these
    # paths into control.mcap's header (a run that never started keeps no control.mcap).
    given: list[RunOptions] = []

    async def run(self: Companion) -> int:
        given.append(self.opts)
        return 1

    monkeypatch.setattr(Companion, "run", run)
    monkeypatch.chdir(ROOT)
    res = CliRunner().invoke(
        cli, ["run", "--connect", "udpin:127.0.0.1:0", "--profile", "vehicle_profiles/f450.yaml",
              "--engage", "none", "--log-dir", str(tmp_path)],
    )  # fmt: skip
    assert res.exit_code == 1, res.output
    (opts,) = given
    assert opts.profile_path == str(PROFILE_PATH)
    assert Path(opts.controller_path).is_absolute()


def test_cli_default_profile_is_found_from_any_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # no vehicle_profiles/ here
    res = CliRunner().invoke(cli, ["check-config"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["profile"]["path"] == str(PROFILE_PATH)
    assert f"using {PROFILE_PATH}" in res.stderr  # said, not silent


def test_cli_run_with_a_bad_mqtt_url_exits_2(held_udp: socket.socket) -> None:
    port = held_udp.getsockname()[1]
    res = CliRunner().invoke(
        cli, ["run", "--connect", f"udpout:127.0.0.1:{port}", "--profile", str(PROFILE_PATH),
              "--mqtt", "notaurl", "--heartbeat-timeout-s", "0.5"],
    )  # fmt: skip
    assert res.exit_code == 2, res.output
    assert "notaurl" in res.output
    assert nothing_arrived(held_udp)


def test_cli_check_config_prints_the_mixer_factors() -> None:
    res = CliRunner().invoke(cli, ["check-config", "--profile", str(PROFILE_PATH)])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    mixer = doc["mixer"]
    for axis in ("roll", "pitch", "yaw"):
        assert len(mixer[axis]) == PROFILE.n_motors
        assert all(math.isfinite(x) for x in mixer[axis])
    # quad-X: the yaw factors alternate with the spin directions, and sum to zero
    assert sum(mixer["yaw"]) == pytest.approx(0.0, abs=1e-9)
    assert doc["profile"]["path"] == str(PROFILE_PATH)
    assert doc["profile"]["physics"]["mass_kg"] == 1.5
