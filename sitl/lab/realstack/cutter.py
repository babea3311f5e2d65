"""A UDP relay between a real stack and the companion that can cut the link, or
only the IMU stream, on demand (the failsafes a cable, a flooded port or an
autopilot that stops streaming make real).

::

    stack --> port P [cutter] --> port Q   companion (udpin:127.0.0.1:Q)
    stack <-- port P [cutter] <-- port Q

The stack sends to P, where the companion would have listened; the cutter
forwards to Q and sends what comes back to whoever last sent to P. ``cut()``
drops everything both ways; ``drop_messages({105, 30})`` drops those MAVLink
messages from the stack to the companion (the rest of each datagram goes on);
``restore()`` passes everything again. One thread; counters say what it did.
"""

from __future__ import annotations

import contextlib
import selectors
import socket
import threading
from collections.abc import Iterable

__all__ = ["LinkCutter", "strip_messages"]

_V2, _V1 = 0xFD, 0xFE


def strip_messages(data: bytes, drop: frozenset[int]) -> bytes:
    """``data`` (MAVLink frames, one datagram) without the frames whose message id is
    in ``drop``; bytes that are no whole frame are kept as they are."""
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        start = data[i]
        if start == _V2 and i + 10 <= n:
            length, incompat = data[i + 1], data[i + 2]
            size = 12 + length + (13 if incompat & 1 else 0)
            msg_id = data[i + 7] | data[i + 8] << 8 | data[i + 9] << 16
        elif start == _V1 and i + 6 <= n:
            size = 8 + data[i + 1]
            msg_id = data[i + 5]
        else:
            out += data[i:]
            break
        frame = data[i : i + size]
        if msg_id not in drop:
            out += frame
        i += size
    return bytes(out)


class LinkCutter:
    """Relay ``listen_port`` (the stack's side) to ``to_port`` (the companion's)."""

    def __init__(self, listen_port: int, to_port: int) -> None:
        self.listen_port = listen_port
        self.to = ("127.0.0.1", to_port)
        self._stack_side = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._stack_side.bind(("127.0.0.1", listen_port))
        self._companion_side = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._companion_side.bind(("127.0.0.1", 0))
        self._stack_addr: tuple[str, int] | None = None
        self._cut = False
        self._drop: frozenset[int] = frozenset()
        self._stop = threading.Event()
        self.counters = {"to_companion": 0, "to_stack": 0, "dropped": 0, "frames_stripped": 0}
        self._thread = threading.Thread(target=self._loop, name="link-cutter", daemon=True)
        self._thread.start()

    def cut(self) -> None:
        """Nothing passes, either way (a cable pulled)."""
        self._cut = True

    def drop_messages(self, ids: Iterable[int]) -> None:
        """These messages from the stack do not reach the companion."""
        self._drop = frozenset(ids)

    def restore(self) -> None:
        self._cut = False
        self._drop = frozenset()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        for s in (self._stack_side, self._companion_side):
            with contextlib.suppress(OSError):
                s.close()

    def _loop(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self._stack_side, selectors.EVENT_READ, "stack")
        sel.register(self._companion_side, selectors.EVENT_READ, "companion")
        while not self._stop.is_set():
            for key, _ in sel.select(timeout=0.1):
                sock: socket.socket = key.fileobj  # type: ignore[assignment]
                try:
                    data, addr = sock.recvfrom(65535)
                except OSError:
                    continue
                if key.data == "stack":
                    self._stack_addr = addr
                    self._forward(data, self._companion_side, self.to, "to_companion")
                elif self._stack_addr is not None:
                    self._forward(data, self._stack_side, self._stack_addr, "to_stack")
        sel.close()

    def _forward(self, data: bytes, sock: socket.socket, addr: tuple[str, int], key: str) -> None:
        if self._cut:
            self.counters["dropped"] += 1
            return
        if self._drop and key == "to_companion":
            kept = strip_messages(data, self._drop)
            if len(kept) != len(data):
                self.counters["frames_stripped"] += 1
            data = kept
            if not data:
                return
        with contextlib.suppress(OSError):
            sock.sendto(data, addr)
        self.counters[key] += 1
