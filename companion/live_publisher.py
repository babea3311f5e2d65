"""The live view's server: what :class:`companion.live.LiveView` runs in a child process.

:class:`Publisher` holds the ``foxglove-sdk`` server, one channel per topic of
the control log and ``/events``, and formats the messages (JSON, one per topic
per sample). It lives in a process of its own (:mod:`companion.child_process`):
formatting thousands of messages a second in the companion's process would hold
the interpreter lock its control loop needs.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from companion.records.topics import (
    EVENTS_TOPIC,
    TopicFormat,
    event_json,
    event_schema,
    stamp_ns,
    stamps_ns,
    topics,
)

__all__ = ["Publisher"]

log = logging.getLogger("companion.live")

BACKLOG = 4096
"""Messages the SDK holds for each viewer (about 3 s of seven topics at 200
samples a second): a viewer behind by more loses its oldest ones."""
_LINGER_S = 0.25
"""At the end, how long the server stays up after the last messages are handed to
it: they are still on their way to the viewers (the run's last counters)."""
_LOSSY_LOGGER = "foxglove.websocket.connected_client.send_lossy"
"""The SDK's logger that says a viewer's backlog is full."""


class _OverflowCounter(logging.Handler):
    """Counts the SDK's "outbox for client ... full" records."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.count = 0

    def emit(self, record: logging.LogRecord) -> None:
        if "full" in record.getMessage():
            self.count += 1


_sdk_logging_lock = threading.Lock()
_sdk_logging_on = False


def _sdk_logging() -> None:
    """The SDK's log records into :mod:`logging` (once per process): its INFO lines
    say when a viewer connects, leaves, or falls behind."""
    global _sdk_logging_on
    import foxglove

    with _sdk_logging_lock:
        if not _sdk_logging_on:
            # The viewer's backlog records are INFO: let them through to our counter
            # whatever the log level.
            logging.getLogger(_LOSSY_LOGGER).setLevel(logging.INFO)
            foxglove.set_log_level("INFO")
            _sdk_logging_on = True


class Publisher:
    """The server at ``host``:``port`` (0: any free one, :meth:`port` says which),
    a channel per topic of the control log's ``columns``, and the messages'
    formatting: :class:`companion.live.LiveView`'s arguments, in its child.

    Raises
    ------
    OSError
        If the SDK cannot listen at ``host``:``port``.
    """

    def __init__(self, columns: Sequence[str], host: str, port: int) -> None:
        import foxglove

        _sdk_logging()
        cols = list(columns)
        self.n_columns = len(cols)
        self._t = cols.index("t_s") if "t_s" in cols else None
        # Kept: the channels are bound to the context only as long as it lives.
        self._context = ctx = foxglove.Context()
        try:
            self._server: Any = foxglove.start_server(
                name="mfc-companion",
                host=host,
                port=port,
                context=ctx,
                message_backlog_size=BACKLOG,
            )
        except RuntimeError as exc:  # the SDK's FoxgloveError
            raise OSError(f"cannot serve the live view on {host}:{port}: {exc}") from exc
        self._channels = []
        for tp in topics(cols):
            schema = foxglove.Schema(name=tp.schema_name, encoding="jsonschema", data=tp.schema())
            ch = foxglove.Channel(tp.name, schema=schema, message_encoding="json", context=ctx)
            self._channels.append((ch, TopicFormat(tp)))
        schema = foxglove.Schema(name="mfc.event", encoding="jsonschema", data=event_schema())
        self._events_channel = foxglove.Channel(
            EVENTS_TOPIC, schema=schema, message_encoding="json", context=ctx
        )
        self._overflows = _OverflowCounter()
        logging.getLogger(_LOSSY_LOGGER).addHandler(self._overflows)
        self.published = 0
        self.errors = 0

    def port(self) -> int:
        """The port listened on (the one chosen, with port 0)."""
        return int(self._server.port)

    def counters(self) -> tuple[int, int, int]:
        """Messages published, the viewers' backlog overflows, and publishing errors, so far."""
        return self.published, self._overflows.count, self.errors

    def publish(self, rows: bytes, n: int, events: list[dict[str, Any]]) -> tuple[int, int, int]:
        """Publish ``n`` rows (float64, in column order) and ``events`` on the topics
        someone subscribed to (the others are not even formatted); the counters
        (:meth:`counters`). An error is counted, never raised: the server goes on."""
        try:
            self._publish(rows, n, events)
        except Exception:
            self.errors += 1
            if self.errors == 1:
                log.exception("live view: publishing failed (logged once, counted after)")
        return self.counters()

    def _publish(self, rows: bytes, n: int, events: list[dict[str, Any]]) -> None:
        data = np.frombuffer(rows, dtype=np.float64)[: n * self.n_columns]
        data = data.reshape(n, self.n_columns)
        t_ns = stamps_ns(data[:, self._t]) if self._t is not None else [0] * n
        for ch, fmt in self._channels:
            if not ch.has_sinks():
                continue
            for msg, lt in zip(fmt.messages(data), t_ns, strict=True):
                if msg is not None:
                    ch.log(msg, log_time=lt)
                    self.published += 1
        ch = self._events_channel
        if events and ch.has_sinks():
            last = t_ns[-1] if n else 0
            for ev in events:
                ch.log(event_json(ev), log_time=stamp_ns(ev.get("t_s"), last))
                self.published += 1

    def close(self) -> None:
        """Let the viewers have the last messages, then stop serving."""
        if self._server is not None:
            time.sleep(_LINGER_S)
            self._server.stop()
            self._server = None
        logging.getLogger(_LOSSY_LOGGER).removeHandler(self._overflows)
