"""``companion run --mode altitude|position``: the outer loops on both estimates.

The app tier (a fake autopilot over a MemoryTransport): both estimates are asked
for, engagement waits for them, the hold flies the vertical loop's collective,
and a stale position is a failsafe with a hand-back.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from companion.control.mfc import LEGS_HOLD_QUIET_S
from companion.errors import EXIT_ERROR
from companion.mission import Mission, Waypoint
from companion.records import read_control_log
from companion.reference import ReferenceScript
from tests.app.fakes import CMD_ARM, CMD_SET_MESSAGE_INTERVAL, PX4_OFFBOARD, settle
from tests.app.flight import Flight, Start, streams_requested

MSG_ATTITUDE_QUATERNION = 31
MSG_LOCAL_POSITION_NED = 32
LEVEL = (1.0, 0.0, 0.0, 0.0)


def estimates_and_imu(
    f: Flight,
    pos: tuple[float, float, float] | None = (0.0, 0.0, -5.0),
    gyro: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> None:
    """The estimates (the position every fourth sample, as at 62.5 Hz), then an IMU sample."""
    f.fake.attitude_quaternion(f.t_ms, LEVEL)
    if pos is not None and f.t_us // 4000 % 4 == 0:
        f.fake.local_position(pos)
    f.t_ms += 4
    f.imu(gyro)


async def engaged(
    start: Start, mode: str, *, output_override: str = "rates", **opts: object
) -> Flight:
    # The fake sends no position of its own (position=False): these tests stream it.
    f = await start(engage="auto", output=output_override, mode=mode, position=False, **opts)
    await streams_requested(f)
    await f.fake.wait_until(
        lambda: (
            {MSG_ATTITUDE_QUATERNION, MSG_LOCAL_POSITION_NED}
            <= {int(m.param1) for m in f.fake.commands(CMD_SET_MESSAGE_INTERVAL)}
        ),
        2.0,
    )
    rates = {int(m.param1): m.param2 for m in f.fake.commands(CMD_SET_MESSAGE_INTERVAL)}
    assert rates[MSG_LOCAL_POSITION_NED] == pytest.approx(1e6 / 50.0)
    f.fake.extended_sys_state(2)  # MAV_LANDED_STATE_IN_AIR
    f.fake.rc(1000, sticks=(1500, 1500, 1500, 1500))  # throttle at mid-stick: hold
    await f.feed_until(lambda: f.fake.commands(CMD_ARM), send=lambda: estimates_and_imu(f))
    f.fake.set_state(PX4_OFFBOARD, armed=True)
    await f.feed_until(lambda: f.companion.engaged, send=lambda: estimates_and_imu(f))
    return f


@pytest.mark.parametrize("mode", ["altitude", "position"])
async def test_the_hold_takes_over_at_the_pilots_collective_and_pushes_up_below_it(
    start: Start, mode: str
) -> None:
    f = await engaged(start, mode)
    hold = f.companion.core.modes.hold
    assert hold is not None
    n = len(f.fake.of_type("SET_ATTITUDE_TARGET"))
    for _ in range(5):
        estimates_and_imu(f)
        await settle(2)
    sent = f.fake.of_type("SET_ATTITUDE_TARGET")[n:]
    assert sent[0].thrust == pytest.approx(0.5, abs=0.02)  # the pilot's throttle
    assert hold.setpoint.vertical.up_m == pytest.approx(5.0)
    for _ in range(60):  # the estimate says half a metre below the hold
        estimates_and_imu(f, (0.0, 0.0, -4.5))
        await settle(2)
    assert f.fake.of_type("SET_ATTITUDE_TARGET")[-1].thrust > sent[0].thrust + 0.02
    if mode == "position":
        assert hold.setpoint.horizontal.position_ne_m == (0.0, 0.0)


async def test_a_position_that_stops_is_a_failsafe_and_no_position_mode_is_handed_back(
    start: Start,
) -> None:
    f = await engaged(start, "position")
    await f.feed_until(
        lambda: "failsafe_stale_position" in f.kinds(),
        send=lambda: estimates_and_imu(f, None),
        what="failsafe_stale_position",
    )
    await f.fake.wait_until(lambda: not f.companion.commanding, 1.0)
    await f.feed_until(lambda: "handed_back" in f.kinds(), what="handed_back")
    # The position the failsafe gave up on is no position to hold on (found in review).
    assert "POSCTL" not in f.details("handed_back")[0], f.details("handed_back")


async def test_no_position_no_engagement(start: Start) -> None:
    # --engage auto waits for the estimates as long as it would wait to arm.
    f = await start(engage="auto", output="rates", mode="altitude", position=False,
                    arm_timeout_s=1.0)  # fmt: skip
    await streams_requested(f)
    f.fake.extended_sys_state(2)
    f.fake.rc(1000, sticks=(1500, 1500, 1500, 1500))
    await f.feed_until(
        lambda: "engage_failed" in f.kinds(), send=lambda: estimates_and_imu(f, None)
    )
    assert "LOCAL_POSITION_NED" in f.details("engage_failed")[0]
    assert await f.finish() == EXIT_ERROR
    assert not f.fake.commands(CMD_ARM)


async def test_a_non_finite_position_is_counted_and_not_flown(start: Start) -> None:
    f = await engaged(start, "altitude")
    nan = float("nan")
    await f.feed_until(
        lambda: "failsafe_stale_position" in f.kinds(),
        send=lambda: estimates_and_imu(f, (0.0, nan, -5.0)),
        what="failsafe_stale_position",
    )
    assert f.companion.counters["position_invalid"] >= 10


async def test_a_mission_flies_its_waypoints_from_where_it_engaged(start: Start) -> None:
    mission = Mission(speed_m_s=2.0, waypoints=[Waypoint(north_m=1.0, east_m=0.0, up_m=0.0)])
    f = await engaged(start, "position", mission=mission)

    def estimates_imu_and_rc() -> None:  # the radio streams too (25 Hz), however long it takes
        estimates_and_imu(f)
        if f.t_us // 4000 % 10 == 0:
            f.fake.rc(1000, sticks=(1500, 1500, 1500, 1500))

    await f.feed_until(
        lambda: "mission_waypoint" in f.kinds(), send=estimates_imu_and_rc, what="waypoint"
    )
    assert f.details("mission_started")[0].startswith("1 waypoints from N 0.00 E 0.00 D -5.00 m")
    assert f.details("mission_waypoint") == ["1 of 1: holding there"]
    hold = f.companion.core.modes.hold
    assert hold is not None and f.companion.core.modes.mission_path is not None
    # 1 m from rest to rest, the jerk 4 m/s^3: too short to reach 2.5 m/s^2 (or 2 m/s):
    # 1 m/s at most, 1 s to it and 1 s back to rest, reached after 2 s of IMU time
    # flown in the air.
    assert f.companion.core.modes.mission_t == pytest.approx(2.0, abs=0.005)
    assert hold.setpoint.horizontal.position_ne_m == pytest.approx((1.0, 0.0), abs=0.01)
    assert hold.setpoint.vertical.up_m == pytest.approx(5.0)


async def test_from_a_mode_that_holds_altitude_the_hold_takes_over_at_its_hover_estimate(
    start: Start,
) -> None:
    """PX4's ALTCTL centres the throttle stick whatever the vehicle needs: the stick is
    no collective to take over at (found in review); the autopilot's hover thrust is."""
    f = await engaged(start, "altitude", custom_mode=2 << 16, params={"MPC_THR_HOVER": 0.42})
    hold = f.companion.core.modes.hold
    assert hold is not None
    n = len(f.fake.of_type("SET_ATTITUDE_TARGET"))
    for _ in range(3):
        estimates_and_imu(f)
        await settle(2)
    first = f.fake.of_type("SET_ATTITUDE_TARGET")[n]
    assert first.thrust == pytest.approx(0.42, abs=0.02)  # not the stick's 0.5
    assert hold.outer.vertical.hover_thrust == pytest.approx(0.42, abs=0.01)  # the prior


