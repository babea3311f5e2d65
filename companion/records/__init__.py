"""Flight records: a MAVLink telemetry log (``.tlog``), the control log (MCAP) and an event log.

The logs are fed from the control path (once per MAVLink message, once per
control sample, once per event), so appending is a cheap copy into an
in-memory buffer; the buffer is handed on, in one piece, on the first append
at least ``flush_interval_s`` after the last hand-over (or on :meth:`flush`,
:meth:`close`).

Where it goes depends on the ``writer`` a log is given:

* with a :class:`RecordWriter` (the app: one per run, for all its records),
  the buffer is swapped for an empty one and queued to the writer's thread,
  which does every ``write``, ``flush`` and ``close``. A slow or stalled disk
  never blocks the caller: the queue is bounded (``max_pending_bytes``,
  ``max_pending_chunks``) and a chunk that does not fit is dropped and
  counted. A write error (``ENOSPC``, ``EIO``) stops that file only; the
  thread keeps writing the others and reports the failure through
  :meth:`RecordWriter.poll_failures`;
* without one (offline tools such as ``companion replay``), the log writes the
  buffer to its own file synchronously, from the caller.

Nothing calls ``fsync`` (it can block for tens of milliseconds on an SD card):
a killed process loses what was buffered or queued (normally the last
``flush_interval_s``); a power cut may also lose what the kernel had not
written back. Opening a file and writing its header are synchronous, at
start-up, and raise ``OSError`` as ``open`` does.

A write error never reaches the caller: it is logged once, the log stops
recording (``failed`` holds the error) and later rows are counted in
``dropped``.

Nothing is overwritten: an earlier run's outputs are moved aside first, and a
``--log-dir`` in use is locked (:mod:`companion.records.folder`).

Formats are described in ``docs/logs.md``.
"""

from companion.records.control_log import (
    FORMAT,
    ControlLog,
    last_sample_time,
    read_control_log,
)
from companion.records.events import EventLog
from companion.records.folder import (
    LOCK_FILE,
    RECORD_FILES,
    lock_log_dir,
    move_earlier,
    prepare_log_dir,
)
from companion.records.tlog import TlogWriter
from companion.records.topics import EVENTS_TOPIC, Topic, columns, topics
from companion.records.writer import RecordFileStats, RecordWriter

__all__ = [
    "EVENTS_TOPIC",
    "FORMAT",
    "LOCK_FILE",
    "RECORD_FILES",
    "ControlLog",
    "EventLog",
    "RecordFileStats",
    "RecordWriter",
    "TlogWriter",
    "Topic",
    "columns",
    "last_sample_time",
    "lock_log_dir",
    "move_earlier",
    "prepare_log_dir",
    "read_control_log",
    "topics",
]
