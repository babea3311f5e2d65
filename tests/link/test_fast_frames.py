"""The per-sample frames packed by the link are byte for byte pymavlink's."""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

import asyncio

from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink2

from companion.link.mavlink import MavlinkLink
from companion.link.transport import MemoryTransport

finite = st.floats(allow_nan=False, allow_infinity=False, width=32)


class _Sink:
    def write(self, data: bytes) -> None:
        pass


def _frames(fn: str, *args: object) -> tuple[bytes, bytes]:
    """(the link's frame, pymavlink's frame) for the same message and sequence number."""
    sent: list[bytes] = []

    async def go() -> None:
        a, b = MemoryTransport.pair()
        await b.open(sent.append)
        link = MavlinkLink(a, heartbeat_hz=0)
        await link.start()
        link.target = (1, 1)
        link.mav.seq = 17
        getattr(link, fn)(*args)
        await asyncio.sleep(0)
        await link.close()

    asyncio.run(go())
    ref = mavlink2.MAVLink(_Sink(), srcSystem=1, srcComponent=191)
    ref.seq = 17
    if fn == "send_actuator_controls":
        t, controls = args[0], list(args[1])  # type: ignore[call-overload]
        msg = ref.set_actuator_control_target_encode(t, 0, 1, 1, controls)
    else:
        t, rates, thrust = args  # type: ignore[misc]
        msg = ref.set_attitude_target_encode(t, 1, 1, 128, [1.0, 0, 0, 0], *rates, thrust)
    return sent[0], msg.pack(ref)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**64 - 1), st.lists(finite, min_size=8, max_size=8))
def test_actuator_controls_frame_is_pymavlinks(t: int, controls: list[float]) -> None:
    ours, theirs = _frames("send_actuator_controls", t, controls)
    assert ours == theirs


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.lists(finite, min_size=3, max_size=3), finite)
def test_body_rates_frame_is_pymavlinks(t: int, rates: list[float], thrust: float) -> None:
    ours, theirs = _frames("send_body_rates", t, rates, thrust)
    assert ours == theirs


def test_zero_payload_tail_is_trimmed_like_pymavlink() -> None:
    ours, theirs = _frames("send_actuator_controls", 0, [0.0] * 8)
    assert ours == theirs


def test_signed_link_signs_the_fast_sends() -> None:
    from companion.link.signing import SigningConfig

    sent: list[bytes] = []

    async def go() -> None:
        a, b = MemoryTransport.pair()
        await b.open(sent.append)
        link = MavlinkLink(a, heartbeat_hz=0, signing=SigningConfig(bytes(range(32))))
        await link.start()
        link.target = (1, 1)
        link.send_actuator_controls(5, [0.1] * 8)
        link.send_body_rates(5, [0.1, 0.2, 0.3], 0.5)
        await asyncio.sleep(0)
        await link.close()

    asyncio.run(go())
    frames = [f for f in sent if f[0] == 0xFD]
    assert len(frames) >= 2
    assert all(f[2] & 0x01 for f in frames[-2:])  # the MAVLink 2 "signed" flag