async def test_the_hold_takes_over_at_the_collective_the_autopilot_flies(start: Start) -> None:
    """Engaged from a mode holding position (PX4 AUTO.LOITER), the first setpoint the
    autopilot flies carries the collective it flew itself (its ATTITUDE_TARGET), not
    a hover estimate that may be far from it (0.3 against PX4 SIH's 0.5: the vehicle
    sagged half a metre on the real PX4)."""
    loiter = (4 << 16) | (3 << 24)
    f = await start(engage="auto", output="rates", mode="position", position=False,
                    custom_mode=loiter)  # fmt: skip
    await streams_requested(f)
    f.fake.extended_sys_state(2)
    for _ in range(3):  # the pilot's radio streams
        f.fake.rc(1000, sticks=(1500, 1500, 1500, 1500))

    def send() -> None:
        f.fake.mav.attitude_target_send(f.t_ms, 0, (1.0, 0.0, 0.0, 0.0), 0.0, 0.0, 0.0, 0.47)
        estimates_and_imu(f)

    await f.feed_until(lambda: f.fake.commands(CMD_ARM), send=send)
    f.fake.set_state(PX4_OFFBOARD, armed=True)
    await f.feed_until(lambda: f.companion.engaged, send=send)
    thrusts = [m.thrust for m in f.fake.of_type("SET_ATTITUDE_TARGET")]
    assert thrusts[0] == pytest.approx(0.47, abs=1e-6)  # streamed before the switch ...
    assert max(abs(t - 0.47) for t in thrusts) < 0.02  # ... and flown from it, no jump


