"""The live view: the control log's topics served over the Foxglove WebSocket protocol.

``companion run --live [HOST:]PORT`` serves what ``control.mcap`` records, the
same topics with the same fields and JSON schemas
(:func:`companion.records.topics`, ``/events``), to any Foxglove app that
connects, as the flight goes. The server is the ``foxglove-sdk`` package's
(the ``live`` extra: ``pip install 'mfc-companion[live]'``).

Off the control path. The loop's only work is :meth:`LiveView.append`: at most
:data:`RATE_HZ` samples a second (the control log keeps them all), each row it
already built for the control log copied into an ``array('d')``, and every
``flush_interval_s`` that buffer handed to a bounded queue in one
non-blocking put. A thread of its own passes the rows to the live view's own
process (:class:`companion.live_publisher.Publisher`, through
:mod:`companion.child_process`, run :data:`NICE` nicer), which runs the server and formats the
messages (JSON, one per topic per sample; topics nobody subscribed to are not
formatted at all): formatting here would hold the interpreter lock the loop's
thread needs. Nothing in it waits on a viewer: the SDK keeps each viewer's
messages in a backlog of its own and drops the oldest when a viewer does not
read them.

What is lost is counted (:attr:`LiveView.counters`, in the run's ``counters``
events as ``live.*``): ``dropped_rows`` and ``dropped_events``, rows and events
the publishing thread was too far behind to take, or that came after the live
view's process ended (exact); ``viewer_overflows``, the times a viewer's
backlog filled, after which the SDK drops that viewer's oldest messages (the
SDK says when, not how many; a viewer counts once per connection);
``publish_errors``, batches that failed, and the live view's process ending.
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import threading
import time
from array import array
from collections.abc import Callable, Sequence
from typing import Any

from companion.child_process import ChildObject
from companion.records.topics import topics

__all__ = [
    "DEFAULT_HOST",
    "INSTALL_HINT",
    "RATE_HZ",
    "LiveView",
    "parse_live_address",
    "sdk_problem",
    "tee",
]

log = logging.getLogger("companion.live")

DEFAULT_HOST = "127.0.0.1"
"""Where the live view listens unless told: this computer only. ``0.0.0.0``
serves every network the companion computer is on (the vehicle's)."""

INSTALL_HINT = "pip install 'mfc-companion[live]'"

RATE_HZ = 200.0
"""Samples per second the live view sends at most, whatever the IMU's rate (the
control log keeps every one): a plot on a screen shows no more, and each sample
costs a JSON object per topic on the companion's computer."""
NICE = 10
"""The live view's process runs this much nicer than the companion: when the two
want the same core, the scheduler gives it to the control loop first (the
viewer then sees its messages a little later)."""
_MAX_PENDING_ROWS = 5000
"""Rows waiting for the publishing thread, at most (5 s at 1 kHz); more are dropped."""
_MAX_PENDING_EVENTS = 1000


def parse_live_address(text: str) -> tuple[str, int]:
    """``[HOST:]PORT`` as ``(host, port)``; the host defaults to :data:`DEFAULT_HOST`.

    Raises
    ------
    ValueError
        Naming what is wrong: an empty host, a port that is not an integer in
        1..65535.
    """
    s = text.strip()
    host, sep, port_text = s.rpartition(":")
    if not sep:
        host = DEFAULT_HOST
    elif not host:
        raise ValueError(f"expected [HOST:]PORT, got {text!r} (the host is empty)")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]  # [::1]:8765
    try:
        port = int(port_text)
    except ValueError:
        raise ValueError(
            f"expected [HOST:]PORT, got {text!r} (the port is not an integer)"
        ) from None
    if not 1 <= port <= 65535:
        raise ValueError(f"expected [HOST:]PORT with PORT in 1..65535, got {text!r}")
    return host, port


def sdk_problem() -> str | None:
    """Why the live view cannot run in this install (the SDK is missing), or None."""
    try:
        import foxglove  # noqa: F401
    except ImportError as exc:
        return f"the live view needs the foxglove-sdk package ({exc}): {INSTALL_HINT}"
    return None


def tee(*appends: Callable[[Sequence[float]], None]) -> Callable[[Sequence[float]], None]:
    """One ``append(row)`` that calls each of ``appends`` with the same row."""
    if len(appends) == 1:
        return appends[0]

    def append(row: Sequence[float]) -> None:
        for a in appends:
            a(row)

    return append


