"""The receive path against garbage, huge datagrams and spoofed frames.

What a fuzz campaign against the running companion found: garbage in one
datagram ate the start of the next, huge datagrams held the loop, and a
heartbeat claiming the autopilot's identity from another address was taken
for the autopilot's. UDP cases run over real sockets on 127.0.0.1; unit
cases feed the link's receiver (``link._receiver.on_bytes``) directly, as a
transport does, on a transport that is never opened.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import os
import random
import socket
import time
import tty
from collections.abc import AsyncIterator, Callable, Iterator
from typing import Any

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from companion.link.mavlink import MavlinkLink, mavlink2
from companion.link.transport import (
    MemoryTransport,
    SerialTransport,
    Transport,
    UdpInTransport,
    UdpOutTransport,
)

PX4_OFFBOARD = 6 << 16  # PX4 custom_mode: main mode OFFBOARD
ARMED = mavlink2.MAV_MODE_FLAG_SAFETY_ARMED | mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
IMU_FIELDS = ("time_usec", "xgyro", "ygyro", "zgyro")


def _enc(sysid: int = 1, compid: int = 1) -> Any:
    return mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=compid)


def _hb(enc: Any, custom_mode: int = 0, base_mode: int = 0) -> bytes:
    msg = enc.heartbeat_encode(
        mavlink2.MAV_TYPE_QUADROTOR,
        mavlink2.MAV_AUTOPILOT_PX4,
        base_mode,
        custom_mode,
        mavlink2.MAV_STATE_STANDBY,
    )
    return bytes(msg.pack(enc))


def _imu(enc: Any, time_usec: int) -> bytes:
    msg = mavlink2.MAVLink_highres_imu_message(
        time_usec, 0, 0, -9.8, 0.1, 0.2, 0.3, 0, 0, 0, 0, 0, 0, 0, 63
    )
    return bytes(msg.pack(enc))


class Probe:
    """A link on a transport that is never opened; chunks are fed by hand."""

    def __init__(self, transport: Transport, *, fast: bool = False) -> None:
        self.heartbeats: list[Any] = []
        self.imu: list[int] = []
        self.link = MavlinkLink(transport, heartbeat_hz=0, on_message=self._on_message)
        if fast:
            self.link.add_fast_handler(105, IMU_FIELDS, lambda v: self.imu.append(v[0]))

    def _on_message(self, msg: Any) -> None:
        if msg.get_type() == "HEARTBEAT":
            self.heartbeats.append(msg)
        elif msg.get_type() == "HIGHRES_IMU":
            self.imu.append(msg.time_usec)

    def feed(self, *chunks: bytes) -> Probe:
        for chunk in chunks:
            self.link._receiver.on_bytes(chunk)
        return self

    def modes(self) -> list[int]:
        return [hb.custom_mode for hb in self.heartbeats]


def _count_parser_calls(link: MavlinkLink) -> list[int]:
    """Count every call into the link's pymavlink parser (internal calls included:
    pymavlink calls ``self.parse_char`` and ``self.decode``, found on the instance)."""
    calls = [0]
    parser = link._receiver._parser
    for name in ("parse_buffer", "parse_char", "decode"):
        real = getattr(parser, name)

        def counted(*args: Any, _real: Callable[..., Any] = real) -> Any:
            calls[0] += 1
            return _real(*args)

        setattr(parser, name, counted)
    return calls


async def _until(cond: Callable[[], bool], timeout_s: float = 2.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, "timed out"
        await asyncio.sleep(0.002)


class UdpRig:
    """A link on ``udpin:127.0.0.1:<ephemeral>`` and sockets to talk to it from."""

    def __init__(self, **link_kw: Any) -> None:
        self.transport = UdpInTransport("127.0.0.1", 0)
        self.heartbeats: list[Any] = []
        self.imu: list[int] = []
        self.link = MavlinkLink(
            self.transport, heartbeat_hz=0, on_message=self.heartbeats.append, **link_kw
        )
        self.link.add_fast_handler(105, IMU_FIELDS, lambda v: self.imu.append(v[0]))
        self._sockets: list[socket.socket] = []

    def peer_socket(self) -> socket.socket:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        s.settimeout(0.3)
        self._sockets.append(s)
        return s

    def send(self, s: socket.socket, data: bytes) -> None:
        assert self.transport.local_address is not None
        s.sendto(data, self.transport.local_address)

    def close_sockets(self) -> None:
        for s in self._sockets:
            s.close()


@contextlib.asynccontextmanager
async def udp_rig(**link_kw: Any) -> AsyncIterator[UdpRig]:
    """A started :class:`UdpRig` (only HEARTBEATs reach ``on_message`` in these tests)."""
    rig = UdpRig(**link_kw)
    await rig.link.start()
    try:
        yield rig
    finally:
        rig.close_sockets()
        await rig.link.close()


# ------------------------------------------------------------- transport kinds


def test_transports_say_whether_they_carry_datagrams() -> None:
    assert UdpInTransport("127.0.0.1", 0).datagrams
    assert UdpOutTransport("127.0.0.1", 14550).datagrams
    assert not SerialTransport("/dev/ttyNOPE0", 57600).datagrams
    assert not MemoryTransport().datagrams  # a byte stream unless asked
    a, b = MemoryTransport.pair(datagrams=True)
    assert a.datagrams and b.datagrams
    # Transports without addresses never see another sender.
    for t in (SerialTransport("/dev/ttyNOPE0", 57600), MemoryTransport()):
        assert t.rx_from_peer and t.rx_address is None


# ---------------------------------------- 7. garbage does not cross datagrams


async def test_udp_truncated_frame_does_not_eat_the_next_datagram() -> None:
    async with udp_rig() as rig:
        ap = rig.peer_socket()
        hb = _hb(_enc(), custom_mode=1)
        rig.send(ap, _hb(_enc(), custom_mode=0xBAD)[:10])  # cut short on the way
        rig.send(ap, hb)
        got = await rig.link.wait_heartbeat(1.0)
        assert got.custom_mode == 1
        assert rig.link.counters["truncated_dropped"] == 1


async def test_udp_random_datagrams_do_not_cost_heartbeats() -> None:
    rng = random.Random(7)
    async with udp_rig() as rig:
        ap, noise = rig.peer_socket(), rig.peer_socket()
        enc = _enc()
        rig.send(ap, _hb(enc, custom_mode=0))
        await rig.link.wait_heartbeat(1.0)
        for k in range(1, 21):
            rig.send(noise, rng.randbytes(rng.randint(1, 300)))
            rig.send(ap, _hb(enc, custom_mode=k))
        await _until(lambda: len(rig.heartbeats) == 21)
        assert [hb.custom_mode for hb in rig.heartbeats] == list(range(21))


@pytest.mark.parametrize("fast", [False, True])
def test_every_cut_of_a_frame_leaves_the_next_datagram_intact(fast: bool) -> None:
    """Cut a frame at each byte: the next datagram decodes, and no frame is made
    of the two (100 cut frames/s once produced a "heartbeat" with a nonsense mode)."""
    enc = _enc()
    p = Probe(UdpInTransport("127.0.0.1", 0), fast=fast).feed(_hb(enc, custom_mode=0))
    liar = _hb(enc, custom_mode=0xDEADBEEF, base_mode=ARMED)
    imu_cut = _imu(enc, 999)
    cuts = range(1, len(imu_cut))
    for k in cuts:
        p.feed(liar[: min(k, len(liar) - 1)], _hb(enc, custom_mode=k))
        p.feed(imu_cut[:k], _imu(enc, k))
    assert p.modes() == [0, *cuts]
    assert p.imu == list(cuts)
    assert p.link.counters["truncated_dropped"] >= 2 * len(cuts)


def test_a_datagram_runs_on_after_a_cut_frame_inside_it() -> None:
    enc = _enc()
    p = Probe(UdpInTransport("127.0.0.1", 0)).feed(_hb(enc, custom_mode=0))
    # A router packed a frame cut short and a whole one: the whole one still decodes.
    p.feed(_hb(enc, custom_mode=0xBAD)[:15] + _hb(enc, custom_mode=2))
    assert p.modes() == [0, 2]


# ------------------------------------- 7. a byte stream resynchronises on garbage

GARBAGE = {
    "noise": b"\x00\x01\x02 line noise",
    "start byte, long length": b"\x13\xfd\x40\x00",
    "start byte, unknown id": b"\xfd\x05\x00\x00\x00\x07\x01\x01\xaa\xbb\xcc",
    "mavlink1 start byte": b"\x55\xfe\x30",
    "bad crc": bytes(bytearray(_hb(_enc(), custom_mode=0xBAD)[:-1]) + b"\x00"),
    "cut frame": _hb(_enc(), custom_mode=0xBAD)[:15],
    "bad flags": b"\xfd\x09\x80" + bytes(9),
}


# Each start byte of a run claims a frame that swallows the rest of the run.
RUNS = {"run of 0xfe": b"\xfe" * 100, "run of 0xfd": b"\xfd" * 100}


@pytest.mark.parametrize("garbage", [*GARBAGE.values(), *RUNS.values()], ids=[*GARBAGE, *RUNS])
def test_a_stream_delivers_the_frame_behind_garbage_however_it_is_split(garbage: bytes) -> None:
    stream = garbage + _hb(_enc(), custom_mode=1)
    for split in range(len(stream) + 1):
        p = Probe(SerialTransport("/dev/ttyNOPE0", 57600))
        p.feed(stream[:split], stream[split:])
        assert p.modes() == [1], f"split at {split}"
        assert p.link.counters["bad_data"] >= 1


# Garbage with fewer start bytes than the per-chunk budget of checks (128).
few_starts = st.binary(max_size=400).filter(lambda b: b.count(0xFD) + b.count(0xFE) < 48)


@settings(max_examples=300, deadline=None)
@given(few_starts, st.lists(st.integers(0, 1000), max_size=4))
def test_no_garbage_costs_a_stream_the_frames_behind_it(garbage: bytes, cuts: list[int]) -> None:
    enc = _enc()
    stream = garbage + b"".join(_hb(enc, custom_mode=k) for k in range(1, 11))
    edges = sorted({0, len(stream), *(c % (len(stream) + 1) for c in cuts)})
    p = Probe(SerialTransport("/dev/ttyNOPE0", 57600))
    p.feed(*(stream[a:b] for a, b in itertools.pairwise(edges)))
    assert p.modes() == list(range(1, 11))
    assert len(p.link._receiver._pending) <= 280  # at most one frame waits for its rest


@settings(max_examples=300, deadline=None)
@given(few_starts)
# A MAVLink 1 header of an id outside the dialect whose length ends exactly at the
# datagram's end: it used to take the whole datagram, and the ten heartbeats in it.
@example(garbage=b"\xfe\xda\x00\x00\x00\x96" + bytes(10))
def test_no_garbage_costs_a_datagram_the_frames_behind_it(garbage: bytes) -> None:
    enc = _enc()
    p = Probe(UdpInTransport("127.0.0.1", 0))
    p.feed(garbage + b"".join(_hb(enc, custom_mode=k) for k in range(1, 11)))
    assert p.modes() == list(range(1, 11))


@pytest.fixture
def pty_pair() -> Iterator[tuple[int, str]]:
    """(master fd, slave path) of a raw-mode pseudo-terminal."""
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    yield master, os.ttyname(slave)
    os.close(master)
    os.close(slave)


async def test_serial_resynchronises_after_line_noise(pty_pair: tuple[int, str]) -> None:
    master, path = pty_pair
    got: list[int] = []
    link = MavlinkLink(
        SerialTransport(path, 57600),
        heartbeat_hz=0,
        on_message=lambda m: got.append(m.custom_mode),
    )
    enc = _enc()
    async with link:
        os.write(master, b"".join(GARBAGE.values()))
        os.write(master, b"".join(_hb(enc, custom_mode=k) for k in range(1, 16)))
        await _until(lambda: len(got) == 15)
    assert got == list(range(1, 16))


async def test_a_memory_pair_can_play_a_udp_link() -> None:
    ours, theirs = MemoryTransport.pair(datagrams=True)
    got: list[int] = []
    link = MavlinkLink(ours, heartbeat_hz=0, on_message=lambda m: got.append(m.custom_mode))
    await theirs.open(lambda chunk: None)
    enc = _enc()
    async with link:
        theirs.write(_hb(enc, custom_mode=0xBAD)[:12])  # each write is a datagram
        theirs.write(_hb(enc, custom_mode=1))
        await _until(lambda: got == [1])
    assert link.counters["truncated_dropped"] == 1


# ----------------------------------------------- 8. the work on one datagram is bounded


async def test_udp_huge_datagram_is_dropped_unread_and_the_next_decodes() -> None:
    async with udp_rig() as rig:
        ap = rig.peer_socket()
        calls = _count_parser_calls(rig.link)
        rig.send(ap, random.Random(8).randbytes(60_000))
        rig.send(ap, _hb(_enc(), custom_mode=1))
        got = await rig.link.wait_heartbeat(1.0)
        assert got.custom_mode == 1
        assert rig.link.counters["oversize_dropped"] == 1
        assert calls[0] <= 1  # the heartbeat's decode at most; the 60 kB: none


# A frame of an id outside the dialect (no CRC to check) followed by a start byte,
# its payload all MAVLink 1 start bytes: each of those must be looked at.
UNKNOWN_FULL_OF_STARTS = bytes([0xFD, 0xFF, 0, 0, 0, 1, 1, 0xAA, 0xBB, 0xCC]) + b"\xfe" * 257


@pytest.mark.parametrize(
    "pattern",
    [
        # HEARTBEAT headers with no payload and a wrong CRC, back to back.
        b"\xfd\x00\x00\x00\x00\x01\x01\x00\x00\x00\x00\x00",
        b"\xfd",  # bad incompatibility flags at every byte
        b"\xfe\x00",  # MAVLink 1 starts that never complete
        UNKNOWN_FULL_OF_STARTS,
    ],
    ids=["bad-crc frames", "all 0xfd", "mavlink1 starts", "unknown id full of starts"],
)
def test_crafted_garbage_costs_a_bounded_number_of_checks(pattern: bytes) -> None:
    """Each start byte examined in vain is one check; a datagram gets at most 128,
    and CRCs are checked before pymavlink is called (counted, not timed)."""
    enc = _enc()
    p = Probe(UdpInTransport("127.0.0.1", 0)).feed(_hb(enc, custom_mode=0))
    calls = _count_parser_calls(p.link)
    datagram = (pattern * 4096)[:4000]
    p.feed(datagram)
    assert calls[0] <= 128
    c = p.link.counters
    assert c["bad_data"] + c["truncated_dropped"] <= 128 + 1
    assert c["resync_abandoned"] == 1
    p.feed(_hb(enc, custom_mode=1))
    assert p.modes() == [0, 1]


def test_garbage_without_start_bytes_is_skipped_in_one_step() -> None:
    p = Probe(UdpInTransport("127.0.0.1", 0))
    calls = _count_parser_calls(p.link)
    p.feed(bytes(range(0xFD)) * 16)  # 4048 bytes, no 0xFD/0xFE
    assert calls[0] == 0
    assert p.link.counters["garbage_bytes"] == 0xFD * 16
    assert p.link.counters["bad_data"] == 1


# ------------------------------------------- 9. spoofed frames from another address


async def test_udpin_ignores_the_autopilots_identity_from_another_address() -> None:
    async with udp_rig() as rig:
        ap, spoofer = rig.peer_socket(), rig.peer_socket()
        enc, fake = _enc(), _enc()
        rig.send(ap, _hb(enc, custom_mode=0))
        await rig.link.wait_heartbeat(1.0)
        rig.send(spoofer, _hb(fake, custom_mode=PX4_OFFBOARD, base_mode=ARMED))
        rig.send(spoofer, _imu(fake, 666))  # the fast road must not take it either
        rig.send(ap, _imu(enc, 1))
        await _until(lambda: rig.imu == [1])
        await asyncio.sleep(0.05)
        assert [hb.custom_mode for hb in rig.heartbeats] == [0]
        assert rig.link.last_heartbeat is not None
        assert rig.link.last_heartbeat.custom_mode == 0
        assert rig.imu == [1]
        assert rig.link.counters["spoofed_ignored"] == 2
        assert rig.transport.peer == ap.getsockname()
        rig.link.send_actuator_controls(1, [0.1] * 8)
        assert ap.recv(1000)[0] == 0xFD  # our commands still go to the autopilot


async def test_a_spoof_flood_raises_one_anomaly_per_second() -> None:
    events: list[tuple[str, str]] = []
    async with udp_rig(on_anomaly=lambda kind, detail: events.append((kind, detail))) as rig:
        ap, spoofer = rig.peer_socket(), rig.peer_socket()
        rig.send(ap, _hb(_enc()))
        await rig.link.wait_heartbeat(1.0)
        fake = _enc()
        for _ in range(50):
            rig.send(spoofer, _hb(fake, custom_mode=PX4_OFFBOARD, base_mode=ARMED))
        await _until(lambda: rig.link.counters["spoofed_ignored"] == 50)
        assert [kind for kind, _ in events] == ["spoofed"]
        assert str(spoofer.getsockname()[1]) in events[0][1]
        await asyncio.sleep(1.05)
        rig.send(spoofer, _hb(fake, custom_mode=PX4_OFFBOARD, base_mode=ARMED))
        await _until(lambda: len(events) == 2)
        assert events[1][0] == "spoofed"
        assert len(rig.heartbeats) == 1


async def test_the_autopilot_may_move_only_after_its_address_fell_silent() -> None:
    events: list[tuple[str, str]] = []
    rig_kw: dict[str, Any] = {
        "peer_silence_s": 0.5,
        "on_anomaly": lambda kind, detail: events.append((kind, detail)),
    }
    async with udp_rig(**rig_kw) as rig:
        old, new = rig.peer_socket(), rig.peer_socket()
        enc = _enc()
        rig.send(old, _hb(enc, custom_mode=1))
        await rig.link.wait_heartbeat(1.0)
        rig.send(new, _hb(enc, custom_mode=2))  # old is still talking: not a move
        await _until(lambda: rig.link.counters["spoofed_ignored"] == 1)
        assert rig.transport.peer == old.getsockname()
        await asyncio.sleep(0.6)  # old falls silent (an autopilot restarting)
        rig.send(new, _hb(enc, custom_mode=3))
        await _until(lambda: len(rig.heartbeats) == 2)
        assert [hb.custom_mode for hb in rig.heartbeats] == [1, 3]
        assert rig.transport.peer == new.getsockname()
        assert [kind for kind, _ in events] == ["spoofed", "peer_changed"]
        rig.link.send_actuator_controls(1, [0.1] * 8)
        assert new.recv(1000)[0] == 0xFD
        rig.send(old, _hb(enc, custom_mode=4))  # now the old address is the stranger
        await _until(lambda: rig.link.counters["spoofed_ignored"] == 2)
        assert len(rig.heartbeats) == 2


async def test_an_anomaly_callback_that_raises_is_counted() -> None:
    def boom(kind: str, detail: str) -> None:
        raise RuntimeError("boom")

    async with udp_rig(on_anomaly=boom) as rig:
        ap, spoofer = rig.peer_socket(), rig.peer_socket()
        rig.send(ap, _hb(_enc()))
        await rig.link.wait_heartbeat(1.0)
        rig.send(spoofer, _hb(_enc(), custom_mode=PX4_OFFBOARD, base_mode=ARMED))
        rig.send(ap, _imu(_enc(), 5))
        await _until(lambda: rig.imu == [5])
        assert rig.link.counters["callback_errors"] == 1


# ------------------------------------------------------------ MAVLink 1 in between


def _v1(msg: Any) -> bytes:
    """``msg`` as a MAVLink 1 frame from 1/1."""
    return bytes(msg.pack(_enc(), force_mavlink1=True))


def _hb_v1() -> bytes:
    return _v1(
        mavlink2.MAVLink_heartbeat_message(
            mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_PX4, 0, 0, 0, 3
        )
    )


def _imu_v1(time_usec: int) -> bytes:
    return _v1(
        mavlink2.MAVLink_highres_imu_message(
            time_usec, 0, 0, -9.8, 0.1, 0.2, 0.3, 0, 0, 0, 0, 0, 0, 0, 63
        )
    )


def test_mavlink1_frames_under_a_mavlink2_autopilots_ids_are_ignored() -> None:
    v2 = _enc()
    probe = Probe(UdpOutTransport("127.0.0.1", 9), fast=True)
    probe.feed(_hb(v2))  # the autopilot, speaking MAVLink 2
    probe.feed(_imu_v1(1_000), _imu(v2, 2_000), _imu_v1(3_000))
    assert probe.imu == [2_000]
    assert probe.link.counters["v1_ignored"] == 2


def test_an_autopilot_speaking_mavlink1_is_still_heard() -> None:
    probe = Probe(UdpOutTransport("127.0.0.1", 9), fast=True)
    probe.feed(_hb_v1(), _imu_v1(1_000))
    assert probe.imu == [1_000]
    assert probe.link.counters["v1_ignored"] == 0
