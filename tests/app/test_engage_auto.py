"""``--engage auto`` against a stack that is not ready yet: it waits for the
stack's pre-arm checks (SYS_STATUS), tries again while the stack refuses the
engage mode or the arming, within ``--arm-timeout-s``, and quotes the stack's
own reason, never an unrelated text.

As ArduCopter 4.5.6 does after boot: "Arm: Need Alt Estimate" for the first
seconds (its EKF has no altitude yet), "PreArm: Need Position Estimate" for
40-50 s; PX4 v1.16: "Preflight Fail: ..." naming the check, then "Arming
denied: ...". The retry period is shortened here (``_RETRY_S``); the bound
(``arm_timeout_s``) is the option's. Both are timed on the engagement's own
clock (``Flight.clock``, tests/app/flight.py), which counts its waits, so the
times below are exact on any machine, however loaded.
"""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import Callable
from typing import Any

import pytest

from companion import engagement
from tests.app.fakes import (
    APM_GUIDED_NOGPS,
    APM_STABILIZE,
    CMD_ARM,
    CMD_DO_SET_MODE,
    PX4_OFFBOARD,
    mavlink2,
)
from tests.app.flight import (
    ACCEPTED,
    ARDUPILOT,
    DENIED,
    MSG_ATTITUDE,
    Flight,
    Start,
    streams_requested,
)

FAILED = mavlink2.MAV_RESULT_FAILED  # ArduCopter's answer to a refused arm
RETRY_S = 0.1
UNRELATED = b"RC7: SaveWaypoint MIDDLE"  # what ArduCopter said next in the flight that failed


