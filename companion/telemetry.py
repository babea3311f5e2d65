"""Optional MQTT telemetry: decimated per-axis samples, status and events.

The control loop calls :meth:`MqttTelemetry.publish_sample` (and
``publish_status`` / ``publish_event``) synchronously; each call is a
decimation test and at most one ``put_nowait`` on a bounded
:class:`asyncio.Queue`. A background task, :meth:`MqttTelemetry.run`,
takes from the queue, formats JSON and publishes with aiomqtt at QoS 1,
keeping at most ``window`` items unacknowledged. The control loop never waits
for the broker: when the queue is full a sample is dropped and counted, and a
warning is logged at most every ``warn_interval_s``. What the broker never
acknowledged when its connection ended is counted lost too: a broker that
stops answering takes what was in flight with it, not more.

All ``publish_*`` methods must be called from the event loop's thread.
Topics and payloads are documented in ``docs/telemetry.md``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import time
from collections.abc import Callable
from typing import Any
from urllib.parse import urlsplit

import aiomqtt

from companion.control import AXES as _AXES

__all__ = ["MqttTelemetry", "parse_mqtt_url"]

log = logging.getLogger(__name__)

Vec3 = tuple[float, float, float]

_SAMPLE = 0
_STATUS = 1
_EVENT = 2
_LINK = 3
_DEG = 180.0 / math.pi


def parse_mqtt_url(url: str) -> tuple[str, int, str]:
    """``mqtt://HOST[:PORT]/PREFIX`` -> ``(host, port, prefix)``; port defaults to 1883.

    Raises
    ------
    ValueError
        Naming the URL and what is wrong with it.
    """

    def bad(why: str) -> ValueError:
        return ValueError(f"bad MQTT URL {url!r}: {why} (expected mqtt://HOST[:PORT]/PREFIX)")

    if not isinstance(url, str):
        raise bad("not a string")
    parts = urlsplit(url.strip())
    if parts.scheme != "mqtt":
        raise bad(f"scheme must be 'mqtt', got {parts.scheme!r}")
    if parts.username is not None or parts.password is not None:
        raise bad("credentials in the URL are not supported")
    if "?" in url or "#" in url:
        raise bad("no query, fragment or '#' wildcard allowed")
    host = parts.hostname
    if not host:
        raise bad("no host")
    try:
        port = parts.port
    except ValueError as exc:
        raise bad(f"invalid port ({exc})") from None
    if port is None:
        port = 1883
    if not 1 <= port <= 65535:
        raise bad(f"port {port} out of range 1..65535")
    prefix = parts.path.strip("/")
    if not prefix:
        raise bad("a topic prefix is required, e.g. mqtt://127.0.0.1:1883/mfc/f450")
    if any(ch in prefix for ch in "+#\0") or "//" in prefix:
        raise bad(f"topic prefix {prefix!r} must not contain '+', '#', NUL or empty levels")
    return host, port, prefix


def _num(x: float) -> float | None:
    # JSON has no NaN/inf: a held (non-finite) value goes out as null.
    x = float(x)
    return x if math.isfinite(x) else None


_STOP_S = 2.0
"""How long a connection's end waits for its publisher and watcher to stop."""


