"""Engagement and hand-back: taking the vehicle, and giving it back to a mode it
can fly on its own.

A part of :class:`companion.app.Companion` (it is mixed in): engaging streams
setpoints, switches to the stack's engage mode and arms (with ``--engage
auto``, once the stack is ready, tried again while it refuses, within
``arm_timeout_s``); releasing stops the commands at once, in the caller's
callback; a failsafe releases and then hands back, trying the safe modes in the
order :mod:`companion.handback` gives and watching that the autopilot keeps the
one it accepted and does not fail safe in it.
"""

from __future__ import annotations

import asyncio
import time
from typing import TYPE_CHECKING, Any

from companion.control import RateController
from companion.errors import EXIT_ERROR, EXIT_FAILSAFE, EngageError, LinkError
from companion.handback import Conditions, adoptable, failsafe_state, judge, next_kind, pick
from companion.stacks import FlightStack, SafeMode, said_why

if TYPE_CHECKING:
    from companion.app import RunOptions
    from companion.records import EventLog

__all__ = ["Engagement"]

# MAVLink numbers used here (common.xml).
_CMD_DO_SET_MODE = 176
_CMD_ARM_DISARM = 400
_RESULT_ACCEPTED = 0
_MODE_FLAG_CUSTOM = 1
_POSITION_TIMEOUT_S = 1.0
"""A position estimate counts as valid while LOCAL_POSITION_NED (sent by PX4 and
ArduPilot only while their estimate is valid) is younger than this."""
_WATCH_POLL_S = 0.05
_SYS_STATUS_WAIT_S = 0.3
"""How long a hand-back that adopts the autopilot's failsafe waits for its next
SYS_STATUS (the companion asks for 5 Hz)."""
_ESTIMATES_WAIT_S = 1.0
"""How long an engagement waits for the estimates its flight mode needs."""
_RETRY_S = 1.0
"""``--engage auto``: the pause after a refused engage mode or arm before the
next try (each try also waits up to 0.5 s for its ACK and ``_REASON_WAIT_S``)."""
_REASON_WAIT_S = 0.2
"""After a refusal: how long the STATUSTEXT saying why may follow the ACK."""
_PILOT_TRIES = 10
"""``--engage rc-switch``: the engage mode is tried this often, ``_REASON_WAIT_S``
apart (the pilot is waiting), before the engagement is given up."""
_READY_POLL_S = 0.05


