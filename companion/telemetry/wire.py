"""What MQTT telemetry puts on the wire: the broker's URL and each queued item's messages.

An item is a tuple whose first field is its kind (``_SAMPLE``, ``_STATUS``,
``_EVENT``, ``_LINK``); :func:`messages` turns it into JSON payloads on their
topics. Topics and payloads are documented in ``docs/telemetry.md``.
"""

from __future__ import annotations

import json
import math
from typing import Any
from urllib.parse import urlsplit

__all__ = ["Vec3", "messages", "parse_mqtt_url"]

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


def messages(
    item: tuple[Any, ...], topics: dict[str, str], axis_topics: tuple[str, ...]
) -> list[tuple[str, str, bool]]:
    """The item's MQTT messages: ``(topic, payload, retain)``, on ``topics``
    (:attr:`companion.telemetry.MqttTelemetry.topics`) and ``axis_topics`` (its
    roll, pitch and yaw topics, in that order)."""
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
            for i, topic in enumerate(axis_topics)
        ]
    if kind == _LINK:
        return [(topics["link"], json.dumps(item[1]), False)]
    if kind == _STATUS:
        return [(topics["status"], json.dumps(item[1], default=str), True)]
    _, ev_kind, detail, t_s = item
    payload = json.dumps({"kind": ev_kind, "detail": detail, "t_s": _num(t_s)})
    return [(topics["event"], payload, False)]
