"""The control log (``control.mcap``): the controller's view of every sample, as MCAP.

One message per topic per sample (:mod:`companion.records.topics`: ``/rates``,
``/law/<axis>``, ``/mixer``, ``/link``, ``/outer``) and one per event
(``/events``), JSON-encoded with a JSON schema per topic: what Foxglove and
PlotJuggler open as they are. Each message's log time is the IMU sample's stamp
on the autopilot's clock, so the file lines up with the autopilot's own log;
its publish time is the datagram's arrival on the companion's monotonic clock.
Both are nanoseconds; the sequence number is the sample's row number, the same
on every topic of a sample. The run's metadata (profile, controller, ...) is
the MCAP metadata record ``companion``.
"""

from __future__ import annotations

import logging
import math
import struct
import time
from array import array
from collections.abc import Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from companion.records.encoder_process import ProcessEncoder
from companion.records.sink import BufferedLog, Sink
from companion.records.topics import (
    EVENTS_TOPIC,
    Topic,
    TopicFormat,
    event_json,
    event_schema,
    stamp_ns,
    stamps_ns,
    topics,
)
from companion.records.writer import Encoder, RecordWriter

__all__ = ["FORMAT", "ControlLog", "last_sample_time", "read_control_log"]

log = logging.getLogger("companion.records")

FORMAT = "mfc-companion control log 1"
"""The ``format`` of the ``companion`` metadata record."""

_METADATA = "companion"
_LEARNT = "companion.learnt"
"""What the run learnt of the autopilot once started (a later metadata record: its
values override the first's on reading)."""
_SLICE_S = 200e-6
"""The writer's thread formats messages for at most this long before it lets go
of the interpreter for a moment (:meth:`_McapEncoder.encode`)..."""
_PAUSE_S = 50e-6
_BEHIND_BYTES = 256 * 1024
"""... unless this much waits for the writer (three 0.2 s batches at 1 kHz): a
process that keeps the interpreter busy (an in-process flight faster than real
time) would otherwise starve it."""
_MAX_EVENTS = 10_000  # held between two flushes at most; more are counted in dropped_events
_EVENT_BYTES = 200  # what one event counts against the writer's bounds (a typical event's JSON)


class _Batch:
    """What a flush hands the writer: rows as float64 bytes, events, and what the
    run learnt since the last flush (metadata, written before the rows)."""

    __slots__ = ("events", "learnt", "rows")

    def __init__(
        self, rows: memoryview, events: list[dict[str, Any]], learnt: dict[str, str] | None = None
    ) -> None:
        self.rows = rows
        self.events = events
        self.learnt = learnt or {}

    def __len__(self) -> int:
        """What it counts against the writer's bounds (never 0 while it holds anything:
        the writer drops an empty batch)."""
        return len(self.rows) + _EVENT_BYTES * (len(self.events) + bool(self.learnt))

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickled for the encoder's process (:mod:`companion.records.encoder_process`):
        the rows as bytes, an event's values that are not plain data as text."""
        plain = (str, int, float, bool, type(None), list, tuple, dict)
        events = [
            {k: v if isinstance(v, plain) else str(v) for k, v in ev.items()} for ev in self.events
        ]
        return (_batch_of, (bytes(self.rows), events, self.learnt))


def _batch_of(rows: bytes, events: list[dict[str, Any]], learnt: dict[str, str]) -> _Batch:
    return _Batch(memoryview(rows), events, learnt)


