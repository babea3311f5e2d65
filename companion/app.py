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
:class:`companion.engagement.Engagement`), and keeps the wall-clock watchdogs,
the background tasks and the signals.

Start-up (:class:`companion.startup.StartUp`)
    Wait for the autopilot's heartbeat; refuse a stack that cannot take the
    chosen output; request the IMU stream at the loop rate and RC_CHANNELS
    (ACK-checked) and EXTENDED_SYS_STATE (best effort: its landed state stops
    identification on the ground); then engage per ``engage``:

    ``auto``       stream setpoints, switch to OFFBOARD, arm once the stack's
                   pre-arm checks pass (ACK-checked, tried again while refused,
                   within ``arm_timeout_s``);
    ``rc-switch``  take over while an RC channel is high, hand back when low;
    ``none``       shadow mode: compute and log; send no setpoint, mode or arm
                   command (only our heartbeat, the stream-rate requests and
                   TIMESYNC, which measures the link).

Engaged means the autopilot's heartbeat shows OFFBOARD and armed; the
controller is reset on that edge, so ``F`` is learnt only from commands that
were really applied.

Failsafes (each ends in the same hand-back; the table is docs/failsafes.md)
    stale IMU (no processed sample for ``stale_imu_s``), invalid IMU
    (non-finite or beyond the gyro range for ``invalid_imu_s``, or in more than
    ``invalid_fraction_max`` of the samples), an IMU clock that restarts (an
    autopilot reboot), a per-sample step that keeps raising, lost link (no
    autopilot heartbeat for ``link_timeout_s``), lost RC (no valid RC for
    ``rc_timeout_s`` while engaged; a glitch holds the last valid sticks),
    envelope (a rate beyond the profile's limit for ``envelope_time_s``, or the
    tracking error averaged over ``envelope_time_s`` beyond
    ``tracking_error_max_deg_s``), the autopilot leaving OFFBOARD by itself, a
    background task that dies, a record file that fails (with
    ``on_record_error = failsafe``), and SIGINT/SIGTERM. Hand-back: stop
    commanding at once, switch the autopilot to ``safe_mode``, then record why
    (best effort: no I/O can stop a hand-back), then exit (``on_failsafe =
    exit``, exit code 3; 0 for a signal) or wait to be engaged again
    (``wait``).

Every command passes the last gate (companion.control.gate) on its way out:
no NaN and nothing out of range reaches the wire.
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
from companion.link.timesync import LINK_RTT_SHOWN_MS, REQUEST_PERIOD_S
from companion.records.run_records import RunRecords
from companion.run_options import RunOptions
from companion.startup import StartUp

_COUNTERS_PERIOD_S = 10.0
"""How often the counters (ours, the link's, the transport's) go to the events."""

_TASKS_STOP_S = 2.0
"""How long the run's end waits for its background tasks after cancelling them."""

_DRAIN_TURNS = 16
"""Turns of the event loop a stale-looking IMU waits for datagrams already there."""

_LINK_REPORT_PERIOD_S = 1.0
"""How often the link's figures go to telemetry (and are judged slow or not)."""

_WARNING_EVENTS = frozenset({"fly_check_skipped"})
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