async def test_the_engaged_edge_does_not_start_the_laws_again(start: Start) -> None:
    """The laws start when the engage mode (and the arming) is accepted: the autopilot
    flies our setpoints from then. Its heartbeat shows it up to a second later; starting
    the loops again there jolted the real PX4 a second time (11 deg, 0.5 m of sag)."""
    f = await start(engage="auto", output="rates", mode="altitude", position=False)
    await streams_requested(f)
    f.fake.extended_sys_state(2)
    for _ in range(3):  # the pilot's radio streams
        f.fake.rc(1000, sticks=(1500, 1500, 1500, 1500))
    await f.feed_until(lambda: f.fake.commands(CMD_ARM), send=lambda: estimates_and_imu(f))
    for _ in range(3):
        estimates_and_imu(f)
        await settle(2)
    assert f.companion.core.setpoints_flown and not f.companion.engaged
    hold = f.companion.core.modes.hold
    assert hold is not None
    held_at = hold.setpoint.vertical.up_m
    for _ in range(80):  # half a metre below the hold: the collective rises
        estimates_and_imu(f, (0.0, 0.0, -4.5))
        await settle(2)
    before = f.fake.of_type("SET_ATTITUDE_TARGET")[-1].thrust
    f.fake.set_state(PX4_OFFBOARD, armed=True)
    await f.feed_until(
        lambda: f.companion.engaged, send=lambda: estimates_and_imu(f, (0.0, 0.0, -4.5))
    )
    for _ in range(2):
        estimates_and_imu(f, (0.0, 0.0, -4.5))
        await settle(2)
    after = f.fake.of_type("SET_ATTITUDE_TARGET")[-1].thrust
    assert hold.setpoint.vertical.up_m == held_at  # the same hold
    assert after == pytest.approx(before, abs=0.01)  # no step back to the take-over


async def test_in_rates_mode_too_the_laws_start_when_the_engage_mode_is_accepted(
    start: Start, tmp_path: Path
) -> None:
    """As in the flight modes: the real PX4 flies our rate setpoints from the ACK
    of OFFBOARD, and its heartbeat shows it up to a second later (1 Hz). The law
    starts at the ACK, learning only from commands flown, and runs on through
    the heartbeat; the control log counts the samples from the ACK as engaged.
    (Started at the heartbeat, the real PX4's rate flights were scored from a
    point that wandered by up to a second: their yaw MAE 21-22 or 28-29 deg/s.)"""
    f = await start(engage="auto", output="rates", log_dir=tmp_path)
    await streams_requested(f)
    core = f.companion.core
    resets: list[bool] = []
    reset_laws = core.reset_laws

    def counted() -> None:
        resets.append(core.setpoints_flown)
        reset_laws()

    core.reset_laws = counted  # type: ignore[method-assign]
    for _ in range(3):  # the pilot's radio streams
        f.fake.rc(1000, sticks=(1500, 1500, 1500, 1500))
    await f.feed_until(lambda: f.fake.commands(CMD_ARM), send=lambda: f.imu())
    for _ in range(40):  # flown, a steady roll rate to correct; no heartbeat yet
        f.imu((0.3, 0.0, 0.0))
        await settle(2)
    assert core.setpoints_flown and not f.companion.engaged
    started = len(resets)
    assert started >= 2 and resets[-1] is False  # streaming, then the ACKs: started there
    f_before = core.step.out.f_hat[0]
    assert abs(f_before) > 0.1  # learnt since
    f.fake.set_state(PX4_OFFBOARD, armed=True)
    await f.feed_until(lambda: f.companion.engaged, send=lambda: f.imu((0.3, 0.0, 0.0)))
    for _ in range(3):
        f.imu((0.3, 0.0, 0.0))
        await settle(2)
    assert len(resets) == started  # the engaged edge started nothing again
    assert core.step.out.f_hat[0] == pytest.approx(f_before, rel=0.2)
    f.companion._stop.set()
    assert await f.finish() == 0
    cols, _ = read_control_log(tmp_path / "control.mcap")
    eng = cols["engaged"] > 0.5
    first = int(np.argmax(eng))
    # Engaged in the log from the ACK: the 40 samples before the heartbeat included.
    assert eng[first:].sum() >= 40 + 3