class _Tail:
    """A write-only stream that keeps what was written since the last :meth:`take`.

    The MCAP writer writes here; ``tell()`` is the offset in the file it becomes."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._pos = 0

    def write(self, data: Any) -> int:
        self._buf += data
        self._pos += len(data)
        return len(data)

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        pass

    def take(self) -> bytes:
        out, self._buf = bytes(self._buf), bytearray()
        return out


class _McapEncoder:
    """Rows and events to MCAP bytes; every method but the constructor runs on the
    writer's thread, one call at a time (:class:`companion.records.writer.Encoder`)."""

    def __init__(self, cols: list[str], meta: dict[str, str], writer: RecordWriter | None) -> None:
        from mcap.writer import CompressionType, IndexType, Writer

        from companion import __version__

        self._topics = topics(cols)
        self._n_cols = len(cols)
        self._t = cols.index("t_s") if "t_s" in cols else None
        self._wall = cols.index("wall_s") if "wall_s" in cols else None
        self._out = _Tail()
        # Chunks end where a flush ends them (the chunk size is never reached), so
        # a killed writer leaves whole samples; chunk indexes only (message
        # indexes would double the file for nothing a plotting tool needs).
        self._w = Writer(
            self._out,  # type: ignore[arg-type]
            chunk_size=1 << 62,
            compression=CompressionType.ZSTD,
            index_types=IndexType.CHUNK | IndexType.METADATA,
        )
        self._w.start(profile="", library=f"mfc-companion {__version__}")
        self._w.add_metadata(_METADATA, meta)
        self._channels: list[int] = []
        schema_ids: dict[str, int] = {}
        for tp in self._topics:
            sid = schema_ids.get(tp.schema_name)
            if sid is None:
                sid = self._w.register_schema(tp.schema_name, "jsonschema", tp.schema())
                schema_ids[tp.schema_name] = sid
            self._channels.append(self._w.register_channel(tp.name, "json", sid))
        sid = self._w.register_schema("mfc.event", "jsonschema", event_schema())
        self._events_channel = self._w.register_channel(EVENTS_TOPIC, "json", sid)
        self._formats = [TopicFormat(tp) for tp in self._topics]
        self._row = 0
        self._n_events = 0
        self._writer = writer

    def header(self) -> bytes:
        """The bytes written so far: the magic, the header, the metadata."""
        return self._out.take()

    def encode(self, batch: _Batch) -> bytes:
        """Rows and events to one MCAP chunk (and its index).

        A 1 kHz flight's 200 rows take milliseconds of formatting; it goes in
        slices of at most ``_SLICE_S``, each followed by a short sleep, so the
        control loop's thread never waits long for the interpreter (a thread
        that wants it waits for the holder's switch interval, 5 ms, otherwise).
        Behind by ``_BEHIND_BYTES`` or more, the writer catches up without the
        sleeps."""
        if batch.learnt:
            self._w.add_metadata(_LEARNT, batch.learnt)
        n_cols = self._n_cols
        data = np.frombuffer(batch.rows, dtype=np.float64)
        n = len(data) // n_cols
        data = data[: n * n_cols].reshape(n, n_cols)
        t_ns = stamps_ns(data[:, self._t]) if self._t is not None else [0] * n
        wall_ns = stamps_ns(data[:, self._wall]) if self._wall is not None else t_ns
        per_topic = [(ch, fm, *fm.codes(data)) for ch, fm in zip(self._channels, self._formats)]
        add = self._w.add_message
        clock = time.perf_counter
        deadline = clock() + _SLICE_S
        for r in range(n):
            if clock() >= deadline:
                w = self._writer
                if w is not None and w.pending_bytes < _BEHIND_BYTES:  # (offline: no loop)
                    time.sleep(_PAUSE_S)
                deadline = clock() + _SLICE_S
            seq = (self._row + r) & 0xFFFFFFFF
            lt, pt = t_ns[r], wall_ns[r]
            for ch, fm, codes, rows in per_topic:
                code = codes[r]
                tmpl = fm.templates[code] if code in fm.templates else fm.template(code)
                if tmpl is None:
                    continue  # a sparse topic with nothing to say
                fmt, keep = tmpl
                row = rows[r]
                args = tuple(row) if not code else tuple(row[i] for i in keep)
                add(ch, lt, (fmt % args).encode(), pt, seq)
        self._row += n
        self._add_events(batch.events, t_ns[-1] if n else None)
        self._w.flush()  # type: ignore[no-untyped-call]
        return self._out.take()

    def _add_events(self, events: list[dict[str, Any]], last_ns: int | None) -> None:
        for ev in events:
            lt = stamp_ns(ev.get("t_s"), last_ns or 0)
            pt = stamp_ns(ev.get("wall"), lt)
            self._w.add_message(
                self._events_channel, lt, event_json(ev).encode(), pt, self._n_events & 0xFFFFFFFF
            )
            self._n_events += 1

    def finish(self) -> bytes:
        """The summary (schemas, channels, statistics, chunk indexes) and the footer."""
        self._w.finish()  # type: ignore[no-untyped-call]
        return self._out.take()