# MAVLink numbers used here (common.xml).
_MSG_ATTITUDE = 30
_MSG_ATTITUDE_QUATERNION = 31
_MSG_RC_CHANNELS = 65
_MSG_MANUAL_CONTROL = 69
_MSG_HIGHRES_IMU = 105
_RC_FIELDS = (*(f"chan{i}_raw" for i in range(1, 19)), "chancount")
_JOYSTICK_FIELDS = ("x", "y", "z", "r", "enabled_extensions", *(f"aux{i}" for i in range(1, 7)))


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
        self.n_event_errors = 0
        self.n_task_failures = 0
        self.n_record_failures = 0
        self._counted_final = False
        self._rc_lost_logged = False
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
        self.core.publish_sample = None if telemetry is None else telemetry.publish_sample

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
            "record_failures": self.n_record_failures,
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
        figures = self.link_figures()
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

    async def _supervise(self) -> None:
        """Wall-clock watchdogs: stale IMU, lost link, lost RC, failed records
        (invalid IMU samples are judged where they arrive, in :meth:`_on_imu`).

        Watched itself (:meth:`_task_done`): if it raises or ends, that is a
        failsafe and the end of the run."""
        fs = self.opts.failsafe
        core = self.core
        next_counters = time.perf_counter() + _COUNTERS_PERIOD_S
        link_lost = False
        while not self._stop.is_set():
            await asyncio.sleep(0.05)  # watchdog thresholds are >= 0.1 s
            now = time.perf_counter()
            if now >= next_counters:
                next_counters = now + _COUNTERS_PERIOD_S
                self.event("counters", self.counters_detail())
            self.records.events.flush()  # the tail of a burst goes out within a tick
            self._check_records()
            hb = self.link.last_heartbeat_monotonic_s
            if hb is not None and time.monotonic() - hb > fs.link_timeout_s:
                if not link_lost:
                    link_lost = True
                    if core.commanding or core.engaged:
                        core.failsafe(
                            "failsafe_link_lost", f"no heartbeat for {fs.link_timeout_s} s"
                        )
                    else:
                        self.event("link_lost", f"no heartbeat for {fs.link_timeout_s} s")
                        if self.opts.engage != "rc-switch":
                            self._exit_code = EXIT_FAILSAFE
                            self._stop.set()
                continue
            if link_lost:
                # Back (a reboot, a cable): streams asked for before are forgotten.
                link_lost = False
                self.event("link_restored", "the autopilot's heartbeat is back")
                self._spawn(self._rerequest_streams("link restored"), "streams")
            if not core.engaged:
                continue
            if core.imu_stale(now, fs.stale_imu_s) and await self._still_stale(fs.stale_imu_s):
                core.failsafe("failsafe_stale_imu", f"no IMU sample for {fs.stale_imu_s} s")
            elif not core.pilot.fresh(now):
                # When all traffic stops (a crash, a cut cable), RC, sent at a lower
                # rate, can expire first; the IMU's age says whether it was RC alone.
                last_imu = core.time.last_arrival
                imu_age = "none yet" if last_imu is None else f"{now - last_imu:.2f} s ago"
                detail = f"no valid RC for {fs.rc_timeout_s} s (last IMU sample {imu_age})"
                if core.rc_needed:
                    core.failsafe("failsafe_rc_lost", detail)
                elif not self._rc_lost_logged:
                    # A reference file with its own collective flies without RC: the
                    # loss only decides the hand-back's mode (no manual one).
                    self._rc_lost_logged = True
                    self.event("rc_lost", detail + ": the reference flies on")
            else:
                self._rc_lost_logged = False

    async def _still_stale(self, limit_s: float) -> bool:
        """The IMU looks stale: is it, once what waits in the socket is read?

        A companion held off the CPU (a loaded computer: measured up to 0.15 s
        with both cores busy) finds the samples that came meanwhile waiting
        unread, and this watchdog may wake first. The loop reads one datagram a
        turn: give it a few turns, then judge again."""
        for _ in range(_DRAIN_TURNS):
            await asyncio.sleep(0)
            if not self.core.imu_stale(time.perf_counter(), limit_s):
                return False
        return True

    def link_figures(self) -> dict[str, float | int | None]:
        """The link as measured: TIMESYNC round trips over the last few seconds
        and the last samples' age when their command left (ms; None: none yet)."""
        import numpy as np

        core = self.core
        figures = core.link_clock.stats().as_dict()
        ages = np.asarray(core.sample_ages_s[: core.n_ages])
        ages = ages[np.isfinite(ages)]
        for name, q in (("sample_age_p50_ms", 50), ("sample_age_p99_ms", 99)):
            figures[name] = round(float(np.percentile(ages, q)) * 1e3, 3) if ages.size else None
        return figures

    def _link_text(self) -> str:
        f = self.link_figures()
        if not f["n"]:
            return "no TIMESYNC answer yet"
        text = (
            f"round trip {f['rtt_median_ms']} ms (min {f['rtt_min_ms']}, max {f['rtt_max_ms']},"
            f" {f['n']} answers)"
        )
        if f["sample_age_p50_ms"] is not None:
            text += f", sample age {f['sample_age_p50_ms']} ms (p99 {f['sample_age_p99_ms']})"
        return text

    async def _measure_link(self) -> None:
        """Ask the autopilot's time every REQUEST_PERIOD_S (the answers arrive in
        ``_on_message``); every _LINK_REPORT_PERIOD_S publish the figures and judge
        the round trip against the slowest link the controller is shown to fly.

        Watched (:meth:`_spawn`): if it raises while engaged, that is a failsafe."""
        clock = self.core.link_clock
        link = self.link
        next_report = time.perf_counter() + _LINK_REPORT_PERIOD_S
        slow = False
        while not self._stop.is_set():
            link.send(link.mav.timesync_encode(0, clock.request(time.perf_counter())))
            await asyncio.sleep(REQUEST_PERIOD_S)
            now = time.perf_counter()
            if now < next_report:
                continue
            next_report = now + _LINK_REPORT_PERIOD_S
            figures = self.link_figures()
            if self._telemetry is not None:
                try:
                    self._telemetry.publish_link(figures)
                except Exception:  # telemetry is never a reason to hand back
                    self.n_event_errors += 1
                    if self.n_event_errors == 1:
                        _log.exception("publishing the link's figures failed (logged once)")
            median = figures["rtt_median_ms"]
            if median is None:
                continue
            if not slow and median > LINK_RTT_SHOWN_MS:
                slow = True
                self.event(
                    "link_slow",
                    f"{self._link_text()}: beyond the {LINK_RTT_SHOWN_MS:g} ms the controller"
                    " is shown to fly (docs/link.md)",
                )
            elif slow and median < 0.8 * LINK_RTT_SHOWN_MS:
                slow = False
                self.event("link_ok", self._link_text())

    def _check_records(self) -> None:
        """A record file that stopped being written: an event, a counter, and with
        ``on_record_error = failsafe`` a failsafe. Flying goes on otherwise."""
        core = self.core
        for name, exc in self.records.poll_failures():
            self.n_record_failures += 1
            detail = f"{name}: {exc}; that record stops, flying goes on"
            if self.opts.failsafe.on_record_error == "failsafe" and (
                core.engaged or core.commanding
            ):
                core.failsafe("failsafe_records", detail)
            else:
                self.event("records_failed", detail)

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
        start_up = StartUp(self.link, self.core, opts, self.event)
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
        core.log_append = records.append
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
        self.engagement.link = link = self.link
        self._add_fast_handlers(link)
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
            self._spawn(self._supervise(), "supervise")
            self._spawn(self._measure_link(), "timesync")
            if opts.engage == "auto":
                self.engagement.start(arm=True)
            await self._stop.wait()
            engagement = self.engagement
            await engagement.hand_back(
                "run ended", was_commanding=True if engagement.hand_back_owed else None
            )
            await engagement.hand_back_once_the_link_is_back()
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

    def _add_fast_handlers(self, link: Any) -> None:
        """The messages on the control path skip pymavlink's generic parser when
        their frame allows: the IMU sample, the estimates, the pilot's frames."""
        core = self.core

        def on_highres_imu(v: tuple[Any, ...]) -> None:
            core.on_highres_imu(v, link.rx_perf_s)

        def on_attitude(v: tuple[Any, ...]) -> None:
            core.on_attitude(v, link.rx_perf_s)

        def on_rc(v: tuple[Any, ...]) -> None:
            core.on_rc(v, time.perf_counter())

        def on_manual_control(v: tuple[Any, ...]) -> None:
            core.on_manual_control(v, time.perf_counter())

        link.add_fast_handler(
            _MSG_HIGHRES_IMU, ("time_usec", "xgyro", "ygyro", "zgyro"), on_highres_imu
        )
        link.add_fast_handler(
            _MSG_ATTITUDE, ("time_boot_ms", "rollspeed", "pitchspeed", "yawspeed"), on_attitude
        )
        if core.needs_attitude:
            link.add_fast_handler(
                _MSG_ATTITUDE_QUATERNION,
                ("time_boot_ms", "q1", "q2", "q3", "q4"),
                core.modes.on_attitude_quaternion,
            )
        # RC_CHANNELS often shares the IMU sample's datagram: keep it short too.
        link.add_fast_handler(_MSG_RC_CHANNELS, _RC_FIELDS, on_rc)
        link.add_fast_handler(_MSG_MANUAL_CONTROL, _JOYSTICK_FIELDS, on_manual_control)

    def _on_message(self, msg: Any) -> None:
        self.core.on_message(msg, self.link.rx_perf_s)