class Engagement:
    """Engaging, releasing, failing safe and handing back (mixed into the app)."""

    # What the app holds and these methods use.
    opts: RunOptions
    link: Any
    controller: RateController
    stack: FlightStack | None
    engaged: bool
    commanding: bool
    _stop: asyncio.Event
    _exit_code: int
    _events_file: EventLog
    _engage_task: asyncio.Task[None] | None
    _tasks: set[asyncio.Task[Any]]
    _handing_back: bool
    _hand_back_accepted: bool
    _hand_back_owed: bool
    _hand_back_idle: asyncio.Event
    _in_failsafe: bool
    _safe_modes: tuple[SafeMode, ...]
    _ap_mode: int | None
    _ap_armed: bool
    _ap_status: int | None
    _prearm_ready: bool | None
    _ap_heartbeats: int
    _rc_wall: float | None
    _pos_wall: float | None
    _rc_receiver_healthy: bool
    n_sys_status: int

    if TYPE_CHECKING:  # the app's

        def _event(self, kind: str, detail: str) -> None: ...

        def _spawn(self, coro: Any, name: str) -> asyncio.Task[Any]: ...

        def _reset_laws(self) -> None: ...

        def _not_ready_to_engage(self) -> str | None: ...

        def position_fresh(self) -> bool: ...

        def _setpoints_now_flown(self) -> None: ...

    needs_position: bool
    setpoints_flown: bool
    mode_before_engaging: int | None

    async def _engage_offboard(self, *, arm: bool) -> None:
        """Stream setpoints, switch to the stack's engage mode, arm if asked.

        PX4 refuses OFFBOARD unless setpoints already stream, so they start
        first; ArduPilot ignores them until GUIDED_NOGPS. Each step is
        ACK-checked and tried again while refused, each refusal an event quoting
        the stack's own words (:meth:`_until_accepted`). With ``--engage auto``
        the stack may not be ready yet (ArduCopter has no altitude estimate for
        the first seconds after boot, no position for 40-50 s): the engage mode
        and the arming are tried every ``_RETRY_S`` until ``arm_timeout_s``
        after the engagement began, and arming waits first for the stack's
        pre-arm checks to pass, where its SYS_STATUS reports them. With
        ``rc-switch`` (the pilot waits) the engage mode is tried
        ``_PILOT_TRIES`` times.
        """
        assert self.stack is not None
        stack = self.stack
        # The estimates a flight mode needs may still be on their way (asked for
        # at start-up, an --engage auto run engages at once): wait for them a while.
        why = self._not_ready_to_engage()
        # An --engage auto run starts with the autopilot, maybe before its estimator
        # or the pilot's input is up: it waits as long as it waits to arm.
        wait_s = self.opts.arm_timeout_s if self.opts.engage == "auto" else _ESTIMATES_WAIT_S
        estimates_by = time.monotonic() + max(wait_s, _ESTIMATES_WAIT_S)
        while why is not None and time.monotonic() < estimates_by and not self._stop.is_set():
            # (The pilot's switch going low meanwhile cancels this task: _on_rc.)
            await asyncio.sleep(0.02)
            why = self._not_ready_to_engage()
        if why is not None:
            self._event("engage_failed", why)
            if self.opts.engage == "auto":
                self._exit_code = EXIT_ERROR
                self._stop.set()
            return
        self.mode_before_engaging = self._ap_mode
        self.setpoints_flown = False
        self.commanding = True
        self._reset_laws()
        auto = self.opts.engage == "auto"
        deadline = time.monotonic() + self.opts.arm_timeout_s if auto else None
        await asyncio.sleep(0.3)  # PX4 wants setpoints already streaming (>= 2 Hz)
        try:
            p2, p3 = stack.engage_mode
            if not await self._until_accepted(
                "engage_mode_refused",
                f"its engage mode ({stack.engage_label})",
                stack.mode_refusals,
                _CMD_DO_SET_MODE,
                (_MODE_FLAG_CUSTOM, p2, p3),
                deadline=deadline,
            ):
                return  # released meanwhile (switch back low, failsafe): stop here
            if arm and not await self._until_accepted(
                "arm_refused",
                "to arm",
                stack.arm_refusals,
                _CMD_ARM_DISARM,
                (1,),
                deadline=deadline,
                when_ready=True,
            ):
                return
            self._setpoints_now_flown()
        except (EngageError, LinkError) as exc:
            self.commanding = False
            self._event("engage_failed", str(exc))
            if self.opts.engage == "auto":
                self._exit_code = EXIT_ERROR
                self._stop.set()

    async def _until_accepted(
        self,
        kind: str,
        what: str,
        refusals: tuple[str, ...],
        command: int,
        params: tuple[float, ...],
        *,
        deadline: float | None,
        when_ready: bool = False,
    ) -> bool:
        """Send ``command`` (COMMAND_LONG, with ``params``) until the autopilot
        accepts it: True; False if the companion was released meanwhile.

        Each refusal is an event ``kind`` with the try's number and the
        autopilot's reason: what it said since that try began in a STATUSTEXT
        beginning as one of ``refusals`` (:func:`companion.stacks.said_why`),
        never an unrelated text. Tried again ``_RETRY_S`` later while that is
        before ``deadline`` (monotonic), or, with no deadline, up to
        ``_PILOT_TRIES`` times; ``when_ready``: each try waits first, until the
        deadline, for the stack's pre-arm checks to pass where it reports them.

        Raises
        ------
        EngageError
            When the tries run out, naming the last reason.
        """
        assert self.stack is not None
        name = self.stack.name
        t0 = time.monotonic()
        attempt = 0
        while True:
            if when_ready and deadline is not None:
                await self._wait_ready_to_arm(deadline)
            if not self.commanding:
                return False
            attempt += 1
            mark = self._events_file.count
            res = await self.link.command_long(command, *params, timeout_s=0.5)
            if res == _RESULT_ACCEPTED:
                return True
            await asyncio.sleep(_REASON_WAIT_S)  # a STATUSTEXT with the reason may follow the ACK
            reason = said_why(self._said_since(mark), refusals) or "it said no reason"
            self._event(kind, f"try {attempt}: MAV_RESULT {res}: {reason}")
            if deadline is None:
                more = attempt < _PILOT_TRIES
            else:
                more = time.monotonic() + _RETRY_S < deadline
            if not more:
                tries = "1 try" if attempt == 1 else f"{attempt} tries"
                raise EngageError(
                    f"{name} refused {what} (MAV_RESULT {res}), {tries} in "
                    f"{time.monotonic() - t0:.1f} s: {reason}"
                )
            if not self.commanding:
                return False
            if deadline is not None:
                await asyncio.sleep(_RETRY_S)

    async def _wait_ready_to_arm(self, deadline: float) -> None:
        """Until ``deadline`` (monotonic): wait while the autopilot's SYS_STATUS says
        its pre-arm checks fail (``_prearm_ready`` False; None, not reported: at
        once). At the deadline the arming is tried all the same: its refusal
        says why in the stack's own words."""
        if self._prearm_ready is not False or not self.commanding:
            return
        t0 = time.monotonic()
        self._event(
            "arm_waiting",
            f"the autopilot's pre-arm checks do not pass yet (SYS_STATUS): waiting up to "
            f"{max(0.0, deadline - t0):.0f} s",
        )
        while self._prearm_ready is False and self.commanding and time.monotonic() < deadline:
            await asyncio.sleep(_READY_POLL_S)
        if self._prearm_ready:
            self._event("arm_ready", f"pre-arm checks pass after {time.monotonic() - t0:.1f} s")

    def _said_since(self, mark: int) -> list[str]:
        """What the autopilot said (its STATUSTEXTs, each recorded as an
        ``autopilot_says`` event) since the run had recorded ``mark`` events."""
        log = self._events_file
        new = min(log.count - mark, len(log.recent))
        if new <= 0:
            return []
        recent = list(log.recent)[-new:]
        return [str(e["detail"]) for e in recent if e["kind"] == "autopilot_says"]

    def _release(self) -> bool:
        """Stop commanding now, in the caller's callback; return whether we were.

        Called the moment a failsafe or the pilot's switch says so, so no later
        sample (even one in the same datagram) gets a command, and an engagement
        still in flight is abandoned rather than switching the autopilot back.
        """
        was = self.commanding
        self.commanding = False
        self.engaged = False
        self.setpoints_flown = False
        task = self._engage_task
        if task is not None and not task.done():
            task.cancel()
        return was

    def _start_engage(self, *, arm: bool) -> None:
        old = self._engage_task
        if old is not None and not old.done():
            old.cancel()
        self._engage_task = asyncio.get_running_loop().create_task(
            self._engage_offboard(arm=arm), name="engage"
        )
        self._tasks.add(self._engage_task)
        self._engage_task.add_done_callback(self._tasks.discard)

    async def _hand_back(
        self, reason: str, *, was_commanding: bool | None = None, kind: str = ""
    ) -> None:
        """Stop commanding and switch the autopilot to a safe mode it can fly.

        ``was_commanding`` comes from :meth:`_release` when the caller already
        stopped the commands; otherwise the current state decides. ``kind`` is
        the failsafe's, if one: after RC loss no manual mode is chosen.
        """
        if self._handing_back:
            # One is under way (a failsafe's, the pilot's switch): stop any
            # engagement that waits behind it, and let it finish rather than be
            # cancelled with the run's tasks (its commands time out within ~1 s).
            self._release()
            await self._hand_back_idle.wait()
            if self._hand_back_accepted or not self._autopilot_in_engage_mode():
                return
            # It ended unanswered with the autopilot still in OFFBOARD: try again.
            was_commanding = True
        self._handing_back = True
        self._hand_back_accepted = False
        self._hand_back_idle.clear()
        try:
            released = self._release()
            was_commanding = released if was_commanding is None else was_commanding
            if (
                not was_commanding
                or self.link is None
                or self.link.target is None
                or self.stack is None
            ):
                return
            await self._switch_to_safe_mode(
                reason,
                rc_failsafe=kind == "failsafe_rc_lost",
                adopt=kind == "failsafe_autopilot_took_over",
            )
        finally:
            self._handing_back = False
            self._hand_back_idle.set()

    def _conditions(self, *, rc_failsafe: bool) -> Conditions:
        now = time.perf_counter()
        rc, pos = self._rc_wall, self._pos_wall
        position = pos is not None and now - pos <= _POSITION_TIMEOUT_S
        if self.needs_position:  # the modes that fly on it judge it themselves
            position = position and self.position_fresh()
        return Conditions(
            # Frames that came while the receiver was healthy, and it still is (ArduPilot
            # streams a lost radio's last pulses; its SYS_STATUS says it is lost).
            rc_valid=rc is not None
            and now - rc <= self.opts.failsafe.rc_timeout_s
            and self._rc_receiver_healthy,
            position_valid=position,
            rc_failsafe=rc_failsafe,
            autopilot_failsafe=failsafe_state(self._ap_status),
        )

    async def _switch_to_safe_mode(self, reason: str, *, rc_failsafe: bool, adopt: bool) -> None:
        """Try the safe modes in order (companion.handback) until one holds.

        A mode the autopilot refuses is followed by the next one; a mode it
        leaves (its own failsafe) or never shows within ``hand_back_watch_s``,
        by the next one of a more conservative kind (manual -> hold -> land). A
        switch that goes unanswered ends it here: the run's end tries again
        (``_hand_back_owed``). With ``adopt`` (the autopilot's heartbeat showed
        it leave OFFBOARD by itself), a mode it can fly there is kept: the
        companion does not override the autopilot's failsafe or the pilot's
        mode switch."""
        assert self.stack is not None
        stack, modes = self.stack, self._safe_modes
        if adopt and failsafe_state(self._ap_status) and self.n_sys_status:
            # The autopilot announces its failsafe's mode at once, in a HEARTBEAT; what
            # failed (its RC receiver) comes in its next SYS_STATUS: judge on that.
            seen = self.n_sys_status
            wait_by = time.monotonic() + _SYS_STATUS_WAIT_S
            while self.n_sys_status == seen and time.monotonic() < wait_by:
                await asyncio.sleep(0.01)
        ap_mode = self._ap_mode
        cond = self._conditions(rc_failsafe=rc_failsafe)
        if adopt and ap_mode is not None and adoptable(stack, ap_mode, cond):
            # The autopilot (its failsafe) or the pilot already chose a mode: keep it.
            self._hand_back_accepted = True
            self._event(
                "handed_back",
                f"{reason}; {cond.describe()} -> {stack.mode_label(ap_mode)} kept "
                "(the autopilot's mode)",
            )
            return
        start = 0
        while True:
            choice = pick(modes, start, cond)
            mode = choice.mode
            skipped = f" ({choice.why_skipped()})" if choice.skipped else ""
            if mode is None:
                self._event("hand_back_failed", f"{reason}; no safe mode left{skipped}")
                return
            name = mode.name.upper()
            why = f"{reason}; {cond.describe()}{skipped} -> {name}"
            before = self._ap_mode  # as shown before the switch (a heartbeat may follow the ACK)
            try:
                res = await self.link.command_long(
                    _CMD_DO_SET_MODE,
                    _MODE_FLAG_CUSTOM,
                    mode.param2,
                    mode.param3,
                    timeout_s=0.3,
                    retries=2,
                )
            except LinkError as exc:
                self._hand_back_accepted = False
                self._hand_back_owed = True
                self._event("handed_back", f"{why}: mode switch unanswered ({exc})")
                return
            if res != _RESULT_ACCEPTED:
                self._event("handed_back", f"{why} refused ({res})")
                reason, start = f"{name} refused", choice.index + 1
                cond = self._conditions(rc_failsafe=rc_failsafe)
                continue
            self._hand_back_accepted = True
            self._hand_back_owed = False
            self._event("handed_back", f"{why} accepted")
            failed = await self._watch_safe_mode(modes, choice.index, before)
            if failed is None:
                return
            self._hand_back_accepted = False
            self._event("safe_mode_lost", failed)
            reason, start = failed, next_kind(modes, choice.index)
            cond = self._conditions(rc_failsafe=rc_failsafe)

    async def _watch_safe_mode(
        self, modes: tuple[SafeMode, ...], index: int, before: int | None
    ) -> str | None:
        """Watch the autopilot's HEARTBEAT for ``hand_back_watch_s`` after a switch to
        ``modes[index]`` from ``before`` (the mode shown when the switch was sent):
        None if the vehicle stays in a mode it can fly, else why not.

        Each heartbeat's mode and failsafe state (its ``system_status``) are judged
        together (:func:`companion.handback.judge`): leaving the mode, or failing
        safe in a mode flown from the sticks, loses it. Until the new mode shows,
        a heartbeat still showing the mode from before the switch (or the engage
        mode) may have been sent before it: only another mode is judged at once.
        So the failsafe state judged is the one sent with the new mode or after:
        a state from before the switch is never held against it, but one that
        was failing safe before and still is when the new mode shows is failing
        safe in it. A pilot-free mode kept (the autopilot's own landing) ends the
        watch; a mode flown from the sticks, ours or one the pilot took, is
        watched to the end (the autopilot may raise its failsafe in it a moment
        after it shows it), and once the pilot has taken one, a pilot-free mode
        they go on to ends the watch as theirs. A new engagement (the pilot's
        switch) or a disarm ends the watch. With no heartbeat at all meanwhile
        (a lost link) there is nothing to judge by: the mode stays."""
        assert self.stack is not None
        stack = self.stack
        target = stack.custom_mode(modes[index])
        watch_s = self.opts.failsafe.hand_back_watch_s
        if watch_s <= 0.0:
            return None  # not watched: the ACK is all there is
        t0 = time.perf_counter()
        heartbeats0 = self._ap_heartbeats
        seen = False
        pilots = False  # the pilot (or the autopilot) put it in another mode flown from the sticks
        while True:
            elapsed = time.perf_counter() - t0
            if self.commanding:
                return None  # engaged again meanwhile: the pilot's call
            mode = self._ap_mode
            if not self._ap_armed and mode is not None and (seen or mode != target):
                self._event("safe_mode_held", f"disarmed after {elapsed:.1f} s")
                return None
            if mode == target:
                seen = True
            if mode is not None and (seen or (mode != before and not stack.is_engage_mode(mode))):
                label = stack.mode_label(mode)
                sticks = stack.needs_rc(mode)
                if pilots and not sticks and not stack.is_engage_mode(mode):
                    self._event("safe_mode_held", f"{label} kept after {elapsed:.1f} s")
                    return None  # from a mode of their own, the pilot's next one is theirs too
                # Judged on RC as it is now: a pilot with the radio back may take it.
                failed = judge(stack, modes, index, mode, self._conditions(rc_failsafe=False))
                if failed is not None:
                    return f"{failed} after {elapsed:.1f} s"
                if mode != target:
                    if not sticks:
                        self._event("safe_mode_held", f"{label} kept after {elapsed:.1f} s")
                        return None
                    pilots = True
            if elapsed >= watch_s:
                if self._ap_heartbeats == heartbeats0:
                    self._event(
                        "safe_mode_unconfirmed",
                        f"no heartbeat for {watch_s:g} s after the switch to "
                        f"{modes[index].name.upper()}: left as it is",
                    )
                    return None
                if not seen and not pilots:
                    return (
                        f"the autopilot accepted {modes[index].name.upper()} but did not show it "
                        f"within {watch_s:g} s"
                    )
                if mode == target:
                    self._event("safe_mode_held", f"{modes[index].name.upper()} for {watch_s:g} s")
                else:
                    label = "its mode" if mode is None else stack.mode_label(mode)
                    self._event("safe_mode_held", f"{label} kept for {watch_s:g} s")
                return None
            await asyncio.sleep(_WATCH_POLL_S)

    def _autopilot_in_engage_mode(self) -> bool:
        """The autopilot's last heartbeat showed the mode we engage in (OFFBOARD, GUIDED_NOGPS)."""
        return (
            self.stack is not None
            and self._ap_mode is not None
            and self.stack.is_engage_mode(self._ap_mode)
        )

    def _failsafe(self, kind: str, detail: str) -> None:
        """Stop commanding now and hand back; record it afterwards, best effort.

        Nothing here waits on or can be stopped by I/O: the commands stop in
        this call, the hand-back task is started before the event is recorded,
        and recording never raises (:meth:`_event`)."""
        if self._stop.is_set() or self._in_failsafe:
            return  # one failsafe at a time: the first reason is the one logged
        self._in_failsafe = True
        was = self._release()
        self._spawn(self._after_failsafe(kind, detail, was), "failsafe")
        self._event(kind, detail)

    async def _after_failsafe(self, kind: str, detail: str, was_commanding: bool) -> None:
        try:
            await self._hand_back(detail, was_commanding=was_commanding, kind=kind)
        finally:
            self._in_failsafe = False
            if self.opts.failsafe.on_failsafe == "exit" or self.opts.engage == "auto":
                self._exit_code = EXIT_FAILSAFE
                self._stop.set()
        # "wait": an rc-switch run re-engages on the next low-to-high edge; a
        # switch still high stays "high" until the pilot moves it low first.
