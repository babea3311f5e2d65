"""Which safe mode a hand-back asks for, and whether the mode the autopilot then
shows is kept: ``companion/handback.py`` and the stacks' tables
(``companion/stacks.py``), against expectations worked out by hand.

Pure functions, no I/O: the app tier (``test_handback_watch.py``) drives the
same rules through a running companion.
"""

from __future__ import annotations

import pytest

from companion.handback import (
    Conditions,
    Pick,
    adoptable,
    candidates,
    failsafe_state,
    judge,
    next_kind,
    pick,
    unmet,
)
from companion.stacks import ARDUPILOT, PX4, FlightStack, SafeMode, said_why

# HEARTBEAT custom_mode values, worked out from the MAVLink / PX4 / ArduCopter
# definitions rather than from companion.stacks. PX4: main mode in bits 16-23,
# sub mode in bits 24-31.
PX4_MANUAL = 1 << 16
PX4_ALTCTL = 2 << 16
PX4_POSCTL = 3 << 16
PX4_ACRO = 5 << 16
PX4_OFFBOARD = 6 << 16
PX4_STABILIZED = 7 << 16
PX4_HOLD = 4 << 16 | 3 << 24  # AUTO.LOITER
PX4_RTL = 4 << 16 | 5 << 24  # AUTO.RTL
PX4_LAND = 4 << 16 | 6 << 24  # AUTO.LAND
# ArduCopter: the mode number.
APM_STABILIZE, APM_ACRO, APM_ALT_HOLD, APM_LOITER, APM_RTL = 0, 1, 2, 5, 6
APM_LAND, APM_POSHOLD, APM_BRAKE, APM_GUIDED_NOGPS = 9, 16, 17, 20

EVERYTHING = Conditions(rc_valid=True, position_valid=True)
RC_ONLY = Conditions(rc_valid=True, position_valid=False)
POSITION_ONLY = Conditions(rc_valid=False, position_valid=True)
NOTHING = Conditions(rc_valid=False, position_valid=False)
RC_BACK_AFTER_RC_LOSS = Conditions(rc_valid=True, position_valid=True, rc_failsafe=True)
# The autopilot failing safe by its own HEARTBEAT (system_status CRITICAL), RC seen all the
# while: PX4 without its own stick input in POSCTL, ArduCopter in its radio failsafe.
FAILING_SAFE = Conditions(rc_valid=True, position_valid=True, autopilot_failsafe="CRITICAL")
FAILING_SAFE_NO_POSITION = Conditions(True, False, autopilot_failsafe="CRITICAL")


def names(modes: tuple[SafeMode, ...]) -> list[str]:
    return [m.name for m in modes]


# ------------------------------------------------------------------ the tables


def test_px4_safe_modes_table() -> None:
    table = {n: (m.param2, m.param3, m.needs, m.position_too) for n, m in PX4.safe_modes.items()}
    assert table == {
        "posctl": (3.0, 0.0, "rc", True),
        "altctl": (2.0, 0.0, "rc", False),
        "stabilized": (7.0, 0.0, "rc", False),
        "manual": (1.0, 0.0, "rc", False),
        "hold": (4.0, 3.0, "position", False),
        "land": (4.0, 6.0, "nothing", False),
    }
    assert all(m.name == n for n, m in PX4.safe_modes.items())
    assert PX4.auto_safe_modes == ("posctl", "altctl", "hold", "land")
    assert PX4.pilot_modes == {PX4_MANUAL, PX4_ALTCTL, PX4_POSCTL, PX4_ACRO, PX4_STABILIZED}


def test_ardupilot_safe_modes_table() -> None:
    table = {
        n: (m.param2, m.param3, m.needs, m.position_too) for n, m in ARDUPILOT.safe_modes.items()
    }
    assert table == {
        "alt_hold": (2.0, 0.0, "rc", False),
        "stabilize": (0.0, 0.0, "rc", False),
        "loiter": (5.0, 0.0, "position", False),
        "brake": (17.0, 0.0, "position", False),
        "land": (9.0, 0.0, "nothing", False),
    }
    assert all(m.name == n for n, m in ARDUPILOT.safe_modes.items())
    assert ARDUPILOT.auto_safe_modes == ("alt_hold", "loiter", "land")
    # STABILIZE, ACRO, ALT_HOLD, DRIFT, SPORT, POSHOLD
    assert ARDUPILOT.pilot_modes == {0, 1, 2, 11, 13, 16}


