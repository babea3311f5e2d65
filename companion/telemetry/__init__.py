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

:mod:`~companion.telemetry.mqtt_telemetry` is the control loop's side (the
queue), :mod:`~companion.telemetry.connection` the broker's and
:mod:`~companion.telemetry.wire` the URL and the payloads.
"""

from companion.telemetry.mqtt_telemetry import MqttTelemetry
from companion.telemetry.wire import parse_mqtt_url

__all__ = ["MqttTelemetry", "parse_mqtt_url"]
