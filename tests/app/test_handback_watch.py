"""The hand-back on the product path: which mode a running companion asks for,
how it watches the autopilot's mode afterwards, and what it tries next.

Each test drives a Companion against the fake autopilot (tests/app/flight.py)
and checks the DO_SET_MODE sequence (param2, param3), the events, and where the
rule is about time, when each mode was asked, on the engagement's own clock
(``Flight.clock``, tests/app/flight.py: it counts the watch's polls, so these
times are exact on any machine, however loaded). The choice itself is
unit-tested in ``test_handback_choice.py``.
"""

from __future__ import annotations

import asyncio
import itertools
from dataclasses import replace
from types import SimpleNamespace
from typing import Any

import pytest

from companion import engagement
from tests.app.fakes import (
    APM_ALT_HOLD,
    APM_GUIDED_NOGPS,
    APM_STABILIZE,
    CMD_ARM,
    CMD_DO_SET_MODE,
    PX4_MANUAL,
    PX4_OFFBOARD,
    PX4_POSCTL,
    mavlink2,
)
from tests.app.flight import (
    ACCEPTED,
    ARDUPILOT,
    DENIED,
    LOOSE,
    MSG_ATTITUDE,
    MSG_HIGHRES_IMU,
    Flight,
    Start,
    StepClock,
    engage_px4_auto,
    streams_requested,
)

# DO_SET_MODE (param2, param3).
OFFBOARD = (6.0, 0.0)
POSCTL = (3.0, 0.0)
ALTCTL = (2.0, 0.0)
HOLD = (4.0, 3.0)  # AUTO.LOITER
LAND = (4.0, 6.0)  # AUTO.LAND
GUIDED_NOGPS = (20.0, 0.0)
APM_LOITER = (5.0, 0.0)
APM_LAND = (9.0, 0.0)
MANUAL_MAIN_MODES = {1.0, 2.0, 3.0, 5.0, 7.0}  # PX4 MANUAL, ALTCTL, POSCTL, ACRO, STABILIZED

# HEARTBEAT custom_mode (PX4: main mode bits 16-23, sub mode bits 24-31).
PX4_RTL = 4 << 16 | 5 << 24
PX4_LAND = 4 << 16 | 6 << 24
ARMED = mavlink2.MAV_MODE_FLAG_SAFETY_ARMED
CRITICAL = mavlink2.MAV_STATE_CRITICAL
FAILING_SAFE = "valid RC, a position estimate, the autopilot failing safe (CRITICAL)"

POLL_S = engagement._WATCH_POLL_S
SOON_S = 10 * POLL_S
"""A mode lost is judged on the watch's next polls (the heartbeat that shows it
takes a few turns of the loop to reach the core): this soon, not at the watch's end."""
# A watch that sees at least two of the fake's 0.2 s background heartbeats.
WATCHED = replace(LOOSE, hand_back_watch_s=0.5)


class Modes:
    """The fake's answer to DO_SET_MODE: ACCEPTED, DENIED for ``refuse``; each
    (param2, param3) asked is kept with the time it arrived on ``clock`` (the
    engagement's: give it to ``start``)."""

    def __init__(self, refuse: tuple[tuple[float, float], ...] = ()) -> None:
        self.refuse = refuse
        self.clock = StepClock()
        self.asked: list[tuple[float, tuple[float, float]]] = []

    def __call__(self, m: Any) -> int:
        mode = (m.param2, m.param3)
        self.asked.append((self.clock(), mode))
        return int(DENIED if mode in self.refuse else ACCEPTED)

    def at(self, mode: tuple[float, float]) -> float:
        """When ``mode`` was asked (the last time)."""
        return [t for t, m in self.asked if m == mode][-1]


def asked(f: Flight) -> list[tuple[float, float]]:
    """Every DO_SET_MODE the fake received, as (param2, param3), in order."""
    return [(m.param2, m.param3) for m in f.fake.commands(CMD_DO_SET_MODE)]


async def event(f: Flight, kind: str, timeout_s: float = 2.0) -> str:
    """Wait for the first event of ``kind``; its detail."""
    await f.fake.wait_until(lambda: kind in f.kinds(), timeout_s)
    return f.details(kind)[0]


