"""Transports over real sockets and a real pseudo-terminal, and the in-memory pair."""

from __future__ import annotations

import asyncio
import os
import socket
import tty
from collections.abc import Iterator

import pytest

from companion.errors import LinkError
from companion.link.transport import (
    MemoryTransport,
    SerialTransport,
    UdpInTransport,
    UdpOutTransport,
    open_transport,
)


class Inbox:
    """Collects chunks; ``await inbox.get()`` returns the next one (with a timeout)."""

    def __init__(self) -> None:
        self.queue: asyncio.Queue[bytes] = asyncio.Queue()

    def __call__(self, chunk: bytes) -> None:
        self.queue.put_nowait(chunk)

    async def get(self, timeout_s: float = 2.0) -> bytes:
        return await asyncio.wait_for(self.queue.get(), timeout_s)


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# ------------------------------------------------------------------------ memory


async def test_memory_pair_round_trip() -> None:
    a, b = MemoryTransport.pair()
    in_a, in_b = Inbox(), Inbox()
    a.write(b"early")  # not open: dropped
    assert a.counters["dropped_not_open"] == 1
    await a.open(in_a)
    a.write(b"nobody")  # b not open yet: dropped
    assert a.counters["dropped_no_peer"] == 1
    await b.open(in_b)
    a.write(b"ping")
    assert in_b.queue.empty()  # delivered via call_soon, not synchronously
    assert await in_b.get() == b"ping"
    b.write(bytearray(b"pong"))
    assert await in_a.get() == b"pong"
    assert a.counters["bytes_out"] == 4 and b.counters["bytes_in"] == 4
    await a.close()
    await a.close()  # idempotent
    b.write(b"lost")
    await asyncio.sleep(0)
    assert in_a.queue.empty()


# --------------------------------------------------------------------------- UDP


async def test_udpin_replies_only_to_the_sender_the_link_confirmed() -> None:
    port = free_udp_port()
    t = UdpInTransport("127.0.0.1", port)
    inbox = Inbox()

    def deliver(chunk: bytes) -> None:
        inbox(chunk)
        if chunk.startswith(b"ap:"):  # the link recognised its autopilot in this chunk
            t.confirm_peer()

    await t.open(deliver)
    try:
        t.write(b"to nobody")
        assert t.counters["dropped_no_peer"] == 1
        s1 = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s2 = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for s in (s1, s2):
            s.bind(("127.0.0.1", 0))
            s.settimeout(0.3)
        s2.sendto(b"junk", ("127.0.0.1", port))
        assert await inbox.get() == b"junk"  # delivered, but nobody to answer yet
        t.write(b"reply")
        assert t.counters["dropped_no_peer"] == 2
        s1.sendto(b"ap: one", ("127.0.0.1", port))
        assert await inbox.get() == b"ap: one"
        t.write(b"reply one")
        assert s1.recv(100) == b"reply one"
        s2.sendto(b"junk again", ("127.0.0.1", port))
        assert await inbox.get() == b"junk again"
        t.write(b"reply two")
        assert s1.recv(100) == b"reply two"  # a stranger does not move our replies
        with pytest.raises(TimeoutError):
            s2.recv(100)
        s2.sendto(b"ap: moved", ("127.0.0.1", port))  # the autopilot from a new address
        assert await inbox.get() == b"ap: moved"
        t.write(b"reply three")
        assert s2.recv(100) == b"reply three"
        assert t.peer == s2.getsockname()
        assert t.counters["peer_changes"] == 1
        assert t.counters["other_sender_chunks"] == 4  # each arrived from a non-peer
        assert t.counters["chunks_in"] == 4 and t.counters["chunks_out"] == 3
        s1.close()
        s2.close()
    finally:
        await t.close()
    await t.close()


async def test_udpout_sends_and_receives_replies() -> None:
    server = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    server.bind(("127.0.0.1", 0))
    server.settimeout(2.0)
    port = server.getsockname()[1]
    t = UdpOutTransport("127.0.0.1", port)
    inbox = Inbox()
    await t.open(inbox)
    try:
        t.write(b"hello")
        data, addr = server.recvfrom(100)
        assert data == b"hello"
        assert addr[1] == t.local_address[1]  # type: ignore[index]
        server.sendto(b"back", addr)
        assert await inbox.get() == b"back"
    finally:
        await t.close()
        server.close()


