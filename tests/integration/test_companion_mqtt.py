"""A SITL flight with ``companion run --mqtt``: telemetry reaches a real mosquitto."""

from __future__ import annotations

import asyncio
import contextlib
import json
import threading
from pathlib import Path
from typing import Any

import aiomqtt
import pytest

from sitl.lab.fly import fly_mavlink
from tests.records.test_mqtt import Broker

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]


def test_flight_telemetry_reaches_the_broker(tmp_path: Path) -> None:
    broker = Broker(tmp_path)
    broker.start()
    got: list[tuple[str, Any]] = []
    ready = threading.Event()
    stop = threading.Event()

    async def subscribe() -> None:
        async with aiomqtt.Client("127.0.0.1", broker.port) as client:
            await client.subscribe("mfc/test/#")
            ready.set()
            async for msg in client.messages:
                got.append((str(msg.topic), json.loads(bytes(msg.payload))))
                if stop.is_set():
                    return

    def run_subscriber() -> None:
        # Ends when the test stops it, the broker goes away, or after 90 s.
        with contextlib.suppress(TimeoutError, asyncio.TimeoutError, aiomqtt.MqttError):
            asyncio.run(asyncio.wait_for(subscribe(), timeout=90))

    sub = threading.Thread(target=run_subscriber, daemon=True)
    sub.start()
    try:
        assert ready.wait(10), "subscriber did not connect"
        flight = fly_mavlink(
            ROOT / "vehicle_profiles" / "f450.yaml", "paper-acro", tmp_path / "flight",
            duration_s=8.0,
            companion_args=("--mqtt", f"mqtt://127.0.0.1:{broker.port}/mfc/test"),
        )  # fmt: skip
        assert flight.companion_rc == 0, flight.why()
    finally:
        stop.set()
        broker.kill()
        sub.join(timeout=10)
    topics = {t for t, _ in got}
    assert {"mfc/test/axis/roll", "mfc/test/axis/pitch", "mfc/test/axis/yaw"} <= topics
    assert "mfc/test/status" in topics and "mfc/test/event" in topics
    roll = [p for t, p in got if t == "mfc/test/axis/roll"]
    # Decimated to 10 Hz of sample time (the whole run's: before engaging, engaged,
    # and the hand-back's watch, when the SITL's lockstep clock runs free), not one
    # per control sample (250 Hz).
    span_s = roll[-1]["t_s"] - roll[0]["t_s"]
    assert span_s > 8.0
    assert 9.0 * span_s <= len(roll) <= 11.0 * span_s + 2, (len(roll), span_s)
    assert {"t_s", "err_deg_s", "f_hat", "u"} <= set(roll[0])
    events = [p["kind"] for t, p in got if t == "mfc/test/event"]
    assert "engaged" in events and "handed_back" in events
    states = [p["state"] for t, p in got if t == "mfc/test/status" and "state" in p]
    assert "engaged" in states