@pytest.fixture(autouse=True)
def quick_retries(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(engagement, "_RETRY_S", RETRY_S)


class Refuses:
    """The fake's answer to a command: ``result`` for the first ``times`` tries
    (each saying ``said`` after its ACK, then an unrelated text), ACCEPTED after;
    ``at``: when each try came, on the engagement's clock."""

    def __init__(
        self, fake_ref: list[Flight], times: int, said: tuple[bytes, ...], result: int = FAILED
    ) -> None:
        self.fake_ref = fake_ref
        self.times = times
        self.said = said
        self.result = result
        self.at: list[float] = []

    def __call__(self, m: Any) -> int:
        self.at.append(self.fake_ref[0].clock())
        if len(self.at) > self.times:
            return int(ACCEPTED)
        fake = self.fake_ref[0].fake
        loop = asyncio.get_running_loop()
        for text in (*self.said, UNRELATED):  # after the ACK, as the stacks send them
            loop.call_soon(fake.statustext, text, mavlink2.MAV_SEVERITY_CRITICAL)
        return int(self.result)


def mode_refused(fake_ref: list[Flight], times: int, said: bytes) -> Callable[[Any], int]:
    """DO_SET_MODE: GUIDED_NOGPS refused ``times`` times, then shown (the fake
    follows accepted modes)."""
    refuses = Refuses(fake_ref, times, (said,))

    def answer(m: Any) -> int:
        return refuses(m) if m.param2 == float(APM_GUIDED_NOGPS) else int(ACCEPTED)

    return answer


async def ardupilot(start: Start, results: dict[int, Any], **opts: Any) -> Flight:
    return await start(autopilot=ARDUPILOT, custom_mode=APM_STABILIZE, engage="auto",
                       output="rates", params={"GUID_OPTIONS": 8.0}, results=results,
                       **opts)  # fmt: skip


def commanding_began(f: Flight, monkeypatch: pytest.MonkeyPatch) -> list[float]:
    """When each engagement begins commanding, on its clock: ``arm_timeout_s``
    counts from there."""
    core = f.companion.core
    begin = core.begin_commanding
    began: list[float] = []

    def noted() -> None:
        began.append(f.clock())
        begin()

    monkeypatch.setattr(core, "begin_commanding", noted)
    return began


def feed(f: Flight) -> Callable[[], None]:
    def send() -> None:
        f.att()
        f.fake.rc(1000)

    return send


async def test_ardupilot_refusing_to_arm_after_boot_is_tried_again_until_it_arms(
    start: Start,
) -> None:
    ref: list[Flight] = []
    arm = Refuses(ref, 2, (b"Arm: Need Alt Estimate",))
    f = await ardupilot(start, {CMD_ARM: arm})
    ref.append(f)
    await streams_requested(f, MSG_ATTITUDE)
    await f.feed_until(lambda: len(arm.at) == 3, send=feed(f), timeout_s=5.0, what="3 ARMs")
    f.fake.set_state(APM_GUIDED_NOGPS, armed=True)
    await f.feed_until(lambda: f.companion.engaged, send=feed(f), what="engaged")
    assert f.details("arm_refused") == [
        f"try 1: MAV_RESULT {FAILED}: Arm: Need Alt Estimate",
        f"try 2: MAV_RESULT {FAILED}: Arm: Need Alt Estimate",
    ]
    assert "engage_failed" not in f.kinds()
    assert not f.task.done()
    for before, after in itertools.pairwise(arm.at):  # the reason's wait, then the retry's
        assert after - before == pytest.approx(engagement._REASON_WAIT_S + RETRY_S)


async def test_an_arm_refused_until_the_bound_exits_1_naming_the_stacks_last_reason(
    start: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    ref: list[Flight] = []
    arm = Refuses(ref, 1000, (b"PreArm: Need Position Estimate",))
    f = await ardupilot(start, {CMD_ARM: arm}, arm_timeout_s=1.0)
    ref.append(f)
    began = commanding_began(f, monkeypatch)
    await streams_requested(f, MSG_ATTITUDE)
    await f.feed_until(f.task.done, send=feed(f), timeout_s=5.0, what="the run's end")
    assert await f.finish() == 1
    [bound] = [t + 1.0 for t in began]
    assert len(arm.at) >= 2
    period = engagement._REASON_WAIT_S + RETRY_S
    assert [b - a for a, b in itertools.pairwise(arm.at)] == pytest.approx(
        [period] * (len(arm.at) - 1)
    )
    assert arm.at[-1] < bound <= arm.at[-1] + period  # tried within the bound, then no more
    refused = f.details("arm_refused")
    assert refused == [
        f"try {i}: MAV_RESULT {FAILED}: PreArm: Need Position Estimate"
        for i in range(1, len(arm.at) + 1)
    ]
    [failed] = f.details("engage_failed")
    assert failed.startswith(f"ardupilot refused to arm (MAV_RESULT {FAILED}), {len(arm.at)} tries")
    assert failed.endswith(": PreArm: Need Position Estimate")
    assert "SaveWaypoint" not in failed
    assert "engaged" not in f.kinds()


async def test_a_refusal_without_a_reason_says_so_rather_than_quote_another_text(
    start: Start,
) -> None:
    ref: list[Flight] = []
    arm = Refuses(ref, 1000, ())  # only the unrelated text follows the refusal
    f = await ardupilot(start, {CMD_ARM: arm}, arm_timeout_s=0.0)
    ref.append(f)
    await streams_requested(f, MSG_ATTITUDE)
    await f.feed_until(f.task.done, send=feed(f), timeout_s=3.0, what="the run's end")
    assert await f.finish() == 1
    assert len(arm.at) == 1  # --arm-timeout-s 0: one try
    [failed] = f.details("engage_failed")
    assert failed.startswith(f"ardupilot refused to arm (MAV_RESULT {FAILED}), 1 try in ")
    assert failed.endswith(": it said no reason")


async def test_px4s_refusal_is_quoted_from_its_preflight_fail_and_arming_denied(
    start: Start,
) -> None:
    ref: list[Flight] = []
    # Both as PX4 v1.16 words them (each within one 50-character STATUSTEXT).
    said = (b"Preflight Fail: ekf2 missing data\t", b"Arming denied: switch to manual mode first\t")
    arm = Refuses(ref, 1000, said, result=DENIED)
    f = await start(engage="auto", output="actuator", results={CMD_ARM: arm}, arm_timeout_s=0.0)
    ref.append(f)
    await streams_requested(f)
    f.fake.rc(1000)  # the pilot's input: an auto engagement waits for it
    await f.feed_until(f.task.done, timeout_s=3.0, what="the run's end")
    assert await f.finish() == 1
    [failed] = f.details("engage_failed")
    assert failed.startswith(f"px4 refused to arm (MAV_RESULT {DENIED}), 1 try in ")
    assert failed.endswith(
        ": Preflight Fail: ekf2 missing data; Arming denied: switch to manual mode first"
    )


async def test_arming_waits_for_the_stacks_pre_arm_checks_to_pass(start: Start) -> None:
    f = await start(engage="auto", output="actuator")
    await streams_requested(f)
    ready = False

    def sample_and_status() -> None:
        f.imu()
        f.fake.rc(1000)
        f.fake.sys_status(prearm=ready)

    await f.feed_until(
        lambda: "arm_waiting" in f.kinds(), send=sample_and_status, what="the wait to arm"
    )
    t_wait = f.clock()
    await f.feed_until(
        lambda: f.clock() - t_wait >= 0.5, send=sample_and_status, what="0.5 s of the wait"
    )
    assert not f.fake.commands(CMD_ARM)  # not while the checks fail
    [waiting] = f.details("arm_waiting")
    assert waiting.startswith("the autopilot's pre-arm checks do not pass yet (SYS_STATUS)")
    ready = True
    await f.feed_until(lambda: f.fake.commands(CMD_ARM), send=sample_and_status, what="ARM")
    f.fake.set_state(PX4_OFFBOARD, armed=True)
    await f.feed_until(lambda: f.companion.engaged, send=sample_and_status, what="engaged")
    assert "arm_refused" not in f.kinds()
    assert [d.split(" after ")[0] for d in f.details("arm_ready")] == ["pre-arm checks pass"]


async def test_pre_arm_checks_that_never_pass_end_in_one_try_at_the_bound(
    start: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The stack's own words say why: the arming is tried once the bound is reached."""
    ref: list[Flight] = []
    arm = Refuses(ref, 1000, (b"PreArm: Need Position Estimate",))
    f = await ardupilot(start, {CMD_ARM: arm}, arm_timeout_s=1.0)
    ref.append(f)
    began = commanding_began(f, monkeypatch)
    await streams_requested(f, MSG_ATTITUDE)

    def not_ready() -> None:
        feed(f)()
        f.fake.sys_status(prearm=False)

    await f.feed_until(f.task.done, send=not_ready, timeout_s=5.0, what="the run's end")
    assert await f.finish() == 1
    [bound] = [t + 1.0 for t in began]
    assert len(arm.at) == 1
    assert bound <= arm.at[0] < bound + engagement._READY_POLL_S  # on the wait's first poll past it
    [failed] = f.details("engage_failed")
    assert failed.endswith(": PreArm: Need Position Estimate")


async def test_a_stack_that_does_not_report_its_pre_arm_checks_is_just_tried(
    start: Start,
) -> None:
    """The fake's SYS_STATUS without the pre-arm bit (the bundled SITL's too)."""
    f = await start(engage="auto", output="actuator")
    await streams_requested(f)

    def sample_and_status() -> None:
        f.imu()
        f.fake.rc(1000)
        f.fake.sys_status()

    await f.feed_until(lambda: f.fake.commands(CMD_ARM), send=sample_and_status, what="ARM")
    assert "arm_waiting" not in f.kinds()


async def test_ardupilot_refusing_guided_nogps_for_a_while_is_tried_again(start: Start) -> None:
    ref: list[Flight] = []
    answer = mode_refused(ref, 2, b"Mode change to GUIDED_NOGPS failed: init failed")
    f = await ardupilot(start, {CMD_DO_SET_MODE: answer})
    ref.append(f)
    await streams_requested(f, MSG_ATTITUDE)
    await f.feed_until(lambda: f.fake.commands(CMD_ARM), send=feed(f), timeout_s=5.0, what="ARM")
    assert len(f.fake.commands(CMD_DO_SET_MODE)) == 3
    assert f.details("engage_mode_refused") == [
        f"try {i}: MAV_RESULT {FAILED}: Mode change to GUIDED_NOGPS failed: init failed"
        for i in (1, 2)
    ]
    f.fake.set_state(APM_GUIDED_NOGPS, armed=True)
    await f.feed_until(lambda: f.companion.engaged, send=feed(f), what="engaged")


def lost_ack(fake_ref: list[Flight], *, arms: bool) -> Callable[[Any], None]:
    """ARM: no ACK ever comes back; the vehicle arms all the same when ``arms``
    (an ACK lost on the way back), or stays disarmed (the command lost)."""

    def answer(m: Any) -> None:
        if arms:
            fake_ref[0].fake.set_state(APM_GUIDED_NOGPS, armed=True)

    return answer


async def test_an_arm_whose_ack_is_lost_counts_when_the_heartbeat_shows_it_armed(
    start: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A loaded lockstep SITL answered the arming late, after the companion's
    last resend: it had armed, and the companion, taking the missing ACK for
    the end, left it flying its setpoints' loss failsafe."""
    monkeypatch.setattr(engagement, "_ACK_TIMEOUT_S", 0.02)
    ref: list[Flight] = []
    f = await ardupilot(start, {CMD_ARM: lost_ack(ref, arms=True)})
    ref.append(f)
    await streams_requested(f, MSG_ATTITUDE)
    await f.feed_until(lambda: f.companion.engaged, send=feed(f), timeout_s=5.0, what="engaged")
    # The link's own resends, none answered, and the heartbeat's word after them:
    await f.feed_until(
        lambda: len(f.fake.commands(CMD_ARM)) == 4, send=feed(f), timeout_s=5.0, what="4 ARMs"
    )
    fed = itertools.count()
    await f.feed_until(lambda: next(fed) == 100, send=feed(f), what="100 samples more")
    assert len(f.fake.commands(CMD_ARM)) == 4
    assert "arm_refused" not in f.kinds()
    assert "engage_failed" not in f.kinds()
    assert not f.task.done()


async def test_an_arm_never_answered_is_tried_again_until_the_bound_then_exits_1(
    start: Start, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(engagement, "_ACK_TIMEOUT_S", 0.02)
    ref: list[Flight] = []
    f = await ardupilot(start, {CMD_ARM: lost_ack(ref, arms=False)}, arm_timeout_s=1.0)
    ref.append(f)
    await streams_requested(f, MSG_ATTITUDE)
    await f.feed_until(f.task.done, send=feed(f), timeout_s=5.0, what="the run's end")
    assert await f.finish() == 1
    refused = f.details("arm_refused")
    assert len(refused) >= 2  # tried again, as a refusal is
    assert all(r.startswith(f"try {i}: no ACK: ") for i, r in enumerate(refused, 1))
    assert all("no COMMAND_ACK for command 400" in r for r in refused)
    [failed] = f.details("engage_failed")
    assert failed.startswith(f"ardupilot refused to arm (no ACK), {len(refused)} tries in ")
    assert "engaged" not in f.kinds()
