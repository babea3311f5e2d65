"""The companion app: MFC in the loop over MAVLink, with failsafes.

Data flows one way: MAVLink bytes -> parsed sample -> control law -> command ->
MAVLink bytes. Each processed IMU sample produces exactly one control update
and (when commanding) one command, inside the link's receive callback: no
queue, no task switch on that path. Logs and telemetry hang off the side
(in-memory buffers handed to one writer thread through a bounded queue; a
bounded MQTT queue) and never wait on I/O.

Start-up
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

This module is the run's life: start-up, the watchdogs, the records, the end.
Its parts: the sample path (:mod:`companion.samples`), engaging and handing back
(:mod:`companion.engagement`), the failsafes judged per sample
(:mod:`companion.failsafe`), the per-sample step shared with the lab
(:mod:`companion.step`).
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import math
import os
import signal
import time
from collections import deque
from collections.abc import Coroutine
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from companion.config import MfcConfig, PidConfig, build_controller
from companion.errors import (
    EXIT_BAD_INPUT,
    EXIT_ERROR,
    EXIT_FAILSAFE,
    EXIT_OK,
    EngageError,
    LinkError,
    LogDirInUseError,
)
from companion.failsafe import FailsafeConfig
from companion.handback import candidates
from companion.link.timesync import LINK_RTT_SHOWN_MS, REQUEST_PERIOD_S
from companion.mission import Mission
from companion.profile import VehicleProfile
from companion.records import EventLog
from companion.reference import ReferenceScript
from companion.samples import SamplePath
from companion.stacks import FlightStack, RateShapingParams, SafeMode, StickParams, stack_for
from companion.step import LANDED_STATE_RATE_HZ

_COUNTERS_PERIOD_S = 10.0
"""How often the counters (ours, the link's, the transport's) go to the events."""

_TASKS_STOP_S = 2.0
"""How long the run's end waits for its background tasks after cancelling them."""

_HAND_BACK_RETRY_S = 15.0
"""How long the run's end goes on asking for a safe mode the autopilot did not
answer (a cut link), unless the autopilot shows it left the engage mode."""
_HAND_BACK_RETRY_PERIOD_S = 0.1
_LINK_QUIET_S = 1.5
"""No autopilot heartbeat for this long (1 Hz) after an unanswered hand-back: the
link is down, and the hand-back waits for it."""

_DRAIN_TURNS = 16
"""Turns of the event loop a stale-looking IMU waits for datagrams already there."""

_LINK_REPORT_PERIOD_S = 1.0
"""How often the link's figures go to telemetry (and are judged slow or not)."""

_EVENTS_KEPT = 1000
"""Events kept in memory (``Companion.events``); the events file has them all."""

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
_MSG_LOCAL_POSITION_NED = 32
_MSG_RC_CHANNELS = 65
_MSG_HIGHRES_IMU = 105
_CMD_SET_MESSAGE_INTERVAL = 511
_RESULT_ACCEPTED = 0
_RESULT_DENIED = 2
_MSG_EXTENDED_SYS_STATE = 245
_POSITION_RATE_HZ = 4.0
_HOLD_POSITION_RATE_HZ = 50.0
"""The position estimate's rate the altitude and position modes fly on."""
_MODE_TEXT = {
    "angle": "angle: sticks to roll and pitch angles up to the autopilot's own limit and a "
    "yaw rate, on the autopilot's ATTITUDE_QUATERNION",
    "altitude": "altitude: sticks to roll and pitch angles, a climb rate (the altitude held "
    "at mid-stick) and a yaw rate, within the autopilot's own limits, on "
    "ATTITUDE_QUATERNION and LOCAL_POSITION_NED",
    "position": "position: sticks to a horizontal velocity and a climb rate (the position "
    "and altitude held at mid-stick) and a yaw rate, shaped as the autopilot's own Position "
    "mode shapes them, on ATTITUDE_QUATERNION and LOCAL_POSITION_NED",
}
_MSG_ATTITUDE_TARGET = 83
_ATTITUDE_TARGET_RATE_HZ = 20.0
"""The autopilot's own collective, which the hold modes take over at."""
_STICK_PARAM_TIMEOUT_S = 0.25
"""Each stick-limit parameter is asked twice at most, all at once: an autopilot that
does not answer one costs the start-up 0.5 s, not a second per parameter."""
_GUID_OPTIONS_THRUST = 8  # ArduPilot GUID_OPTIONS bit 3: SET_ATTITUDE_TARGET thrust is thrust
_RC_FIELDS = (*(f"chan{i}_raw" for i in range(1, 19)), "chancount")
_JOYSTICK_FIELDS = ("x", "y", "z", "r", "enabled_extensions", *(f"aux{i}" for i in range(1, 7)))
_MSG_MANUAL_CONTROL = 69
_MSG_SYS_STATUS = 1
_SYS_STATUS_RATE_HZ = 5.0