async def test_udp_busy_port_raises_link_error() -> None:
    holder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    holder.bind(("127.0.0.1", 0))
    port = holder.getsockname()[1]
    try:
        t = open_transport(f"udpin:127.0.0.1:{port}")
        with pytest.raises(LinkError, match=rf"udpin:127.0.0.1:{port}.*in use"):
            await t.open(lambda b: None)
        assert not t.is_open
    finally:
        holder.close()


async def test_udpin_unresolvable_host_raises_link_error() -> None:
    t = UdpInTransport("no-such-host.invalid", 0)
    with pytest.raises(LinkError, match=r"no-such-host\.invalid"):
        await t.open(lambda b: None)


# ------------------------------------------------------------------------ serial


@pytest.fixture
def pty_pair() -> Iterator[tuple[int, str]]:
    """(master fd, slave path) of a raw-mode pseudo-terminal."""
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    path = os.ttyname(slave)
    yield master, path
    os.close(master)
    os.close(slave)


def read_exactly(fd: int, n: int, timeout_s: float = 2.0) -> bytes:
    import select

    out = b""
    while len(out) < n:
        r, _, _ = select.select([fd], [], [], timeout_s)
        assert r, f"timed out after {out!r}"
        out += os.read(fd, n - len(out))
    return out


async def test_serial_round_trip_over_pty(pty_pair: tuple[int, str]) -> None:
    master, path = pty_pair
    t = open_transport(f"serial:{path}:57600")
    assert isinstance(t, SerialTransport) and t.device == path
    inbox = Inbox()
    await t.open(inbox)
    try:
        payload = bytes(range(256))  # raw mode: every byte value survives
        os.write(master, payload)
        got = b""
        while len(got) < len(payload):
            got += await inbox.get()
        assert got == payload
        out = b"\x00\xfdfrom companion\r\n"
        t.write(out)
        assert read_exactly(master, len(out)) == out
        assert t.counters["bytes_in"] == 256 and t.counters["bytes_out"] == len(out)
    finally:
        await t.close()
    await t.close()


async def test_serial_missing_device_raises_link_error(tmp_path: os.PathLike[str]) -> None:
    dev = f"{tmp_path}/ttyNOPE0"
    t = SerialTransport(dev, 115200)
    with pytest.raises(LinkError, match="ttyNOPE0"):
        await t.open(lambda b: None)


# --------------------------------------------------------------------------- URLs


def test_open_transport_parses_forms() -> None:
    t = open_transport("udpin:0.0.0.0:14540")
    assert isinstance(t, UdpInTransport) and (t.host, t.port) == ("0.0.0.0", 14540)
    assert t.description == "udpin:0.0.0.0:14540"
    t = open_transport("udpout:127.0.0.1:14550")
    assert isinstance(t, UdpOutTransport) and t.port == 14550
    t = open_transport("udpin:[::1]:14540")
    assert isinstance(t, UdpInTransport) and t.host == "::1"
    t = open_transport("serial:/dev/serial/by-id/usb-Holybro_Pixhawk6C:0-if00:921600")
    assert isinstance(t, SerialTransport)
    assert t.device == "/dev/serial/by-id/usb-Holybro_Pixhawk6C:0-if00" and t.baud == 921600
    assert not t.is_open  # nothing opened


@pytest.mark.parametrize(
    "url",
    [
        "",
        "udp:127.0.0.1:14540",
        "udpin:127.0.0.1",
        "udpin::14540",
        "udpin:127.0.0.1:port",
        "udpin:127.0.0.1:70000",
        "udpout:127.0.0.1:0",
        "udpin:::1:14540",
        "serial:/dev/ttyUSB0",
        "serial:/dev/ttyUSB0:fast",
        "serial::57600",
        "serial:/dev/ttyUSB0:-9600",
        "tcp:127.0.0.1:5760",
    ],
)
def test_bad_urls_raise_value_error_naming_url(url: str) -> None:
    with pytest.raises(ValueError) as info:
        open_transport(url)
    msg = str(info.value)
    assert repr(url) in msg
    assert "udpin:HOST:PORT" in msg and "serial:DEVICE:BAUD" in msg