async def engage_with_rc(f: Flight) -> None:
    """``engage_px4_auto`` with RC sent with every sample, so that a short RC
    timeout cannot expire while the engagement is under way."""
    await streams_requested(f)

    def sample_and_rc() -> None:
        f.imu()
        f.fake.rc(1000)

    await f.feed_until(lambda: f.fake.commands(CMD_ARM), send=sample_and_rc, what="ARM")
    f.fake.set_state(PX4_OFFBOARD, armed=True)
    await f.feed_until(lambda: f.companion.engaged, send=sample_and_rc, what="engaged")


async def stopped_without_rc(f: Flight, *, imu: int = MSG_HIGHRES_IMU) -> None:
    """``--engage auto``: one RC frame (an auto engagement waits for the pilot's
    input), setpoints, the engage mode (the fake shows it) and ARM; then the RC is
    gone and the run ends before the autopilot shows itself armed, and then it
    does, so the run's hand-back flies an armed vehicle without RC.

    (Engaged with no valid RC, the RC-lost failsafe fires within one supervisor
    tick: a run's end without RC can only be this one.)"""
    await streams_requested(f, imu)
    send = f.imu if imu == MSG_HIGHRES_IMU else f.att
    f.fake.rc(1000)
    await f.feed_until(lambda: f.fake.commands(CMD_ARM), send=send, what="ARM")
    pilot = f.companion.core.pilot
    pilot.last_valid = pilot.last_radio = None  # the radio is gone
    f.companion._stop.set()  # the run ends: nothing engages after this
    f.fake.set_state(armed=True)


# ------------------------------------------------------------ PX4, the run's end


async def test_run_end_with_valid_rc_and_a_position_hands_back_to_posctl(start: Start) -> None:
    f = await start(engage="auto", output="actuator", failsafe=WATCHED)
    await engage_px4_auto(f)  # RC sent, LOOSE's 5 s RC timeout: valid
    f.companion._stop.set()
    assert await f.finish() == 0
    assert asked(f) == [OFFBOARD, POSCTL]
    assert f.details("handed_back") == [
        "run ended; valid RC, a position estimate -> POSCTL accepted"
    ]
    assert f.details("safe_mode_held") == ["POSCTL for 0.5 s"]
    assert "safe_mode_lost" not in f.kinds()


async def test_run_end_without_rc_holds_position(start: Start) -> None:
    f = await start(engage="auto", output="actuator", failsafe=WATCHED)
    await stopped_without_rc(f)
    assert await f.finish() == 0
    assert asked(f) == [OFFBOARD, HOLD]
    assert f.details("handed_back") == [
        "run ended; no valid RC, a position estimate (posctl needs RC (none valid); "
        "altctl needs RC (none valid)) -> HOLD accepted"
    ]
    assert f.details("safe_mode_held") == ["HOLD for 0.5 s"]


async def test_run_end_without_rc_or_a_position_lands(start: Start) -> None:
    f = await start(engage="auto", output="actuator", failsafe=WATCHED, position=False)
    await stopped_without_rc(f)
    assert await f.finish() == 0
    assert asked(f) == [OFFBOARD, LAND]
    assert f.details("handed_back") == [
        "run ended; no valid RC, no position estimate (posctl needs RC (none valid); "
        "altctl needs RC (none valid); hold needs a position estimate (none)) -> LAND accepted"
    ]
    assert f.details("safe_mode_held") == ["LAND for 0.5 s"]


# ------------------------------------------------------------------- RC loss


async def test_rc_loss_hands_back_to_hold_never_a_manual_mode(start: Start) -> None:
    fs = replace(WATCHED, rc_timeout_s=0.3)
    f = await start(engage="auto", output="actuator", failsafe=fs)
    await engage_with_rc(f)
    await f.feed_until(lambda: "failsafe_rc_lost" in f.kinds(), what="the RC-lost failsafe")

    def sample_and_rc_back() -> None:  # the radio comes back during the hand-back
        f.imu()
        f.fake.rc(1000)

    await f.feed_until(
        lambda: "safe_mode_held" in f.kinds(), send=sample_and_rc_back, what="the watch's end"
    )
    assert await f.finish() == 3
    assert asked(f) == [OFFBOARD, HOLD]
    assert not [m for m in asked(f) if m[0] in MANUAL_MAIN_MODES]
    [detail] = f.details("handed_back")
    assert detail.startswith("no valid RC for 0.3 s")
    assert detail.endswith(
        "; RC lost, a position estimate (posctl needs RC (the failsafe is RC loss); "
        "altctl needs RC (the failsafe is RC loss)) -> HOLD accepted"
    )
    assert f.details("safe_mode_held") == ["HOLD for 0.5 s"]