class ControlLog(BufferedLog):
    """The control log: one row of numbers per sample, written as MCAP.

    :meth:`append` copies the row into an ``array('d')`` (well under a
    microsecond for 64 columns) and :meth:`event` keeps the event; a flush
    swaps them for empty ones and hands them on. The MCAP formatting (JSON per
    topic, compression) is done by the writer's thread
    (:class:`companion.records.RecordWriter`), never on the control path; each
    flush becomes one MCAP chunk, so a killed writer leaves whole samples up to
    its last flush. Without a writer (offline tools) the log formats and writes
    them itself, synchronously.

    Parameters
    ----------
    path
        The file to create (parent directories are created; an existing file
        is replaced).
    columns
        Column names, in order: :func:`companion.records.columns`, or any of
        its names (each must have a topic: :func:`companion.records.topics`).
    meta
        The run's metadata, written as the MCAP metadata record ``companion``
        (values as strings). ``format``, ``version``, ``columns``,
        ``start_unix_s`` and ``start_utc`` are added unless given.
    flush_interval_s
        Buffered rows are handed on at the first :meth:`append` at least this
        long after the last flush.
    writer
        Hand the rows to this :class:`RecordWriter` (file key: the file's name);
        the header (the MCAP magic, header and metadata) is written at once, by
        :meth:`RecordWriter.open`. None: write synchronously.
    """

    _sink: Sink  # always a file here

    def __init__(
        self,
        path: str | Path,
        columns: list[str],
        *,
        meta: dict[str, Any] | None = None,
        flush_interval_s: float = 0.2,
        writer: RecordWriter | None = None,
    ) -> None:
        cols = list(columns)
        if not cols:
            raise ValueError("columns must not be empty")
        topics(cols)  # raises on an unknown or repeated column
        if not (math.isfinite(flush_interval_s) and flush_interval_s >= 0.0):
            raise ValueError(f"flush_interval_s must be >= 0, got {flush_interval_s!r}")
        self.path = Path(path)
        self.columns = cols
        self.n_columns = len(cols)
        self._buf = array("d")
        self._events: list[dict[str, Any]] = []
        self._learnt: dict[str, str] = {}
        self._interval = flush_interval_s
        self.rows = 0
        """Rows appended."""
        self.dropped = 0
        """Rows not recorded because of an earlier write error."""
        self.dropped_events = 0
        """Events not recorded (a write error, or more than 10000 between two flushes)."""

        from companion import __version__

        now = time.time()
        full_meta: dict[str, Any] = {
            "format": FORMAT,
            "version": __version__,
            "start_unix_s": f"{now:.6f}",
            "start_utc": datetime.fromtimestamp(now, timezone.utc).isoformat(),
        }
        full_meta.update(meta or {})
        full_meta["columns"] = ",".join(cols)
        text_meta = {str(k): str(v) for k, v in full_meta.items()}
        local = _McapEncoder(cols, text_meta, writer)
        header = local.header()
        encoder: Encoder = local
        if writer is not None:
            # Formatting a 1 kHz flight's messages takes milliseconds of Python: in
            # another process it never holds the lock the control loop needs.
            encoder = ProcessEncoder(
                "companion.records.control_log:_McapEncoder", (cols, text_meta, None), local
            )
        # The header goes out at once: a killed process leaves a file MCAP readers open.
        self._sink = Sink(self.path, "control log", writer, header=header, encoder=encoder)
        self._open = True  # False once closed, or stopped by a write error
        self._next_flush = time.monotonic() + flush_interval_s

    def append(self, row: Sequence[float]) -> None:
        """Record one row (numbers in column order; bools and ints are fine).

        Raises
        ------
        ValueError
            If ``len(row)`` is not the number of columns, or a value is not a number.
        """
        if len(row) != self.n_columns:
            raise ValueError(f"{self.path}: row has {len(row)} values, expected {self.n_columns}")
        if not self._open:
            if self._sink.failed is not None:
                self.dropped += 1
                return
            raise ValueError(f"{self.path}: ControlLog is closed")
        n = len(self._buf)
        try:
            self._buf.extend(row)
        except TypeError as exc:
            del self._buf[n:]  # keep rows whole
            raise ValueError(f"{self.path}: row has a value that is not a number: {exc}") from None
        self.rows += 1
        if time.monotonic() >= self._next_flush:
            self.flush()

    def event(self, event: dict[str, Any]) -> None:
        """Record an event on ``/events`` with the next flush (kept by reference).

        Never raises: an event after :meth:`close`, after a write error, or
        beyond 10000 waiting for a flush is counted in :attr:`dropped_events`."""
        if not self._open or len(self._events) >= _MAX_EVENTS:
            self.dropped_events += 1
            return
        self._events.append(event)

    def learnt(self, meta: dict[str, str]) -> None:
        """Metadata the run learnt once started (what it chose at start-up), written
        with the next flush as the metadata record ``companion.learnt``;
        :func:`read_control_log` returns it over the run's first metadata."""
        if self._open:
            self._learnt.update(meta)

    def flush(self) -> None:
        """Hand the rows, events and what was learnt on now: to the writer's queue,
        or to the file."""
        self._next_flush = time.monotonic() + self._interval
        if not self._open or not (self._buf or self._events or self._learnt):
            return
        buf, self._buf = self._buf, array("d")
        events, self._events = self._events, []
        learnt, self._learnt = self._learnt, {}
        if not self._sink.put(_Batch(memoryview(buf).cast("B"), events, learnt)):
            self._open = False


