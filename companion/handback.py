"""Which mode to hand the vehicle back to, and whether it stays there.

A hand-back must leave the vehicle in a mode it can fly without the companion.
PX4's and ArduPilot's manual modes need a pilot's radio: without one, PX4
refuses them or fails safe out of them, ArduPilot's radio failsafe takes over.
Their hold modes need a position estimate. Land needs neither.

:func:`candidates` orders the modes to try: with ``--safe-mode auto`` the
stack's list (a manual mode, a hold, land); with a named mode, that mode and
then the pilot-free modes after it. :func:`pick` takes the first whose needs
the vehicle meets now, saying why the ones before it were passed over. After a
switch the app watches the autopilot's mode and its failsafe state
(:class:`SafeModeWatch`, :func:`judge`): a mode refused is followed by the next candidate; one the
autopilot leaves, never shows, or fails safe in while it is flown from the
sticks, by the next of a more conservative kind (:func:`next_kind`). No I/O and
no clock here: the app feeds in what it saw.

The autopilot's own failsafe shows in its HEARTBEAT ``system_status``
(:func:`failsafe_state`). PX4 in a manual mode without its own stick input
keeps showing the mode (POSCTL, also for ALTCTL, STABILIZED and MANUAL) while
it fails safe and descends, with MAV_STATE_CRITICAL; ArduCopter shows CRITICAL
while its radio failsafe is active. A mode flown from the sticks is then lost,
and none is chosen; a hold or a land mode is what such a failsafe does anyway,
and is kept.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from companion.stacks import FlightStack, SafeMode

__all__ = [
    "FAILSAFE_STATES",
    "Conditions",
    "Pick",
    "SafeModeWatch",
    "WatchEnd",
    "adoptable",
    "candidates",
    "failsafe_state",
    "judge",
    "next_kind",
    "pick",
    "unmet",
]

_TIER = {"rc": 0, "position": 1, "nothing": 2}

FAILSAFE_STATES = {5: "CRITICAL", 6: "EMERGENCY"}
"""HEARTBEAT ``system_status`` (MAV_STATE) values with which PX4 and ArduPilot
say they are failing safe, whatever mode they show: MAV_STATE_CRITICAL (PX4
while a failsafe is active, ArduPilot while its radio or another failsafe is),
MAV_STATE_EMERGENCY."""


def failsafe_state(system_status: int | None) -> str | None:
    """The name of the failsafe state a HEARTBEAT ``system_status`` shows
    (``"CRITICAL"``, ``"EMERGENCY"``), or None: not failing safe, or not seen."""
    if system_status is None:
        return None
    return FAILSAFE_STATES.get(system_status)


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
    autopilot_failsafe: str | None = None
    """The autopilot says it is failing safe (:func:`failsafe_state` of its last
    HEARTBEAT, e.g. ``"CRITICAL"``): no manual mode, whatever RC is seen (PX4
    and ArduPilot fail safe out of them when their own stick input is gone)."""

    def describe(self) -> str:
        rc = "RC lost" if self.rc_failsafe else "valid RC" if self.rc_valid else "no valid RC"
        pos = "a position estimate" if self.position_valid else "no position estimate"
        failing = self.autopilot_failsafe
        if failing is None:
            return f"{rc}, {pos}"
        return f"{rc}, {pos}, the autopilot failing safe ({failing})"


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
        failing = cond.autopilot_failsafe
        if failing is not None:
            return f"{mode.name} needs RC (the autopilot is failing safe: {failing})"
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

    A mode flown from the sticks (ours or another) while the autopilot says it
    is failing safe (``cond.autopilot_failsafe``) is lost: the autopilot is
    not flying the pilot's sticks but its own failsafe, and PX4 shows the
    manual mode all the while (POSCTL also for ALTCTL, STABILIZED, MANUAL).
    Otherwise kept: our mode; a later candidate (the autopilot's failsafe chose
    what we would have tried next, e.g. land); a mode flown from the sticks
    while valid RC is seen, even after an RC-loss failsafe (the pilot, with the
    radio back, took the vehicle; or the autopilot fell back between its manual
    modes). A hold or land mode is kept whatever the autopilot's failsafe state
    (holding or landing is what its failsafe does). Anything else is the
    autopilot's own failsafe or a mode the vehicle cannot hold: the caller goes
    on with :func:`next_kind`.
    """
    ours = modes[index]
    failing = cond.autopilot_failsafe
    if failing is not None and stack.needs_rc(custom_mode):
        return f"the autopilot is failing safe ({failing}) in {stack.mode_label(custom_mode)}"
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

    Yes, unless it is a mode flown from the sticks with no valid RC seen, or
    while the autopilot says it is failing safe (then it is the autopilot's
    failsafe, not the pilot, flying it): the companion does not override what
    the autopilot or the pilot chose."""
    if stack.is_engage_mode(custom_mode):
        return False
    if not stack.needs_rc(custom_mode):
        return True
    return cond.rc_valid and not cond.rc_failsafe and cond.autopilot_failsafe is None


@dataclass(frozen=True)
class WatchEnd:
    """How a :class:`SafeModeWatch` ended: ``failed``, why the vehicle did not stay
    in a mode it can fly (None: it did, or the watch had to stop); ``event``, what
    to record of it (``safe_mode_held``, ``safe_mode_unconfirmed``), if anything."""

    failed: str | None = None
    event: tuple[str, str] | None = None


class SafeModeWatch:
    """The autopilot's HEARTBEATs for ``watch_s`` after a switch to
    ``modes[index]`` from ``before`` (the mode shown when the switch was sent):
    does the vehicle stay in a mode it can fly? Fed what the heartbeats say, by
    :meth:`look`, as often as the caller looks.

    Each heartbeat's mode and failsafe state (its ``system_status``) are judged
    together (:func:`judge`): leaving the mode, or failing safe in a mode flown
    from the sticks, loses it. Until the new mode shows, a heartbeat still
    showing the mode from before the switch (or the engage mode) may have been
    sent before it: only another mode is judged at once. So the failsafe state
    judged is the one sent with the new mode or after: a state from before the
    switch is never held against it, but one that was failing safe before and
    still is when the new mode shows is failing safe in it. A pilot-free mode
    kept (the autopilot's own landing) ends the watch; a mode flown from the
    sticks, ours or one the pilot took, is watched to the end (the autopilot may
    raise its failsafe in it a moment after it shows it), and once the pilot has
    taken one, a pilot-free mode they go on to ends the watch as theirs. A new
    engagement (the pilot's switch) or a disarm ends the watch. With no
    heartbeat at all meanwhile (a lost link) there is nothing to judge by: the
    mode stays.
    """

    def __init__(
        self,
        stack: FlightStack,
        modes: tuple[SafeMode, ...],
        index: int,
        before: int | None,
        watch_s: float,
        heartbeats: int,
    ) -> None:
        self.stack = stack
        self.modes = modes
        self.index = index
        self.before = before
        self.watch_s = watch_s
        self.target = stack.custom_mode(modes[index])
        self._heartbeats0 = heartbeats
        self._seen = False
        self._pilots = False
        """The pilot (or the autopilot) put it in another mode flown from the sticks."""

    def look(
        self,
        elapsed: float,
        mode: int | None,
        armed: bool,
        heartbeats: int,
        commanding: bool,
        conditions: Callable[[], Conditions],
    ) -> WatchEnd | None:
        """``elapsed`` s after the switch, the last heartbeat's ``mode`` and
        ``armed``, the heartbeats counted so far; ``commanding``: engaged again;
        ``conditions``: what a mode is judged on, now. None: watch on."""
        if commanding:
            return WatchEnd()  # engaged again meanwhile: the pilot's call
        stack, target, name = self.stack, self.target, self.modes[self.index].name.upper()
        if not armed and mode is not None and (self._seen or mode != target):
            return WatchEnd(event=("safe_mode_held", f"disarmed after {elapsed:.1f} s"))
        if mode == target:
            self._seen = True
        if mode is not None and (
            self._seen or (mode != self.before and not stack.is_engage_mode(mode))
        ):
            label = stack.mode_label(mode)
            sticks = stack.needs_rc(mode)
            held = WatchEnd(event=("safe_mode_held", f"{label} kept after {elapsed:.1f} s"))
            if self._pilots and not sticks and not stack.is_engage_mode(mode):
                return held  # from a mode of their own, the pilot's next one is theirs too
            # Judged on RC as it is now: a pilot with the radio back may take it.
            failed = judge(stack, self.modes, self.index, mode, conditions())
            if failed is not None:
                return WatchEnd(failed=f"{failed} after {elapsed:.1f} s")
            if mode != target:
                if not sticks:
                    return held
                self._pilots = True
        if elapsed < self.watch_s:
            return None
        watch_s = self.watch_s
        if heartbeats == self._heartbeats0:
            return WatchEnd(event=(
                "safe_mode_unconfirmed",
                f"no heartbeat for {watch_s:g} s after the switch to {name}: left as it is",
            ))  # fmt: skip
        if not self._seen and not self._pilots:
            return WatchEnd(
                failed=f"the autopilot accepted {name} but did not show it within {watch_s:g} s"
            )
        if mode == target:
            return WatchEnd(event=("safe_mode_held", f"{name} for {watch_s:g} s"))
        label = "its mode" if mode is None else stack.mode_label(mode)
        return WatchEnd(event=("safe_mode_held", f"{label} kept for {watch_s:g} s"))