# ------------------------------------------------------------------- refusals


async def test_a_refused_hold_is_followed_by_land_at_once(start: Start) -> None:
    fs = replace(LOOSE, hand_back_watch_s=1.0)
    modes = Modes(refuse=(HOLD,))
    f = await start(engage="auto", output="actuator", failsafe=fs, clock=modes.clock,
                    results={CMD_DO_SET_MODE: modes})  # fmt: skip
    await stopped_without_rc(f)
    assert await f.finish() == 0
    assert asked(f) == [OFFBOARD, HOLD, LAND]
    assert f.details("handed_back") == [
        "run ended; no valid RC, a position estimate (posctl needs RC (none valid); "
        f"altctl needs RC (none valid)) -> HOLD refused ({DENIED})",
        "HOLD refused; no valid RC, a position estimate -> LAND accepted",
    ]
    assert f.details("safe_mode_held") == ["LAND for 1 s"]
    assert "safe_mode_lost" not in f.kinds()
    # A refusal is not watched: LAND follows at once (no wait between), not after the 1 s watch.
    assert modes.at(LAND) == modes.at(HOLD)


# ----------------------------------------------- the autopilot after accepting


async def test_the_autopilots_own_rtl_after_posctl_is_lost_and_hold_follows(
    start: Start,
) -> None:
    """POSCTL accepted with valid RC; the radio goes, and PX4's own failsafe takes
    the vehicle to AUTO.RTL within the watch: POSCTL is lost, and with no valid
    RC left the next mode is HOLD (a manual one would meet the same failsafe)."""
    fs = replace(LOOSE, rc_timeout_s=0.4, hand_back_watch_s=1.5)
    modes = Modes()
    f = await start(engage="auto", output="actuator", failsafe=fs, clock=modes.clock,
                    results={CMD_DO_SET_MODE: modes})  # fmt: skip
    await engage_with_rc(f)
    f.companion._stop.set()  # the RC frames stop with the samples
    await event(f, "handed_back")
    assert f.details("handed_back")[0].endswith("-> POSCTL accepted")
    await asyncio.sleep(0.4 + 0.25)  # valid RC expires (the wall's); the watch (1.5 s) goes on
    t_rtl = f.clock()
    assert t_rtl - modes.at(POSCTL) < 1.5 - SOON_S  # (its clock is never ahead of the wall's)
    f.fake.set_state(PX4_RTL)
    lost = await event(f, "safe_mode_lost")
    assert lost.startswith("the autopilot left POSCTL for AUTO.RTL after ")
    assert await f.finish(timeout_s=4.0) == 0
    assert asked(f) == [OFFBOARD, POSCTL, HOLD]
    assert 0.0 < modes.at(HOLD) - t_rtl < SOON_S  # judged on the next polls, not the watch's end
    assert f.details("handed_back")[1] == (
        f"{lost}; no valid RC, a position estimate -> HOLD accepted"
    )
    assert f.details("safe_mode_held") == ["HOLD for 1.5 s"]


async def test_the_autopilot_landing_after_posctl_is_kept(start: Start) -> None:
    """LAND is a later candidate than POSCTL: what the companion would have tried
    next, so the watch ends there and nothing more is asked."""
    fs = replace(LOOSE, hand_back_watch_s=2.0)
    f = await start(engage="auto", output="actuator", failsafe=fs)
    await engage_px4_auto(f)
    f.companion._stop.set()
    await event(f, "handed_back")
    assert f.details("handed_back")[0].endswith("-> POSCTL accepted")
    f.fake.set_state(PX4_LAND)
    assert await f.finish() == 0
    assert asked(f) == [OFFBOARD, POSCTL]
    # The watch ended on LAND: at its 2 s bound it would say "POSCTL for 2 s".
    [held] = f.details("safe_mode_held")
    assert held.startswith("LAND kept after ")
    assert "safe_mode_lost" not in f.kinds()