_PLAIN = (str, int, float, bool, type(None), list, tuple, dict)


def _plain(event: dict[str, Any]) -> dict[str, Any]:
    """An event for the live view's process: values that are not plain data as text."""
    return {k: v if isinstance(v, _PLAIN) else str(v) for k, v in event.items()}


class LiveView:
    """The control log's topics served live over the Foxglove WebSocket protocol.

    Parameters
    ----------
    columns
        The control log's columns, in row order (:func:`companion.records.columns`).
    host, port
        Where to listen (``port`` 0: any free port, :attr:`port` says which).
    flush_interval_s
        Rows are handed to the publishing thread at the first :meth:`append` at
        least this long after the last hand-over: a viewer sees the flight this
        much late at most, plus its own link. Each hand-over wakes the thread,
        which takes the interpreter for a moment: at 20 a second the viewer's
        cost to the loop's 99th percentile was 1.07-1.24x (five runs), at 4 a
        second 1.03-1.14x (seven; ``scripts/bench.py loop --viewer``).
    max_rate_hz
        At most this many samples a second are sent (by their ``t_s``); the rest
        are skipped where they come, before any copy.

    Nothing is started until :meth:`start`; :meth:`close` stops it all.
    """

    def __init__(
        self,
        columns: Sequence[str],
        *,
        host: str = DEFAULT_HOST,
        port: int = 8765,
        flush_interval_s: float = 0.25,
        max_rate_hz: float = RATE_HZ,
    ) -> None:
        cols = list(columns)
        topics(cols)  # raises on an unknown column
        if not isinstance(port, int) or isinstance(port, bool) or not 0 <= port <= 65535:
            raise ValueError(f"port must be an integer in 0..65535, got {port!r}")
        if not (math.isfinite(flush_interval_s) and 0.0 <= flush_interval_s <= 1.0):
            raise ValueError(f"flush_interval_s must be in [0, 1], got {flush_interval_s!r}")
        self.host = host
        self._port = port
        self.n_columns = len(cols)
        self._t = cols.index("t_s") if "t_s" in cols else None
        if not (math.isfinite(max_rate_hz) and 1.0 <= max_rate_hz <= 10_000.0):
            raise ValueError(f"max_rate_hz must be in [1, 10000], got {max_rate_hz!r}")
        self._min_dt = 1.0 / max_rate_hz
        self._due = -math.inf
        """The stamp from which the next row is taken: one slot of ``1 / max_rate_hz``
        after the last, so a 250 Hz stream gives 200 a second, four in five."""
        self._interval = flush_interval_s
        self._next_flush = 0.0
        self._buf = array("d")
        self._events: list[dict[str, Any]] = []
        self._queue: queue.SimpleQueue[tuple[array[float], list[dict[str, Any]]] | None] = (
            queue.SimpleQueue()
        )
        # Pending = in - out; "in" written by the loop's thread only, "out" by the
        # publishing thread only.
        self._in_rows = self._out_rows = 0
        self._in_events = self._out_events = 0
        self.dropped_rows = 0
        self.dropped_events = 0
        self.published = 0
        """Messages handed to the SDK (each goes to every viewer subscribed to its topic)."""
        self.publish_errors = 0
        self._overflows = 0
        self._columns = cols
        self._child: ChildObject | None = None
        self._bound_port: int | None = None
        self._thread: threading.Thread | None = None
        self._open = False

    # ------------------------------------------------------------ the loop's side
    def start(self) -> None:
        """Start the live view's process, listening, and the publishing thread.

        Raises
        ------
        OSError
            If the live view's process cannot start or cannot listen there (the
            port is taken, the host unknown).
        """
        try:
            child = ChildObject(
                "companion.live_publisher:Publisher",
                (self._columns, self.host, self._port),
                nice=NICE,
            )
        except OSError as exc:
            raise OSError(f"cannot serve the live view on {self.host}:{self._port}: {exc}") from exc
        self._child = child
        self._bound_port = int(child.call("port"))
        self._thread = threading.Thread(target=self._run, name="live-view", daemon=True)
        self._thread.start()
        self._open = True
        self._next_flush = time.monotonic() + self._interval
        log.info("live view: ws://%s:%d (Foxglove WebSocket)", self.host, self.port)

    @property
    def port(self) -> int:
        """The port listened on (the one chosen, with ``port=0``)."""
        return self._bound_port if self._bound_port is not None else self._port

    def append(self, row: Sequence[float]) -> None:
        """Take one row (the control log's, in column order). O(1), never blocks.

        Rows come at most ``max_rate_hz`` a second on average (by ``t_s``); the
        others are skipped here."""
        if not self._open:
            return
        if self._t is not None:
            t = row[self._t]
            if t < self._due - 1.0:  # the stamps went back (an autopilot's reboot)
                self._due = t
            if t < self._due:
                return
            # The next slot: kept in phase while the stream comes, restarted after a gap.
            late = t >= self._due + self._min_dt
            self._due = t + self._min_dt if late else self._due + self._min_dt
        n = len(self._buf)
        try:
            self._buf.extend(row)
        except TypeError:
            del self._buf[n:]  # the control log says why; here the row is skipped
            return
        if time.monotonic() >= self._next_flush:
            self.flush()

    def event(self, event: dict[str, Any]) -> None:
        """Take an event for ``/events``, published with the next rows."""
        if self._open:
            self._events.append(event)

    def flush(self) -> None:
        """Hand what is buffered to the publishing thread now; never blocks.

        What does not fit in its bounds is dropped and counted."""
        self._next_flush = time.monotonic() + self._interval
        if not self._open or not (self._buf or self._events):
            return
        buf, self._buf = self._buf, array("d")
        events, self._events = self._events, []
        n_rows = len(buf) // self.n_columns if self.n_columns else 0
        if (
            self._in_rows - self._out_rows + n_rows > _MAX_PENDING_ROWS
            or self._in_events - self._out_events + len(events) > _MAX_PENDING_EVENTS
        ):
            self.dropped_rows += n_rows
            self.dropped_events += len(events)
            return
        self._in_rows += n_rows
        self._in_events += len(events)
        self._queue.put((buf, events))

    @property
    def counters(self) -> dict[str, int]:
        """``published``, ``dropped_rows``, ``dropped_events``, ``viewer_overflows``
        and ``publish_errors`` so far."""
        return {
            "published": self.published,
            "dropped_rows": self.dropped_rows,
            "dropped_events": self.dropped_events,
            "viewer_overflows": self._overflows,
            "publish_errors": self.publish_errors,
        }

    @property
    def pending(self) -> int:
        """Rows and events handed over and not yet published (after :meth:`flush`,
        0 means :attr:`counters` count everything so far)."""
        return self._in_rows - self._out_rows + self._in_events - self._out_events

    def close(self, timeout_s: float = 1.0) -> None:
        """Publish what is buffered (waiting at most ``timeout_s``), then stop serving;
        a live view's process that has not answered by then is killed.

        Closing twice, or a view never started, is harmless."""
        if not self._open:
            return
        self.flush()
        self._open = False
        self._queue.put(None)
        if self._thread is not None:
            self._thread.join(timeout_s)
        child, self._child = self._child, None
        if child is not None:
            if self._thread is not None and self._thread.is_alive():
                child.kill()  # it has not answered in time: what it held is lost
            else:
                with contextlib.suppress(OSError):
                    child.call("close")  # lets the viewers have the last messages
            child.close()

    def __enter__(self) -> LiveView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------ the publishing thread
    def _run(self) -> None:
        get = self._queue.get
        while True:
            item = get()
            if item is None:
                return
            buf, events = item
            n_rows = len(buf) // self.n_columns
            try:
                self._publish(buf, n_rows, events)
            finally:
                self._out_rows += n_rows
                self._out_events += len(events)

    def _publish(self, buf: array[float], n: int, events: list[dict[str, Any]]) -> None:
        child = self._child
        if child is None or child.pid is None:  # its process has ended: counted, dropped
            self.dropped_rows += n
            self.dropped_events += len(events)
            return
        try:
            published, self._overflows, errors = child.call(
                "publish", buf.tobytes(), n, [_plain(ev) for ev in events]
            )
        except OSError as exc:  # the process ended: nothing more is served
            self.publish_errors += 1
            self.dropped_rows += n
            self.dropped_events += len(events)
            log.error("live view: its process ended, nothing more is served (%s)", exc)
            return
        self.published = published
        self.publish_errors = errors
