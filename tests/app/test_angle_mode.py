"""``companion run --mode angle``: the sticks as angles, on the autopilot's estimate.

The app tier (a fake autopilot over a MemoryTransport): the estimate is asked
for, engagement waits for it, a tilted estimate is levelled, and a stale or
invalid one is a failsafe with a hand-back.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import replace
from pathlib import Path

import pytest
from click.testing import CliRunner

from companion.cli import cli
from companion.control.attitude import DEFAULT_ATTITUDE_GAINS
from companion.errors import EXIT_BAD_INPUT, EXIT_ERROR
from companion.records import read_control_log
from tests.app.fakes import (
    CMD_ARM,
    CMD_DO_SET_MODE,
    CMD_SET_MESSAGE_INTERVAL,
    PX4_OFFBOARD,
    settle,
)
from tests.app.flight import LOOSE, PROFILE_PATH, Flight, Start, streams_requested

MSG_ATTITUDE_QUATERNION = 31
KP = DEFAULT_ATTITUDE_GAINS.kp_roll_pitch_1_s
DEG = math.pi / 180.0


def rolled(deg: float) -> tuple[float, float, float, float]:
    """A quaternion rolled ``deg`` right (body FRD to NED)."""
    h = 0.5 * deg * DEG
    return (math.cos(h), math.sin(h), 0.0, 0.0)


def estimate_and_imu(f: Flight, q: tuple[float, ...]) -> None:
    """One estimate, then one IMU sample, as an autopilot streams them."""
    f.fake.attitude_quaternion(f.t_ms, q)
    f.t_ms += 4
    f.imu()


async def engaged_in_angle_mode(start: Start, q: tuple[float, ...], **opts: object) -> Flight:
    f = await start(engage="auto", output="rates", rates_passthrough=True, mode="angle", **opts)
    await streams_requested(f)
    await f.fake.wait_until(
        lambda: (
            MSG_ATTITUDE_QUATERNION
            in {int(m.param1) for m in f.fake.commands(CMD_SET_MESSAGE_INTERVAL)}
        ),
        2.0,
    )
    f.fake.extended_sys_state(2)  # MAV_LANDED_STATE_IN_AIR
    f.fake.rc(1000, sticks=(1500, 1500, 1500, 1500))
    await f.feed_until(
        lambda: f.fake.commands(CMD_ARM), send=lambda: estimate_and_imu(f, q), what="ARM"
    )
    f.fake.set_state(PX4_OFFBOARD, armed=True)
    await f.feed_until(
        lambda: f.companion.engaged, send=lambda: estimate_and_imu(f, q), what="engaged"
    )
    return f


def body_rates(f: Flight) -> list[tuple[float, float, float]]:
    return [
        (m.body_roll_rate, m.body_pitch_rate, m.body_yaw_rate)
        for m in f.fake.of_type("SET_ATTITUDE_TARGET")
    ]


async def test_a_tilted_estimate_with_centred_sticks_is_levelled(start: Start) -> None:
    f = await engaged_in_angle_mode(start, rolled(10.0))
    n = len(body_rates(f))
    for _ in range(25):
        estimate_and_imu(f, rolled(10.0))
        await settle(2)
    rates = body_rates(f)[n:]
    assert len(rates) >= 20
    # The attitude loop's K_P (5.5 1/s) on a 10 deg error: -0.96 rad/s of roll at first.
    assert rates[0][0] == pytest.approx(-KP * 10.0 * DEG, rel=0.02)
    # This vehicle does not turn (a fake): F learns it, the reference grows, within
    # the loop's 220 deg/s.
    rolls = [r[0] for r in rates]
    assert all(b <= a for a, b in itertools.pairwise(rolls))
    assert -220.0 * DEG <= rolls[-1] < rolls[0]
    assert all(abs(p) < 1e-6 and abs(y) < 1e-6 for _, p, y in rates)
    assert "mode" in f.kinds() and "estimate_stream" in f.kinds()


async def test_full_right_stick_on_a_level_vehicle_rolls_right(start: Start) -> None:
    f = await engaged_in_angle_mode(start, rolled(0.0))
    f.fake.rc(1000, sticks=(2000, 1500, 1500, 1500))  # roll full right: 35 deg
    await settle()
    n = len(body_rates(f))
    for _ in range(10):
        estimate_and_imu(f, rolled(0.0))
        await settle(2)
    roll = body_rates(f)[n:][0][0]
    assert roll == pytest.approx(KP * 35.0 * DEG, rel=0.02)


async def test_engagement_waits_for_an_estimate(start: Start) -> None:
    # --engage auto waits for the estimates as long as it would wait to arm.
    f = await start(engage="auto", output="rates", mode="angle", arm_timeout_s=1.0)
    await streams_requested(f)
    f.fake.extended_sys_state(2)
    f.fake.rc(1000, sticks=(1500, 1500, 1500, 1500))
    await f.feed_until(lambda: "engage_failed" in f.kinds(), what="engage_failed")
    assert "ATTITUDE_QUATERNION" in f.details("engage_failed")[0]
    assert await f.finish() == EXIT_ERROR
    assert not f.fake.commands(CMD_ARM) and not f.fake.setpoints()


async def test_an_estimate_that_stops_is_a_failsafe_within_its_threshold(start: Start) -> None:
    f = await engaged_in_angle_mode(start, rolled(0.0))
    since = f.t_us - 4000  # the last estimate followed the sample before the last
    await f.feed_until(
        lambda: "failsafe_stale_estimate" in f.kinds(), what="failsafe_stale_estimate"
    )
    # stale_estimate_s of IMU time after it, two samples (8 ms) late at most.
    assert 100_000 <= f.t_us - since <= 108_000  # us
    await f.fake.wait_until(lambda: not f.companion.commanding, 1.0)


async def test_an_invalid_estimate_is_counted_and_not_flown(start: Start) -> None:
    f = await engaged_in_angle_mode(start, rolled(0.0))
    bad = (math.nan, 0.0, 0.0, 0.0)
    await f.feed_until(
        lambda: "failsafe_stale_estimate" in f.kinds(),
        send=lambda: estimate_and_imu(f, bad),
        what="failsafe_stale_estimate",
    )
    assert f.companion.counters["estimate_invalid"] >= 20


async def test_on_the_ground_the_attitude_loop_asks_for_nothing(start: Start) -> None:
    f = await engaged_in_angle_mode(start, rolled(10.0))
    f.fake.extended_sys_state(1)  # MAV_LANDED_STATE_ON_GROUND
    await f.fake.wait_until(lambda: f.companion.core.controller.on_ground, 1.0)
    n = len(body_rates(f))
    for _ in range(5):
        estimate_and_imu(f, rolled(10.0))
        await settle(2)
    assert body_rates(f)[n:][-1] == (0.0, 0.0, 0.0)


async def test_the_threshold_is_the_runs(start: Start) -> None:
    f = await engaged_in_angle_mode(
        start, rolled(0.0), failsafe=replace(LOOSE, stale_estimate_s=0.2)
    )
    since = f.t_us - 4000
    await f.feed_until(lambda: "failsafe_stale_estimate" in f.kinds(), what="failsafe")
    assert 200_000 <= f.t_us - since <= 208_000  # us


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["--mode", "angle", "--reference", "ref.csv"], "needs --mode rates"),
        (["--mode", "angle", "--stale-estimate-s", "0.6"], "--stale-estimate-s 0.6: beyond 0.5"),
        (["--mode", "level"], "'level' is not one of 'rates', 'angle'"),
    ],
)
def test_bad_angle_mode_options_are_refused(args: list[str], said: str) -> None:
    r = CliRunner().invoke(
        cli, ["run", "--connect", "udpin:127.0.0.1:0", "--profile", str(PROFILE_PATH), *args]
    )
    assert r.exit_code == EXIT_BAD_INPUT, r.output
    assert said in r.output


async def test_engagement_waits_for_the_landed_state(start: Start) -> None:
    f = await start(engage="auto", output="rates", mode="angle", arm_timeout_s=1.0)
    await streams_requested(f)
    f.fake.rc(1000, sticks=(1500, 1500, 1500, 1500))
    await f.feed_until(
        lambda: "engage_failed" in f.kinds(), send=lambda: estimate_and_imu(f, rolled(0.0))
    )
    assert "EXTENDED_SYS_STATE" in f.details("engage_failed")[0]
    assert not f.fake.commands(CMD_ARM) and not f.fake.setpoints()


async def test_the_switch_going_low_while_waiting_for_estimates_abandons_it(
    start: Start,
) -> None:
    """Found in review: the engagement waited for its estimates past the pilot's
    switch going low, then took the vehicle."""
    f = await start(engage="rc-switch", output="rates", mode="angle", armed=True)
    await streams_requested(f)
    await f.fake.wait_until(lambda: f.companion.started_up, 2.0)
    f.fake.extended_sys_state(2)
    f.fake.rc(1000)
    await settle()
    f.fake.rc(2000)  # engage: no estimate yet, so it waits
    for _ in range(5):
        f.imu()
        await settle(2)
    f.fake.rc(1000)  # the pilot changes their mind
    await settle(5)
    for _ in range(100):  # the estimates come after all
        estimate_and_imu(f, rolled(0.0))
        await settle(2)
    assert "engagement abandoned" in " ".join(f.details("rc_switch"))
    assert not f.companion.commanding and not f.companion.engaged
    assert not f.fake.commands(CMD_DO_SET_MODE) and not f.fake.setpoints()


async def test_the_control_log_holds_the_angle_asked_and_the_estimate(
    start: Start, tmp_path: Path
) -> None:
    f = await engaged_in_angle_mode(start, rolled(10.0), log_dir=tmp_path)
    f.fake.rc(1000, sticks=(2000, 1500, 1500, 1500))  # full right roll: 35 deg asked
    for _ in range(10):
        estimate_and_imu(f, rolled(10.0))
        await settle(2)
    f.companion._stop.set()
    assert await f.finish() == 0
    cols, _ = read_control_log(tmp_path / "control.mcap")
    last = {k: float(v[-1]) for k, v in cols.items()}
    assert last["sp_roll_rad"] == pytest.approx(35.0 * DEG)
    assert last["sp_pitch_rad"] == 0.0 and math.isnan(last["sp_yaw_rad"])
    assert last["est_roll_rad"] == pytest.approx(10.0 * DEG, abs=1e-6)  # a float32 quaternion
    # Angle mode holds no position and asks for none.
    assert all(math.isnan(last[k]) for k in ("sp_north_m", "sp_up_m", "est_north_m", "est_up_m"))
    # The gain's backoff, logged as the mode keeps it.
    angle = f.companion.core.modes.angle
    assert angle is not None and last["outer_gain_scale"] == angle.backoff.scale
