"""A UDP relay that delays, and optionally jitters, drops, duplicates and reorders.

It sits between two MAVLink ends that would otherwise talk directly, e.g. the
SITL (``--mavlink udpout:127.0.0.1:LISTEN``) and the companion (``--connect
udpin:127.0.0.1:TO``)::

    SITL --> LISTEN [relay] ephemeral port --> TO   companion
    SITL <-- LISTEN [relay] ephemeral port <-- TO   companion

Datagrams arriving at ``listen`` go out to ``to``; datagrams coming back from
``to`` go to whoever last sent to ``listen``. Each direction is impaired on its
own, with the same settings; every random draw comes from one
``np.random.default_rng(seed)``.

The delay is wall-clock time: against a SITL on its lockstep clock (which
stops simulation time while it waits for each setpoint) it only slows the run
down; fly the SITL on ``--clock realtime`` to put the delay into the loop.
Timers run on the asyncio loop, so a datagram leaves up to about 1 ms after
its due time (``counters``: ``late_max_s``, ``late_total_s`` over ``sent``).

Use from async code::

    async with UdpRelay(("127.0.0.1", 0), ("127.0.0.1", port), delay_s=0.01) as relay:
        ...  # point the SITL at relay.listen_port

from blocking code (e.g. around :func:`sitl.lab.fly.fly_mavlink`)::

    with UdpRelay(("127.0.0.1", 0), ("127.0.0.1", port), delay_s=0.01).in_thread() as relay:
        ...

or by hand::

    python -m tests.relay --listen 127.0.0.1:14550 --to 127.0.0.1:14540 --delay-ms 10
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import heapq
import logging
import signal
import threading
from collections.abc import Iterator
from typing import Any

import numpy as np

__all__ = ["UdpRelay", "main"]

logger = logging.getLogger(__name__)

Address = tuple[str, int]


class _Side(asyncio.DatagramProtocol):
    """One socket of the relay: what it receives goes to the other side."""

    def __init__(self, relay: UdpRelay, name: str) -> None:
        self.relay = relay
        self.name = name
        self.transport: asyncio.DatagramTransport | None = None
        self.dest: Address | None = None  # where this side sends
        self.queue: list[tuple[float, int, bytes]] = []  # (due, seq, datagram), a heap
        self.last_due = 0.0  # keeps the delayed stream in order under jitter
        self.timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: Address) -> None:
        self.relay._received(self, data, addr)

    def error_received(self, exc: Exception) -> None:
        # ECONNREFUSED: the other end is not listening (yet); it may come back.
        self.relay.counters["send_errors"] += 1


class UdpRelay:
    """Relay UDP datagrams between ``listen`` and ``to``, impaired both ways.

    Parameters
    ----------
    listen
        (host, port) to bind; port 0 binds an ephemeral one (see :attr:`listen_port`).
    to
        (host, port) to forward to; its answers go back to the last sender to ``listen``.
    delay_s
        Fixed one-way delay, s.
    jitter_s
        Extra one-way delay drawn uniformly from [0, jitter_s]; the order of the
        stream is kept (a later datagram never leaves before an earlier one).
    loss, duplicate, reorder
        Probabilities per datagram: dropped; sent twice; held ``reorder_s``
        longer outside the ordered stream, so that later datagrams overtake it.
    seed
        Seed of ``np.random.default_rng`` for all of the above.
    """

    def __init__(
        self,
        listen: Address,
        to: Address,
        *,
        delay_s: float = 0.0,
        jitter_s: float = 0.0,
        loss: float = 0.0,
        duplicate: float = 0.0,
        reorder: float = 0.0,
        reorder_s: float = 0.002,
        seed: int = 0,
    ) -> None:
        for name, p in (("loss", loss), ("duplicate", duplicate), ("reorder", reorder)):
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name} must be a probability in [0, 1], got {p!r}")
        for name, s in (("delay_s", delay_s), ("jitter_s", jitter_s), ("reorder_s", reorder_s)):
            if not s >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {s!r}")
        self.listen, self.to = listen, to
        self.delay_s, self.jitter_s = delay_s, jitter_s
        self.loss, self.duplicate = loss, duplicate
        self.reorder, self.reorder_s = reorder, reorder_s
        self.rng = np.random.default_rng(seed)
        self.counters: dict[str, Any] = dict.fromkeys(
            ("received", "sent", "lost", "duplicated", "reordered", "no_peer", "send_errors"), 0
        )
        self.counters.update(late_max_s=0.0, late_total_s=0.0)
        self._seq = 0
        self._a: _Side | None = None  # bound to `listen`, sends back to its last sender
        self._b: _Side | None = None  # ephemeral port, sends to `to`
        self._loop: asyncio.AbstractEventLoop | None = None

    @property
    def listen_port(self) -> int:
        """The port bound for ``listen`` (after :meth:`start`)."""
        if self._a is None or self._a.transport is None:
            raise RuntimeError("the relay is not started")
        return int(self._a.transport.get_extra_info("sockname")[1])

    async def start(self) -> None:
        loop = self._loop = asyncio.get_running_loop()
        _, a = await loop.create_datagram_endpoint(lambda: _Side(self, "a"), local_addr=self.listen)
        _, b = await loop.create_datagram_endpoint(
            lambda: _Side(self, "b"), local_addr=(self.listen[0], 0)
        )
        self._a, self._b = a, b
        b.dest = self.to
        logger.info(
            "relay %s:%d <-> %s:%d, %.1f ms each way",
            self.listen[0], self.listen_port, *self.to, self.delay_s * 1e3,
        )  # fmt: skip

    async def close(self) -> None:
        """Stop; datagrams still in flight are dropped. Idempotent."""
        for side in (self._a, self._b):
            if side is not None:
                if side.timer is not None:
                    side.timer.cancel()
                if side.transport is not None:
                    side.transport.close()
        self._a = self._b = None

    async def __aenter__(self) -> UdpRelay:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    @contextlib.contextmanager
    def in_thread(self) -> Iterator[UdpRelay]:
        """Run the relay on its own event loop in a daemon thread while the block runs."""
        started = threading.Event()
        stop: list[asyncio.Event] = []
        errors: list[BaseException] = []

        async def serve() -> None:
            stop.append(asyncio.Event())
            try:
                async with self:
                    started.set()
                    await stop[0].wait()
            except BaseException as exc:  # reported to the caller below
                errors.append(exc)
                started.set()

        thread = threading.Thread(target=asyncio.run, args=(serve(),), name="relay", daemon=True)
        thread.start()
        started.wait()
        if errors:
            raise errors[0]
        loop = self._loop
        assert loop is not None
        try:
            yield self
        finally:
            loop.call_soon_threadsafe(stop[0].set)
            thread.join(timeout=5.0)

    # ------------------------------------------------------------------ the path

    def _received(self, side: _Side, data: bytes, addr: Address) -> None:
        assert self._a is not None and self._b is not None and self._loop is not None
        if side is self._a:
            self._a.dest = addr  # answers from `to` go back to the last sender here
            out = self._b
        else:
            out = self._a
        c = self.counters
        c["received"] += 1
        rng = self.rng
        if self.loss and rng.random() < self.loss:
            c["lost"] += 1
            return
        copies = 2 if self.duplicate and rng.random() < self.duplicate else 1
        c["duplicated"] += copies - 1
        now = self._loop.time()
        for _ in range(copies):
            due = now + self.delay_s + (self.jitter_s * rng.random() if self.jitter_s else 0.0)
            if self.reorder and rng.random() < self.reorder:
                c["reordered"] += 1
                due = max(due, out.last_due) + self.reorder_s
            else:
                due = out.last_due = max(due, out.last_due)
            self._seq += 1
            heapq.heappush(out.queue, (due, self._seq, data))
        self._schedule(out)

    def _schedule(self, side: _Side) -> None:
        assert self._loop is not None
        due = side.queue[0][0]
        if side.timer is not None:
            if side.timer.when() <= due:
                return
            side.timer.cancel()
        side.timer = self._loop.call_at(due, self._release, side)

    def _release(self, side: _Side) -> None:
        """Send every datagram of ``side`` that is due, then wait for the next one."""
        assert self._loop is not None
        side.timer = None
        now = self._loop.time()
        c = self.counters
        while side.queue and side.queue[0][0] <= now:
            due, _, data = heapq.heappop(side.queue)
            c["late_max_s"] = max(c["late_max_s"], now - due)
            c["late_total_s"] += now - due
            if side.dest is None or side.transport is None:
                c["no_peer"] += 1
                continue
            side.transport.sendto(data, side.dest)
            c["sent"] += 1
        if side.queue:
            self._schedule(side)


# ---------------------------------------------------------------------- command line


def _address(text: str) -> Address:
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit():
        raise argparse.ArgumentTypeError(f"expected HOST:PORT, got {text!r}")
    return host, int(port)


def main(argv: list[str] | None = None) -> None:
    """``python -m tests.relay --listen HOST:PORT --to HOST:PORT --delay-ms MS [...]``."""
    p = argparse.ArgumentParser(prog="python -m tests.relay", description=__doc__.split("\n")[0])
    p.add_argument("--listen", type=_address, required=True, help="HOST:PORT to bind.")
    p.add_argument("--to", type=_address, required=True, help="HOST:PORT to forward to.")
    p.add_argument("--delay-ms", type=float, default=0.0, help="One-way delay, ms.")
    p.add_argument("--jitter-ms", type=float, default=0.0, help="Extra uniform [0, J] ms.")
    p.add_argument("--loss", type=float, default=0.0, help="Drop probability.")
    p.add_argument("--duplicate", type=float, default=0.0, help="Duplicate probability.")
    p.add_argument("--reorder", type=float, default=0.0, help="Reorder probability.")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    try:
        relay = UdpRelay(
            args.listen, args.to, delay_s=args.delay_ms * 1e-3, jitter_s=args.jitter_ms * 1e-3,
            loss=args.loss, duplicate=args.duplicate, reorder=args.reorder, seed=args.seed,
        )  # fmt: skip
    except ValueError as exc:
        p.error(str(exc))

    async def serve() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        async with relay:
            await stop.wait()
        logger.info("relay counters: %s", relay.counters)

    asyncio.run(serve())


if __name__ == "__main__":
    main()