async def test_a_mode_accepted_but_never_shown_is_followed_by_the_next_after_the_watch(
    start: Start,
) -> None:
    watch_s = 0.5
    modes = Modes()
    f = await start(engage="auto", output="actuator", follow_modes=False, failsafe=WATCHED,
                    clock=modes.clock, results={CMD_DO_SET_MODE: modes})  # fmt: skip
    await engage_px4_auto(f)  # the fake stays in OFFBOARD from here on
    f.companion._stop.set()
    assert await f.finish(timeout_s=5.0) == 0
    # Valid RC and a position all along: one candidate of each kind in turn (after
    # POSCTL failed, another manual mode is passed over), then none left.
    assert asked(f) == [OFFBOARD, POSCTL, HOLD, LAND]
    times = [t for t, _ in modes.asked[1:]]
    for before, after in itertools.pairwise(times):  # each after the whole watch, to its poll
        assert watch_s - 1e-9 <= after - before < watch_s + POLL_S + 1e-9
    never = "the autopilot accepted {} but did not show it within 0.5 s"
    lost = [never.format(m) for m in ("POSCTL", "HOLD", "LAND")]
    assert f.details("safe_mode_lost") == lost
    assert f.details("handed_back") == [
        "run ended; valid RC, a position estimate -> POSCTL accepted",
        f"{never.format('POSCTL')}; valid RC, a position estimate -> HOLD accepted",
        f"{never.format('HOLD')}; valid RC, a position estimate -> LAND accepted",
    ]
    assert f.details("hand_back_failed") == [f"{never.format('LAND')}; no safe mode left"]
    assert "safe_mode_held" not in f.kinds()


async def test_a_disarm_during_the_watch_ends_it(start: Start) -> None:
    fs = replace(LOOSE, hand_back_watch_s=2.0)
    f = await start(engage="auto", output="actuator", failsafe=fs)
    await engage_px4_auto(f)
    f.companion._stop.set()
    await event(f, "handed_back")
    f.fake.set_state(armed=False)  # landed and disarmed in POSCTL
    assert await f.finish() == 0
    assert asked(f) == [OFFBOARD, POSCTL]
    # The watch ended on the disarm: at its 2 s bound it would say "POSCTL for 2 s".
    [held] = f.details("safe_mode_held")
    assert held.startswith("disarmed after ")
    assert "safe_mode_lost" not in f.kinds()


# ------------------------------------------------------------------ ArduPilot


@pytest.mark.parametrize(
    ("position", "mode", "name", "detail"),
    [
        pytest.param(
            True,
            APM_LOITER,
            "LOITER",
            "run ended; no valid RC, a position estimate (alt_hold needs RC (none valid)) "
            "-> LOITER accepted",
            id="position-loiter",
        ),
        pytest.param(
            False,
            APM_LAND,
            "LAND",
            "run ended; no valid RC, no position estimate (alt_hold needs RC (none valid); "
            "loiter needs a position estimate (none)) -> LAND accepted",
            id="no-position-land",
        ),
    ],
)
async def test_ardupilot_without_rc_loiters_with_a_position_else_lands(
    start: Start, position: bool, mode: tuple[float, float], name: str, detail: str
) -> None:
    f = await start(autopilot=ARDUPILOT, custom_mode=APM_STABILIZE, engage="auto",
                    output="rates", params={"GUID_OPTIONS": 8.0}, failsafe=WATCHED,
                    position=position)  # fmt: skip
    await stopped_without_rc(f, imu=MSG_ATTITUDE)
    assert await f.finish() == 0
    assert asked(f) == [GUIDED_NOGPS, mode]
    assert f.details("handed_back") == [detail]
    assert f.details("safe_mode_held") == [f"{name} for 0.5 s"]


# ----------------------------------------------------------- --safe-mode named


async def test_a_named_posctl_without_rc_is_passed_over_for_hold(start: Start) -> None:
    f = await start(engage="auto", output="actuator", failsafe=replace(WATCHED, safe_mode="posctl"))
    await stopped_without_rc(f)
    assert await f.finish() == 0
    assert asked(f) == [OFFBOARD, HOLD]
    assert f.details("handed_back") == [
        "run ended; no valid RC, a position estimate (posctl needs RC (none valid)) "
        "-> HOLD accepted"
    ]


# ------------------------------------------------- the autopilot took over itself