@pytest.mark.parametrize(
    ("stack", "name", "custom_mode"),
    [
        (PX4, "posctl", PX4_POSCTL),
        (PX4, "altctl", PX4_ALTCTL),
        (PX4, "stabilized", PX4_STABILIZED),
        (PX4, "manual", PX4_MANUAL),
        (PX4, "hold", 0x0304_0000),
        (PX4, "land", 0x0604_0000),
        (ARDUPILOT, "alt_hold", 2),
        (ARDUPILOT, "stabilize", 0),
        (ARDUPILOT, "loiter", 5),
        (ARDUPILOT, "brake", 17),
        (ARDUPILOT, "land", 9),
    ],
)
def test_custom_mode_shows_each_safe_mode_and_back(
    stack: FlightStack, name: str, custom_mode: int
) -> None:
    mode = stack.mode(name)
    assert stack.custom_mode(mode) == custom_mode
    assert stack.safe_mode_shown(custom_mode) is mode
    assert stack.mode_label(custom_mode) == name.upper()
    assert not stack.is_engage_mode(custom_mode)


def test_px4_hold_and_land_custom_modes_carry_the_sub_mode() -> None:
    assert PX4.custom_mode(PX4.mode("hold")) == 4 << 16 | 3 << 24 == PX4_HOLD
    assert PX4.custom_mode(PX4.mode("land")) == 4 << 16 | 6 << 24 == PX4_LAND
    # Same main mode (AUTO), different sub modes: three different modes.
    assert len({PX4_HOLD, PX4_LAND, PX4_RTL}) == 3
    assert PX4.safe_mode_shown(PX4_RTL) is None
    assert PX4.safe_mode_shown(4 << 16) is None  # AUTO with no sub mode


def test_modes_that_are_no_safe_mode_get_a_readable_label() -> None:
    assert PX4.mode_label(PX4_OFFBOARD) == "OFFBOARD"
    assert PX4.mode_label(PX4_RTL) == "AUTO.RTL"
    assert PX4.mode_label(PX4_ACRO) == "ACRO"
    assert PX4.mode_label(8 << 16) == "main 8"  # one it does not know
    assert PX4.mode_label(4 << 16 | 7 << 24) == "main 4 sub 7"
    assert ARDUPILOT.mode_label(APM_GUIDED_NOGPS) == "GUIDED_NOGPS"
    assert ARDUPILOT.mode_label(APM_RTL) == "RTL"
    assert ARDUPILOT.mode_label(99) == "mode 99"
    assert ARDUPILOT.safe_mode_shown(APM_RTL) is None


@pytest.mark.parametrize(
    ("stack", "custom_mode", "flown_from_the_sticks"),
    [
        (PX4, PX4_MANUAL, True),
        (PX4, PX4_ALTCTL, True),
        (PX4, PX4_POSCTL, True),
        (PX4, PX4_ACRO, True),
        (PX4, PX4_STABILIZED, True),
        (PX4, PX4_HOLD, False),
        (PX4, PX4_LAND, False),
        (PX4, PX4_RTL, False),
        (PX4, PX4_OFFBOARD, False),
        (ARDUPILOT, APM_STABILIZE, True),
        (ARDUPILOT, APM_ACRO, True),
        (ARDUPILOT, APM_ALT_HOLD, True),
        (ARDUPILOT, APM_POSHOLD, True),
        (ARDUPILOT, APM_LOITER, False),
        (ARDUPILOT, APM_BRAKE, False),
        (ARDUPILOT, APM_LAND, False),
        (ARDUPILOT, APM_RTL, False),
        (ARDUPILOT, APM_GUIDED_NOGPS, False),
    ],
)
def test_needs_rc_is_true_for_the_modes_flown_from_the_sticks(
    stack: FlightStack, custom_mode: int, flown_from_the_sticks: bool
) -> None:
    assert stack.needs_rc(custom_mode) is flown_from_the_sticks


