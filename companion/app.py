"""The companion app: MFC in the loop over MAVLink, with failsafes.

Data flows one way: MAVLink bytes -> parsed sample -> control law -> command ->
MAVLink bytes. Each processed IMU sample produces exactly one control update
and (when commanding) one command, inside the link's receive callback: no
queue, no task switch on that path. Logs and telemetry hang off the side
(in-memory buffers handed to one writer thread through a bounded queue; a
bounded MQTT queue) and never wait on I/O.

:class:`Companion` is the run's asyncio shell around its flight core
(:class:`companion.core.FlightCore`, the run's decisions, with no I/O): it
opens the link and the records, feeds the core what arrives and carries out
what the core asks (the commands, the events, engaging and handing back:
:class:`companion.engagement.Engagement`), and keeps the background tasks
(the wall-clock watchdogs and the link's measure:
:class:`companion.watchdogs.Watchdogs`) and the signals.

Start-up (:class:`companion.startup.StartUp`): wait for the autopilot's
heartbeat, refuse a stack that cannot take the chosen output, request the
streams; then engage per ``engage``: ``auto`` (stream setpoints, switch to the
stack's engage mode, arm once its pre-arm checks pass), ``rc-switch`` (while an
RC channel is high) or ``none`` (shadow mode: compute and log, send no
setpoint, mode or arm command). Engaged means the autopilot's heartbeat shows
the engage mode and armed; the controller is reset on that edge, so ``F`` is
learnt only from commands that were really applied.

Every failsafe (the table: docs/failsafes.md) ends in the same hand-back: stop
commanding at once, switch the autopilot to a safe mode it can fly, record why
(no I/O can stop a hand-back), then exit or wait to be engaged again. Every
command passes the last gate (companion.control.gate) on its way out: no NaN
and nothing out of range reaches the wire.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import signal
import time
from collections import deque
from collections.abc import Coroutine, Sequence
from typing import Any

from companion.core import FlightCore
from companion.engagement import Engagement
from companion.errors import (
    EXIT_BAD_INPUT,
    EXIT_ERROR,
    EXIT_FAILSAFE,
    EXIT_OK,
    EngageError,
    LinkError,
    LogDirInUseError,
)
from companion.fast_path import add_fast_handlers
from companion.records.run_records import RunRecords
from companion.run_options import RunOptions
from companion.startup import StartUp
from companion.watchdogs import Watchdogs, link_figures

_TASKS_STOP_S = 2.0
"""How long the run's end waits for its background tasks after cancelling them."""

_WARNING_EVENTS = frozenset({"fly_check_skipped", "rates_law_axes_assumed"})
"""Events logged as warnings, as the failsafes are: the pilot should see them."""

__all__ = [
    "EXIT_BAD_INPUT",
    "EXIT_ERROR",
    "EXIT_FAILSAFE",
    "EXIT_OK",
    "Companion",
    "RunOptions",
]

_log = logging.getLogger("companion.app")


