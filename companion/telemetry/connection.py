"""MQTT telemetry's broker side: the connection that publishes what the queue holds.

:class:`BrokerConnection` takes the items :class:`companion.telemetry.MqttTelemetry`
queues, publishes their messages with aiomqtt at QoS 1, keeping at most
``window`` items unacknowledged, and reconnects when the broker goes; what a
lost connection took with it is counted, and each outage is said once.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
from collections.abc import Callable
from typing import Any

import aiomqtt

from companion.control import AXES as _AXES
from companion.telemetry.wire import _EVENT, _LINK, _SAMPLE, _STATUS, messages

__all__ = ["BrokerConnection"]

log = logging.getLogger("companion.telemetry")

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


class BrokerConnection:
    """Publish one telemetry queue to an MQTT broker, connection after connection.

    :class:`companion.telemetry.MqttTelemetry` makes one, hands it its queue,
    its ``counters`` (both updated here) and its ``topics``; the other
    parameters are its own, as it documents them. ``period_s`` is the
    decimation period, for the seconds of telemetry an outage lost.
    """

    def __init__(
        self,
        host: str,
        port: int,
        queue: asyncio.Queue[tuple[Any, ...]],
        counters: dict[str, int],
        topics: dict[str, str],
        *,
        client_id: str | None,
        backoff_min_s: float,
        backoff_max_s: float,
        keepalive_s: int,
        timeout_s: float,
        window: int,
        period_s: float,
    ) -> None:
        self.host = host
        self.port = port
        self.client_id = client_id
        self.topics = topics
        self._axis_topics = tuple(self.topics[a] for a in _AXES)
        self._queue = queue
        self.counters = counters
        self._period = period_s
        self._backoff_min = backoff_min_s
        self._backoff_max = backoff_max_s
        self._keepalive = keepalive_s
        self._timeout = timeout_s
        self.status: dict[str, Any] | None = None
        """The latest status: restated on every connection."""
        self._window = window
        self._inflight: dict[asyncio.Task[None], tuple[Any, ...]] = {}
        """Items handed to the client, until the broker acknowledges them."""
        self._taken: tuple[Any, ...] | None = None  # from the queue, waiting for room
        self._resend: list[tuple[Any, ...]] = []  # events (and an item never sent)
        self._stalled = False
        self.connected = False
        self.on_outage: Callable[[str, str], None] | None = None
        """Told of each outage and of its end (:attr:`MqttTelemetry.on_outage
        <companion.telemetry.MqttTelemetry.on_outage>`)."""
        self._outage_lost: int | None = None  # samples_lost when this outage began
        self._lost_when_up = 0  # samples_lost at the broker's last acknowledgement

    async def drain(self, timeout_s: float = 1.0) -> bool:
        """:meth:`companion.telemetry.MqttTelemetry.drain`: True when all that was
        queued was acknowledged within ``timeout_s``."""
        deadline = asyncio.get_running_loop().time() + timeout_s
        while not self._queue.empty() or self._taken is not None or self._inflight:
            if not self.connected or asyncio.get_running_loop().time() >= deadline:
                return False
            await asyncio.sleep(0.01)
        return True

    async def run(self) -> None:
        """:meth:`companion.telemetry.MqttTelemetry.run`: connect, publish, reconnect;
        until cancelled, when the status goes ``offline``."""
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
        if self.status is not None:
            # Retained state is gone if the broker restarted: restate it.
            self._launch(client, (_STATUS, self.status))
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
            for topic, payload, retain in messages(item, self.topics, self._axis_topics)
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