async def test_the_autopilot_leaving_offboard_for_land_is_kept(start: Start) -> None:
    f = await start(engage="auto", output="actuator")
    await engage_px4_auto(f)
    f.fake.set_state(PX4_LAND, armed=True)  # its own failsafe: AUTO.LAND
    assert await f.finish() == 3
    assert "failsafe_autopilot_took_over" in f.kinds()
    assert asked(f) == [OFFBOARD]  # nothing asked after OFFBOARD
    assert f.details("handed_back") == [
        f"autopilot left OFFBOARD for LAND (mode {PX4_LAND:#x}, armed=True); valid RC, a position "
        "estimate -> LAND kept (the autopilot's mode)"
    ]
    assert not {"safe_mode_held", "safe_mode_lost"} & set(f.kinds())  # adopted, not watched


async def test_the_autopilot_leaving_offboard_for_manual_without_rc_is_not_kept(
    start: Start,
) -> None:
    f = await start(engage="auto", output="actuator", failsafe=WATCHED)
    await engage_px4_auto(f)
    # No valid RC and the autopilot in MANUAL, in one step: with anything in
    # between, the supervisor would call the missing RC an RC-lost failsafe.
    f.fake.custom_mode = PX4_MANUAL  # its later heartbeats say the same
    f.companion.core.pilot.last_valid = None
    f.companion.core.on_heartbeat(
        SimpleNamespace(custom_mode=PX4_MANUAL, base_mode=ARMED, system_status=4)
    )
    assert await f.finish() == 3
    assert "failsafe_autopilot_took_over" in f.kinds()
    assert "failsafe_rc_lost" not in f.kinds()
    assert asked(f) == [OFFBOARD, HOLD]
    assert f.details("handed_back") == [
        f"autopilot left OFFBOARD for MANUAL (mode {PX4_MANUAL:#x}, armed=True); no valid RC, "
        "a position estimate (posctl needs RC (none valid); altctl needs RC (none valid)) "
        "-> HOLD accepted"
    ]
    assert f.details("safe_mode_held") == ["HOLD for 0.5 s"]


# ------------------------------------------- real stacks: the HEARTBEAT after the ACK


def shown_late(f_ref: list[Flight], delay_s: float = 0.2) -> Any:
    """DO_SET_MODE answered as PX4 does: ACK now, the new mode in a HEARTBEAT a
    little later (the fake's ``follow_modes`` shows it at once)."""

    def answer(m: Any) -> int:
        if (m.param2, m.param3) != OFFBOARD:
            mode = (int(m.param2) << 16) | (int(m.param3) << 24)
            asyncio.get_running_loop().call_later(delay_s, f_ref[0].fake.set_state, mode)
        return int(ACCEPTED)

    return answer


async def test_a_heartbeat_from_before_the_switch_is_not_the_autopilot_leaving_it(
    start: Start,
) -> None:
    """The autopilot took the vehicle to MANUAL with no RC: HOLD is asked. A
    heartbeat still showing MANUAL after the ACK was sent before the switch: the
    watch waits for HOLD to show rather than call HOLD lost (found in review: it
    landed the vehicle and logged the hand-back as failed)."""
    ref: list[Flight] = []
    f = await start(engage="auto", output="actuator", follow_modes=False, failsafe=WATCHED,
                    results={CMD_DO_SET_MODE: shown_late(ref)})  # fmt: skip
    ref.append(f)
    await engage_px4_auto(f)
    f.fake.custom_mode = PX4_MANUAL  # the fake's background heartbeats show it from now on
    f.companion.core.pilot.last_valid = None
    f.companion.core.on_heartbeat(
        SimpleNamespace(custom_mode=PX4_MANUAL, base_mode=ARMED, system_status=4)
    )
    assert await f.finish(timeout_s=3.0) == 3
    assert asked(f) == [OFFBOARD, HOLD]
    assert "safe_mode_lost" not in f.kinds()
    assert f.details("safe_mode_held") == ["HOLD for 0.5 s"]