def test_each_safe_modes_needs_agree_with_needs_rc() -> None:
    for stack in (PX4, ARDUPILOT):
        for mode in stack.safe_modes.values():
            assert stack.needs_rc(stack.custom_mode(mode)) is (mode.needs == "rc"), mode


# ----------------------------------------------------------------- conditions


@pytest.mark.parametrize(
    ("cond", "text"),
    [
        (EVERYTHING, "valid RC, a position estimate"),
        (RC_ONLY, "valid RC, no position estimate"),
        (POSITION_ONLY, "no valid RC, a position estimate"),
        (NOTHING, "no valid RC, no position estimate"),
        (RC_BACK_AFTER_RC_LOSS, "RC lost, a position estimate"),
        (Conditions(False, False, rc_failsafe=True), "RC lost, no position estimate"),
        (FAILING_SAFE, "valid RC, a position estimate, the autopilot failing safe (CRITICAL)"),
        (
            Conditions(False, False, autopilot_failsafe="EMERGENCY"),
            "no valid RC, no position estimate, the autopilot failing safe (EMERGENCY)",
        ),
    ],
)
def test_conditions_describe_themselves(cond: Conditions, text: str) -> None:
    assert cond.describe() == text


def test_unmet_says_why_a_mode_cannot_be_flown() -> None:
    posctl, hold, land = PX4.mode("posctl"), PX4.mode("hold"), PX4.mode("land")
    assert unmet(posctl, EVERYTHING) is None
    assert unmet(posctl, RC_ONLY) == "posctl needs a position estimate (none)"
    assert unmet(posctl, POSITION_ONLY) == "posctl needs RC (none valid)"
    assert unmet(posctl, NOTHING) == "posctl needs RC (none valid)"  # RC is said first
    assert unmet(posctl, RC_BACK_AFTER_RC_LOSS) == "posctl needs RC (the failsafe is RC loss)"
    assert unmet(PX4.mode("altctl"), RC_ONLY) is None  # no position needed
    assert unmet(hold, POSITION_ONLY) is None
    assert unmet(hold, RC_ONLY) == "hold needs a position estimate (none)"
    for cond in (EVERYTHING, RC_ONLY, POSITION_ONLY, NOTHING, RC_BACK_AFTER_RC_LOSS, FAILING_SAFE):
        assert unmet(land, cond) is None
        assert unmet(ARDUPILOT.mode("land"), cond) is None


def test_failsafe_state_names_the_heartbeats_failing_safe_states_only() -> None:
    # MAV_STATE: UNINIT 0, BOOT 1, CALIBRATING 2, STANDBY 3, ACTIVE 4, CRITICAL 5,
    # EMERGENCY 6, POWEROFF 7, FLIGHT_TERMINATION 8 (common.xml).
    assert failsafe_state(5) == "CRITICAL"
    assert failsafe_state(6) == "EMERGENCY"
    for status in (None, 0, 1, 2, 3, 4, 7, 8):
        assert failsafe_state(status) is None


def test_no_mode_flown_from_the_sticks_while_the_autopilot_fails_safe() -> None:
    failing = "needs RC (the autopilot is failing safe: CRITICAL)"
    assert unmet(PX4.mode("posctl"), FAILING_SAFE) == f"posctl {failing}"
    assert unmet(PX4.mode("manual"), FAILING_SAFE) == f"manual {failing}"
    assert unmet(ARDUPILOT.mode("alt_hold"), FAILING_SAFE) == f"alt_hold {failing}"
    # The more basic reasons first: the failsafe is RC loss, or no RC at all.
    assert unmet(PX4.mode("altctl"), Conditions(True, True, True, "CRITICAL")) == (
        "altctl needs RC (the failsafe is RC loss)"
    )
    assert unmet(PX4.mode("altctl"), Conditions(False, True, autopilot_failsafe="CRITICAL")) == (
        "altctl needs RC (none valid)"
    )
    # Holding and landing is what the autopilot's own failsafe does: still chosen.
    assert unmet(PX4.mode("hold"), FAILING_SAFE) is None
    assert unmet(ARDUPILOT.mode("loiter"), FAILING_SAFE) is None
    assert unmet(ARDUPILOT.mode("brake"), FAILING_SAFE) is None