def read_control_log(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Read a control log: ``({column: float64 array}, {key: value})``.

    Read with the ``mcap`` package's stream reader, from the start: a file its
    writer did not close (killed) is read up to its last whole chunk, and the
    returned metadata then has ``cut_short: "true"``. What the run learnt once
    started (:meth:`ControlLog.learnt`) overrides its first metadata. Samples a topic skipped
    (``/outer`` outside the outer modes) are NaN, as are ``null`` values.

    Raises
    ------
    ValueError
        Naming the file when it is not MCAP, or not a control log of this format.
    """
    import json

    from mcap.exceptions import McapError
    from mcap.records import Channel, Message, Metadata
    from mcap.stream_reader import StreamReader

    p = Path(path)
    meta: dict[str, str] | None = None
    learnt: dict[str, str] = {}
    layout: dict[str, Topic] = {}
    channels: dict[int, Topic] = {}
    got: dict[int, tuple[list[int], list[bytes]]] = {}
    cut_short = False
    try:
        with p.open("rb") as f:
            try:
                for rec in StreamReader(f).records:
                    if isinstance(rec, Message):
                        if rec.channel_id in channels:
                            seqs, bodies = got[rec.channel_id]
                            seqs.append(rec.sequence)
                            bodies.append(rec.data)
                    elif isinstance(rec, Channel) and rec.id not in channels:
                        tp = layout.get(rec.topic)  # (the summary repeats the channels)
                        if tp is not None:
                            channels[rec.id] = tp
                            got[rec.id] = ([], [])
                    elif isinstance(rec, Metadata) and rec.name == _METADATA:
                        meta = dict(rec.metadata)
                        fmt = meta.get("format", "")
                        if fmt != FORMAT:
                            raise ValueError(f"{p}: format {fmt!r}; this version reads {FORMAT!r}")
                        layout = {tp.name: tp for tp in topics(meta["columns"].split(","))}
                    elif isinstance(rec, Metadata) and rec.name == _LEARNT:
                        learnt.update(rec.metadata)
            except ValueError:
                raise
            except (McapError, struct.error) as exc:
                # Past the metadata, a file that ends (or breaks off) mid-record is
                # one whose writer did not close it: what came before is whole.
                if meta is None:
                    raise ValueError(f"{p}: not a control log (MCAP: {exc!r})") from None
                cut_short = True
    except OSError as exc:
        raise ValueError(f"{p}: cannot read: {exc}") from None
    if meta is None:
        raise ValueError(f"{p}: not a control log (no '{_METADATA}' metadata record)")
    cols = meta["columns"].split(",")
    meta.update({k: v for k, v in learnt.items() if k not in ("format", "columns")})
    # Sequence numbers are the row numbers (modulo 2**32, in the order written).
    rownums: dict[int, np.ndarray] = {}
    for ch, (seqs, _) in got.items():
        s = np.array(seqs, dtype=np.int64)
        wraps = np.concatenate([[0], np.cumsum(np.diff(s) < -(1 << 31))]) if len(s) else s
        rownums[ch] = s + (wraps.astype(np.int64) << 32)
    n = max((int(r.max()) + 1 for r in rownums.values() if len(r)), default=0)
    out = np.full((n, len(cols)), np.nan)
    loads = json.loads
    for ch, (_, bodies) in got.items():
        if not bodies:
            continue
        fields = channels[ch].fields
        # None (a null) becomes NaN in a float array.
        objs = loads(b"[" + b",".join(bodies) + b"]")  # one call: far cheaper than one each
        vals = np.array([[obj.get(k) for k in fields] for obj in objs], dtype=np.float64)
        out[rownums[ch][:, None], list(channels[ch].columns)] = vals
    if cut_short:
        meta["cut_short"] = "true"
        log.info("%s: its writer did not close it; read up to its last whole chunk", p)
    return {c: np.ascontiguousarray(out[:, j]) for j, c in enumerate(cols)}, meta


def last_sample_time(path: str | Path) -> float | None:
    """The IMU time (s) of the last sample in a control log being written, or None.

    Reads the chunks' headers, not their messages: cheap enough to poll a live log."""
    from mcap.exceptions import McapError
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    last: int | None = None
    try:
        with open(path, "rb") as f:
            try:
                for rec in StreamReader(f, emit_chunks=True).records:
                    if isinstance(rec, Chunk) and rec.message_end_time:
                        last = rec.message_end_time
            except McapError:
                pass  # a file still being written ends mid-record
    except OSError:
        return None
    return None if last is None else last * 1e-9