async def test_an_unanswered_failsafe_hand_back_is_tried_again_at_the_runs_end(
    start: Start,
) -> None:
    """The failsafe's switch goes unanswered three times (the command's retries):
    the run's end tries again rather than leave the autopilot in OFFBOARD
    (found in review; so before this change too)."""
    tries: list[tuple[float, float]] = []

    def first_three_lost(m: Any) -> int | None:
        if (m.param2, m.param3) != OFFBOARD:
            tries.append((m.param2, m.param3))
            if len(tries) <= 3:
                return None
        return int(ACCEPTED)

    f = await start(engage="auto", output="actuator", failsafe=WATCHED,
                    results={CMD_DO_SET_MODE: first_three_lost})  # fmt: skip
    await engage_px4_auto(f)
    f.companion.core.failsafe("failsafe_envelope", "a test's failsafe")
    assert await f.finish(timeout_s=5.0) == 3
    assert len(tries) == 4
    details = f.details("handed_back")
    assert "mode switch unanswered" in details[0]
    assert details[1].startswith("run ended;") and details[1].endswith("accepted")
    assert f.fake.custom_mode != PX4_OFFBOARD


async def test_a_watch_of_zero_takes_the_ack_alone(start: Start) -> None:
    """``--hand-back-watch-s 0``: no watch, so no mode is called unshown at once."""
    f = await start(engage="auto", output="actuator", follow_modes=False,
                    failsafe=replace(LOOSE, hand_back_watch_s=0.0))  # fmt: skip
    await engage_px4_auto(f)
    f.companion._stop.set()
    assert await f.finish() == 0
    assert asked(f) == [OFFBOARD, POSCTL]
    assert "safe_mode_lost" not in f.kinds() and "hand_back_failed" not in f.kinds()


# ------------------------------------------------ the autopilot's own failsafe


async def test_px4_failing_safe_in_posctl_loses_it_and_hold_follows(start: Start) -> None:
    """PX4 without its own stick input keeps showing POSCTL but fails safe in it
    (HEARTBEAT system_status CRITICAL, "Failsafe activated", a descent): POSCTL is
    lost, and the next mode is HOLD (another manual mode would fail the same way).
    HOLD is kept though PX4 still says CRITICAL: holding is what its failsafe does."""
    fs = replace(LOOSE, hand_back_watch_s=1.5)
    modes = Modes()
    f = await start(engage="auto", output="actuator", failsafe=fs, clock=modes.clock,
                    results={CMD_DO_SET_MODE: modes})  # fmt: skip
    await engage_px4_auto(f)  # RC sent, LOOSE's 5 s RC timeout: valid all along
    f.companion._stop.set()
    await event(f, "handed_back")
    assert (
        f.details("handed_back")[0] == "run ended; valid RC, a position estimate -> POSCTL accepted"
    )
    await asyncio.sleep(0.3)  # POSCTL shows, PX4 not failing safe yet
    t_failsafe = f.clock()
    assert t_failsafe - modes.at(POSCTL) < 1.5 - SOON_S  # the watch goes on
    f.fake.system_status = CRITICAL  # its heartbeats say so from now on, POSCTL still shown
    f.fake.statustext(b"Failsafe activated", mavlink2.MAV_SEVERITY_CRITICAL)
    f.fake.heartbeat()
    lost = await event(f, "safe_mode_lost")
    assert lost.startswith("the autopilot is failing safe (CRITICAL) in POSCTL after ")
    assert await f.finish(timeout_s=4.0) == 0
    assert asked(f) == [OFFBOARD, POSCTL, HOLD]
    assert 0.0 < modes.at(HOLD) - t_failsafe < SOON_S  # on the next polls, not the watch's end
    assert f.details("handed_back")[1] == f"{lost}; {FAILING_SAFE} -> HOLD accepted"
    assert f.details("safe_mode_held") == ["HOLD for 1.5 s"]
    assert f.details("autopilot_failsafe") == ["system status CRITICAL"]


def px4_without_sticks(f_ref: list[Flight], failsafe_after_s: float) -> Any:
    """DO_SET_MODE answered as PX4 v1.16 without its own stick input: any manual
    mode is accepted and shown as POSCTL, and ``failsafe_after_s`` later its
    heartbeat says CRITICAL (in the same heartbeat with 0); hold and land show as
    asked. OFFBOARD is left to the test (``follow_modes=False``)."""

    def answer(m: Any) -> int:
        fake = f_ref[0].fake
        asked_mode = (m.param2, m.param3)
        if asked_mode == OFFBOARD:
            return int(ACCEPTED)
        if m.param2 in MANUAL_MAIN_MODES:

            def failing() -> None:
                fake.system_status = CRITICAL
                fake.heartbeat()

            fake.custom_mode = PX4_POSCTL
            if failsafe_after_s <= 0.0:
                fake.system_status = CRITICAL
            else:
                asyncio.get_running_loop().call_later(failsafe_after_s, failing)
        else:
            fake.custom_mode = (int(m.param2) << 16) | (int(m.param3) << 24)
        asyncio.get_running_loop().call_soon(fake.heartbeat)  # after the ACK, as PX4 does
        return int(ACCEPTED)

    return answer