def _cancel_requested() -> bool:
    """Whether the current task has been asked to stop (Python >= 3.11; False
    before). On 3.11 ``asyncio.wait_for`` (which aiomqtt's publish uses) can lose
    a cancellation that arrives just as its inner future completes; a loop that
    checks this still ends."""
    task = asyncio.current_task()
    cancelling = getattr(task, "cancelling", None)
    return bool(cancelling is not None and cancelling())


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
        self._axis_topics = tuple(self.topics[a] for a in _AXES)
        self._queue: asyncio.Queue[tuple[Any, ...]] = asyncio.Queue(maxsize=queue_size)
        self._put = self._queue.put_nowait
        self._period = 1.0 / decimate_hz
        # Tolerance on the decimation grid: sample times are microseconds on
        # the wire, so 1 us is below any real sample spacing.
        self._eps = min(1e-6, 0.5 * self._period)
        self._next_t = -math.inf
        self._last_t = -math.inf
        self._backoff_min = backoff_min_s
        self._backoff_max = backoff_max_s
        self._warn_interval = warn_interval_s
        self._last_warn = -math.inf
        self._keepalive = keepalive_s
        self._timeout = timeout_s
        self._status: dict[str, Any] | None = None
        self._window = window
        self._inflight: dict[asyncio.Task[None], tuple[Any, ...]] = {}
        """Items handed to the client, until the broker acknowledges them."""
        self._taken: tuple[Any, ...] | None = None  # from the queue, waiting for room
        self._resend: list[tuple[Any, ...]] = []  # events (and an item never sent)
        self._stalled = False
        self.connected = False
        self.on_outage: Callable[[str, str], None] | None = None
        """Told ``("telemetry_lost", detail)`` once per outage (the broker went
        away, could not be reached, or acknowledged nothing for ``timeout_s``)
        and ``("telemetry_restored", detail)`` when it is back, with the samples
        lost meanwhile: the app records both."""
        self._outage_lost: int | None = None  # samples_lost when this outage began
        self._lost_when_up = 0  # samples_lost at the broker's last acknowledgement
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
        self._status = snap
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
            # An evicted status is superseded by the latest one (kept in _status).
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
        deadline = asyncio.get_running_loop().time() + timeout_s
        while not self._queue.empty() or self._taken is not None or self._inflight:
            if not self.connected or asyncio.get_running_loop().time() >= deadline:
                return False
            await asyncio.sleep(0.01)
        return True

    async def run(self) -> None:
        """Connect, publish what the queue holds, reconnect on loss; until cancelled.

        On cancellation, a connected client publishes status ``offline``
        (retained) before disconnecting.
        """
        backoff = self._backoff_min
        first = True
        failing = False
        offline = json.dumps({"state": "offline"})
        will = aiomqtt.Will(self.topics["status"], offline, qos=1, retain=True)
        while True:
            try:
                async with aiomqtt.Client(
                    self.host,
                    self.port,
                    identifier=self.client_id,
                    keepalive=self._keepalive,
                    will=will,
                    timeout=self._timeout,
                    # Everything handed over goes on the wire at once: the window,
                    # plus the restated status, bounds it.
                    max_inflight_messages=3 * self._window + 3,
                ) as client:
                    client.pending_calls_threshold = 3 * self._window + 3
                    self.connected = True
                    self._stalled = False
                    if not first:
                        self.counters["reconnects"] += 1
                    self._outage_ended()
                    self._lost_when_up = self.counters["samples_lost"]
                    first = False
                    failing = False
                    backoff = self._backoff_min
                    log.info("telemetry connected to %s:%d", self.host, self.port)
                    try:
                        await self._serve(client)
                    except asyncio.CancelledError:
                        with contextlib.suppress(Exception):
                            await asyncio.wait_for(
                                client.publish(self.topics["status"], offline, retain=True),
                                timeout=0.5,
                            )
                        raise
            except aiomqtt.MqttError as exc:
                if self.connected:
                    self.counters["disconnects"] += 1
                    log.warning("telemetry lost the broker %s:%d: %s", self.host, self.port, exc)
                    self._outage_began(f"lost the broker {self.host}:{self.port}: {exc}")
                else:
                    self.counters["connect_failures"] += 1
                    # One warning per outage, then quiet until it comes back.
                    (log.debug if failing else log.warning)(
                        "telemetry cannot reach the broker %s:%d: %s (retrying)",
                        self.host,
                        self.port,
                        exc,
                    )
                    if not failing:
                        self._outage_began(
                            f"cannot reach the broker {self.host}:{self.port}: {exc}"
                        )
                    failing = True
            except Exception:
                # A bug here must not end telemetry for the rest of the flight.
                self.counters["errors"] += 1
                log.exception("telemetry publisher failed; restarting it")
            finally:
                self.connected = False
            await asyncio.sleep(backoff)
            backoff = min(2.0 * backoff, self._backoff_max)

    def _outage_began(self, detail: str) -> None:
        if self._outage_lost is not None:
            return  # one outage, however many attempts
        # From the broker's last acknowledgement: what was in flight then is this
        # outage's too.
        self._outage_lost = self._lost_when_up
        if self.on_outage is not None:
            self.on_outage("telemetry_lost", detail)

    def _outage_ended(self) -> None:
        if self._outage_lost is None:
            return
        lost = self.counters["samples_lost"] - self._outage_lost
        self._outage_lost = None
        if self.on_outage is not None:
            self.on_outage(
                "telemetry_restored",
                f"the broker {self.host}:{self.port} is back; {lost} samples lost meanwhile "
                f"({lost * self._period:.1f} s of telemetry)",
            )

    async def _serve(self, client: aiomqtt.Client) -> None:
        """Publish until the connection drops (MqttError) or we are cancelled."""
        publisher = asyncio.create_task(self._publish_loop(client), name="telemetry-publish")
        # A publish does not fail when the broker has gone (paho queues it); the
        # message iterator is what raises on disconnection, so watch it.
        watcher = asyncio.create_task(self._watch(client), name="telemetry-watch")
        try:
            done, _ = await asyncio.wait((publisher, watcher), return_when=asyncio.FIRST_COMPLETED)
        finally:
            publisher.cancel()
            watcher.cancel()
            # Bounded: the connection's end must not wait on a task that missed
            # its cancellation.
            await asyncio.wait((publisher, watcher), timeout=_STOP_S)
            for task in (publisher, watcher):
                if task.done() and not task.cancelled():
                    task.exception()  # retrieved: the one that matters is re-raised below
            await self._connection_ended()
        for task in done:
            task.result()  # re-raises the MqttError that ended it

    async def _connection_ended(self) -> None:
        """What the broker did not acknowledge went with the connection: samples
        and link figures are counted lost (re-sent, one the broker did take and
        only its acknowledgement was lost would arrive twice); events are re-sent
        first on the next connection; the status is restated anyway."""
        inflight = self._inflight
        for task in inflight:
            task.cancel()
        if inflight:
            await asyncio.wait(tuple(inflight), timeout=_STOP_S)
        resend = []
        c = self.counters
        for task, item in inflight.items():
            if task.done() and not task.cancelled():
                task.exception()  # retrieved (a refused publish): counted below
            if item[0] in (_SAMPLE, _LINK):
                c["lost_unacked"] += 1
                c["samples_lost"] += item[0] == _SAMPLE
            elif item[0] == _EVENT:
                resend.append(item)
        inflight.clear()
        if self._taken is not None:  # never sent: sent next time
            resend.append(self._taken)
            self._taken = None
        self._resend[:0] = resend

    @staticmethod
    async def _watch(client: aiomqtt.Client) -> None:
        async for _ in client.messages:  # nothing is subscribed: returns only by raising
            pass

    async def _publish_loop(self, client: aiomqtt.Client) -> None:
        if self._status is not None:
            # Retained state is gone if the broker restarted: restate it.
            self._launch(client, (_STATUS, self._status))
        resend = self._resend
        get = self._queue.get
        while True:
            if _cancel_requested():
                raise asyncio.CancelledError
            item = resend.pop(0) if resend else await get()
            self._taken = item
            await self._room()
            self._taken = None
            self._launch(client, item)

    async def _room(self) -> None:
        """Until fewer than ``window`` items await the broker's acknowledgement.

        A broker that acknowledges nothing for ``timeout_s`` is an outage (said
        once); the connection is kept, for it may answer again (a frozen broker
        that wakes before its keepalive expires delivers all it was sent), and
        the client's keepalive ends it otherwise."""
        inflight = self._inflight
        while len(inflight) >= self._window:
            done, _ = await asyncio.wait(
                tuple(inflight), timeout=self._timeout, return_when=asyncio.FIRST_COMPLETED
            )
            for task in done:
                if task in inflight:  # it raised instead of being acknowledged
                    task.result()
            if done and self._stalled:
                self._stalled = False
                log.info("telemetry: the broker %s:%d answers again", self.host, self.port)
                self._outage_ended()
            elif not done and not self._stalled:
                self._stalled = True
                self.counters["stalls"] += 1
                log.warning(
                    "telemetry: the broker %s:%d acknowledged nothing for %g s",
                    self.host,
                    self.port,
                    self._timeout,
                )
                self._outage_began(
                    f"the broker {self.host}:{self.port} acknowledged nothing for "
                    f"{self._timeout:g} s"
                )

    def _launch(self, client: aiomqtt.Client, item: tuple[Any, ...]) -> None:
        task = asyncio.create_task(self._publish(client, item), name="telemetry-item")
        self._inflight[task] = item

    async def _publish(self, client: aiomqtt.Client, item: tuple[Any, ...]) -> None:
        """Publish one item at QoS 1 and wait for the broker's acknowledgement of
        each of its messages, as long as the connection lives."""
        parts = [
            asyncio.ensure_future(
                client.publish(topic, payload, qos=1, retain=retain, timeout=math.inf)
            )
            for topic, payload, retain in self._messages(item)
        ]
        try:
            for part in parts:
                await part
        finally:
            for part in parts:
                if not part.done():
                    part.cancel()
                elif not part.cancelled():
                    part.exception()  # retrieved: the first one raised above
        task = asyncio.current_task()
        if task is not None:
            self._inflight.pop(task, None)
        self.counters["published"] += 1
        self._lost_when_up = self.counters["samples_lost"]

    def _messages(self, item: tuple[Any, ...]) -> list[tuple[str, str, bool]]:
        """The item's MQTT messages: ``(topic, payload, retain)``."""
        kind = item[0]
        if kind == _SAMPLE:
            _, t_s, err, f_hat, u = item
            return [
                (
                    topic,
                    json.dumps(
                        {
                            "t_s": _num(t_s),
                            "err_deg_s": _num(err[i] * _DEG),
                            "f_hat": _num(f_hat[i]),
                            "u": _num(u[i]),
                        }
                    ),
                    False,
                )
                for i, topic in enumerate(self._axis_topics)
            ]
        if kind == _LINK:
            return [(self.topics["link"], json.dumps(item[1]), False)]
        if kind == _STATUS:
            return [(self.topics["status"], json.dumps(item[1], default=str), True)]
        _, ev_kind, detail, t_s = item
        payload = json.dumps({"kind": ev_kind, "detail": detail, "t_s": _num(t_s)})
        return [(self.topics["event"], payload, False)]
