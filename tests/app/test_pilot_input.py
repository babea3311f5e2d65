"""The pilot's input: a radio (RC_CHANNELS) or a joystick (MANUAL_CONTROL), and what
the autopilot says of its receiver and of its own failsafe.

Found against the real stacks: PX4 SIH has no radio and streams a ground station's
joystick as MANUAL_CONTROL (no RC_CHANNELS); ArduCopter keeps streaming the last
RC_CHANNELS after its radio is lost and says so only in SYS_STATUS (RC receiver
unhealthy) and in its HEARTBEAT (CRITICAL).
"""

from __future__ import annotations

import math

import pytest

from companion.control.sticks import joystick_channels
from companion.failsafe import FailsafeConfig
from tests.app.fakes import (
    APM_ALT_HOLD,
    APM_GUIDED_NOGPS,
    CMD_ARM,
    CMD_DO_SET_MODE,
    CMD_SET_MESSAGE_INTERVAL,
    PX4_OFFBOARD,
    PX4_POSCTL,
    mavlink2,
    settle,
)
from tests.app.flight import (
    ARDUPILOT,
    MSG_ATTITUDE,
    Start,
    engage_px4_auto,
    started_up,
    streams_requested,
)

MSG_MANUAL_CONTROL = 69
MSG_SYS_STATUS = 1


# ------------------------------------------------------------- the conversion


def test_a_joystick_maps_as_the_radio_it_stands_for() -> None:
    aetr = (1, 2, 3, 4)
    # x (pitch) forward +, y (roll) right +, z thrust 0..1000, r (yaw) right +.
    chans = joystick_channels((400, 1000, 250, -1000, 0b100, 1000, 0, 0, 0, 0, 0), aetr)
    assert chans[:5] == (2000, 1300, 1250, 1000, 2000)  # nose-down stick is a low ch2
    assert chans[5:10] == (1500,) * 5  # aux2..6 absent: centred, neither high nor low
    # The sticks go where the stick map reads them.
    taer = joystick_channels((0, 500, 1000, 0, 0, 0, 0, 0, 0, 0, 0), (2, 3, 1, 4))
    assert taer[:4] == (2000, 1750, 1500, 1500)


def test_an_out_of_range_joystick_is_an_invalid_frame() -> None:
    from companion.control.sticks import StickMap

    sticks = StickMap()
    assert sticks.map(joystick_channels((0, 0, 500, 0, 0, 0, 0, 0, 0, 0, 0), (1, 2, 3, 4))).valid
    beyond = joystick_channels((0, 3000, 500, 0, 0, 0, 0, 0, 0, 0, 0), (1, 2, 3, 4))
    assert not sticks.map(beyond).valid


# -------------------------------------------------------------- a joystick pilot


async def test_a_joystick_engages_and_flies_where_the_autopilot_has_no_radio(
    start: Start,
) -> None:
    f = await start(engage="rc-switch", output="actuator", custom_mode=PX4_POSCTL, armed=True,
                    follow_modes=False)  # fmt: skip
    await streams_requested(f)
    await started_up(f)
    asked = {int(m.param1) for m in f.fake.commands(CMD_SET_MESSAGE_INTERVAL)}
    assert {MSG_MANUAL_CONTROL, MSG_SYS_STATUS} <= asked
    for _ in range(2):  # the first frame of a stream is not taken (PX4 sends one on request)
        f.fake.manual_control(-1000, sticks=(0, 500, 500, 0))  # roll half right, half thrust
        await settle()
    assert not f.fake.commands(CMD_DO_SET_MODE)
    f.fake.manual_control(1000, sticks=(0, 500, 500, 0))
    await f.fake.wait_until(lambda: f.fake.commands(CMD_DO_SET_MODE), 2.0)
    assert f.details("rc_switch") == ["ch5 high (2000 us): engaging"]
    roll, pitch, yaw = f.companion.core.pilot.rate_rad_s
    assert roll == pytest.approx(math.radians(360.0))  # half of 720 deg/s
    assert (pitch, yaw) == (0.0, 0.0)
    assert f.companion.core.pilot.thrust == pytest.approx(0.5)


async def test_a_joystick_without_its_switches_engages_nothing(start: Start) -> None:
    f = await start(engage="rc-switch", output="actuator", custom_mode=PX4_POSCTL, armed=True,
                    follow_modes=False)  # fmt: skip
    await streams_requested(f)
    await started_up(f)
    for _ in range(5):
        f.fake.manual_control(1000, aux_present=False)  # aux1 not sent: centred
        await settle()
    assert not f.fake.commands(CMD_DO_SET_MODE)
    assert f.companion.core.pilot.last_valid is not None  # its sticks are valid all the same