# ------------------------------------------------------------------ candidates


def test_auto_candidates_are_the_stacks_list() -> None:
    assert names(candidates(PX4, "auto")) == ["posctl", "altctl", "hold", "land"]
    assert names(candidates(ARDUPILOT, "auto")) == ["alt_hold", "loiter", "land"]


@pytest.mark.parametrize(
    ("stack", "requested", "expected"),
    [
        (PX4, "posctl", ["posctl", "hold", "land"]),
        (PX4, "altctl", ["altctl", "hold", "land"]),
        (PX4, "stabilized", ["stabilized", "hold", "land"]),
        (PX4, "manual", ["manual", "hold", "land"]),
        (PX4, "hold", ["hold", "land"]),
        (PX4, "land", ["land"]),
        (ARDUPILOT, "alt_hold", ["alt_hold", "loiter", "land"]),
        (ARDUPILOT, "stabilize", ["stabilize", "loiter", "land"]),
        (ARDUPILOT, "loiter", ["loiter", "land"]),
        (ARDUPILOT, "brake", ["brake", "land"]),
        (ARDUPILOT, "land", ["land"]),
    ],
)
def test_a_named_mode_comes_first_then_the_pilot_free_modes_after_it(
    stack: FlightStack, requested: str, expected: list[str]
) -> None:
    modes = candidates(stack, requested)
    assert names(modes) == expected
    assert modes[0] is stack.mode(requested)


@pytest.mark.parametrize(
    ("stack", "requested", "message"),
    [
        (
            PX4,
            "loiter",
            "px4 has no safe mode 'loiter': expected one of "
            "altctl, hold, land, manual, posctl, stabilized",
        ),
        (
            ARDUPILOT,
            "posctl",
            "ardupilot has no safe mode 'posctl': expected one of "
            "alt_hold, brake, land, loiter, stabilize",
        ),
        (
            PX4,
            "offboard",
            "px4 has no safe mode 'offboard': expected one of "
            "altctl, hold, land, manual, posctl, stabilized",
        ),
    ],
)
def test_an_unknown_mode_name_is_a_value_error_naming_the_stack_and_its_modes(
    stack: FlightStack, requested: str, message: str
) -> None:
    with pytest.raises(ValueError) as info:
        candidates(stack, requested)
    assert str(info.value) == message


# ------------------------------------------------------------------------ pick


@pytest.mark.parametrize(
    ("stack", "cond", "expected", "index"),
    [
        (PX4, EVERYTHING, "posctl", 0),
        (PX4, RC_ONLY, "altctl", 1),  # POSCTL needs a position too
        (PX4, POSITION_ONLY, "hold", 2),
        (PX4, NOTHING, "land", 3),
        (PX4, RC_BACK_AFTER_RC_LOSS, "hold", 2),  # no manual mode after RC loss
        (PX4, Conditions(True, False, rc_failsafe=True), "land", 3),
        (ARDUPILOT, EVERYTHING, "alt_hold", 0),
        (ARDUPILOT, RC_ONLY, "alt_hold", 0),  # ALT_HOLD needs no position
        (ARDUPILOT, POSITION_ONLY, "loiter", 1),
        (ARDUPILOT, NOTHING, "land", 2),
        (ARDUPILOT, RC_BACK_AFTER_RC_LOSS, "loiter", 1),
        (PX4, FAILING_SAFE, "hold", 2),  # no manual mode while the autopilot fails safe
        (PX4, FAILING_SAFE_NO_POSITION, "land", 3),
        (ARDUPILOT, FAILING_SAFE, "loiter", 1),
        (ARDUPILOT, FAILING_SAFE_NO_POSITION, "land", 2),
    ],
)
def test_auto_picks_by_what_the_vehicle_has(
    stack: FlightStack, cond: Conditions, expected: str, index: int
) -> None:
    modes = candidates(stack, "auto")
    choice = pick(modes, 0, cond)
    assert choice.mode is stack.mode(expected)
    assert choice.index == index
    assert len(choice.skipped) == index  # one reason per mode passed over