@pytest.mark.parametrize("failsafe_after_s", [0.0, 0.4], ids=["at-once", "a-moment-later"])
async def test_a_named_altctl_px4_shows_as_posctl_while_failing_safe_is_lost(
    start: Start, failsafe_after_s: float
) -> None:
    """``--safe-mode altctl`` on a PX4 without its own stick input: it shows POSCTL
    and fails safe. Not the pilot's choice of POSCTL (valid RC is seen): the
    autopilot's failsafe, whether it says so with the mode or a moment after."""
    ref: list[Flight] = []
    fs = replace(LOOSE, safe_mode="altctl", hand_back_watch_s=1.0)
    answer = px4_without_sticks(ref, failsafe_after_s)
    f = await start(engage="auto", output="actuator", follow_modes=False, failsafe=fs,
                    results={CMD_DO_SET_MODE: answer})  # fmt: skip
    ref.append(f)
    await engage_px4_auto(f)
    f.companion._stop.set()
    assert await f.finish(timeout_s=4.0) == 0
    assert asked(f) == [OFFBOARD, ALTCTL, HOLD]
    [lost] = f.details("safe_mode_lost")
    assert lost.startswith("the autopilot is failing safe (CRITICAL) in POSCTL after ")
    assert f.details("handed_back") == [
        "run ended; valid RC, a position estimate -> ALTCTL accepted",
        f"{lost}; {FAILING_SAFE} -> HOLD accepted",
    ]
    assert f.details("safe_mode_held") == ["HOLD for 1 s"]


async def test_no_manual_mode_is_chosen_while_the_autopilot_already_fails_safe(
    start: Start,
) -> None:
    f = await start(engage="auto", output="actuator", failsafe=WATCHED)
    await engage_px4_auto(f)
    f.fake.system_status = CRITICAL
    f.fake.heartbeat()
    await f.fake.wait_until(lambda: "autopilot_failsafe" in f.kinds(), 1.0)
    f.companion._stop.set()
    assert await f.finish() == 0
    assert asked(f) == [OFFBOARD, HOLD]
    failing = "needs RC (the autopilot is failing safe: CRITICAL)"
    assert f.details("handed_back") == [
        f"run ended; {FAILING_SAFE} (posctl {failing}; altctl {failing}) -> HOLD accepted"
    ]
    assert f.details("safe_mode_held") == ["HOLD for 0.5 s"]


async def test_a_failsafe_state_from_before_the_switch_is_not_held_against_the_new_mode(
    start: Start,
) -> None:
    """A heartbeat sent just before the switch (OFFBOARD, CRITICAL) arrives after
    the ACK; the one that shows POSCTL says ACTIVE: the state judged is the one
    the new mode shows with, so POSCTL is held. (Had that heartbeat said CRITICAL
    too, POSCTL would be lost: a failsafe from before the switch that goes on in
    the new mode is failing safe in it.)"""
    ref: list[Flight] = []

    def answer(m: Any) -> int:
        fake = ref[0].fake
        if (m.param2, m.param3) != OFFBOARD:
            fake.system_status = CRITICAL
            fake.heartbeat()  # the old mode, the old state: sent before the switch

            def switched() -> None:
                fake.system_status = None  # ACTIVE (armed)
                fake.set_state((int(m.param2) << 16) | (int(m.param3) << 24))

            asyncio.get_running_loop().call_later(0.2, switched)
        return int(ACCEPTED)

    f = await start(engage="auto", output="actuator", follow_modes=False, failsafe=WATCHED,
                    results={CMD_DO_SET_MODE: answer})  # fmt: skip
    ref.append(f)
    await engage_px4_auto(f)
    f.companion._stop.set()
    assert await f.finish(timeout_s=3.0) == 0
    assert asked(f) == [OFFBOARD, POSCTL]
    assert "safe_mode_lost" not in f.kinds()
    assert f.details("safe_mode_held") == ["POSCTL for 0.5 s"]


