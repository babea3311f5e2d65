"""MQTT telemetry's control-loop side: :class:`MqttTelemetry`, whose ``publish_*`` never wait.

Each ``publish_*`` call is a decimation test and at most one ``put_nowait`` on
a bounded :class:`asyncio.Queue`; the :class:`BrokerConnection` it owns takes
from that queue and publishes (:meth:`MqttTelemetry.run`).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from typing import Any

from companion.control import AXES as _AXES
from companion.telemetry.connection import BrokerConnection
from companion.telemetry.wire import _EVENT, _LINK, _SAMPLE, _STATUS, Vec3, parse_mqtt_url

__all__ = ["MqttTelemetry"]

log = logging.getLogger("companion.telemetry")


class MqttTelemetry:
    """Publish flight telemetry to an MQTT broker without ever blocking the control loop.

    Parameters
    ----------
    url
        ``mqtt://HOST[:PORT]/PREFIX``; port 1883 by default; the prefix is
        required (e.g. ``mqtt://127.0.0.1:1883/mfc/f450``).
    queue_size
        Capacity of the queue between the control loop and the publisher.
    decimate_hz
        Samples published per second of *sample* time (``t_s``).
    client_id
        MQTT client identifier; a random one by default.
    backoff_min_s, backoff_max_s
        Reconnection delay, doubled after each failure between these bounds.
    warn_interval_s
        At most one "queue full" warning per this many seconds.
    keepalive_s
        MQTT keepalive; the broker publishes the will (status ``offline``)
        after 1.5 times this without hearing from us.
    timeout_s
        How long connecting may take; and how long the broker may acknowledge
        nothing while items wait before ``telemetry_lost`` is said (the
        connection is kept: a broker that comes back loses nothing).
    window
        Items (a sample: its three messages) sent and not yet acknowledged, at
        most. A broker that stops answering takes at most these with it; the
        rest wait in the queue. 10 is a second of samples at 10 Hz, and keeps
        up with a round trip of up to 1 s.

    Attributes
    ----------
    counters
        ``samples`` (calls to publish_sample), ``queued``, ``published``
        (items the broker acknowledged: one sample is three MQTT messages),
        ``dropped_full`` (samples and link figures refused or evicted because
        the queue was full), ``dropped_events`` (events evicted by a full
        queue), ``lost_unacked`` (samples and link figures sent that the broker
        had not acknowledged when the connection ended: lost with it),
        ``samples_lost`` (samples lost either way: what ``telemetry_restored``
        reports), ``stalls`` (times the broker acknowledged nothing for
        ``timeout_s`` while items waited), ``reconnects`` (successful
        connections after the first), ``connect_failures``, ``disconnects``,
        ``errors`` (unexpected exceptions in the publisher, logged; it
        restarts).
    topics
        ``roll``/``pitch``/``yaw``/``status``/``event``/``link`` -> topic name.
    connected
        True while a broker connection is up.
    """

    def __init__(
        self,
        url: str,
        *,
        queue_size: int = 1000,
        decimate_hz: float = 10.0,
        client_id: str | None = None,
        backoff_min_s: float = 0.2,
        backoff_max_s: float = 5.0,
        warn_interval_s: float = 5.0,
        keepalive_s: int = 10,
        timeout_s: float = 2.0,
        window: int = 10,
    ) -> None:
        self.host, self.port, self.prefix = parse_mqtt_url(url)
        self.url = url
        if not (isinstance(queue_size, int) and queue_size >= 1):
            raise ValueError(f"queue_size must be an integer >= 1, got {queue_size!r}")
        if not (math.isfinite(decimate_hz) and decimate_hz > 0.0):
            raise ValueError(f"decimate_hz must be > 0, got {decimate_hz!r}")
        if not (0.0 < backoff_min_s <= backoff_max_s):
            raise ValueError("need 0 < backoff_min_s <= backoff_max_s")
        if not (isinstance(window, int) and window >= 1):
            raise ValueError(f"window must be an integer >= 1, got {window!r}")
        self.client_id = client_id
        self.topics: dict[str, str] = {a: f"{self.prefix}/axis/{a}" for a in _AXES}
        self.topics["status"] = f"{self.prefix}/status"
        self.topics["event"] = f"{self.prefix}/event"
        self.topics["link"] = f"{self.prefix}/link"
        self._queue: asyncio.Queue[tuple[Any, ...]] = asyncio.Queue(maxsize=queue_size)
        self._put = self._queue.put_nowait
        self._period = 1.0 / decimate_hz
        # Tolerance on the decimation grid: sample times are microseconds on
        # the wire, so 1 us is below any real sample spacing.
        self._eps = min(1e-6, 0.5 * self._period)
        self._next_t = -math.inf
        self._last_t = -math.inf
        self._warn_interval = warn_interval_s
        self._last_warn = -math.inf
        self.counters: dict[str, int] = {
            "samples": 0,
            "queued": 0,
            "published": 0,
            "dropped_full": 0,
            "dropped_events": 0,
            "lost_unacked": 0,
            "samples_lost": 0,
            "stalls": 0,
            "reconnects": 0,
            "connect_failures": 0,
            "disconnects": 0,
            "errors": 0,
        }
        self._connection = BrokerConnection(
            self.host,
            self.port,
            self._queue,
            self.counters,
            self.topics,
            client_id=client_id,
            backoff_min_s=backoff_min_s,
            backoff_max_s=backoff_max_s,
            keepalive_s=keepalive_s,
            timeout_s=timeout_s,
            window=window,
            period_s=self._period,
        )

    @property
    def connected(self) -> bool:
        """True while a broker connection is up."""
        return self._connection.connected

    @property
    def on_outage(self) -> Callable[[str, str], None] | None:
        """Told ``("telemetry_lost", detail)`` once per outage (the broker went
        away, could not be reached, or acknowledged nothing for ``timeout_s``)
        and ``("telemetry_restored", detail)`` when it is back, with the samples
        lost meanwhile: the app records both."""
        return self._connection.on_outage

    @on_outage.setter
    def on_outage(self, tell: Callable[[str, str], None] | None) -> None:
        self._connection.on_outage = tell

    # -- control-loop side: never awaits, never raises on a full queue --------

    def publish_sample(self, t_s: float, err_rad_s: Vec3, f_hat: Vec3, u: Vec3) -> None:
        """Offer one control sample; one in every ``1 / decimate_hz`` s of ``t_s`` is queued.

        ``err_rad_s``, ``f_hat`` and ``u`` are the roll, pitch, yaw values of
        :class:`companion.control.mfc.ControlOutput` (``error``, ``f_hat``,
        ``u``). A time stamp that goes backwards (a new flight, a simulator
        restart) restarts the decimation grid.
        """
        c = self.counters
        c["samples"] += 1
        t_next = self._next_t
        if t_s < self._last_t:
            t_next = -math.inf  # time went back: restart the grid
        self._last_t = t_s
        if t_s < t_next - self._eps:
            return
        # Stay on the grid (no drift) unless we fell behind it by a whole period.
        t_next += self._period
        self._next_t = t_s + self._period if t_s >= t_next - self._eps else t_next
        try:
            self._put((_SAMPLE, t_s, err_rad_s, f_hat, u))
        except asyncio.QueueFull:
            c["dropped_full"] += 1
            c["samples_lost"] += 1
            self._warn_full()
            return
        c["queued"] += 1

    def publish_status(self, status: dict[str, Any]) -> None:
        """Publish the app's state (retained on ``<prefix>/status``).

        Never dropped: with the queue full the oldest queued item is evicted
        (and counted); the latest status is also re-sent on every (re)connection.
        """
        snap = dict(status)
        self._connection.status = snap
        self._put_priority((_STATUS, snap))

    def publish_link(self, figures: dict[str, Any]) -> None:
        """Offer the link's figures (round trip, sample age) on ``<prefix>/link``;
        dropped, like a sample, when the queue is full."""
        try:
            self._put((_LINK, dict(figures)))
        except asyncio.QueueFull:
            self.counters["dropped_full"] += 1
            self._warn_full()
            return
        self.counters["queued"] += 1

    def publish_event(self, kind: str, detail: str, t_s: float) -> None:
        """Publish an event (failsafe, engage, disengage, ...) on ``<prefix>/event``."""
        self._put_priority((_EVENT, str(kind), str(detail), t_s))

    def _put_priority(self, item: tuple[Any, ...]) -> None:
        q = self._queue
        if q.full():
            evicted = q.get_nowait()
            if evicted[0] in (_SAMPLE, _LINK):
                self.counters["dropped_full"] += 1
                self.counters["samples_lost"] += evicted[0] == _SAMPLE
            elif evicted[0] == _EVENT:
                self.counters["dropped_events"] += 1
                log.warning("telemetry queue full: dropped event %r", evicted[1])
            # An evicted status is superseded by the latest one (the connection's status).
            self._warn_full()
        q.put_nowait(item)
        self.counters["queued"] += 1

    def _warn_full(self) -> None:
        now = time.monotonic()
        if now - self._last_warn >= self._warn_interval:
            self._last_warn = now
            log.warning(
                "telemetry queue full (%d items, broker %s): %d samples dropped so far",
                self._queue.maxsize,
                "connected" if self.connected else "unreachable",
                self.counters["dropped_full"],
            )

    # -- background side ------------------------------------------------------

    async def drain(self, timeout_s: float = 1.0) -> bool:
        """Wait (bounded) until everything queued has been published and acknowledged.

        Returns True when the queue emptied in time; used at shutdown so the
        last events (the hand-back and its reason) reach the broker.
        """
        return await self._connection.drain(timeout_s)

    async def run(self) -> None:
        """Connect, publish what the queue holds, reconnect on loss; until cancelled.

        On cancellation, a connected client publishes status ``offline``
        (retained) before disconnecting.
        """
        await self._connection.run()