class Companion:
    """One run of the companion against one autopilot.

    Parameters
    ----------
    opts
        The run's options.
    transport
        A transport to use instead of opening ``opts.connect`` (tests).
    """

    def __init__(self, opts: RunOptions, *, transport: Any | None = None) -> None:
        self.opts = opts
        self._transport = transport
        self.link: Any = None
        self.autopilot: int | None = None
        self._stop = asyncio.Event()
        self._exit_code = EXIT_OK
        self._tasks: set[asyncio.Task[Any]] = set()
        self.records = RunRecords(opts)
        self.core = core = FlightCore(opts, self, time.perf_counter)
        self.engagement = Engagement(
            core,
            opts,
            events=lambda: self.records.events,
            event=self.event,
            end_run=self._end_run,
            stopping=self._stop.is_set,
            tasks=self._tasks,
        )
        self.watchdogs = Watchdogs(
            core,
            opts,
            self.records,
            event=self.event,
            end_run=self._end_run,
            stopped=self._stop.is_set,
            rerequest_streams=self.rerequest_streams,
            counters_detail=self.counters_detail,
            telemetry=lambda: self._telemetry,
            telemetry_failed=self._telemetry_failed,
        )
        self.n_event_errors = 0
        self.n_task_failures = 0
        self._counted_final = False
        self._mqtt: Any = None

    # ------------------------------------------------------- the core's shell
    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def send_actuator_controls(self, time_usec: int, controls: tuple[float, ...]) -> None:
        self.link.send_actuator_controls(time_usec, controls)

    def send_body_rates(self, time_boot_ms: int, rates: Sequence[float], thrust: float) -> None:
        self.link.send_body_rates(time_boot_ms, rates, thrust)

    def engage(self) -> None:
        self.engagement.start(arm=False)

    def cancel_engaging(self) -> bool:
        return self.engagement.cancel()

    def hand_back(self, reason: str, *, was_commanding: bool) -> None:
        self._spawn(self.engagement.hand_back(reason, was_commanding=was_commanding), "hand-back")

    def after_failsafe(self, kind: str, detail: str, *, was_commanding: bool) -> None:
        self._spawn(self.engagement.after_failsafe(kind, detail, was_commanding), "failsafe")

    def rerequest_streams(self, why: str) -> None:
        self._spawn(self._rerequest_streams(why), "streams")

    def stop(self, *, hand_back_owed: bool) -> None:
        if hand_back_owed:
            self.engagement.hand_back_owed = True  # the run's end hands back
        self._stop.set()

    def _end_run(self, code: int) -> None:
        self._exit_code = code
        self._stop.set()

    @property
    def _telemetry(self) -> Any:
        """MQTT telemetry (companion.telemetry.MqttTelemetry), with --mqtt."""
        return self._mqtt

    @_telemetry.setter
    def _telemetry(self, telemetry: Any) -> None:
        self._mqtt = telemetry
        self.core.output.publish_sample = None if telemetry is None else telemetry.publish_sample

    # ------------------------------------------------------------ the run's state
    @property
    def engaged(self) -> bool:
        return self.core.engaged

    @property
    def commanding(self) -> bool:
        return self.core.commanding

    @property
    def started_up(self) -> bool:
        return self.core.started_up

    @property
    def events(self) -> deque[dict[str, Any]]:
        """The last events kept in memory (the events file, with --log-dir, has all)."""
        return self.records.events.recent

    @property
    def counters(self) -> dict[str, int]:
        return {
            **self.core.counters(),
            "events": self.records.events.count,
            "event_errors": self.n_event_errors,
            "task_failures": self.n_task_failures,
            "record_failures": self.watchdogs.n_record_failures,
        }

    def counters_detail(self) -> str:
        """Ours, the link's and the transport's non-zero counters, as ``name=value``,
        then the link's measured figures (``timesync.*``, ms) once it has answered."""
        c: dict[str, Any] = {k: v for k, v in self.counters.items() if v}
        if self.link is not None:
            c.update({f"link.{k}": v for k, v in self.link.counters.items() if v})
            c.update({f"transport.{k}": v for k, v in self.link.transport.counters.items() if v})
        telemetry_counters = getattr(self._telemetry, "counters", None)
        if isinstance(telemetry_counters, dict):
            c.update({f"telemetry.{k}": v for k, v in telemetry_counters.items() if v})
        live = self.records.live
        if live is not None:
            c.update({f"live.{k}": v for k, v in live.counters.items() if v})
        figures = link_figures(self.core)
        if figures["n"]:
            c.update({f"timesync.{k}": v for k, v in figures.items() if v is not None})
        return " ".join(f"{k}={v}" for k, v in c.items())

    # ------------------------------------------------------------------ events
    def event(self, kind: str, detail: str) -> None:
        """Record an event: in memory, the log, the events file, telemetry.

        Never raises: a failsafe calls it, and recording must not stop one. What
        fails is counted (``event_errors``) and logged once."""
        t_prev = self.core.time.t_prev
        t = t_prev if t_prev is not None else 0.0
        ev = {"t_s": round(t, 6), "wall": time.time(), "kind": kind, "detail": detail}
        warn = kind.startswith("failsafe") or kind in _WARNING_EVENTS
        level = logging.WARNING if warn else logging.INFO
        _log.log(level, "%s: %s", kind, detail)
        try:
            self.records.record_event(ev)
            if self._telemetry is not None:
                self._telemetry.publish_event(kind, detail, t)
                if kind != "counters":  # bookkeeping: the retained status keeps what matters
                    self._telemetry.publish_status(self._status(kind, t))
        except Exception:
            self.n_event_errors += 1
            if self.n_event_errors == 1:
                _log.exception("recording an event failed (logged once, counted after)")

    def _telemetry_failed(self, what: str) -> None:
        self.n_event_errors += 1
        if self.n_event_errors == 1:
            _log.exception("%s (logged once)", what)

    def _status(self, last_event: str, t: float) -> dict[str, Any]:
        core = self.core
        return {
            "state": "engaged" if core.engaged else ("commanding" if core.commanding else "idle"),
            "last_event": last_event,
            "t_s": t,
            "autopilot_mode": core.ap.mode,
            "armed": core.ap.armed,
            "output": self.opts.output,
            "engage": self.opts.engage,
        }

    def _spawn(self, coro: Any, name: str) -> asyncio.Task[Any]:
        """Start a background task that is watched: see :meth:`_task_done`."""
        task = asyncio.get_running_loop().create_task(coro, name=name)
        self._tasks.add(task)
        task.add_done_callback(self._task_done)
        return task

    def _task_done(self, task: asyncio.Task[Any]) -> None:
        """No background task ends quietly.

        A task that raised is counted, logged and recorded; so is the
        supervisor ending before the run does. Engaged (or commanding), either
        is a failsafe. Without the supervisor nobody watches the vehicle, so
        its loss also ends the run (exit 3), even with ``on_failsafe = wait``;
        so does a failed hand-back, whose retry is the run's own at its end.
        """
        self._tasks.discard(task)
        if task.cancelled():
            return
        name = task.get_name()
        exc = task.exception()
        if exc is None and not (name == "supervise" and not self._stop.is_set()):
            return
        self.n_task_failures += 1
        what = f"task {name} " + (f"raised {exc!r}" if exc is not None else "ended")
        _log.error("%s", what, exc_info=exc)
        core = self.core
        if core.engaged or core.commanding:
            core.failsafe("failsafe_task_failed", what)
        else:
            self.event("task_failed", what)
        if name in ("failsafe", "hand-back"):
            self.engagement.hand_back_owed = (
                True  # the run's own hand-back, at its end, tries again
            )
        if name in ("supervise", "failsafe", "hand-back") and not self._stop.is_set():
            core.failsafe_over()
            self._exit_code = EXIT_FAILSAFE
            self._stop.set()

    async def _rerequest_streams(self, why: str) -> None:
        """Ask for the streams again after the autopilot may have forgotten them."""
        try:
            await StartUp(self.link, self.core, self.opts, self.event).request_streams()
        except (LinkError, EngageError) as exc:
            self.event("streams_refused", f"{why}: {exc}")

    def _on_link_anomaly(self, kind: str, detail: str) -> None:
        """The link saw something wrong (frames spoofing the autopilot from another
        address, the autopilot moving address): an event (the link rate-limits it)."""
        self.event(f"link_{kind}", detail)

    async def _start_up(self) -> None:
        """Link up, wait for the autopilot, recognise it, request the streams."""
        opts = self.opts
        await self.link.start()
        hb_task = self.link.heartbeat_task
        if hb_task is not None:  # our heartbeat dying is a task failure like any other
            self._tasks.add(hb_task)
            hb_task.add_done_callback(self._task_done)
        if opts.mqtt_url:
            from companion.telemetry import MqttTelemetry

            self._telemetry = MqttTelemetry(opts.mqtt_url)
            self._telemetry.on_outage = self.event
            self._spawn(self._telemetry.run(), "mqtt")
        hb = await self.link.wait_heartbeat(opts.heartbeat_timeout_s)
        self.autopilot = int(hb.autopilot)
        start_up = StartUp(self.link, self.core, opts, self.event, self.records.learnt)
        self.engagement.safe_modes = await start_up.recognise(self.autopilot)
        await start_up.request_streams()
        self.core.started_up = True

    async def _until_stopped(self, coro: Coroutine[Any, Any, None]) -> bool:
        """Run ``coro`` unless the run is stopped first (then cancel it); True if it ran."""
        work = asyncio.ensure_future(coro)
        stop = asyncio.ensure_future(self._stop.wait())
        try:
            await asyncio.wait({work, stop}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            stop.cancel()
            if not work.done():
                work.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await work
        if work.cancelled():
            return False
        work.result()  # its exception, if it raised one
        return True

    def _final_counters(self) -> None:
        """Once per run, last: what was counted (and ignored) over the whole run."""
        if self._counted_final:
            return
        self._counted_final = True
        with contextlib.suppress(Exception):
            self.event("counters", self.counters_detail())

    async def _live_published(self, timeout_s: float) -> None:
        """Wait (bounded) until the live view has published what it was handed, so
        the run's last counters count all of it."""
        live = self.records.live
        if live is None:
            return
        live.flush()
        end = time.monotonic() + timeout_s
        while live.pending and time.monotonic() < end:
            await asyncio.sleep(0.01)

    def _on_signal(self, sig: int) -> None:
        self.event("signal", signal.Signals(sig).name)
        self._exit_code = EXIT_OK
        self._stop.set()
        # An engagement in flight sends no more mode commands; ``commanding`` is
        # left as it is, so the run's hand-back still switches to the safe mode.
        self.engagement.cancel()

    async def run(self) -> int:
        """Run until a signal, the duration, or a failsafe; returns the exit code."""
        from companion.link.mavlink import MavlinkLink
        from companion.link.signing import load_signing_key
        from companion.link.transport import open_transport

        opts = self.opts
        signing = load_signing_key(opts.signing_key) if opts.signing_key else None
        transport = self._transport or open_transport(opts.connect)
        records = self.records
        try:
            moved = records.open()
        except LogDirInUseError as exc:
            _log.error("%s", exc)
            return EXIT_ERROR
        except (OSError, ValueError) as exc:
            _log.error("cannot open the records in %s: %s", opts.log_dir, exc)
            records.close()
            return EXIT_ERROR
        if moved is not None:
            _log.warning("--log-dir %s: an earlier run's records moved to %s", opts.log_dir, moved)
            self.event("records_moved", f"an earlier run's records moved to {moved}")
        try:
            records.open_live()
        except OSError as exc:
            _log.error("%s", exc)
            records.close()
            return EXIT_ERROR
        core = self.core
        core.output.log_append = records.append
        if opts.failsafe.bounds_lifted:
            self.event(
                "bounds_lifted",
                "thresholds beyond their bounds (--beyond-bounds): "
                + "; ".join(opts.failsafe.bounds_lifted),
            )
        if opts.fly_check_event is not None:
            self.event(*opts.fly_check_event)
        mode = self.core.modes.mode
        if mode.needs_attitude:
            self.event("mode", mode.description)
        on_raw = records.tlog.write if records.tlog is not None else None
        self.link = MavlinkLink(
            transport,
            signing=signing,
            on_message=self._on_message,
            on_raw=on_raw,
            target_system=opts.autopilot_sysid,
            target_component=opts.autopilot_compid,
            on_anomaly=self._on_link_anomaly,
        )
        self.engagement.link = self.watchdogs.link = link = self.link
        add_fast_handlers(link, self.core)
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(NotImplementedError, RuntimeError):
                loop.add_signal_handler(sig, self._on_signal, sig)
        try:
            if not await self._until_stopped(self._start_up()):
                # A signal during start-up: nothing was engaged, nothing to hand back.
                self.event("stopped", "signal during start-up")
                return self._exit_code
            # Everything built during start-up lives as long as the run: move it out
            # of the cyclic collector's reach so its passes stay short.
            gc.collect()
            gc.freeze()
            self._spawn(self.watchdogs.supervise(), "supervise")
            self._spawn(self.watchdogs.measure_link(), "timesync")
            if opts.engage == "auto":
                self.engagement.start(arm=True)
            await self._stop.wait()
            engagement = self.engagement
            await engagement.hand_back(
                "run ended", was_commanding=True if engagement.hand_back_owed else None
            )
            await engagement.hand_back_once_the_link_is_back()
            await self._live_published(1.0)
            self._final_counters()
            if self._telemetry is not None:
                await self._telemetry.drain(1.0)  # the last events say why it ended
        except (LinkError, EngageError) as exc:
            self.event("error", str(exc))
            _log.error("%s", exc)
            self._exit_code = EXIT_ERROR
        finally:
            tasks = list(self._tasks)
            for task in tasks:
                task.cancel()
            if tasks:
                # Bounded: a task that does not end (a cancellation lost inside a
                # library) must not keep the program from stopping.
                _, stuck = await asyncio.wait(tasks, timeout=_TASKS_STOP_S)
                for task in stuck:
                    _log.error("task %s did not stop when cancelled; leaving it", task.get_name())
            with contextlib.suppress(Exception):
                await self.link.close()
            self._final_counters()  # if an error or a signal ended the run early
            records.close()
            records.close_live()
            gc.unfreeze()
            for sig in (signal.SIGINT, signal.SIGTERM):
                with contextlib.suppress(NotImplementedError, RuntimeError):
                    loop.remove_signal_handler(sig)
        return self._exit_code

    def _on_message(self, msg: Any) -> None:
        self.core.messages.on_message(msg, self.link.rx_perf_s)
