"""Engagement and hand-back: taking the vehicle, and giving it back to a mode it
can fly on its own.

The asyncio side of the run's decisions, held by the shell
(:class:`companion.app.Companion`) beside the flight core
(:class:`companion.core.FlightCore`), whose state it reads and moves: engaging
streams setpoints, switches to the stack's engage mode and arms (with
``--engage auto``, once the stack is ready, tried again while it refuses,
within ``arm_timeout_s``); the core releases at once, in the call that finds a
reason; a hand-back then tries the safe modes in the order
:mod:`companion.handback` gives and watches that the autopilot keeps the one it
accepted and does not fail safe in it.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from typing import Any

from companion.core import FlightCore
from companion.errors import EXIT_ERROR, EXIT_FAILSAFE, EngageError, LinkError
from companion.handback import (
    Conditions,
    SafeModeWatch,
    adoptable,
    failsafe_state,
    next_kind,
    pick,
)
from companion.records import EventLog
from companion.run_options import RunOptions
from companion.stacks import SafeMode, said_why

__all__ = ["Engagement"]

# MAVLink numbers used here (common.xml).
_CMD_DO_SET_MODE = 176
_CMD_ARM_DISARM = 400
_RESULT_ACCEPTED = 0
_MODE_FLAG_CUSTOM = 1
_WATCH_POLL_S = 0.05
_SYS_STATUS_WAIT_S = 0.3
"""How long a hand-back that adopts the autopilot's failsafe waits for its next
SYS_STATUS (the companion asks for 5 Hz)."""
_ESTIMATES_WAIT_S = 1.0
"""How long an engagement waits for the estimates its flight mode needs."""
_RETRY_S = 1.0
"""``--engage auto``: the pause after a refused engage mode or arm before the
next try (each try also waits up to 0.5 s for its ACK and ``_REASON_WAIT_S``)."""
_ACK_TIMEOUT_S = 0.5
"""How long each of an engagement command's sends waits for its COMMAND_ACK."""
_REASON_WAIT_S = 0.2
"""After a refusal: how long the STATUSTEXT saying why may follow the ACK."""
_PILOT_TRIES = 10
"""``--engage rc-switch``: the engage mode is tried this often, ``_REASON_WAIT_S``
apart (the pilot is waiting), before the engagement is given up."""
_READY_POLL_S = 0.05
_HAND_BACK_RETRY_S = 15.0
"""How long the run's end goes on asking for a safe mode the autopilot did not
answer (a cut link), unless the autopilot shows it left the engage mode."""
_HAND_BACK_RETRY_PERIOD_S = 0.1
_LINK_QUIET_S = 1.5
"""No autopilot heartbeat for this long (1 Hz) after an unanswered hand-back: the
link is down, and the hand-back waits for it."""


