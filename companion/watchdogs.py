"""The run's wall-clock watchdogs and the link's measure: the shell's background watch.

:meth:`Watchdogs.supervise` looks every 50 ms (the thresholds are 0.1 s and
more): a stale IMU (no sample processed for ``stale_imu_s``, judged once what
waits in the socket is read), a lost link (no autopilot heartbeat for
``link_timeout_s``; back, the streams are asked for again), lost RC (no valid
frame of the pilot's for ``rc_timeout_s``), a record file that stopped being
written; and every ``_COUNTERS_PERIOD_S`` it records the counters. Invalid IMU
samples are judged where they arrive, in the flight core.

:meth:`Watchdogs.measure_link` asks the autopilot's time (TIMESYNC) every
:data:`~companion.link.timesync.REQUEST_PERIOD_S` and every
``_LINK_REPORT_PERIOD_S`` publishes the link's figures and judges the round
trip against the slowest link the controller is shown to fly.

Both run as the shell's watched tasks: one that raises or ends while engaged
is a failsafe (:class:`companion.app.Companion`).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from typing import Any

from companion.core import FlightCore
from companion.errors import EXIT_FAILSAFE
from companion.link.timesync import LINK_RTT_SHOWN_MS, REQUEST_PERIOD_S
from companion.records.run_records import RunRecords
from companion.run_options import RunOptions

__all__ = ["Watchdogs", "link_figures"]

_log = logging.getLogger("companion.app")

_COUNTERS_PERIOD_S = 10.0
"""How often the counters (ours, the link's, the transport's) go to the events."""

_DRAIN_TURNS = 16
"""Turns of the event loop a stale-looking IMU waits for datagrams already there."""

_LINK_REPORT_PERIOD_S = 1.0
"""How often the link's figures go to telemetry (and are judged slow or not)."""


def link_figures(core: FlightCore) -> dict[str, float | int | None]:
    """The link as measured: TIMESYNC round trips over the last few seconds and
    the last samples' age when their command left (ms; None: none yet)."""
    import numpy as np

    figures = core.link_clock.stats().as_dict()
    ages = np.asarray(core.output.sample_ages_s[: core.output.n_ages])
    ages = ages[np.isfinite(ages)]
    for name, q in (("sample_age_p50_ms", 50), ("sample_age_p99_ms", 99)):
        figures[name] = round(float(np.percentile(ages, q)) * 1e3, 3) if ages.size else None
    return figures


def _link_text(f: dict[str, float | int | None]) -> str:
    if not f["n"]:
        return "no TIMESYNC answer yet"
    text = (
        f"round trip {f['rtt_median_ms']} ms (min {f['rtt_min_ms']}, max {f['rtt_max_ms']},"
        f" {f['n']} answers)"
    )
    if f["sample_age_p50_ms"] is not None:
        text += f", sample age {f['sample_age_p50_ms']} ms (p99 {f['sample_age_p99_ms']})"
    return text


class Watchdogs:
    """The run's background watch (module docstring).

    Parameters
    ----------
    core, opts, records
        The run's flight core, options and records.
    event
        Records an event.
    end_run
        Ends the run with an exit code.
    stopped
        Whether the run is ending.
    rerequest_streams
        Asks the autopilot for the streams again (a task), saying why.
    counters_detail
        The run's counters as one line.
    telemetry
        The run's MQTT telemetry, or None.
    telemetry_failed
        Counts (and logs once) a telemetry publish that raised.
    """

    def __init__(
        self,
        core: FlightCore,
        opts: RunOptions,
        records: RunRecords,
        *,
        event: Callable[[str, str], None],
        end_run: Callable[[int], None],
        stopped: Callable[[], bool],
        rerequest_streams: Callable[[str], None],
        counters_detail: Callable[[], str],
        telemetry: Callable[[], Any],
        telemetry_failed: Callable[[str], None],
    ) -> None:
        self.core = core
        self.opts = opts
        self.records = records
        self.event = event
        self.end_run = end_run
        self.stopped = stopped
        self.rerequest_streams = rerequest_streams
        self.counters_detail = counters_detail
        self.telemetry = telemetry
        self.telemetry_failed = telemetry_failed
        self.link: Any = None
        """The MAVLink link, once the shell has opened it."""
        self.n_record_failures = 0
        self._rc_lost_logged = False

    async def supervise(self) -> None:
        """The wall-clock watchdogs (module docstring), until the run ends."""
        fs = self.opts.failsafe
        core = self.core
        next_counters = time.perf_counter() + _COUNTERS_PERIOD_S
        link_lost = False
        while not self.stopped():
            await asyncio.sleep(0.05)  # watchdog thresholds are >= 0.1 s
            now = time.perf_counter()
            if now >= next_counters:
                next_counters = now + _COUNTERS_PERIOD_S
                self.event("counters", self.counters_detail())
            self.records.events.flush()  # the tail of a burst goes out within a tick
            self.check_records()
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
                            self.end_run(EXIT_FAILSAFE)
                continue
            if link_lost:
                # Back (a reboot, a cable): streams asked for before are forgotten.
                link_lost = False
                self.event("link_restored", "the autopilot's heartbeat is back")
                self.rerequest_streams("link restored")
            if not core.engaged:
                continue
            if core.imu_stale(now, fs.stale_imu_s) and await self.still_stale(fs.stale_imu_s):
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

    async def still_stale(self, limit_s: float) -> bool:
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

    def check_records(self) -> None:
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

    async def measure_link(self) -> None:
        """TIMESYNC and the link's figures (module docstring), until the run ends;
        the answers arrive through the core."""
        clock = self.core.link_clock
        link = self.link
        next_report = time.perf_counter() + _LINK_REPORT_PERIOD_S
        slow = False
        while not self.stopped():
            link.send(link.mav.timesync_encode(0, clock.request(time.perf_counter())))
            await asyncio.sleep(REQUEST_PERIOD_S)
            now = time.perf_counter()
            if now < next_report:
                continue
            next_report = now + _LINK_REPORT_PERIOD_S
            figures = link_figures(self.core)
            telemetry = self.telemetry()
            if telemetry is not None:
                try:
                    telemetry.publish_link(figures)
                except Exception:  # telemetry is never a reason to hand back
                    self.telemetry_failed("publishing the link's figures failed")
            median = figures["rtt_median_ms"]
            if median is None:
                continue
            if not slow and median > LINK_RTT_SHOWN_MS:
                slow = True
                self.event(
                    "link_slow",
                    f"{_link_text(figures)}: beyond the {LINK_RTT_SHOWN_MS:g} ms the controller"
                    " is shown to fly (docs/link.md)",
                )
            elif slow and median < 0.8 * LINK_RTT_SHOWN_MS:
                slow = False
                self.event("link_ok", _link_text(figures))