async def test_a_reference_file_and_the_duration_count_from_the_first_sample_flown(
    start: Start,
) -> None:
    """A ``--reference`` flight starts its script, and ``--duration-s`` its clock, with
    the first sample the autopilot flies (after the ACK), not at the heartbeat that
    shows the mode up to a second later, so a scripted experiment starts at the same
    point of the flight on every stack and every run."""
    script = ReferenceScript(
        t_s=(0.0, 10.0), rates_rad_s=((0.2, 0.0, 0.0),) * 2, thrust=(0.62, 0.62)
    )
    f = await start(engage="auto", output="rates", reference=script, duration_s=0.1)
    await streams_requested(f)
    for _ in range(3):  # the pilot's radio streams
        f.fake.rc(1000, sticks=(1500, 1500, 1500, 1500))
    await f.feed_until(lambda: f.fake.commands(CMD_ARM), send=lambda: f.imu())
    await settle(2)
    n0 = len(f.fake.setpoints())
    for _ in range(10):  # flown; no heartbeat shows it yet
        f.imu()
        await settle(2)
    assert not f.companion.engaged
    assert {round(m.thrust, 5) for m in f.fake.setpoints()[n0:]} == {0.62}  # the script's
    for _ in range(30):  # 0.1 s is 25 samples at 250 Hz: the run ends, never engaged
        f.imu()
        await settle(2)
    assert await f.finish() == 0
    assert "duration" in f.kinds() and "engaged" not in f.kinds()


async def test_the_sticks_limits_are_the_autopilots_own(start: Start) -> None:
    f = await start(
        engage="auto", output="rates", mode="position", position=False,
        params={"MPC_VEL_MANUAL": 5.0, "MPC_MAN_TILT_MAX": 20.0, "MPC_Z_VEL_MAX_UP": 2.0},
    )  # fmt: skip
    await streams_requested(f)
    await f.fake.wait_until(lambda: f.companion.core.modes.hold is not None, 2.0)
    hold = f.companion.core.modes.hold
    assert hold is not None
    limits = hold.limits
    assert limits.tilt_max_deg == 20.0 and limits.climb.up_max_m_s == 2.0
    assert limits.horizontal.speed_max_m_s == 5.0
    assert limits.climb.down_max_m_s == 1.5  # not answered: PX4's default, and said so
    (assumed,) = f.details("stick_limits_assumed")
    assert "MPC_Z_VEL_MAX_DN 1.5" in assumed and "MPC_VEL_MANUAL" not in assumed
    assert "5 m/s" in f.details("stick_limits")[0]


async def test_an_autopilot_with_unusable_limits_flies_its_defaults(start: Start) -> None:
    f = await start(engage="auto", output="rates", mode="altitude", position=False,
                    params={"MPC_Z_VEL_MAX_UP": -1.0})  # fmt: skip
    await streams_requested(f)
    await f.fake.wait_until(lambda: f.companion.core.modes.hold is not None, 2.0)
    hold = f.companion.core.modes.hold
    assert hold is not None and hold.limits.climb.up_max_m_s == 3.0
    assert any("no usable limits" in d for d in f.details("stick_limits_assumed"))


