"""The SITL's MAVLink face on a real UDP socket: garbage costs it no good frame."""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink2

from companion.profile import load_profile
from sitl.autopilot import Autopilot, AutopilotConfig
from sitl.lab.fly import free_udp_port
from sitl.mavlink_link import parse_endpoint
from sitl.px4_face import Px4Face, px4_streams

ROOT = Path(__file__).resolve().parents[2]


class _Collect:
    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, buf: bytes) -> None:
        self.frames.append(bytes(buf))


@pytest.fixture
def face() -> Iterator[Px4Face]:
    profile = load_profile(ROOT / "vehicle_profiles" / "f450.yaml")
    endpoint = parse_endpoint(f"udpin:127.0.0.1:{free_udp_port()}")
    f = Px4Face(endpoint, Autopilot(profile, AutopilotConfig()), px4_streams(250.0))
    with f:
        yield f


def heartbeat() -> bytes:
    out = _Collect()
    mavlink2.MAVLink(out, srcSystem=255, srcComponent=190).heartbeat_send(
        mavlink2.MAV_TYPE_GCS, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, 0
    )
    return out.frames[-1]


def received_after(face: Px4Face, datagrams: list[bytes]) -> int:
    """Send each datagram, let the face read them all; the heartbeats it took."""
    seen: list[str] = []
    handle = face._handle

    def spy(msg: Any, t_s: float) -> None:
        seen.append(msg.get_type())
        handle(msg, t_s)

    face._handle = spy  # type: ignore[method-assign]
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for d in datagrams:  # read as they come: the socket's buffer holds only so much
        sock.sendto(d, (face.endpoint.host, face.endpoint.port))
        face.wait_readable(0.05)
        face.poll(0.0)
    sock.close()
    deadline = time.monotonic() + 0.3
    while time.monotonic() < deadline:
        face.wait_readable(0.05)
        face.poll(0.0)
    return seen.count("HEARTBEAT")


def test_a_truncated_frame_does_not_eat_the_next_datagram(face: Px4Face) -> None:
    hb = heartbeat()
    got = received_after(face, [hb[: len(hb) // 2], hb] * 20)
    assert got == 20


def test_random_and_huge_datagrams_cost_no_heartbeat(face: Px4Face) -> None:
    rng = np.random.default_rng(7)
    hb = heartbeat()
    datagrams = []
    for i in range(40):
        size = 60_000 if i % 4 == 0 else int(rng.integers(1, 300))
        datagrams += [rng.integers(0, 256, size, dtype=np.uint8).tobytes(), hb]
    assert received_after(face, datagrams) == 40
