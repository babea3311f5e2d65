"""A viewer of the companion's live view: a Foxglove WebSocket client, as the app is one.

It speaks the protocol as the Foxglove app does (``foxglove-sdk``'s server
takes the subprotocol ``foxglove.sdk.v1``): it reads ``serverInfo`` and
``advertise``, subscribes to every channel advertised, and decodes the binary
message-data frames (opcode 1: subscription id, uint32 LE; log time, uint64 LE
ns; the message, JSON here). The tests and ``scripts/bench.py loop --viewer``
watch a flight with it; ``python -m sitl.lab.live_viewer ws://HOST:PORT
SECONDS`` prints what it saw as JSON.
"""

from __future__ import annotations

import asyncio
import json
import socket
import struct
import sys
import time
from dataclasses import dataclass, field
from typing import Any

__all__ = ["SUBPROTOCOL", "Seen", "watch"]

SUBPROTOCOL = "foxglove.sdk.v1"
_MESSAGE_DATA = 0x01
_HEADER = struct.Struct("<BIQ")


@dataclass
class Seen:
    """What a viewer received."""

    server_info: dict[str, Any] = field(default_factory=dict)
    channels: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Per topic, its ``advertise`` entry (id, encoding, schema name, ...)."""
    messages: dict[str, list[tuple[int, dict[str, Any]]]] = field(default_factory=dict)
    """Per topic, ``(log time ns, message)`` in the order received (with ``keep``)."""
    counts: dict[str, int] = field(default_factory=dict)
    """Messages received per topic."""
    bytes: int = 0
    connected_s: float = float("nan")
    """How long after the call the connection was up (the server answered)."""


async def _connect(url: str, timeout_s: float, rcvbuf_bytes: int | None, **kwargs: Any) -> Any:
    import websockets

    host, _, port = url.removeprefix("ws://").rstrip("/").rpartition(":")
    deadline = time.monotonic() + timeout_s
    while True:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        if rcvbuf_bytes is not None:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf_bytes)
        sock.setblocking(False)
        try:
            await asyncio.get_running_loop().sock_connect(sock, (host, int(port)))
            return await websockets.connect(
                url,
                sock=sock,
                subprotocols=[SUBPROTOCOL],  # type: ignore[list-item]
                **kwargs,
            )
        except (OSError, websockets.InvalidHandshake):
            sock.close()
            if time.monotonic() >= deadline:
                raise
            await asyncio.sleep(0.1)


async def watch(
    url: str,
    *,
    seconds: float,
    keep: bool = True,
    stop_reading_after_s: float | None = None,
    rcvbuf_bytes: int | None = None,
    connect_timeout_s: float = 30.0,
    until_closed: bool = False,
) -> Seen:
    """Connect to ``url``, subscribe to everything, and read for ``seconds``.

    Parameters
    ----------
    keep
        Keep every message decoded (else only count them).
    stop_reading_after_s
        This long after the first message, stop reading, the connection left
        open: a viewer that stalls (its socket fills up, then the server's
        backlog for it).
    rcvbuf_bytes
        The socket's receive buffer (``SO_RCVBUF``): small, a viewer on a slow
        link, whose socket fills up soon.
    connect_timeout_s
        Retry the connection this long (the server may not be up yet).
    until_closed
        Stop early when the server closes the connection (the flight ended).
    """
    t0 = time.monotonic()
    # A small receive queue: a viewer that stops reading stops the socket soon.
    ws = await _connect(url, connect_timeout_s, rcvbuf_bytes, max_size=None, max_queue=4)
    seen = Seen(connected_s=time.monotonic() - t0)
    subs: dict[int, str] = {}
    end = time.monotonic() + seconds
    stall_at: float | None = None  # set at the first message, with stop_reading_after_s
    try:
        next_id = 1
        while True:
            now = time.monotonic()
            if now >= end:
                break
            if stall_at is not None and now >= stall_at:
                await asyncio.sleep(end - now)
                break
            limit = end - now if stall_at is None else min(end, stall_at) - now
            try:
                frame = await asyncio.wait_for(ws.recv(), timeout=max(limit, 0.001))
            except asyncio.TimeoutError:
                continue
            except Exception:  # closed by the server
                if until_closed:
                    break
                raise
            if isinstance(frame, bytes):
                seen.bytes += len(frame)
                if not frame or frame[0] != _MESSAGE_DATA:
                    continue
                _, sub, log_time = _HEADER.unpack_from(frame)
                topic = subs.get(sub)
                if topic is None:
                    continue
                seen.counts[topic] = seen.counts.get(topic, 0) + 1
                if stop_reading_after_s is not None and stall_at is None:
                    stall_at = time.monotonic() + stop_reading_after_s
                if keep:
                    body = json.loads(frame[_HEADER.size :])
                    seen.messages.setdefault(topic, []).append((log_time, body))
                continue
            msg = json.loads(frame)
            op = msg.get("op")
            if op == "serverInfo":
                seen.server_info = msg
            elif op == "advertise":
                new = []
                for ch in msg.get("channels", []):
                    seen.channels[ch["topic"]] = ch
                    subs[next_id] = ch["topic"]
                    new.append({"id": next_id, "channelId": ch["id"]})
                    next_id += 1
                await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
    finally:
        # The close handshake of a viewer that stopped reading would wait for it.
        ws.transport.abort() if stop_reading_after_s is not None else await ws.close()
    return seen


def main(argv: list[str] | None = None) -> int:
    """``python -m sitl.lab.live_viewer URL SECONDS``: watch, then print the counts."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        print("usage: python -m sitl.lab.live_viewer ws://HOST:PORT SECONDS", file=sys.stderr)
        return 2
    seen = asyncio.run(watch(args[0], seconds=float(args[1]), keep=False, until_closed=True))
    print(json.dumps({"topics": sorted(seen.channels), "counts": seen.counts, "bytes": seen.bytes}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