def test_pick_says_why_each_mode_before_it_was_passed_over() -> None:
    auto = candidates(PX4, "auto")
    assert pick(auto, 0, EVERYTHING) == Pick(PX4.mode("posctl"), 0, ())
    assert pick(auto, 0, RC_ONLY).skipped == ("posctl needs a position estimate (none)",)
    assert pick(auto, 0, POSITION_ONLY).skipped == (
        "posctl needs RC (none valid)",
        "altctl needs RC (none valid)",
    )
    nothing = pick(auto, 0, NOTHING)
    assert nothing.skipped == (
        "posctl needs RC (none valid)",
        "altctl needs RC (none valid)",
        "hold needs a position estimate (none)",
    )
    assert nothing.why_skipped() == (
        "posctl needs RC (none valid); altctl needs RC (none valid); "
        "hold needs a position estimate (none)"
    )
    assert pick(auto, 0, RC_BACK_AFTER_RC_LOSS).skipped == (
        "posctl needs RC (the failsafe is RC loss)",
        "altctl needs RC (the failsafe is RC loss)",
    )
    apm = pick(candidates(ARDUPILOT, "auto"), 0, NOTHING)
    assert apm.mode is ARDUPILOT.mode("land")
    assert apm.skipped == (
        "alt_hold needs RC (none valid)",
        "loiter needs a position estimate (none)",
    )


def test_pick_starts_where_it_is_told() -> None:
    auto = candidates(PX4, "auto")
    # After POSCTL failed, with RC and a position: the next, ALTCTL.
    assert pick(auto, 1, EVERYTHING) == Pick(PX4.mode("altctl"), 1, ())
    # After POSCTL failed and RC went meanwhile: HOLD, ALTCTL passed over.
    assert pick(auto, 1, POSITION_ONLY) == Pick(
        PX4.mode("hold"), 2, ("altctl needs RC (none valid)",)
    )
    assert pick(auto, 3, NOTHING) == Pick(PX4.mode("land"), 3, ())
    # Past the end: no mode left, index = len(modes).
    assert pick(auto, 4, EVERYTHING) == Pick(None, 4, ())


def test_a_named_manual_mode_without_rc_is_passed_over_for_hold() -> None:
    named = candidates(PX4, "posctl")
    choice = pick(named, 0, POSITION_ONLY)
    assert choice.mode is PX4.mode("hold")
    assert choice.index == 1
    assert choice.skipped == ("posctl needs RC (none valid)",)
    assert pick(named, 0, NOTHING).mode is PX4.mode("land")
    assert pick(candidates(ARDUPILOT, "brake"), 0, RC_ONLY) == Pick(
        ARDUPILOT.mode("land"), 1, ("brake needs a position estimate (none)",)
    )


def test_no_mode_left_when_none_of_them_can_be_flown() -> None:
    only_hold = (PX4.mode("hold"),)
    assert pick(only_hold, 0, NOTHING) == Pick(None, 1, ("hold needs a position estimate (none)",))


def test_auto_always_finds_a_mode_land_last() -> None:
    for stack in (PX4, ARDUPILOT):
        modes = candidates(stack, "auto")
        assert modes[-1].needs == "nothing"
        for rc in (False, True):
            for pos in (False, True):
                for rc_failsafe in (False, True):
                    for failing in (None, "CRITICAL", "EMERGENCY"):
                        choice = pick(modes, 0, Conditions(rc, pos, rc_failsafe, failing))
                        assert choice.mode is not None
                        if not rc or rc_failsafe or failing:
                            assert choice.mode.needs != "rc"


