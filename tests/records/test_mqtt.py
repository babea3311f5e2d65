"""MqttTelemetry: URL parsing, a full queue, and a real mosquitto broker."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import os
import re
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import aiomqtt
import pytest

from companion.telemetry import MqttTelemetry, parse_mqtt_url
from sitl.lab import children
from sitl.lab.fly import free_tcp_port

PREFIX = "mfc/f450"


# -- no broker needed -----------------------------------------------------------


def test_url_parsing() -> None:
    assert parse_mqtt_url("mqtt://127.0.0.1:1884/mfc/f450") == ("127.0.0.1", 1884, "mfc/f450")
    assert parse_mqtt_url("mqtt://broker.local/mfc/") == ("broker.local", 1883, "mfc")
    t = MqttTelemetry("mqtt://localhost/a/b")
    assert t.topics == {
        "roll": "a/b/axis/roll",
        "pitch": "a/b/axis/pitch",
        "yaw": "a/b/axis/yaw",
        "status": "a/b/status",
        "event": "a/b/event",
        "link": "a/b/link",
    }
    for bad in (
        "mqtt://127.0.0.1:1883",  # no prefix
        "mqtt://127.0.0.1:1883/",
        "http://127.0.0.1/mfc",
        "127.0.0.1:1883/mfc",
        "mqtt://:1883/mfc",
        "mqtt://127.0.0.1:notaport/mfc",
        "mqtt://127.0.0.1:70000/mfc",
        "mqtt://127.0.0.1/mfc/#",
        "mqtt://127.0.0.1/mfc//x",
    ):
        with pytest.raises(ValueError, match="bad MQTT URL") as info:
            MqttTelemetry(bad)
        assert repr(bad) in str(info.value)


def test_decimation_is_on_sample_time() -> None:
    t = MqttTelemetry("mqtt://127.0.0.1/x", decimate_hz=10.0)
    for k in range(2000):  # 2 s at 1 kHz
        t.publish_sample(k * 0.001, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    times = []
    while not t._queue.empty():
        times.append(t._queue.get_nowait()[1])
    assert times == pytest.approx([0.1 * i for i in range(20)], abs=1e-9)
    assert t.counters["samples"] == 2000 and t.counters["queued"] == 20
    # time going back (a new flight) restarts the grid; a gap does not bunch samples
    for s in (5.0, 5.05, 5.1, 9.0, 9.05, 9.1, 0.0, 0.05, 0.1):
        t.publish_sample(s, (0.0,) * 3, (0.0,) * 3, (0.0,) * 3)
    times = [t._queue.get_nowait()[1] for _ in range(t._queue.qsize())]
    assert times == pytest.approx([5.0, 5.1, 9.0, 9.1, 0.0, 0.1])


async def test_full_queue_drops_counts_and_never_blocks(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # Nothing listens on this port: run() keeps failing to connect meanwhile.
    port = free_tcp_port()
    t = MqttTelemetry(f"mqtt://127.0.0.1:{port}/{PREFIX}", queue_size=50, decimate_hz=1000.0)
    task = asyncio.create_task(t.run(), name="telemetry")
    for _ in range(500):  # until the first failed connect (bounded: 5 s)
        if t.counters["connect_failures"] >= 1:
            break
        await asyncio.sleep(0.01)
    assert t.counters["connect_failures"] >= 1 and not t.connected
    caplog.set_level(logging.WARNING, logger="companion.telemetry")
    # publish_sample is synchronous: 5000 calls in a row with no await in between
    # cannot wait for anything; the counts show what became of each.
    for k in range(5000):
        t.publish_sample(k * 0.001, (0.1, 0.2, 0.3), (1.0, 2.0, 3.0), (4.0, 5.0, 6.0))
    assert t.counters["queued"] == 50
    assert t.counters["dropped_full"] == 5000 - 50
    full_warnings = [r for r in caplog.records if "queue full" in r.getMessage()]
    assert len(full_warnings) == 1  # rate-limited, not one per drop
    # status and events are still taken, evicting the oldest samples
    t.publish_status({"state": "engaged", "mode": "OFFBOARD", "armed": True})
    t.publish_event("failsafe", "rc lost", 4.9)
    assert t.counters["dropped_full"] == 5000 - 50 + 2
    kinds = [item[0] for item in list(t._queue._queue)]  # type: ignore[attr-defined]
    assert kinds[-2:] == [1, 2] and len(kinds) == 50
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await stopped(task)


# -- a real mosquitto -------------------------------------------------------------


def mosquitto_binary() -> str:
    exe = shutil.which("mosquitto") or shutil.which("mosquitto", path="/usr/sbin:/usr/local/sbin")
    if exe is None:
        pytest.fail(
            "mosquitto not found: install the MQTT broker (Debian/Ubuntu: "
            "`sudo apt-get install mosquitto`; macOS: `brew install mosquitto`) "
            "to run the MQTT telemetry integration tests"
        )
    return exe


class Broker:
    """A mosquitto subprocess on a fixed loopback port, restartable."""

    def __init__(self, tmp: Path) -> None:
        self.exe = mosquitto_binary()
        self.port = free_tcp_port()
        self.conf = tmp / "mosquitto.conf"
        self.conf.write_text(
            f"listener {self.port} 127.0.0.1\nallow_anonymous true\npersistence false\n"
        )
        self.log = tmp / "mosquitto.log"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        with open(self.log, "ab") as out:
            self.proc = children.start(
                [self.exe, "-c", str(self.conf)], stdout=out, stderr=subprocess.STDOUT
            )
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                pytest.fail(f"mosquitto exited: {self.log.read_text()}")
            with (
                contextlib.suppress(OSError),
                socket.create_connection(("127.0.0.1", self.port), timeout=0.2),
            ):
                return
            time.sleep(0.05)
        pytest.fail(f"mosquitto did not listen on {self.port}: {self.log.read_text()}")

    def freeze(self) -> None:
        """SIGSTOP: the broker's sockets keep taking bytes, nothing answers them."""
        assert self.proc is not None
        self.proc.send_signal(signal.SIGSTOP)

    def thaw(self) -> None:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGCONT)

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)
        self.proc = None


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Broker]:
    b = Broker(tmp_path)
    b.start()
    try:
        yield b
    finally:
        b.kill()