async def test_ardupilot_failing_safe_in_alt_hold_loses_it_and_loiter_follows(
    start: Start,
) -> None:
    """ArduCopter shows CRITICAL while its radio failsafe is active."""
    f = await start(autopilot=ARDUPILOT, custom_mode=APM_STABILIZE, engage="auto",
                    output="rates", params={"GUID_OPTIONS": 8.0},
                    failsafe=replace(LOOSE, hand_back_watch_s=1.0))  # fmt: skip
    await streams_requested(f, MSG_ATTITUDE)
    f.fake.rc(1000)
    await f.feed_until(lambda: f.fake.commands(CMD_ARM), send=f.att, what="ARM")
    f.fake.set_state(APM_GUIDED_NOGPS, armed=True)
    await f.feed_until(lambda: f.companion.engaged, send=f.att, what="engaged")
    f.companion._stop.set()
    await event(f, "handed_back")
    assert f.details("handed_back")[0].endswith("-> ALT_HOLD accepted")
    await asyncio.sleep(0.2)
    f.fake.system_status = CRITICAL
    f.fake.statustext(b"Radio Failsafe", mavlink2.MAV_SEVERITY_WARNING)
    f.fake.heartbeat()  # ALT_HOLD still shown
    lost = await event(f, "safe_mode_lost")
    assert lost.startswith("the autopilot is failing safe (CRITICAL) in ALT_HOLD after ")
    assert await f.finish(timeout_s=4.0) == 0
    assert asked(f) == [GUIDED_NOGPS, (float(APM_ALT_HOLD), 0.0), APM_LOITER]
    assert f.details("safe_mode_held") == ["LOITER for 1 s"]


async def test_the_autopilot_leaving_offboard_for_posctl_while_failing_safe_is_not_kept(
    start: Start,
) -> None:
    """With valid RC, the autopilot's POSCTL would be the pilot's choice and kept;
    shown while it says CRITICAL, it is the autopilot's failsafe: HOLD is asked."""
    f = await start(engage="auto", output="actuator", failsafe=WATCHED)
    await engage_px4_auto(f)
    f.fake.system_status = CRITICAL
    f.fake.set_state(PX4_POSCTL, armed=True)  # one heartbeat: the mode and the state
    assert await f.finish() == 3
    assert "failsafe_autopilot_took_over" in f.kinds()
    assert asked(f) == [OFFBOARD, HOLD]
    failing = "needs RC (the autopilot is failing safe: CRITICAL)"
    assert f.details("handed_back") == [
        f"autopilot left OFFBOARD for POSCTL (mode {PX4_POSCTL:#x}, armed=True); "
        f"{FAILING_SAFE} (posctl {failing}; altctl {failing}) -> HOLD accepted"
    ]
    assert f.details("safe_mode_held") == ["HOLD for 0.5 s"]


async def test_a_hand_back_unanswered_across_a_cut_link_is_tried_again_once_it_is_back(
    start: Start,
) -> None:
    """Found on the real ArduCopter: the link cut for 3 s while engaged, the hand-back
    went unanswered, the companion ended, and ArduCopter stayed in GUIDED_NOGPS with
    nobody flying it. The run's end now waits for the link and hands back then."""
    cut = True

    def while_cut(m: Any) -> int | None:
        return None if cut else int(ACCEPTED)

    f = await start(engage="auto", output="actuator", failsafe=WATCHED)
    await engage_px4_auto(f)
    f.fake.results[CMD_DO_SET_MODE] = while_cut
    task = f.fake._hb_task
    assert task is not None
    task.cancel()  # nothing comes from the autopilot any more
    f.companion.core.failsafe("failsafe_stale_imu", "a test's cut link")
    await asyncio.sleep(3.0)
    assert not f.task.done()  # waiting for the link
    cut = False  # the link is back
    f.fake.heartbeat()
    assert await f.finish(timeout_s=5.0) == 3
    details = f.details("handed_back")
    assert "mode switch unanswered" in details[0]
    assert details[-1].startswith("link back;") and details[-1].endswith("accepted")
    assert f.fake.custom_mode != PX4_OFFBOARD