# ----------------------------------------------------------------------- judge

AUTO = candidates(PX4, "auto")  # posctl 0, altctl 1, hold 2, land 3


def test_judge_keeps_our_mode() -> None:
    for i, mode in enumerate(AUTO):
        for cond in (EVERYTHING, NOTHING, RC_BACK_AFTER_RC_LOSS):
            assert judge(PX4, AUTO, i, PX4.custom_mode(mode), cond) is None


def test_judge_keeps_a_later_candidate_the_autopilot_chose() -> None:
    assert judge(PX4, AUTO, 0, PX4_LAND, NOTHING) is None
    assert judge(PX4, AUTO, 0, PX4_HOLD, NOTHING) is None
    assert judge(PX4, AUTO, 2, PX4_LAND, NOTHING) is None
    apm = candidates(ARDUPILOT, "auto")
    assert judge(ARDUPILOT, apm, 0, APM_LAND, NOTHING) is None
    assert judge(ARDUPILOT, apm, 1, APM_LAND, NOTHING) is None


def test_judge_rejects_an_earlier_candidate_or_another_mode() -> None:
    # HOLD is earlier than LAND: the autopilot left the land we asked for.
    assert judge(PX4, AUTO, 3, PX4_HOLD, EVERYTHING) == "the autopilot left LAND for HOLD"
    # The autopilot's own failsafe: AUTO.RTL is no candidate.
    assert judge(PX4, AUTO, 0, PX4_RTL, EVERYTHING) == "the autopilot left POSCTL for AUTO.RTL"
    assert judge(PX4, AUTO, 2, PX4_RTL, NOTHING) == "the autopilot left HOLD for AUTO.RTL"
    # OFFBOARD again is not a mode to stay in without the companion.
    assert judge(PX4, AUTO, 2, PX4_OFFBOARD, EVERYTHING) == "the autopilot left HOLD for OFFBOARD"
    # A safe mode of the stack that is not among the candidates after ours.
    apm = candidates(ARDUPILOT, "auto")
    assert judge(ARDUPILOT, apm, 1, APM_BRAKE, EVERYTHING) == "the autopilot left LOITER for BRAKE"
    assert judge(ARDUPILOT, apm, 0, APM_RTL, EVERYTHING) == "the autopilot left ALT_HOLD for RTL"
    named = candidates(PX4, "hold")  # hold, land
    assert judge(PX4, named, 1, PX4_HOLD, EVERYTHING) == "the autopilot left LAND for HOLD"


def test_judge_keeps_a_mode_flown_from_the_sticks_only_with_valid_rc() -> None:
    # We asked for HOLD (no RC then); the pilot's radio is back and they took MANUAL.
    assert judge(PX4, AUTO, 2, PX4_MANUAL, EVERYTHING) is None
    assert judge(PX4, AUTO, 2, PX4_ACRO, RC_ONLY) is None  # ACRO: no candidate, still sticks
    # We asked for ALTCTL; the pilot took POSCTL, an earlier candidate: kept for the sticks.
    assert judge(PX4, AUTO, 1, PX4_POSCTL, EVERYTHING) is None
    # The same without valid RC: nobody flies it.
    assert judge(PX4, AUTO, 2, PX4_MANUAL, POSITION_ONLY) == "the autopilot left HOLD for MANUAL"
    assert judge(PX4, AUTO, 2, PX4_ACRO, NOTHING) == "the autopilot left HOLD for ACRO"
    assert judge(PX4, AUTO, 3, PX4_POSCTL, NOTHING) == "the autopilot left LAND for POSCTL"
    # After RC loss, with the radio back, a manual mode is the pilot's own choice: kept.
    assert judge(PX4, AUTO, 2, PX4_MANUAL, RC_BACK_AFTER_RC_LOSS) is None
    apm = candidates(ARDUPILOT, "auto")
    assert judge(ARDUPILOT, apm, 1, APM_POSHOLD, EVERYTHING) is None
    assert (
        judge(ARDUPILOT, apm, 1, APM_STABILIZE, POSITION_ONLY)
        == "the autopilot left LOITER for STABILIZE"
    )


