"""One run's records: the log folder, ``flight.tlog``, ``control.mcap``, ``events.jsonl``
and the live view, opened before the run and closed after it.

Every write goes through one writer thread (:class:`RecordWriter`), so the
disk never holds the control loop; the live view serves the same rows to
viewers on its own thread (:class:`companion.live.LiveView`).
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from companion.records.events import EventLog
from companion.records.topics import columns
from companion.run_options import RunOptions
from companion.step import law_axes_names

__all__ = ["EVENTS_KEPT", "RunRecords"]

_log = logging.getLogger("companion.app")

EVENTS_KEPT = 1000
"""Events kept in memory (``Companion.events``); the events file has them all."""


class RunRecords:
    """The records of one run of ``opts`` (none but the events in memory until
    :meth:`open`)."""

    def __init__(self, opts: RunOptions) -> None:
        self.opts = opts
        self.events = EventLog(ring_size=EVENTS_KEPT)
        """The run's events: the last ``EVENTS_KEPT`` in memory; once opened with
        a log folder, all of them in its events file too."""
        self.rows: Any = None  # companion.records.ControlLog, with a log folder
        self.append: Callable[[Sequence[float]], None] | None = None
        """Where each sample's row goes (the control log, the live view, or both)."""
        self.tlog: Any = None
        self.writer: Any = None  # companion.records.RecordWriter, with a log folder
        self.live: Any = None  # companion.live.LiveView, with --live
        self._lock: int | None = None  # the log folder's lock file, held till the end

    def open(self) -> Path | None:
        """Lock the log folder, move an earlier run's records aside, open the run's
        records; returns where the earlier ones went (None: nowhere).

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
        from companion.records import ControlLog, RecordWriter, TlogWriter
        from companion.records.folder import lock_log_dir, prepare_log_dir

        d = self.opts.log_dir
        if d is None:
            return None
        d.mkdir(parents=True, exist_ok=True)
        # The lock first: a second run on this folder must refuse before it moves
        # the live run's records away.
        self._lock = lock_log_dir(d)
        moved = prepare_log_dir(d)
        self.writer = writer = RecordWriter()
        self.tlog = TlogWriter(d / "flight.tlog", writer=writer)
        opts = self.opts
        meta = {
            "profile": opts.profile.name,
            "profile_path": opts.profile_path,
            "controller": opts.controller.kind,
            "controller_path": opts.controller_path,
            "output": opts.output,
            "mode": opts.mode,
            "engage": opts.engage,
            "version": __version__,
            "control_compiled": COMPILED,
            "rates_full_scale_deg_s": repr(opts.rates_full_scale_deg_s),
            "rates_lead_s": repr(opts.rates_lead_s),
            "rates_passthrough": str(opts.rates_passthrough),
            # auto: the start-up's choice follows (learnt).
            "rates_law_axes": (
                "auto" if opts.rates_law_axes is None else law_axes_names(opts.rates_law_axes)
            ),
        }
        self.rows = ControlLog(
            d / "control.mcap", columns(opts.profile.n_motors), meta=meta, writer=writer
        )
        self.append = self.rows.append
        self.events = EventLog(d / "events.jsonl", writer=writer)
        return moved

    def open_live(self) -> None:
        """With ``--live``: serve the control log's rows and the events to viewers.

        Raises
        ------
        OSError
            If it cannot listen there.
        """
        if self.opts.live is None:
            return
        from companion.live import LiveView, tee

        host, port = self.opts.live
        self.live = live = LiveView(columns(self.opts.profile.n_motors), host=host, port=port)
        live.start()
        appends = [a for a in (self.append, live.append) if a is not None]
        self.append = tee(*appends)

    def learnt(self, meta: dict[str, str]) -> None:
        """What the run chose once the autopilot was known, into the control log's
        metadata (:meth:`companion.records.ControlLog.learnt`)."""
        if self.rows is not None:
            self.rows.learnt(meta)

    def record_event(self, ev: dict[str, Any]) -> None:
        """An event into memory, the events file, the control log and the live view."""
        self.events.append(ev)  # memory, and a buffer the writer thread empties
        if self.rows is not None:
            self.rows.event(ev)  # the control log's /events, with its next rows
        if self.live is not None:
            self.live.event(ev)

    def poll_failures(self) -> list[tuple[str, BaseException]]:
        """The record files that stopped being written since the last call."""
        return [] if self.writer is None else list(self.writer.poll_failures())

    def close(self) -> None:
        """Hand the last buffers to the writer, let it drain (bounded), remove the
        records that hold nothing of a flight, then release the log folder."""
        for obj in (self.rows, self.tlog, self.events):
            if obj is not None:
                with contextlib.suppress(Exception):
                    obj.close()
        if self.writer is not None:
            with contextlib.suppress(Exception):
                self.writer.close(2.0)
        # A start that failed (no autopilot, a refused stack) must not leave files
        # that look like a flight: a control log without a row and a flight.tlog
        # without a frame from the autopilot go; events.jsonl stays and says why.
        rows, tlog = self.rows, self.tlog
        for record, empty in (
            (rows, rows is not None and rows.rows == 0),
            (tlog, tlog is not None and tlog.written_in == 0),
        ):
            if empty:
                with contextlib.suppress(OSError):
                    record.path.unlink()
        if self._lock is not None:
            os.close(self._lock)
            self._lock = None

    def close_live(self) -> None:
        if self.live is not None:
            self.live.close()
