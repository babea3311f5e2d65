"""The SITL's own MAVLink 2 signing, on a real UDP socket: what it accepts and what it drops."""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink2

from companion.link.signing import signing_timestamp_now
from companion.profile import load_profile
from sitl.autopilot import Autopilot, AutopilotConfig
from sitl.lab.fly import free_udp_port
from sitl.mavlink_link import enable_signing, parse_endpoint
from sitl.px4_face import Px4Face, px4_streams

ROOT = Path(__file__).resolve().parents[2]
KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
MAX_TIMESTAMP = 2**48 - 1
"""The largest signing timestamp a frame can carry (48 bits)."""


class _Collect:
    """pymavlink's output file: keeps each packed frame."""

    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, buf: bytes) -> None:
        self.frames.append(bytes(buf))


def ground_station(key: bytes, timestamp: int) -> tuple[Any, _Collect]:
    """A pymavlink encoder for 255/190 on link 0, signing with ``key`` from ``timestamp``."""
    out = _Collect()
    mav = mavlink2.MAVLink(out, srcSystem=255, srcComponent=190)
    mav.signing.secret_key = key
    mav.signing.link_id = 0
    mav.signing.sign_outgoing = True
    mav.signing.timestamp = timestamp
    return mav, out


def request_heartbeat(mav: Any, out: _Collect) -> bytes:
    """A signed COMMAND_LONG asking the SITL for a HEARTBEAT (it answers ACCEPTED)."""
    mav.command_long_send(
        1, 1, mavlink2.MAV_CMD_REQUEST_MESSAGE, 0, mavlink2.MAVLINK_MSG_ID_HEARTBEAT,
        0, 0, 0, 0, 0, 0,
    )  # fmt: skip
    return out.frames[-1]


@pytest.fixture
def face() -> Iterator[Px4Face]:
    profile = load_profile(ROOT / "vehicle_profiles" / "f450.yaml")
    endpoint = parse_endpoint(f"udpin:127.0.0.1:{free_udp_port()}")
    f = Px4Face(endpoint, Autopilot(profile, AutopilotConfig()), px4_streams(250.0))
    enable_signing(f.mav, KEY)
    with f:
        yield f


@pytest.fixture
def sender() -> Iterator[socket.socket]:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(2.0)
    yield s
    s.close()


def deliver(face: Px4Face, sock: socket.socket, *frames: bytes) -> None:
    """Send each frame as its own datagram and let the face read them all."""
    before = face.messages_received + face.bad_packets
    for frame in frames:
        sock.sendto(frame, (face.endpoint.host, face.endpoint.port))
    deadline = time.monotonic() + 2.0
    while face.messages_received + face.bad_packets < before + len(frames):
        assert time.monotonic() < deadline, "the SITL did not read what was sent"
        face.wait_readable(0.1)
        face.poll(0.0)


def acks(sock: socket.socket) -> list[Any]:
    """The COMMAND_ACKs waiting on ``sock`` (checked with the shared key)."""
    parser = mavlink2.MAVLink(None)
    parser.signing.secret_key = KEY
    parser.robust_parsing = True
    got = []
    sock.settimeout(0.3)
    while True:
        try:
            data = sock.recv(4096)
        except TimeoutError:
            return got
        got += [m for m in parser.parse_buffer(data) or [] if m.get_type() == "COMMAND_ACK"]


def test_a_forged_far_future_timestamp_does_not_block_the_real_sender(
    face: Px4Face, sender: socket.socket
) -> None:
    # Same stream (link 0, 255/190) as the real ground station, wrong key, and
    # the largest timestamp there is: if it counted, nothing could follow it.
    forger, forged = ground_station(OTHER_KEY, MAX_TIMESTAMP)
    real, genuine = ground_station(KEY, signing_timestamp_now())
    deliver(face, sender, request_heartbeat(forger, forged))
    assert face.bad_packets == 1 and face.messages_received == 0
    deliver(face, sender, request_heartbeat(real, genuine), request_heartbeat(real, genuine))
    assert face.bad_packets == 1
    assert face.messages_received == 2
    got = acks(sender)
    assert [(a.command, a.result) for a in got] == [
        (mavlink2.MAV_CMD_REQUEST_MESSAGE, mavlink2.MAV_RESULT_ACCEPTED)
    ] * 2
    # Our own signing clock did not follow the forged timestamp either.
    assert face.mav.signing.timestamp < MAX_TIMESTAMP - 10**9


def test_replays_and_stale_new_streams_are_still_dropped(
    face: Px4Face, sender: socket.socket
) -> None:
    real, genuine = ground_station(KEY, signing_timestamp_now())
    frame = request_heartbeat(real, genuine)
    deliver(face, sender, frame, frame)  # byte-for-byte replay
    assert (face.messages_received, face.bad_packets) == (1, 1)
    # A validly signed frame older than the stream's last one is a replay too.
    real.signing.timestamp -= 10
    deliver(face, sender, request_heartbeat(real, genuine))
    assert (face.messages_received, face.bad_packets) == (1, 2)
    # A new stream (another link id) more than a minute behind the SITL's clock.
    late, late_out = ground_station(KEY, face.mav.signing.timestamp - 60 * 100_000 - 1000)
    late.signing.link_id = 7
    deliver(face, sender, request_heartbeat(late, late_out))
    assert (face.messages_received, face.bad_packets) == (1, 3)


def test_a_valid_newer_timestamp_moves_the_sitl_clock_forward(
    face: Px4Face, sender: socket.socket
) -> None:
    ahead = face.mav.signing.timestamp + 10**7
    real, genuine = ground_station(KEY, ahead)
    deliver(face, sender, request_heartbeat(real, genuine))
    assert face.messages_received == 1
    assert face.mav.signing.timestamp >= ahead