async def test_the_control_log_holds_the_setpoints_and_the_estimates_flown(
    start: Start, tmp_path: Path
) -> None:
    f = await engaged(start, "position", log_dir=tmp_path)
    tilt = (math.cos(0.05), math.sin(0.05), 0.0, 0.0)  # 0.1 rad of roll
    for _ in range(20):
        f.fake.attitude_quaternion(f.t_ms, tilt)
        f.fake.local_position((1.0, -2.0, -5.0))
        f.t_ms += 4
        f.imu()
        await settle(2)
    f.companion._stop.set()
    assert await f.finish() == 0
    cols, _ = read_control_log(tmp_path / "control.mcap")
    last = {k: float(v[-1]) for k, v in cols.items()}
    assert (last["est_roll_rad"], last["est_pitch_rad"], last["est_yaw_rad"]) == pytest.approx(
        (0.1, 0.0, 0.0), abs=1e-9
    )
    assert (last["est_north_m"], last["est_east_m"], last["est_up_m"]) == (1.0, -2.0, 5.0)
    # Held where the sticks centred (the estimate at engagement), the heading free.
    assert (last["sp_north_m"], last["sp_east_m"], last["sp_up_m"]) == (0.0, 0.0, 5.0)
    assert math.isnan(last["sp_yaw_rad"])
    # Pushed back north-west of the hold: the setpoint tilts against the error.
    hold = f.companion.core.modes.hold
    assert hold is not None and hold.attitude_setpoint is not None
    assert last["sp_roll_rad"] == hold.attitude_setpoint.roll_rad
    assert last["sp_pitch_rad"] == hold.attitude_setpoint.pitch_rad
    assert (last["sp_roll_rad"], last["sp_pitch_rad"]) != (0.0, 0.0)


async def test_in_rates_mode_the_outer_columns_are_nan(start: Start, tmp_path: Path) -> None:
    f = await start(engage="auto", output="rates", log_dir=tmp_path)
    await streams_requested(f)
    for _ in range(10):
        f.imu()
        await settle(2)
    f.companion._stop.set()
    await f.finish()
    cols, _ = read_control_log(tmp_path / "control.mcap")
    assert len(cols["t_s"]) >= 10
    outer = [k for k in cols if k.startswith(("sp_", "est_", "outer_"))]
    assert len(outer) == 13
    assert all(np.isnan(cols[k]).all() for k in outer)


async def test_on_the_ground_the_rate_law_forgets_what_it_learnt_in_the_air(
    start: Start,
) -> None:
    f = await engaged(start, "altitude")
    for _ in range(60):  # in the air, a roll rate the law fights: it learns an F
        estimates_and_imu(f, gyro=(0.5, 0.0, 0.0))
        await settle(2)
    air = f.fake.of_type("SET_ATTITUDE_TARGET")[-1]
    assert abs(air.body_roll_rate) > 0.05
    f.fake.extended_sys_state(1)  # MAV_LANDED_STATE_ON_GROUND
    controller = f.companion.core.controller
    await f.feed_until(lambda: controller.on_ground, send=lambda: estimates_and_imu(f))
    for _ in range(5):  # just down: the legs may not hold it yet (a bounce is flown)
        estimates_and_imu(f)
        await settle(2)
    assert not controller.held_on_ground
    assert abs(f.fake.of_type("SET_ATTITUDE_TARGET")[-1].body_roll_rate) > 0.05
    for _ in range(round(LEGS_HOLD_QUIET_S / 0.004)):  # quiet on the legs: nothing held
        estimates_and_imu(f)
        await settle(2)
    assert controller.held_on_ground
    ground = f.fake.of_type("SET_ATTITUDE_TARGET")[-1]
    assert abs(ground.body_roll_rate) < 1e-3


@pytest.mark.parametrize("output", ["actuator", "rates"])
async def test_the_outer_gains_back_off_only_when_our_own_rate_loop_saturates(
    start: Start, output: str, tmp_path: Path
) -> None:
    # A roll rate far beyond what the law can answer within its output: with the
    # actuator output our mixer saturates and the outer gains back off; with the
    # rates output the autopilot's mixer is not seen, and they stay as they are.
    f = await engaged(start, "position", output_override=output, log_dir=tmp_path)
    hold = f.companion.core.modes.hold
    assert hold is not None
    for _ in range(150):
        estimates_and_imu(f, gyro=(8.0, -8.0, 0.0))
        await settle(2)
    outer = hold.outer
    if output == "actuator":
        assert outer.rate_saturation[0] > 0.1
        assert outer.gain_scale < 1.0
    else:
        assert outer.rate_saturation == (0.0, 0.0)
        assert outer.gain_scale == 1.0
    scale = outer.gain_scale
    f.companion._stop.set()
    await f.finish()
    cols, _ = read_control_log(tmp_path / "control.mcap")
    logged = cols["outer_gain_scale"][cols["engaged"] > 0.5]
    assert logged[-1] == scale  # the log says how far the gains backed off
    assert (logged.min() < 1.0) == (output == "actuator")