class Engagement:
    """Engaging and handing back, for one run: the shell's, beside its core.

    Parameters
    ----------
    core
        The run's flight core: the state engaged, commanding and the
        autopilot's, which this reads and moves.
    opts
        The run's options.
    events, event
        The run's event log as it is now (what the autopilot said since a
        command was sent); what records an event.
    end_run, stopping
        What ends the run with an exit code; whether it is ending.
    tasks
        The run's tasks (an engagement is one, cancelled at the run's end).
    clock
        The clock, s, that the engagement's own waits, retries, deadlines and
        the safe-mode watch are timed on (monotonic).
    sleep
        How it waits that long (``sleep(seconds)``). A test gives both, to time
        the engagement deterministically; the readings judged against the
        core's arrival stamps come from the core's own clock.
    """

    def __init__(
        self,
        core: FlightCore,
        opts: RunOptions,
        *,
        events: Callable[[], EventLog],
        event: Callable[[str, str], None],
        end_run: Callable[[int], None],
        stopping: Callable[[], bool],
        tasks: set[asyncio.Task[Any]],
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], Awaitable[None]] = asyncio.sleep,
    ) -> None:
        self.core = core
        self.opts = opts
        self.link: Any = None
        """The MAVLink link, once the shell has opened it."""
        self.events_log = events
        self.event = event
        self.end_run = end_run
        self.stopping = stopping
        self.tasks = tasks
        self.clock = clock
        self.sleep = sleep
        self.safe_modes: tuple[SafeMode, ...] = ()
        self._task: asyncio.Task[None] | None = None
        self.hand_back_accepted = False
        """The last hand-back's mode switch was ACKed."""
        self.hand_back_owed = False
        """A hand-back failed or went unanswered: the run's end tries again."""
        self.idle = asyncio.Event()
        self.idle.set()

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
        assert self.core.stack is not None
        stack = self.core.stack
        # The estimates a flight mode needs may still be on their way (asked for
        # at start-up, an --engage auto run engages at once): wait for them a while.
        why = self.core.not_ready_to_engage(self.core.clock())
        # An --engage auto run starts with the autopilot, maybe before its estimator
        # or the pilot's input is up: it waits as long as it waits to arm.
        wait_s = self.opts.arm_timeout_s if self.opts.engage == "auto" else _ESTIMATES_WAIT_S
        estimates_by = self.clock() + max(wait_s, _ESTIMATES_WAIT_S)
        while why is not None and self.clock() < estimates_by and not self.stopping():
            # (The pilot's switch going low meanwhile cancels this task: _on_rc.)
            await self.sleep(0.02)
            why = self.core.not_ready_to_engage(self.core.clock())
        if why is not None:
            self.event("engage_failed", why)
            if self.opts.engage == "auto":
                self.end_run(EXIT_ERROR)
            return
        self.core.begin_commanding()
        auto = self.opts.engage == "auto"
        deadline = self.clock() + self.opts.arm_timeout_s if auto else None
        await self.sleep(0.3)  # PX4 wants setpoints already streaming (>= 2 Hz)
        try:
            p2, p3 = stack.engage_mode
            ap = self.core.ap
            if not await self._until_accepted(
                "engage_mode_refused",
                f"its engage mode ({stack.engage_label})",
                stack.mode_refusals,
                _CMD_DO_SET_MODE,
                (_MODE_FLAG_CUSTOM, p2, p3),
                deadline=deadline,
                shows=lambda: ap.mode is not None and stack.is_engage_mode(ap.mode),
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
                shows=lambda: ap.armed,
            ):
                return
            self.core.setpoints_now_flown()
        except (EngageError, LinkError) as exc:
            self.core.commanding = False
            self.event("engage_failed", str(exc))
            if self.opts.engage == "auto":
                self.end_run(EXIT_ERROR)

    async def _until_accepted(
        self,
        kind: str,
        what: str,
        refusals: tuple[str, ...],
        command: int,
        params: tuple[float, ...],
        *,
        deadline: float | None,
        shows: Callable[[], bool],
        when_ready: bool = False,
    ) -> bool:
        """Send ``command`` (COMMAND_LONG, with ``params``) until the autopilot
        accepts it: True; False if the companion was released meanwhile.

        An ACK may be lost on the way back while the command took effect: a try
        no ACK answered counts as accepted when the autopilot's heartbeat
        ``shows`` the effect (the mode, armed) after ``_REASON_WAIT_S``, or by the
        next try; otherwise as a refusal ("no COMMAND_ACK"), tried again like one
        (a mode already set or an arming already done is accepted again).

        Each refusal is an event ``kind`` with the try's number and the
        autopilot's reason: what it said since that try began in a STATUSTEXT
        beginning as one of ``refusals`` (:func:`companion.stacks.said_why`),
        never an unrelated text. Tried again ``_RETRY_S`` later while that is
        before ``deadline`` (the engagement's clock), or, with no deadline, up to
        ``_PILOT_TRIES`` times; ``when_ready``: each try waits first, until the
        deadline, for the stack's pre-arm checks to pass where it reports them.

        Raises
        ------
        EngageError
            When the tries run out, naming the last reason.
        """
        assert self.core.stack is not None
        name = self.core.stack.name
        t0 = self.clock()
        attempt = 0
        while True:
            if when_ready and deadline is not None:
                await self._wait_ready_to_arm(deadline)
            if not self.core.commanding:
                return False
            if attempt and shows():
                return True  # the last try took effect, its ACK lost
            attempt += 1
            mark = self.events_log().count
            try:
                res: int | None = await self.link.command_long(
                    command, *params, timeout_s=_ACK_TIMEOUT_S
                )
            except LinkError as exc:
                res, unanswered = None, str(exc)
            if res == _RESULT_ACCEPTED:
                return True
            await self.sleep(_REASON_WAIT_S)  # a STATUSTEXT with the reason may follow the ACK
            if res is None:
                if shows():
                    return True
                answer, reason = "no ACK", unanswered
            else:
                answer = f"MAV_RESULT {res}"
                reason = said_why(self._said_since(mark), refusals) or "it said no reason"
            self.event(kind, f"try {attempt}: {answer}: {reason}")
            if deadline is None:
                # The pilot is waiting: an autopilot that does not answer is told at once.
                more = attempt < _PILOT_TRIES and res is not None
            else:
                more = self.clock() + _RETRY_S < deadline
            if not more:
                tries = "1 try" if attempt == 1 else f"{attempt} tries"
                raise EngageError(
                    f"{name} refused {what} ({answer}), {tries} in "
                    f"{self.clock() - t0:.1f} s: {reason}"
                )
            if not self.core.commanding:
                return False
            if deadline is not None:
                await self.sleep(_RETRY_S)

    async def _wait_ready_to_arm(self, deadline: float) -> None:
        """Until ``deadline`` (the engagement's clock): wait while the autopilot's
        SYS_STATUS says its pre-arm checks fail (``_prearm_ready`` False; None, not
        reported: at once). At the deadline the arming is tried all the same: its refusal
        says why in the stack's own words."""
        if self.core.ap.prearm_ready is not False or not self.core.commanding:
            return
        t0 = self.clock()
        self.event(
            "arm_waiting",
            f"the autopilot's pre-arm checks do not pass yet (SYS_STATUS): waiting up to "
            f"{max(0.0, deadline - t0):.0f} s",
        )
        ap = self.core.ap
        while ap.prearm_ready is False and self.core.commanding and self.clock() < deadline:
            await self.sleep(_READY_POLL_S)
        if self.core.ap.prearm_ready:
            self.event("arm_ready", f"pre-arm checks pass after {self.clock() - t0:.1f} s")

    def _said_since(self, mark: int) -> list[str]:
        """What the autopilot said (its STATUSTEXTs, each recorded as an
        ``autopilot_says`` event) since the run had recorded ``mark`` events."""
        log = self.events_log()
        new = min(log.count - mark, len(log.recent))
        if new <= 0:
            return []
        recent = list(log.recent)[-new:]
        return [str(e["detail"]) for e in recent if e["kind"] == "autopilot_says"]

    def start(self, *, arm: bool) -> None:
        """Start engaging (a task); an engagement under way is cancelled first."""
        old = self._task
        if old is not None and not old.done():
            old.cancel()
        self._task = asyncio.get_running_loop().create_task(
            self._engage_offboard(arm=arm), name="engage"
        )
        self.tasks.add(self._task)
        self._task.add_done_callback(self.tasks.discard)

    def cancel(self) -> bool:
        """Abandon an engagement under way; whether there was one."""
        task = self._task
        if task is None or task.done():
            return False
        task.cancel()
        return True

    async def hand_back(
        self, reason: str, *, was_commanding: bool | None = None, kind: str = ""
    ) -> None:
        """Stop commanding and switch the autopilot to a safe mode it can fly.

        ``was_commanding`` comes from :meth:`FlightCore.release` when the caller already
        stopped the commands; otherwise the current state decides. ``kind`` is
        the failsafe's, if one: after RC loss no manual mode is chosen.
        """
        if self.core.handing_back:
            # One is under way (a failsafe's, the pilot's switch): stop any
            # engagement that waits behind it, and let it finish rather than be
            # cancelled with the run's tasks (its commands time out within ~1 s).
            self.core.release()
            await self.idle.wait()
            if self.hand_back_accepted or not self.core.in_engage_mode():
                return
            # It ended unanswered with the autopilot still in OFFBOARD: try again.
            was_commanding = True
        self.core.handing_back = True
        self.hand_back_accepted = False
        self.idle.clear()
        try:
            released = self.core.release()
            was_commanding = released if was_commanding is None else was_commanding
            if (
                not was_commanding
                or self.link is None
                or self.link.target is None
                or self.core.stack is None
            ):
                return
            await self._switch_to_safe_mode(
                reason,
                rc_failsafe=kind == "failsafe_rc_lost",
                adopt=kind == "failsafe_autopilot_took_over",
            )
        finally:
            self.core.handing_back = False
            self.idle.set()

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
        core, ap = self.core, self.core.ap
        assert core.stack is not None
        stack, modes = core.stack, self.safe_modes
        if adopt and failsafe_state(ap.status) and ap.n_sys_status:
            # The autopilot announces its failsafe's mode at once, in a HEARTBEAT; what
            # failed (its RC receiver) comes in its next SYS_STATUS: judge on that.
            seen, wait_by = ap.n_sys_status, self.clock() + _SYS_STATUS_WAIT_S
            while ap.n_sys_status == seen and self.clock() < wait_by:
                await self.sleep(0.01)
        ap_mode = ap.mode
        cond = core.conditions(core.clock(), rc_failsafe=rc_failsafe)
        if adopt and ap_mode is not None and adoptable(stack, ap_mode, cond):
            # The autopilot (its failsafe) or the pilot already chose a mode: keep it.
            self.hand_back_accepted = True
            self.event(
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
                self.event("hand_back_failed", f"{reason}; no safe mode left{skipped}")
                return
            name = mode.name.upper()
            why = f"{reason}; {cond.describe()}{skipped} -> {name}"
            before = ap.mode  # as shown before the switch (a heartbeat may follow the ACK)
            try:
                res = await self.link.command_long(
                    _CMD_DO_SET_MODE, _MODE_FLAG_CUSTOM, mode.param2, mode.param3,
                    timeout_s=0.3, retries=2,
                )  # fmt: skip
            except LinkError as exc:
                self.hand_back_accepted = False
                self.hand_back_owed = True
                self.event("handed_back", f"{why}: mode switch unanswered ({exc})")
                return
            if res != _RESULT_ACCEPTED:
                self.event("handed_back", f"{why} refused ({res})")
                reason, start = f"{name} refused", choice.index + 1
                cond = core.conditions(core.clock(), rc_failsafe=rc_failsafe)
                continue
            self.hand_back_accepted = True
            self.hand_back_owed = False
            self.event("handed_back", f"{why} accepted")
            failed = await self._watch_safe_mode(modes, choice.index, before)
            if failed is None:
                return
            self.hand_back_accepted = False
            self.event("safe_mode_lost", failed)
            reason, start = failed, next_kind(modes, choice.index)
            cond = core.conditions(core.clock(), rc_failsafe=rc_failsafe)

    async def _watch_safe_mode(
        self, modes: tuple[SafeMode, ...], index: int, before: int | None
    ) -> str | None:
        """Watch the autopilot's HEARTBEAT for ``hand_back_watch_s`` after a switch to
        ``modes[index]`` from ``before`` (the mode shown when the switch was sent)
        (:class:`companion.handback.SafeModeWatch`): None if the vehicle stays in a
        mode it can fly, else why not."""
        core = self.core
        assert core.stack is not None
        watch_s = self.opts.failsafe.hand_back_watch_s
        if watch_s <= 0.0:
            return None  # not watched: the ACK is all there is
        watch = SafeModeWatch(core.stack, modes, index, before, watch_s, core.ap.heartbeats)

        def conditions() -> Conditions:
            return core.conditions(core.clock(), rc_failsafe=False)

        t0 = self.clock()
        while True:
            ap = core.ap
            end = watch.look(
                self.clock() - t0, ap.mode, ap.armed, ap.heartbeats, core.commanding, conditions
            )
            if end is not None:
                if end.event is not None:
                    self.event(*end.event)
                return end.failed
            await self.sleep(_WATCH_POLL_S)

    async def after_failsafe(self, kind: str, detail: str, was_commanding: bool) -> None:
        """Hand back after the core's failsafe; then end the run (``on_failsafe =
        exit``, or ``--engage auto``) or wait to be engaged again."""
        try:
            await self.hand_back(detail, was_commanding=was_commanding, kind=kind)
        finally:
            self.core.failsafe_over()
            if self.opts.failsafe.on_failsafe == "exit" or self.opts.engage == "auto":
                self.end_run(EXIT_FAILSAFE)
        # "wait": an rc-switch run re-engages on the next low-to-high edge; a
        # switch still high stays "high" until the pilot moves it low first.

    async def hand_back_once_the_link_is_back(self) -> None:
        """A hand-back that went unanswered (the link cut while engaged) is tried
        again until the autopilot answers, shows it left the engage mode by itself,
        or ``_HAND_BACK_RETRY_S`` has passed. An autopilot with no offboard-loss
        failsafe of its own (ArduCopter: after GUID_TIMEOUT it levels and stays in
        GUIDED_NOGPS) would otherwise be left in the companion's mode with nobody
        flying it (measured on the real ArduCopter 4.5.6: a link cut for 3 s)."""
        core, ap = self.core, self.core.ap
        deadline = self.clock() + _HAND_BACK_RETRY_S
        while self.hand_back_owed and self.clock() < deadline:
            # Only across a silent link: an autopilot whose heartbeats come but which
            # ignores the switch has had its answer (the run's own try, above).
            heard = self.link.last_heartbeat_monotonic_s  # stamped on time.monotonic
            if heard is not None and time.monotonic() - heard < _LINK_QUIET_S:
                return
            beats = ap.heartbeats
            while ap.heartbeats == beats and self.clock() < deadline:
                await self.sleep(_HAND_BACK_RETRY_PERIOD_S)  # until it is heard again
            if ap.heartbeats == beats:
                return
            stack, mode = core.stack, ap.mode
            if stack is not None and mode is not None and not core.in_engage_mode():
                left = f"{stack.engage_label} by itself for {stack.mode_label(mode)}"
                self.event("hand_back_dropped", f"the link is back; the autopilot left {left}")
                return
            await self.hand_back("link back", was_commanding=True)