@dataclass(frozen=True)
class RunOptions:
    """Everything a run needs, validated before anything is opened."""

    connect: str
    profile: VehicleProfile
    controller: MfcConfig | PidConfig
    profile_path: str = ""
    controller_path: str = ""
    output: Literal["actuator", "rates"] = "actuator"
    mode: Literal["rates", "angle", "altitude", "position"] = "rates"
    """What the sticks ask: body rates, or the outer loops on the autopilot's
    estimates (:mod:`companion.modes`)."""
    mission: Mission | None = None
    """With ``mode="position"``: waypoints flown from where each engagement starts,
    instead of the sticks (:mod:`companion.mission`)."""
    engage: Literal["auto", "rc-switch", "none"] = "rc-switch"
    imu_source: Literal["auto", "highres_imu", "attitude"] = "auto"
    """"auto": the stack's (PX4 HIGHRES_IMU, ArduPilot ATTITUDE)."""
    loop_rate_hz: float = 250.0
    rc_rate_hz: float = 50.0
    engage_channel: int = 5
    rates_full_scale_deg_s: float = 360.0
    """With ``output="rates"``: the rate correction a full-scale law output makes.
    It sets the input gain the law sees through the autopilot's rate loop:
    measured on paper-acro with the PX4-like SITL, the profile's 1080 deg/s made
    the Tarot oscillate into the envelope failsafe, 360 flew every vehicle."""
    rates_lead_s: float = 0.03
    """With ``output="rates"`` (not pass-through): a feed-forward lead added to the
    setpoint, ``rates_lead_s`` times the derivative of the prefiltered pilot rate.
    The autopilot's closed rate loop lags its setpoint (about 70 ms for the SITL's
    ArduPilot personality); the law's own feed-forward ``y_r''/alpha``, with alpha
    identified on that closed loop, is only about 8 ms of it. The lead is not
    taught to the F estimate as applied: taught, it drags the identified alpha
    down and the law's feedback rings. Measured: docs/research/ardupilot.md."""
    rates_passthrough: bool = False
    """With ``output="rates"``: send the pilot's rates unchanged (the baseline the
    MFC-on-top is compared with); the law still runs and is logged."""
    log_dir: Path | None = None
    mqtt_url: str | None = None
    live: tuple[str, int] | None = None
    """Serve the control log's topics live here, ``(host, port)`` (:mod:`companion.live`)."""
    signing_key: Path | None = None
    duration_s: float | None = None
    reference: ReferenceScript | None = None
    """Scripted rates (and maybe thrust) from engagement on, instead of the sticks."""
    heartbeat_timeout_s: float = 10.0
    arm_timeout_s: float = 60.0
    """With ``engage="auto"``: how long to keep trying the engage mode and the
    arming while the stack refuses them or its pre-arm checks fail (ArduCopter
    needs a few seconds after boot for an altitude estimate, 40-50 s for a
    position); 0: one try each."""
    fly_check_event: tuple[str, str] | None = None
    """The controller file's fly check (:mod:`companion.fly_check`) as an event
    ``(kind, detail)`` recorded at the start: ``fly_check_passed``, or
    ``fly_check_skipped`` (a warning too); None for a shipped file."""
    autopilot_sysid: int | None = None
    autopilot_compid: int | None = None
    """Pin the autopilot; ``None``: learn it from its first HEARTBEAT."""
    failsafe: FailsafeConfig = field(default_factory=FailsafeConfig)


