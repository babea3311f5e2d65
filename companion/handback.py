"""Which mode to hand the vehicle back to, and whether it stays there.

A hand-back must leave the vehicle in a mode it can fly without the companion.
PX4's and ArduPilot's manual modes need a pilot's radio: without one, PX4
refuses them or fails safe out of them, ArduPilot's radio failsafe takes over.
Their hold modes need a position estimate. Land needs neither.

:func:`candidates` orders the modes to try: with ``--safe-mode auto`` the
stack's list (a manual mode, a hold, land); with a named mode, that mode and
then the pilot-free modes after it. :func:`pick` takes the first whose needs
the vehicle meets now, saying why the ones before it were passed over. After a
switch the app watches the autopilot's mode (:func:`judge`): a mode refused
is followed by the next candidate; one the autopilot leaves or never shows, by
the next of a more conservative kind (:func:`next_kind`). No I/O and no clock
here: the app feeds in what it saw.
"""

from __future__ import annotations

from dataclasses import dataclass

from companion.stacks import FlightStack, SafeMode

__all__ = ["Conditions", "Pick", "adoptable", "candidates", "judge", "next_kind", "pick", "unmet"]

_TIER = {"rc": 0, "position": 1, "nothing": 2}


@dataclass(frozen=True)
class Conditions:
    """What the vehicle has, as the companion sees it now."""

    rc_valid: bool
    """Valid RC seen within the RC timeout."""
    position_valid: bool
    """A position estimate (LOCAL_POSITION_NED, which both stacks send only
    while their estimate is valid) seen recently."""
    rc_failsafe: bool = False
    """The hand-back follows an RC-loss failsafe: no manual mode, even if RC
    frames come back meanwhile."""

    def describe(self) -> str:
        rc = "RC lost" if self.rc_failsafe else "valid RC" if self.rc_valid else "no valid RC"
        pos = "a position estimate" if self.position_valid else "no position estimate"
        return f"{rc}, {pos}"


@dataclass(frozen=True)
class Pick:
    """The mode to try next and why the candidates before it were passed over."""

    mode: SafeMode | None
    index: int
    """Its place in the candidate list (len(list) when none is left)."""
    skipped: tuple[str, ...] = ()

    def why_skipped(self) -> str:
        return "; ".join(self.skipped)


def unmet(mode: SafeMode, cond: Conditions) -> str | None:
    """Why ``mode`` cannot be flown now, or None if it can."""
    if mode.needs == "rc":
        if cond.rc_failsafe:
            return f"{mode.name} needs RC (the failsafe is RC loss)"
        if not cond.rc_valid:
            return f"{mode.name} needs RC (none valid)"
    if (mode.needs == "position" or mode.position_too) and not cond.position_valid:
        return f"{mode.name} needs a position estimate (none)"
    return None


def candidates(stack: FlightStack, requested: str) -> tuple[SafeMode, ...]:
    """The modes to try, in order.

    ``"auto"``: the stack's list, most capable first (PX4 posctl, altctl, hold,
    land; ArduPilot alt_hold, loiter, land). A named mode comes first, followed
    by the auto list's pilot-free modes that are more conservative than it
    (posctl -> hold -> land; brake -> land; land alone).

    Raises
    ------
    ValueError
        For a name the stack does not have.
    """
    auto = tuple(stack.mode(n) for n in stack.auto_safe_modes)
    if requested == "auto":
        return auto
    first = stack.mode(requested)
    return (first, *(m for m in auto if _TIER[m.needs] > _TIER[first.needs]))


def pick(modes: tuple[SafeMode, ...], start: int, cond: Conditions) -> Pick:
    """The first of ``modes[start:]`` the vehicle can fly now (land always can)."""
    skipped: list[str] = []
    for i in range(start, len(modes)):
        why = unmet(modes[i], cond)
        if why is None:
            return Pick(modes[i], i, tuple(skipped))
        skipped.append(why)
    return Pick(None, len(modes), tuple(skipped))


def next_kind(modes: tuple[SafeMode, ...], index: int) -> int:
    """Where to go on after the autopilot left ``modes[index]`` (its own failsafe):
    the first candidate of a more conservative kind. Another manual mode would
    meet the same failsafe; hold or land might not."""
    tier = _TIER[modes[index].needs]
    for i in range(index + 1, len(modes)):
        if _TIER[modes[i].needs] > tier:
            return i
    return len(modes)


def judge(
    stack: FlightStack,
    modes: tuple[SafeMode, ...],
    index: int,
    custom_mode: int,
    cond: Conditions,
) -> str | None:
    """The autopilot shows ``custom_mode`` after we switched it to ``modes[index]``:
    None if the vehicle can stay in that mode, else why not.

    Kept: our mode; a later candidate (the autopilot's failsafe chose what we
    would have tried next, e.g. land); a mode flown from the sticks while valid
    RC is seen, even after an RC-loss failsafe (the pilot, with the radio back,
    took the vehicle; or the autopilot fell back between its manual modes).
    Anything else is the autopilot's own failsafe or a mode the vehicle cannot
    hold: the caller goes on with :func:`next_kind`.
    """
    ours = modes[index]
    if custom_mode == stack.custom_mode(ours):
        return None
    shown = stack.safe_mode_shown(custom_mode)
    if shown is not None and shown in modes[index + 1 :]:
        return None
    if stack.needs_rc(custom_mode) and cond.rc_valid:
        return None  # with valid RC now, only the pilot puts it in a manual mode
    return f"the autopilot left {ours.name.upper()} for {stack.mode_label(custom_mode)}"


def adoptable(stack: FlightStack, custom_mode: int, cond: Conditions) -> bool:
    """After the autopilot took the vehicle out of the engage mode by itself (its
    failsafe, or the pilot's mode switch): whether to leave it where it is.

    Yes, unless it is a mode flown from the sticks with no valid RC seen: the
    companion does not override what the autopilot or the pilot chose."""
    if stack.is_engage_mode(custom_mode):
        return False
    return not stack.needs_rc(custom_mode) or (cond.rc_valid and not cond.rc_failsafe)