async def test_a_radio_is_the_pilot_while_it_is_there(start: Start) -> None:
    f = await start(engage="rc-switch", output="actuator", custom_mode=PX4_POSCTL, armed=True,
                    follow_modes=False)  # fmt: skip
    await streams_requested(f)
    await started_up(f)
    for _ in range(3):
        f.fake.rc(1000)  # the radio: switch low
        f.fake.manual_control(1000, sticks=(0, 1000, 500, 0))  # a joystick says high
        await settle()
    assert not f.fake.commands(CMD_DO_SET_MODE)
    assert f.companion.core.pilot.rate_rad_s == (0.0, 0.0, 0.0)  # the radio's centred sticks


# ----------------------------------------------- the autopilot's own RC verdict


async def test_an_rc_receiver_the_autopilot_calls_lost_is_rc_lost(start: Start) -> None:
    f = await start(
        engage="auto",
        output="actuator",
        failsafe=FailsafeConfig(stale_imu_s=2.0, rc_timeout_s=1.0, link_timeout_s=5.0,
                                hand_back_watch_s=0.3),
    )  # fmt: skip
    await streams_requested(f)
    await f.feed_until(
        lambda: f.fake.commands(CMD_ARM), send=lambda: (f.fake.rc(1000), f.imu()), what="ARM"
    )
    f.fake.set_state(PX4_OFFBOARD, armed=True)
    await f.feed_until(lambda: f.companion.engaged, send=lambda: (f.fake.rc(1000), f.imu()))
    f.fake.sys_status(rc_healthy=True)
    await f.feed_until(
        lambda: "rc_receiver_lost" in f.kinds(),
        send=lambda: (f.fake.rc(1000), f.fake.sys_status(rc_healthy=False), f.imu()),
        what="the receiver called lost",
    )
    # Its frames keep coming (frozen, as ArduPilot sends them): they are not the pilot's.
    await f.feed_until(
        lambda: "failsafe_rc_lost" in f.kinds(),
        send=lambda: (f.fake.rc(1000), f.imu()),
        what="the RC-lost failsafe",
    )
    assert f.companion.core.pilot.n_unhealthy > 0
    await f.fake.wait_until(lambda: bool(f.details("handed_back")), 2.0)
    (handed,) = f.details("handed_back")
    assert "RC lost" in handed and "POSCTL" not in handed.split("->")[-1]


async def test_the_autopilot_failing_safe_is_recorded(start: Start) -> None:
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)
    f.fake.system_status = mavlink2.MAV_STATE_CRITICAL
    f.fake.heartbeat()
    await f.fake.wait_until(lambda: "autopilot_failsafe" in f.kinds(), 1.0)
    assert f.details("autopilot_failsafe") == ["system status CRITICAL"]


async def test_ardupilot_is_engaged_in_guided_nogps_and_says_so(start: Start) -> None:
    f = await start(autopilot=ARDUPILOT, custom_mode=APM_ALT_HOLD, engage="auto",
                    output="rates", params={"GUID_OPTIONS": 8.0})  # fmt: skip
    await streams_requested(f, MSG_ATTITUDE)
    f.fake.rc(1000, sticks=(1500, 1500, 1500, 1500))
    await f.feed_until(lambda: f.fake.commands(CMD_ARM), send=f.att, what="ARM")
    f.fake.set_state(APM_GUIDED_NOGPS, armed=True)
    await f.feed_until(lambda: f.companion.engaged, send=f.att, what="engaged")
    (engaged,) = f.details("engaged")
    assert engaged.startswith("GUIDED_NOGPS and armed")
    f.fake.set_state(APM_ALT_HOLD)  # the pilot's mode switch
    await f.feed_until(
        lambda: "failsafe_autopilot_took_over" in f.kinds(), send=f.att, what="took over"
    )
    (took,) = f.details("failsafe_autopilot_took_over")
    assert took.startswith("autopilot left GUIDED_NOGPS for ALT_HOLD")


async def test_an_auto_engagement_waits_for_the_pilots_input(start: Start) -> None:
    """Found on the real PX4: a companion started with the autopilot engaged before the
    ground station's joystick came, flew no throttle and failed safe at once."""
    f = await start(engage="auto", output="actuator")
    await streams_requested(f)
    for _ in range(50):  # 0.2 s of samples, no pilot
        f.imu()
        await settle(2)
    assert not f.fake.commands(CMD_DO_SET_MODE) and not f.fake.setpoints()
    f.fake.manual_control(-1000)  # one frame (PX4 sends one on request): no pilot yet
    for _ in range(50):
        f.imu()
        await settle(2)
    assert not f.fake.commands(CMD_DO_SET_MODE)
    await f.feed_until(  # the joystick streams
        lambda: f.fake.commands(CMD_ARM), send=lambda: (f.fake.manual_control(-1000), f.imu())
    )
    assert "failsafe_rc_lost" not in f.kinds()