class Companion(SamplePath):
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
        self.controller = build_controller(opts.controller, opts.profile)
        self._init_sample_path(opts)
        self.link: Any = None
        # Per-sample counters are plain attributes (a dict lookup per sample
        # adds up at 1 kHz); ``counters`` gathers them.
        self.n_event_errors = 0
        self.n_task_failures = 0
        self.n_record_failures = 0
        self.autopilot: int | None = None
        self.stack: FlightStack | None = None
        self.imu_rate_hz: float | None = None
        self._last_statustext = ""
        self.engaged = False
        self.commanding = False  # setpoints are being sent
        self._stop = asyncio.Event()
        self._exit_code = EXIT_OK
        self._rc_wall: float | None = None
        self._pos_wall: float | None = None
        self._safe_modes: tuple[SafeMode, ...] = ()
        self._ap_mode: int | None = None
        self._ap_armed = False
        self._ap_heartbeats = 0
        self._tasks: set[asyncio.Task[Any]] = set()
        self._engage_task: asyncio.Task[None] | None = None
        self._handing_back = False
        self._hand_back_idle = asyncio.Event()
        self._hand_back_idle.set()
        self._hand_back_accepted = False  # the last hand-back's mode switch was ACKed
        self._hand_back_owed = False  # a hand-back task failed: the run's end tries again
        self._counted_final = False
        self._in_failsafe = False
        self._log_rows: Any = None
        self._log_append: Any = None  # self._log_rows.append, looked up once
        # The law takes something from RC (the sticks, the throttle, the engage
        # switch) unless a reference file with its own collective flies it.
        self._rc_needed = (
            opts.engage == "rc-switch" or opts.reference is None or opts.reference.thrust is None
        )
        self._rc_lost_logged = False
        self._tlog: Any = None
        # The run's events: the last _EVENTS_KEPT in memory; with --log-dir,
        # _open_records gives it a file (all of them, through the writer thread).
        self._events_file = EventLog(ring_size=_EVENTS_KEPT)
        self._telemetry: Any = None
        self._writer: Any = None  # companion.records.RecordWriter, with --log-dir
        self._live: Any = None  # companion.live.LiveView, with --live
        self._log_dir_lock: int | None = None  # its lock file's descriptor, held till the end

    @property
    def events(self) -> deque[dict[str, Any]]:
        """The last ``_EVENTS_KEPT`` events (the events file, with --log-dir, has all)."""
        return self._events_file.recent

    @property
    def counters(self) -> dict[str, int]:
        return {
            "imu_samples": self.n_imu,
            "imu_duplicate_or_late": self.n_imu_duplicate_or_late,
            "imu_invalid": self.n_imu_invalid,
            "imu_time_jumps": self.n_imu_time_jumps,
            "imu_gaps": self.n_imu_gaps,
            "imu_time_outliers": self.n_imu_time_outliers,
            "imu_clock_resets": self.n_imu_clock_resets,
            "commands_sent": self.n_commands,
            "commands_gated": self.n_commands_gated,
            "sample_errors": self.n_sample_errors,
            "rc_invalid": self.n_rc_invalid,
            "rc_unhealthy": self.n_rc_unhealthy,
            "estimate_invalid": self.n_estimate_invalid,
            "position_invalid": self.n_position_invalid,
            "events": self._events_file.count,
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
        if self._live is not None:
            c.update({f"live.{k}": v for k, v in self._live.counters.items() if v})
        figures = self.link_figures()
        if figures["n"]:
            c.update({f"timesync.{k}": v for k, v in figures.items() if v is not None})
        return " ".join(f"{k}={v}" for k, v in c.items())

    # ------------------------------------------------------------------ events
    def _event(self, kind: str, detail: str) -> None:
        """Record an event: in memory, the log, the events file, telemetry.

        Never raises: a failsafe calls it, and recording must not stop one. What
        fails is counted (``event_errors``) and logged once."""
        t = self._t_prev if self._t_prev is not None else 0.0
        ev = {"t_s": round(t, 6), "wall": time.time(), "kind": kind, "detail": detail}
        warn = kind.startswith("failsafe") or kind in _WARNING_EVENTS
        level = logging.WARNING if warn else logging.INFO
        _log.log(level, "%s: %s", kind, detail)
        try:
            self._events_file.append(ev)  # memory, and a buffer the writer thread empties
            if self._log_rows is not None:
                self._log_rows.event(ev)  # the control log's /events, with its next rows
            if self._live is not None:
                self._live.event(ev)
            if self._telemetry is not None:
                self._telemetry.publish_event(kind, detail, t)
                if kind != "counters":  # bookkeeping: the retained status keeps what matters
                    self._telemetry.publish_status(self._status(kind, t))
        except Exception:
            self.n_event_errors += 1
            if self.n_event_errors == 1:
                _log.exception("recording an event failed (logged once, counted after)")

    def _status(self, last_event: str, t: float) -> dict[str, Any]:
        return {
            "state": "engaged" if self.engaged else ("commanding" if self.commanding else "idle"),
            "last_event": last_event,
            "t_s": t,
            "autopilot_mode": self._ap_mode,
            "armed": self._ap_armed,
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
        if self.engaged or self.commanding:
            self._failsafe("failsafe_task_failed", what)
        else:
            self._event("task_failed", what)
        if name in ("failsafe", "hand-back"):
            self._hand_back_owed = True  # the run's own hand-back, at its end, tries again
        if name in ("supervise", "failsafe", "hand-back") and not self._stop.is_set():
            self._in_failsafe = False
            self._exit_code = EXIT_FAILSAFE
            self._stop.set()

    async def _supervise(self) -> None:
        """Wall-clock watchdogs: stale IMU, lost link, lost RC, failed records
        (invalid IMU samples are judged where they arrive, in :meth:`_on_imu`).

        Watched itself (:meth:`_task_done`): if it raises or ends, that is a
        failsafe and the end of the run."""
        fs = self.opts.failsafe
        next_counters = time.perf_counter() + _COUNTERS_PERIOD_S
        link_lost = False
        while not self._stop.is_set():
            await asyncio.sleep(0.05)  # watchdog thresholds are >= 0.1 s
            now = time.perf_counter()
            if now >= next_counters:
                next_counters = now + _COUNTERS_PERIOD_S
                self._event("counters", self.counters_detail())
            self._events_file.flush()  # the tail of a burst goes out within a tick
            self._check_records()
            hb = self.link.last_heartbeat_monotonic_s
            if hb is not None and time.monotonic() - hb > fs.link_timeout_s:
                if not link_lost:
                    link_lost = True
                    if self.commanding or self.engaged:
                        self._failsafe(
                            "failsafe_link_lost", f"no heartbeat for {fs.link_timeout_s} s"
                        )
                    else:
                        self._event("link_lost", f"no heartbeat for {fs.link_timeout_s} s")
                        if self.opts.engage != "rc-switch":
                            self._exit_code = EXIT_FAILSAFE
                            self._stop.set()
                continue
            if link_lost:
                # Back (a reboot, a cable): streams asked for before are forgotten.
                link_lost = False
                self._event("link_restored", "the autopilot's heartbeat is back")
                self._spawn(self._rerequest_streams("link restored"), "streams")
            if not self.engaged:
                continue
            if self._imu_stale(now, fs.stale_imu_s) and await self._still_stale(fs.stale_imu_s):
                self._failsafe("failsafe_stale_imu", f"no IMU sample for {fs.stale_imu_s} s")
            elif self._rc_wall is None or now - self._rc_wall > fs.rc_timeout_s:
                # When all traffic stops (a crash, a cut cable), RC, sent at a lower
                # rate, can expire first; the IMU's age says whether it was RC alone.
                imu_age = (
                    "none yet"
                    if self._last_imu_wall is None
                    else f"{now - self._last_imu_wall:.2f} s ago"
                )
                detail = f"no valid RC for {fs.rc_timeout_s} s (last IMU sample {imu_age})"
                if self._rc_needed:
                    self._failsafe("failsafe_rc_lost", detail)
                elif not self._rc_lost_logged:
                    # A reference file with its own collective flies without RC: the
                    # loss only decides the hand-back's mode (no manual one).
                    self._rc_lost_logged = True
                    self._event("rc_lost", detail + ": the reference flies on")
            else:
                self._rc_lost_logged = False

    def _imu_stale(self, now: float, limit_s: float) -> bool:
        last = self._last_imu_wall
        return last is not None and now - last > limit_s

    async def _still_stale(self, limit_s: float) -> bool:
        """The IMU looks stale: is it, once what waits in the socket is read?

        A companion held off the CPU (a loaded computer: measured up to 0.15 s
        with both cores busy) finds the samples that came meanwhile waiting
        unread, and this watchdog may wake first. The loop reads one datagram a
        turn: give it a few turns, then judge again."""
        for _ in range(_DRAIN_TURNS):
            await asyncio.sleep(0)
            if not self._imu_stale(time.perf_counter(), limit_s):
                return False
        return True

    def link_figures(self) -> dict[str, float | int | None]:
        """The link as measured: TIMESYNC round trips over the last few seconds
        and the last samples' age when their command left (ms; None: none yet)."""
        import numpy as np

        figures = self.link_clock.stats().as_dict()
        ages = np.asarray(self.sample_ages_s[: self._n_ages])
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
        clock = self.link_clock
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
                self._event(
                    "link_slow",
                    f"{self._link_text()}: beyond the {LINK_RTT_SHOWN_MS:g} ms the controller"
                    " is shown to fly (docs/link.md)",
                )
            elif slow and median < 0.8 * LINK_RTT_SHOWN_MS:
                slow = False
                self._event("link_ok", self._link_text())

    def _check_records(self) -> None:
        """A record file that stopped being written: an event, a counter, and with
        ``on_record_error = failsafe`` a failsafe. Flying goes on otherwise."""
        writer = self._writer
        if writer is None:
            return
        for name, exc in writer.poll_failures():
            self.n_record_failures += 1
            detail = f"{name}: {exc}; that record stops, flying goes on"
            if self.opts.failsafe.on_record_error == "failsafe" and (
                self.engaged or self.commanding
            ):
                self._failsafe("failsafe_records", detail)
            else:
                self._event("records_failed", detail)

    async def _rerequest_streams(self, why: str) -> None:
        """Ask for the streams again after the autopilot may have forgotten them."""
        try:
            await self._request_streams()
        except (LinkError, EngageError) as exc:
            self._event("streams_refused", f"{why}: {exc}")

    # ------------------------------------------------------------------- run
    def _open_records(self) -> None:
        """Lock the log folder, move an earlier run's records aside, open the run's
        records; their writes go through one writer thread
        (companion.records.RecordWriter), so the disk never holds the loop.

        Raises
        ------
        LogDirInUseError
            If another run holds the folder (nothing in it is touched).
        OSError, ValueError
            If the folder cannot be locked or tidied, or a file cannot be created
            or its header written (start-up only).
        """
        from companion import __version__
        from companion.control import COMPILED
        from companion.records import (
            ControlLog,
            RecordWriter,
            TlogWriter,
            columns,
            lock_log_dir,
            prepare_log_dir,
        )

        d = self.opts.log_dir
        if d is None:
            return
        d.mkdir(parents=True, exist_ok=True)
        # The lock first: a second run on this folder must refuse before it moves
        # the live run's records away.
        self._log_dir_lock = lock_log_dir(d)
        moved = prepare_log_dir(d)
        self._writer = writer = RecordWriter()
        self._tlog = TlogWriter(d / "flight.tlog", writer=writer)
        opts = self.opts
        meta = {
            "profile": opts.profile.name,
            "profile_path": opts.profile_path,
            "controller": opts.controller.kind,
            "controller_path": opts.controller_path,
            "output": opts.output,
            "engage": opts.engage,
            "version": __version__,
            "control_compiled": COMPILED,
            "rates_full_scale_deg_s": repr(opts.rates_full_scale_deg_s),
            "rates_lead_s": repr(opts.rates_lead_s),
            "rates_passthrough": str(opts.rates_passthrough),
        }
        self._log_rows = ControlLog(
            d / "control.mcap", columns(opts.profile.n_motors), meta=meta, writer=writer
        )
        self._log_append = self._log_rows.append
        self._events_file = EventLog(d / "events.jsonl", writer=writer)
        if moved is not None:
            _log.warning("--log-dir %s: an earlier run's records moved to %s", d, moved)
            self._event("records_moved", f"an earlier run's records moved to {moved}")

    def _open_live(self) -> None:
        """With ``live``: serve the control log's rows and the events to viewers
        (:class:`companion.live.LiveView`); the loop hands it the row it builds.

        Raises
        ------
        OSError
            If it cannot listen there.
        """
        if self.opts.live is None:
            return
        from companion.live import LiveView, tee
        from companion.records import columns

        host, port = self.opts.live
        self._live = live = LiveView(columns(self.opts.profile.n_motors), host=host, port=port)
        live.start()
        appends = [a for a in (self._log_append, live.append) if a is not None]
        self._log_append = tee(*appends)

    def _close_records(self) -> None:
        """Hand the last buffers to the writer, let it drain (bounded), remove the
        records that hold nothing of a flight, then release the log folder."""
        for obj in (self._log_rows, self._tlog, self._events_file):
            if obj is not None:
                with contextlib.suppress(Exception):
                    obj.close()
        if self._writer is not None:
            with contextlib.suppress(Exception):
                self._writer.close(2.0)
        # A start that failed (no autopilot, a refused stack) must not leave files
        # that look like a flight: a control log without a row and a flight.tlog
        # without a frame from the autopilot go; events.jsonl stays and says why.
        rows, tlog = self._log_rows, self._tlog
        for record, empty in (
            (rows, rows is not None and rows.rows == 0),
            (tlog, tlog is not None and tlog.written_in == 0),
        ):
            if empty:
                with contextlib.suppress(OSError):
                    record.path.unlink()
        if self._log_dir_lock is not None:
            os.close(self._log_dir_lock)
            self._log_dir_lock = None

    async def run(self) -> int:
        """Run until a signal, the duration, or a failsafe; returns the exit code."""
        from companion.link.mavlink import MavlinkLink
        from companion.link.signing import load_signing_key
        from companion.link.transport import open_transport

        opts = self.opts
        signing = load_signing_key(opts.signing_key) if opts.signing_key else None
        transport = self._transport or open_transport(opts.connect)
        try:
            self._open_records()
        except LogDirInUseError as exc:
            _log.error("%s", exc)
            return EXIT_ERROR
        except (OSError, ValueError) as exc:
            _log.error("cannot open the records in %s: %s", opts.log_dir, exc)
            self._close_records()
            return EXIT_ERROR
        try:
            self._open_live()
        except OSError as exc:
            _log.error("%s", exc)
            self._close_records()
            return EXIT_ERROR
        if opts.failsafe.bounds_lifted:
            self._event(
                "bounds_lifted",
                "thresholds beyond their bounds (--beyond-bounds): "
                + "; ".join(opts.failsafe.bounds_lifted),
            )
        if opts.fly_check_event is not None:
            self._event(*opts.fly_check_event)
        if self.flight_mode != "rates":
            self._event("mode", _MODE_TEXT[self.flight_mode])
        on_raw = self._tlog.write if self._tlog is not None else None
        self.link = MavlinkLink(
            transport,
            signing=signing,
            on_message=self._on_message,
            on_raw=on_raw,
            target_system=opts.autopilot_sysid,
            target_component=opts.autopilot_compid,
            on_anomaly=self._on_link_anomaly,
        )
        # The IMU sample skips pymavlink's generic parser when its frame allows.
        self.link.add_fast_handler(
            _MSG_HIGHRES_IMU, ("time_usec", "xgyro", "ygyro", "zgyro"), self._on_highres_imu
        )
        self.link.add_fast_handler(
            _MSG_ATTITUDE,
            ("time_boot_ms", "rollspeed", "pitchspeed", "yawspeed"),
            self._on_attitude,
        )
        if self.needs_attitude:
            self.link.add_fast_handler(
                _MSG_ATTITUDE_QUATERNION,
                ("time_boot_ms", "q1", "q2", "q3", "q4"),
                self._on_attitude_quaternion,
            )
        # RC_CHANNELS often shares the IMU sample's datagram: keep it short too.
        self.link.add_fast_handler(_MSG_RC_CHANNELS, _RC_FIELDS, self._on_rc)
        self.link.add_fast_handler(_MSG_MANUAL_CONTROL, _JOYSTICK_FIELDS, self._on_manual_control)
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            with contextlib.suppress(NotImplementedError, RuntimeError):
                loop.add_signal_handler(sig, self._on_signal, sig)
        try:
            if not await self._until_stopped(self._start_up()):
                # A signal during start-up: nothing was engaged, nothing to hand back.
                self._event("stopped", "signal during start-up")
                return self._exit_code
            # Everything built during start-up lives as long as the run: move it out
            # of the cyclic collector's reach so its passes stay short.
            gc.collect()
            gc.freeze()
            self._spawn(self._supervise(), "supervise")
            self._spawn(self._measure_link(), "timesync")
            if opts.engage == "auto":
                self._start_engage(arm=True)
            await self._stop.wait()
            await self._hand_back(
                "run ended", was_commanding=True if self._hand_back_owed else None
            )
            await self._hand_back_once_the_link_is_back()
            self._final_counters()
            if self._telemetry is not None:
                await self._telemetry.drain(1.0)  # the last events say why it ended
        except (LinkError, EngageError) as exc:
            self._event("error", str(exc))
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
            self._close_records()
            if self._live is not None:
                self._live.close()
            gc.unfreeze()
            for sig in (signal.SIGINT, signal.SIGTERM):
                with contextlib.suppress(NotImplementedError, RuntimeError):
                    loop.remove_signal_handler(sig)
        return self._exit_code

    async def _hand_back_once_the_link_is_back(self) -> None:
        """A hand-back that went unanswered (the link cut while engaged) is tried
        again until the autopilot answers, shows it left the engage mode by itself,
        or ``_HAND_BACK_RETRY_S`` has passed. An autopilot with no offboard-loss
        failsafe of its own (ArduCopter: after GUID_TIMEOUT it levels and stays in
        GUIDED_NOGPS) would otherwise be left in the companion's mode with nobody
        flying it (measured on the real ArduCopter 4.5.6: a link cut for 3 s)."""
        deadline = time.monotonic() + _HAND_BACK_RETRY_S
        while self._hand_back_owed and time.monotonic() < deadline:
            # Only across a silent link: an autopilot whose heartbeats come but which
            # ignores the switch has had its answer (the run's own try, above).
            heard = self.link.last_heartbeat_monotonic_s
            if heard is not None and time.monotonic() - heard < _LINK_QUIET_S:
                return
            beats = self._ap_heartbeats
            while self._ap_heartbeats == beats and time.monotonic() < deadline:
                await asyncio.sleep(_HAND_BACK_RETRY_PERIOD_S)  # until it is heard again
            if self._ap_heartbeats == beats:
                return
            left = self._ap_mode is not None and not self._autopilot_in_engage_mode()
            if self.stack is not None and self._ap_mode is not None and left:
                self._event(
                    "hand_back_dropped",
                    f"the link is back; the autopilot left {self.stack.engage_label} by "
                    f"itself for {self.stack.mode_label(self._ap_mode)}",
                )
                return
            await self._hand_back("link back", was_commanding=True)

    def _on_link_anomaly(self, kind: str, detail: str) -> None:
        """The link saw something wrong (frames spoofing the autopilot from another
        address, the autopilot moving address): an event (the link rate-limits it)."""
        self._event(f"link_{kind}", detail)

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
            self._telemetry.on_outage = self._event
            self._spawn(self._telemetry.run(), "mqtt")
        hb = await self.link.wait_heartbeat(opts.heartbeat_timeout_s)
        self.autopilot = int(hb.autopilot)
        await self._recognise_stack()
        await self._request_streams()
        self.started_up = True

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
            self._event("counters", self.counters_detail())

    def _on_signal(self, sig: int) -> None:
        self._event("signal", signal.Signals(sig).name)
        self._exit_code = EXIT_OK
        self._stop.set()
        # An engagement in flight sends no more mode commands; ``commanding`` is
        # left as it is, so the run's hand-back still switches to the safe mode.
        task = self._engage_task
        if task is not None and not task.done():
            task.cancel()

    async def _recognise_stack(self) -> None:
        """Pick the stack's dialect and refuse what it cannot do, before sending anything."""
        stack = stack_for(self.autopilot or 0)
        if stack is None:
            raise EngageError(
                f"autopilot type {self.autopilot} is not supported (PX4 = 12, ArduPilot = 3)"
            )
        self.stack = stack
        self._event("connected", f"{stack.name} (autopilot {self.autopilot}) at {self.link.target}")
        opts = self.opts
        if opts.output == "actuator" and not stack.supports_actuator_output:
            raise EngageError(
                f"{stack.name} accepts no actuator setpoints over MAVLink: use --output rates"
            )
        try:
            self._safe_modes = candidates(stack, opts.failsafe.safe_mode)
        except ValueError as exc:
            raise EngageError(str(exc)) from None
        if self._imu_source == "auto":
            self._imu_source = stack.imu_message  # type: ignore[assignment]
        if stack.name == "ardupilot" and opts.output == "rates" and opts.engage != "none":
            # Our thrust is a normalised collective; ArduPilot reads it as a climb-rate
            # request unless GUID_OPTIONS bit 3 is set. Flying with the wrong meaning
            # would be dangerous: refuse instead.
            value = await self.link.param_read("GUID_OPTIONS")
            if not int(value) & _GUID_OPTIONS_THRUST:
                raise EngageError(
                    f"ArduPilot GUID_OPTIONS = {int(value)}: SET_ATTITUDE_TARGET thrust would "
                    "be read as a climb rate; set bit 3 (add 8, e.g. GUID_OPTIONS = "
                    f"{int(value) | _GUID_OPTIONS_THRUST}) so it is a normalised thrust"
                )
        if opts.output == "rates" and stack.rate_shaping is not None:
            await self._learn_rate_shaping(stack.rate_shaping)
        if self.needs_attitude:
            await self._learn_stick_limits(stack.stick_params)

    async def _learn_stick_limits(self, params: StickParams) -> None:
        """Read the autopilot's stick limits (companion.stacks: what its own modes
        let the sticks ask) and its hover thrust, and build the flight mode's law
        with them. A parameter it does not answer takes the stack's documented
        default, and an event says so; so do values the limits cannot take."""

        async def read(name: str) -> float | None:
            try:
                value = await self.link.param_read(
                    name, timeout_s=_STICK_PARAM_TIMEOUT_S, retries=1
                )
            except LinkError:
                return None
            return value if math.isfinite(value) else None

        names = params.names
        got = await asyncio.gather(*(read(n) for n in names))
        values = {n: v for n, v in zip(names, got, strict=True) if v is not None}
        missing = [n for n in names if n not in values]
        if missing:
            shown = ", ".join(f"{n} {params.defaults[n]:g}" for n in missing)
            self._event(
                "stick_limits_assumed",
                f"the autopilot did not answer {len(missing)} of {len(names)} parameters: "
                f"their defaults assumed ({shown})",
            )
        try:
            limits = params.limits(values)
        except ValueError as exc:
            self._event(
                "stick_limits_assumed",
                f"the autopilot's parameters give no usable limits ({exc}): its defaults assumed",
            )
            limits = params.limits()
            values = {}
        hover = values.get(params.hover_thrust, params.defaults[params.hover_thrust])
        self._event(
            "stick_limits",
            f"{limits.summary()}; hover thrust {hover:.3g} ({params.hover_thrust})",
        )
        self._build_mode_laws(limits, hover)

    async def _learn_rate_shaping(self, shaping: RateShapingParams) -> None:
        """Read how the autopilot shapes body-rate setpoints (ArduCopter's input
        shaping: companion.control.shaping) and give it to the step. Unreadable, its
        documented defaults are assumed, and an event says so."""
        values: list[float] = []
        try:
            enabled = await self.link.param_read(shaping.enable_param)
            for name in shaping.accel_params:
                values.append(await self.link.param_read(name))
        except LinkError as exc:
            values = list(shaping.default_accel_cdeg_s2)
            enabled = 1.0
            self._event(
                "rate_shaping_assumed",
                f"the autopilot's {shaping.enable_param} and {', '.join(shaping.accel_params)} "
                f"could not be read ({exc}): its defaults assumed",
            )
        if not int(enabled):
            self._event("rate_shaping", f"{shaping.enable_param} = 0: rate setpoints not shaped")
            return
        deg = tuple(v * 0.01 for v in values)
        self.step.set_rate_shaping(tuple(math.radians(d) for d in deg))  # type: ignore[arg-type]
        if self.step.shaper is not None:
            shown = "/".join(f"{d:g}" if d > 0 else "none" for d in deg)
            self._event(
                "rate_shaping",
                f"the autopilot limits a rate setpoint's acceleration to {shown} deg/s^2 "
                f"(roll/pitch/yaw, {', '.join(shaping.accel_params)}): the law flies the "
                "pilot's rates so shaped, its setpoints within them, no lead",
            )

    async def _request_streams(self) -> None:
        """The IMU stream at the highest rate the stack accepts up to the loop rate,
        falling back when a rate is DENIED; then RC_CHANNELS. ACK-checked. Then
        EXTENDED_SYS_STATE, best effort (a refusal is logged, not fatal)."""
        assert self.stack is not None
        imu_id = _MSG_HIGHRES_IMU if self._imu_source == "highres_imu" else _MSG_ATTITUDE
        want = min(self.opts.loop_rate_hz, self.stack.max_imu_rate_hz)
        rates = [want] + [r for r in (400.0, 333.0, 250.0, 200.0, 100.0, 50.0) if r < want]
        res = _RESULT_ACCEPTED
        for hz in rates:
            res = await self.link.command_long(_CMD_SET_MESSAGE_INTERVAL, imu_id, 1e6 / hz)
            if res == _RESULT_ACCEPTED:
                self.imu_rate_hz = hz
                self._event("imu_stream", f"message {imu_id} at {hz:g} Hz")
                break
            if res != _RESULT_DENIED:
                break
            self._event("imu_rate_denied", f"message {imu_id} at {hz:g} Hz denied")
        if self.imu_rate_hz is None:
            raise EngageError(
                f"the autopilot refused the IMU stream (message {imu_id}, last MAV_RESULT {res})"
            )
        res = await self.link.command_long(
            _CMD_SET_MESSAGE_INTERVAL, _MSG_RC_CHANNELS, 1e6 / self.opts.rc_rate_hz
        )
        if res != _RESULT_ACCEPTED:
            raise EngageError(
                f"the autopilot refused RC_CHANNELS at {self.opts.rc_rate_hz} Hz (MAV_RESULT {res})"
            )
        # The pilot's joystick where there is no radio (PX4 streams its MANUAL_CONTROL),
        # and the RC receiver's health (ArduPilot's RC_CHANNELS freeze when it is lost).
        await self._request_best_effort(
            "joystick_refused", "MANUAL_CONTROL", _MSG_MANUAL_CONTROL, self.opts.rc_rate_hz,
            "the pilot's input is RC_CHANNELS alone",
        )  # fmt: skip
        await self._request_best_effort(
            "sys_status_refused", "SYS_STATUS", _MSG_SYS_STATUS, _SYS_STATUS_RATE_HZ,
            "an RC receiver the autopilot calls lost is seen only when its frames stop",
        )  # fmt: skip
        if self.needs_attitude:
            # The outer loops fly on the autopilot's attitude estimate, as often as the IMU.
            assert self.imu_rate_hz is not None
            await self._request_for_mode(
                "ATTITUDE_QUATERNION", _MSG_ATTITUDE_QUATERNION, self.imu_rate_hz, event=True
            )
        if self.needs_position:
            await self._request_for_mode(
                "LOCAL_POSITION_NED", _MSG_LOCAL_POSITION_NED, _HOLD_POSITION_RATE_HZ, event=True
            )
            await self._request_best_effort(
                "attitude_target_refused", "ATTITUDE_TARGET", _MSG_ATTITUDE_TARGET,
                _ATTITUDE_TARGET_RATE_HZ,
                "the hold modes take over at the autopilot's hover thrust, not its collective",
            )  # fmt: skip
        # The landed state stops identification on the ground (MfcController.on_ground);
        # the flight modes hold their loops on the ground by it: for them it is needed.
        if self.needs_attitude:
            await self._request_for_mode(
                "EXTENDED_SYS_STATE", _MSG_EXTENDED_SYS_STATE, LANDED_STATE_RATE_HZ
            )
        else:
            await self._request_best_effort(
                "landed_state_refused", "EXTENDED_SYS_STATE", _MSG_EXTENDED_SYS_STATE,
                LANDED_STATE_RATE_HZ,
                "identification is gated by the collective alone unless the autopilot sends it",
            )  # fmt: skip
        # Whether a position estimate exists decides the hand-back's hold.
        if not self.needs_position:
            await self._request_best_effort(
                "position_refused", "LOCAL_POSITION_NED", _MSG_LOCAL_POSITION_NED,
                _POSITION_RATE_HZ, "a hand-back without RC lands unless the autopilot sends it",
            )  # fmt: skip

    async def _request_for_mode(
        self, name: str, msg_id: int, hz: float, *, event: bool = False
    ) -> None:
        """Ask for a stream the flight mode cannot fly without: a refusal stops the
        start-up (EngageError); ``event``: an ``estimate_stream`` event once granted."""
        res = await self.link.command_long(_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)
        if res != _RESULT_ACCEPTED:
            raise EngageError(
                f"the autopilot refused {name} at {hz:g} Hz (MAV_RESULT {res}): "
                f"--mode {self.flight_mode} flies on it"
            )
        if event:
            self._event("estimate_stream", f"{name} at {hz:g} Hz")

    async def _request_best_effort(
        self, kind: str, name: str, msg_id: int, hz: float, without: str
    ) -> None:
        """Ask for a stream the run can do without: a refusal is an event saying so."""
        res = await self.link.command_long(_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)
        if res != _RESULT_ACCEPTED:
            self._event(kind, f"{name} at {hz:g} Hz refused (MAV_RESULT {res}): {without}")