def test_judge_loses_a_mode_flown_from_the_sticks_the_autopilot_fails_safe_in() -> None:
    """PX4 without its own stick input keeps showing POSCTL (asked for POSCTL, or
    for ALTCTL, STABILIZED or MANUAL) while it fails safe and descends: lost, valid
    RC seen or not; ArduCopter in its radio failsafe likewise."""
    for i in (0, 1):  # posctl asked, altctl asked: PX4 shows POSCTL
        assert judge(PX4, AUTO, i, PX4_POSCTL, FAILING_SAFE) == (
            "the autopilot is failing safe (CRITICAL) in POSCTL"
        )
    manual = candidates(PX4, "manual")
    assert judge(PX4, manual, 0, PX4_MANUAL, FAILING_SAFE) == (
        "the autopilot is failing safe (CRITICAL) in MANUAL"
    )
    assert judge(PX4, manual, 0, PX4_POSCTL, FAILING_SAFE) == (
        "the autopilot is failing safe (CRITICAL) in POSCTL"
    )
    emergency = Conditions(False, True, autopilot_failsafe="EMERGENCY")
    assert judge(PX4, AUTO, 2, PX4_ACRO, emergency) == (
        "the autopilot is failing safe (EMERGENCY) in ACRO"
    )
    apm = candidates(ARDUPILOT, "auto")
    assert judge(ARDUPILOT, apm, 0, APM_ALT_HOLD, FAILING_SAFE) == (
        "the autopilot is failing safe (CRITICAL) in ALT_HOLD"
    )
    # Lost: what follows is a more conservative kind (hold), not another manual mode.
    assert next_kind(AUTO, 0) == 2


def test_judge_keeps_a_hold_or_land_the_autopilot_fails_safe_in() -> None:
    assert judge(PX4, AUTO, 2, PX4_HOLD, FAILING_SAFE) is None
    assert judge(PX4, AUTO, 3, PX4_LAND, FAILING_SAFE) is None
    assert judge(PX4, AUTO, 0, PX4_LAND, FAILING_SAFE) is None  # its failsafe landing: later
    apm = candidates(ARDUPILOT, "auto")
    assert judge(ARDUPILOT, apm, 1, APM_LOITER, FAILING_SAFE) is None
    assert judge(ARDUPILOT, apm, 2, APM_LAND, FAILING_SAFE) is None
    # A mode that is no candidate stays the autopilot leaving ours, as without a failsafe.
    assert judge(PX4, AUTO, 2, PX4_RTL, FAILING_SAFE) == "the autopilot left HOLD for AUTO.RTL"


# ------------------------------------------------------------------- adoptable


def test_the_engage_mode_is_never_adopted() -> None:
    for cond in (EVERYTHING, NOTHING):
        assert not adoptable(PX4, PX4_OFFBOARD, cond)
        assert not adoptable(PX4, PX4_OFFBOARD | 1 << 24, cond)  # any sub mode of it
        assert not adoptable(ARDUPILOT, APM_GUIDED_NOGPS, cond)


def test_a_manual_mode_is_adopted_only_with_valid_rc_and_no_rc_loss() -> None:
    assert adoptable(PX4, PX4_MANUAL, EVERYTHING)
    assert adoptable(PX4, PX4_POSCTL, RC_ONLY)
    assert not adoptable(PX4, PX4_MANUAL, POSITION_ONLY)
    assert not adoptable(PX4, PX4_POSCTL, NOTHING)
    assert not adoptable(PX4, PX4_MANUAL, RC_BACK_AFTER_RC_LOSS)
    assert adoptable(ARDUPILOT, APM_ALT_HOLD, EVERYTHING)
    assert not adoptable(ARDUPILOT, APM_STABILIZE, POSITION_ONLY)