class Subscriber:
    """A separate aiomqtt client collecting everything under the prefix."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.messages: list[tuple[str, Any, bool]] = []
        self.ready = asyncio.Event()

    async def run(self) -> None:
        async with aiomqtt.Client("127.0.0.1", self.port, identifier=f"sub-{os.getpid()}") as c:
            await c.subscribe(f"{PREFIX}/#", qos=1)
            self.ready.set()
            async for m in c.messages:
                payload = bytes(m.payload).decode()
                self.messages.append((str(m.topic), json.loads(payload), bool(m.retain)))

    def on(self, topic: str) -> list[Any]:
        return [p for t, p, _ in self.messages if t == f"{PREFIX}/{topic}"]


@contextlib.asynccontextmanager
async def subscribed(port: int) -> AsyncIterator[Subscriber]:
    sub = Subscriber(port)
    task = asyncio.create_task(sub.run(), name="subscriber")
    try:
        await asyncio.wait_for(sub.ready.wait(), 5.0)
        yield sub
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
            await asyncio.wait_for(task, 15.0)


async def stopped(task: asyncio.Task[None], timeout: float = 10.0) -> None:
    """Await a cancelled task, failing (not hanging) if it does not end."""
    done, _ = await asyncio.wait({task}, timeout=timeout)
    assert done, f"task {task.get_name()} did not end within {timeout} s of its cancellation"
    await task


async def until(cond: Any, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        await asyncio.sleep(0.02)


def sample(t: MqttTelemetry, k: int) -> None:
    """Sample k of a 1 kHz stream with recognisable values."""
    s = k * 0.001
    t.publish_sample(s, (math.radians(10.0), -0.5, 0.25), (1.5, -2.5, 3.5), (100.0, -50.0, s))


@pytest.mark.integration
async def test_topics_payloads_decimation_and_clean_cancel(broker: Broker) -> None:
    t = MqttTelemetry(f"mqtt://127.0.0.1:{broker.port}/{PREFIX}", decimate_hz=10.0)
    task = asyncio.create_task(t.run(), name="telemetry")
    async with subscribed(broker.port) as sub:
        await until(lambda: t.connected)
        t.publish_status({"state": "engaged", "mode": "OFFBOARD", "armed": True})
        for k in range(2000):  # 2 s of samples at 1 kHz
            sample(t, k)
        t.publish_event("failsafe", "rc lost: holding", 1.999)
        await until(lambda: len(sub.on("event")) == 1 and len(sub.on("axis/yaw")) == 20)
        await asyncio.sleep(0.2)  # nothing more arrives

        roll, pitch, yaw = sub.on("axis/roll"), sub.on("axis/pitch"), sub.on("axis/yaw")
        assert len(roll) == len(pitch) == len(yaw) == 20
        assert [p["t_s"] for p in roll] == pytest.approx([0.1 * i for i in range(20)])
        assert set(roll[0]) == {"t_s", "err_deg_s", "f_hat", "u"}
        assert roll[5]["err_deg_s"] == pytest.approx(10.0)
        assert pitch[5]["err_deg_s"] == pytest.approx(math.degrees(-0.5))
        assert (roll[5]["f_hat"], pitch[5]["f_hat"], yaw[5]["f_hat"]) == (1.5, -2.5, 3.5)
        assert (roll[5]["u"], pitch[5]["u"]) == (100.0, -50.0)
        assert yaw[5]["u"] == pytest.approx(0.5)
        assert sub.on("status") == [{"state": "engaged", "mode": "OFFBOARD", "armed": True}]
        assert sub.on("event") == [{"kind": "failsafe", "detail": "rc lost: holding", "t_s": 1.999}]
        assert t.counters["published"] == 22 and t.counters["dropped_full"] == 0

    # the status is retained: a late subscriber gets it at once
    async with subscribed(broker.port) as late:
        await until(lambda: late.on("status"))
        assert late.messages[0][2] is True  # retain flag
        assert late.on("status")[-1]["state"] == "engaged"

    # cancelling is clean and leaves "offline" retained
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await stopped(task)
    assert task.cancelled() and not t.connected
    async with subscribed(broker.port) as after:
        await until(lambda: after.on("status"))
        assert after.on("status")[-1] == {"state": "offline"}


@pytest.mark.integration
async def test_reconnects_after_the_broker_restarts(broker: Broker) -> None:
    t = MqttTelemetry(f"mqtt://127.0.0.1:{broker.port}/{PREFIX}", decimate_hz=100.0)
    outages: list[tuple[str, str]] = []
    t.on_outage = lambda kind, detail: outages.append((kind, detail))
    task = asyncio.create_task(t.run(), name="telemetry")
    k = 0

    async def stream(seconds: float) -> None:
        """1 kHz samples in real time, every one due by now sent every 10 ms (on a
        loaded machine a sleep lasts longer: a fixed count per wake-up streamed too
        few, and the 20 below never came)."""
        nonlocal k
        start, k0 = time.monotonic(), k
        while (now := time.monotonic()) < start + seconds:
            while k < k0 + int((now - start) * 1000.0):
                sample(t, k)
                k += 1
            await asyncio.sleep(0.01)

    async with subscribed(broker.port) as sub:
        await until(lambda: t.connected)
        t.publish_status({"state": "engaged", "mode": "OFFBOARD", "armed": True})
        await stream(0.3)
        await until(lambda: len(sub.on("axis/roll")) >= 20)

    broker.kill()
    await stream(1.0)  # publish_* keep working while the broker is gone
    assert not t.connected
    assert t.counters["disconnects"] == 1
    # The outage is said once (the app records it in events.jsonl), however many
    # attempts fail meanwhile.
    assert [kind for kind, _ in outages] == ["telemetry_lost"]
    assert f"lost the broker 127.0.0.1:{broker.port}" in outages[0][1]
    t.publish_event("link", "broker restarted", k * 0.001)
    k_restart = k
    broker.start()  # same port
    async with subscribed(broker.port) as sub2:
        await until(lambda: t.connected, timeout=15.0)
        await stream(0.5)
        # after reconnecting, fresh samples flow (behind whatever the queue kept from
        # the outage, which drains first), the retained status is restated, and the
        # event published during the outage arrives
        t_restart = k_restart * 0.001
        await until(lambda: any(p["t_s"] > t_restart for p in sub2.on("axis/roll")))
        await until(lambda: sub2.on("event"))
        assert sub2.on("event")[0]["detail"] == "broker restarted"
    assert t.counters["reconnects"] == 1
    assert [kind for kind, _ in outages] == ["telemetry_lost", "telemetry_restored"]
    assert lost_said(outages[1][1]) == t.counters["samples_lost"]
    async with subscribed(broker.port) as late:
        await until(lambda: late.on("status"))
        assert late.on("status")[-1]["state"] == "engaged"

    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await stopped(task)


def lost_said(detail: str) -> int:
    """The samples a ``telemetry_restored`` detail says were lost."""
    m = re.search(r"is back; (\d+) samples lost meanwhile \(([\d.]+) s of telemetry\)$", detail)
    assert m is not None, detail
    return int(m.group(1))


@pytest.mark.integration
@pytest.mark.slow
async def test_a_frozen_broker_costs_what_the_counters_say(broker: Broker) -> None:
    """SIGSTOP the broker for 5 s: TCP still takes bytes, nothing is acknowledged.

    With keepalive 2 s the broker's own cutoff (1.5 x 2 s) passes while it is
    frozen: waking, it drops the connection and the bytes it held, as a broker
    frozen beyond 15 s does with the default 10 s. What the subscriber misses
    must be what the counters and ``telemetry_restored`` say was lost: the
    samples in flight (the window), and those the small queue could not hold.
    Equal, give or take one sample (one whose acknowledgement was on its way
    when the connection ended: counted lost, yet delivered)."""
    t = MqttTelemetry(
        f"mqtt://127.0.0.1:{broker.port}/{PREFIX}", decimate_hz=10.0, queue_size=20, keepalive_s=2
    )
    outages: list[tuple[str, str]] = []
    t.on_outage = lambda kind, detail: outages.append((kind, detail))
    task = asyncio.create_task(t.run(), name="telemetry")
    offered: list[float] = []
    k = 0

    async def stream(seconds: float) -> None:
        """250 Hz samples in real time, every one due by now sent on each wake-up (on
        a loaded machine a 4 ms sleep lasts longer: one sample per wake-up streamed
        too few to fill the queue while the broker was frozen); keeps the t_s the
        decimation took."""
        nonlocal k
        start, k0 = time.monotonic(), k
        while (now := time.monotonic()) < start + seconds:
            while k < k0 + int((now - start) * 250.0):
                taken = t.counters["queued"] + t.counters["dropped_full"]
                sample(t, k * 4)  # sample() counts milliseconds
                if t.counters["queued"] + t.counters["dropped_full"] > taken:
                    offered.append(round(k * 0.004, 6))
                k += 1
            await asyncio.sleep(0.004)

    async with subscribed(broker.port) as sub:
        await until(lambda: t.connected)
        await stream(1.0)
        broker.freeze()
        try:
            await stream(5.0)
        finally:
            broker.thaw()
        await stream(1.0)
        await until(lambda: [kind for kind, _ in outages][-1:] == ["telemetry_restored"])
        await until(lambda: t._queue.empty() and not t._connection._inflight)
        await asyncio.sleep(0.3)  # the last deliveries reach the subscriber
        got = {round(p["t_s"], 6) for p in sub.on("axis/roll")}

    missing = len(set(offered) - got)
    c = t.counters
    assert missing > 10, (missing, c)  # the window and the full queue: something was lost
    assert abs(c["samples_lost"] - missing) <= 1, (missing, c)
    assert c["samples_lost"] == c["lost_unacked"] + c["dropped_full"]  # no link figures here
    assert 0 < c["lost_unacked"] <= 10  # the window: what the broker took down with it
    assert [kind for kind, _ in outages] == ["telemetry_lost", "telemetry_restored"]
    assert lost_said(outages[1][1]) == c["samples_lost"]
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await stopped(task)