def test_a_mode_flown_from_the_sticks_is_not_adopted_while_the_autopilot_fails_safe() -> None:
    """PX4 showing POSCTL while CRITICAL is its failsafe flying, not the pilot."""
    assert not adoptable(PX4, PX4_POSCTL, FAILING_SAFE)
    assert not adoptable(PX4, PX4_MANUAL, FAILING_SAFE)
    assert not adoptable(ARDUPILOT, APM_ALT_HOLD, FAILING_SAFE)


def test_a_pilot_free_mode_the_autopilot_chose_is_adopted_whatever_is_seen() -> None:
    for cond in (EVERYTHING, NOTHING, RC_BACK_AFTER_RC_LOSS, FAILING_SAFE):
        assert adoptable(PX4, PX4_LAND, cond)
        assert adoptable(PX4, PX4_HOLD, cond)
        assert adoptable(PX4, PX4_RTL, cond)
        assert adoptable(ARDUPILOT, APM_LAND, cond)
        assert adoptable(ARDUPILOT, APM_RTL, cond)


# ------------------------------------------------------ why the stack refused


def test_ardupilot_says_why_it_refused_to_arm_in_a_prearm_or_arm_text() -> None:
    """The texts since the attempt, oldest first, as ArduCopter 4.5 sent them after
    boot: the reason, then an unrelated text that came later."""
    said = ["Arm: Need Alt Estimate", "RC7: SaveWaypoint MIDDLE"]
    assert said_why(said, ARDUPILOT.arm_refusals) == "Arm: Need Alt Estimate"
    assert said_why(["PreArm: Need Position Estimate"], ARDUPILOT.arm_refusals) == (
        "PreArm: Need Position Estimate"
    )
    assert (
        said_why(["RC7: SaveWaypoint MIDDLE", "EKF3 IMU0 is using GPS"], ARDUPILOT.arm_refusals)
        is None
    )
    assert said_why([], ARDUPILOT.arm_refusals) is None


def test_px4_says_why_in_its_preflight_fail_and_arming_denied_texts() -> None:
    """PX4 v1.16 names the failing check ("Preflight Fail: ..."), then says it
    denied arming; both end in a tab (its events marker), stripped."""
    said = [
        "[logger] /fs/microsd/log/sess001/log001.ulg",
        "Preflight Fail: ekf2 missing data\t",
        "Arming denied: Resolve system health failures first\t",
        "Preflight Fail: ekf2 missing data\t",  # said twice: quoted once
    ]
    assert said_why(said, PX4.arm_refusals) == (
        "Preflight Fail: ekf2 missing data; Arming denied: Resolve system health failures first"
    )
    assert said_why(["PREFLIGHT FAIL: High Gyro Bias"], PX4.arm_refusals) == (
        "PREFLIGHT FAIL: High Gyro Bias"
    )  # case aside
    # An arming refusal is not the reason for a refused mode, nor the other way round.
    assert said_why(said, PX4.mode_refusals) is None
    assert said_why(["Switching to Offboard is currently not available\t"], PX4.mode_refusals) == (
        "Switching to Offboard is currently not available"
    )


def test_at_most_three_reasons_are_quoted() -> None:
    said = [f"PreArm: check {i}" for i in range(6)]
    assert (
        said_why(said, ARDUPILOT.arm_refusals)
        == "PreArm: check 0; PreArm: check 1; PreArm: check 2"
    )


def test_ardupilot_says_why_it_refused_a_mode() -> None:
    assert (
        said_why(
            ["Mode change to GUIDED_NOGPS failed: init failed", "Radio Failsafe"],
            ARDUPILOT.mode_refusals,
        )
        == "Mode change to GUIDED_NOGPS failed: init failed"
    )
    # The bundled SITL's personality speaks as older ArduPilot did.
    assert said_why(["Flight mode change failed GUIDED_NOGPS"], ARDUPILOT.mode_refusals) == (
        "Flight mode change failed GUIDED_NOGPS"
    )
