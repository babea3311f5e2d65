"""The fast receive road (``MavlinkLink.add_fast_handler``) gives what pymavlink gives.

Each test feeds the link's ``_on_bytes`` directly (what a transport does with a
datagram) and compares with a link on pymavlink's road for the same bytes.
"""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

import math
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink2

from companion.link.mavlink import MavlinkLink
from companion.link.signing import SigningConfig
from companion.link.transport import MemoryTransport

IMU_FIELDS = ("time_usec", "xgyro", "ygyro", "zgyro")
ATT_FIELDS = ("time_boot_ms", "rollspeed", "pitchspeed", "yawspeed")
f32 = st.floats(width=32)  # NaN and infinities included: the app judges them


class _Sink:
    def write(self, data: bytes) -> None:
        pass


def _mav(sysid: int = 1, compid: int = 1) -> Any:
    return mavlink2.MAVLink(_Sink(), srcSystem=sysid, srcComponent=compid)


def _imu(mav: Any, t: int, gyro: tuple[float, float, float], **kw: float) -> bytes:
    acc = (kw.get("xacc", 0.0), kw.get("yacc", 0.0), kw.get("zacc", 0.0))
    msg = mavlink2.MAVLink_highres_imu_message(t, *acc, *gyro, 0, 0, 0, 0, 0, 0, 0, 0)
    return bytes(msg.pack(mav))


def _heartbeat(mav: Any) -> bytes:
    return bytes(mavlink2.MAVLink_heartbeat_message(2, 12, 129, 6 << 16, 4, 3).pack(mav))


class Probe:
    """A link with the IMU handler registered and everything it delivers recorded."""

    def __init__(self, *, fast: bool = True, signing: SigningConfig | None = None) -> None:
        self.events: list[tuple[str, Any]] = []
        self.raw: list[bytes] = []
        a, _ = MemoryTransport.pair()
        self.link = MavlinkLink(
            a,
            heartbeat_hz=0,
            signing=signing,
            on_message=lambda m: self.events.append((m.get_type(), m)),
            on_raw=lambda t, b, out: self.raw.append(b),
        )
        self.link.target = (1, 1)
        if fast:
            self.link.add_fast_handler(105, IMU_FIELDS, lambda v: self.events.append(("IMU", v)))
            self.link.add_fast_handler(30, ATT_FIELDS, lambda v: self.events.append(("ATT", v)))

    def feed(self, *chunks: bytes) -> Probe:
        for c in chunks:
            self.link._receiver.on_bytes(c)
        return self

    def imu_values(self) -> list[tuple[Any, ...]]:
        return [v for kind, v in self.events if kind == "IMU"]


def _same(a: tuple[Any, ...], b: tuple[Any, ...]) -> bool:
    return all((x == y) or (math.isnan(x) and math.isnan(y)) for x, y in zip(a, b))


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 2**64 - 1), f32, f32, f32, f32)
def test_fast_values_are_pymavlinks(t: int, g0: float, g1: float, g2: float, acc: float) -> None:
    frame = _imu(_mav(), t, (g0, g1, g2), xacc=acc)
    ref = mavlink2.MAVLink(None).parse_buffer(frame)[0]
    got = Probe().feed(frame).imu_values()
    assert len(got) == 1
    assert _same(got[0], (ref.time_usec, ref.xgyro, ref.ygyro, ref.zgyro))


def test_a_payload_with_its_zero_tail_dropped_decodes_as_zeros() -> None:
    frame = _imu(_mav(), 123, (0.0, 0.0, 0.0))
    assert frame[1] < 32  # MAVLink 2 cut the payload short of the gyro fields
    assert Probe().feed(frame).imu_values() == [(123, 0.0, 0.0, 0.0)]


def test_both_roads_agree_on_events_counters_and_raw_frames() -> None:
    mav = _mav()
    frames = [_imu(mav, 1000 * k, (0.1 * k, -0.2, 0.3)) for k in range(1, 4)]
    att = bytes(mavlink2.MAVLink_attitude_message(77, 0, 0, 0, 0.5, 0.25, -1.0).pack(mav))
    hb = _heartbeat(mav)
    # One datagram: IMU, HEARTBEAT, IMU (PX4 packs several messages per datagram),
    # then ATTITUDE and a last IMU alone.
    chunks = [frames[0] + hb + frames[1], att, frames[2]]
    fast = Probe().feed(*chunks)
    slow = Probe(fast=False).feed(*chunks)
    assert [k for k, _ in fast.events] == ["IMU", "HEARTBEAT", "IMU", "ATT", "IMU"]
    assert [k for k, _ in slow.events] == [
        "HIGHRES_IMU", "HEARTBEAT", "HIGHRES_IMU", "ATTITUDE", "HIGHRES_IMU",
    ]  # fmt: skip
    assert fast.imu_values() == [
        (m.time_usec, m.xgyro, m.ygyro, m.zgyro) for k, m in slow.events if k == "HIGHRES_IMU"
    ]
    assert [v for k, v in fast.events if k == "ATT"] == [(77, 0.5, 0.25, -1.0)]
    assert fast.raw == slow.raw == [frames[0], hb, frames[1], att, frames[2]]
    assert fast.link.counters == slow.link.counters


def test_a_bad_crc_is_bad_data_and_not_delivered() -> None:
    frame = bytearray(_imu(_mav(), 5, (0.1, 0.2, 0.3)))
    frame[-1] ^= 0xFF
    p = Probe().feed(bytes(frame))
    assert p.events == []
    assert p.link.counters["bad_data"] == 1 and p.link.counters["accepted"] == 0


def test_another_sender_is_ignored_and_logged() -> None:
    frame = _imu(_mav(sysid=7), 5, (0.1, 0.2, 0.3))
    p = Probe().feed(frame)
    assert p.events == []
    assert p.link.counters["foreign_ignored"] == 1
    assert p.raw == [frame]


def test_before_the_autopilot_is_known_nothing_is_delivered() -> None:
    p = Probe()
    p.link.target = None
    p.feed(_imu(_mav(), 5, (0.1, 0.2, 0.3)))
    assert p.events == [] and p.link.counters["foreign_ignored"] == 1


def test_a_frame_split_across_chunks_arrives_once_by_pymavlink() -> None:
    mav = _mav()
    a, b, c = (_imu(mav, 1000 * k, (0.1 * k, 0.2, 0.3)) for k in (1, 2, 3))
    p = Probe().feed(a[:20], a[20:] + b[:5], b[5:], c)
    assert [v[0] for v in p.imu_values()] == [1000, 2000, 3000]
    assert p.raw == [a, b, c]
    assert p.link.counters["accepted"] == 3


def test_mavlink1_goes_to_pymavlink_and_still_reaches_the_handler() -> None:
    mav = _mav()
    msg = mavlink2.MAVLink_highres_imu_message(42, 0, 0, 0, 1.0, 2.0, 3.0, 0, 0, 0, 0, 0, 0, 0, 0)
    frame = bytes(msg.pack(mav, force_mavlink1=True))
    assert frame[0] == 0xFE
    assert Probe().feed(frame).imu_values() == [(42, 1.0, 2.0, 3.0)]


def test_a_signed_link_judges_signatures_and_delivers_to_the_handler() -> None:
    key = bytes(range(32))
    mav = _mav()
    mav.signing.secret_key = key
    mav.signing.sign_outgoing = True
    mav.signing.link_id = 1
    mav.signing.timestamp = 1_000_000
    signed = _imu(mav, 1000, (0.1, 0.2, 0.3))
    unsigned = _imu(_mav(), 2000, (0.1, 0.2, 0.3))
    p = Probe(signing=SigningConfig(key))
    p.link.mav.signing.timestamp = 1_000_000
    p.feed(signed, unsigned)
    assert [v[0] for v in p.imu_values()] == [1000]
    assert p.link.counters["unsigned_rejected"] == 1


def test_handler_exceptions_are_counted_like_on_message_ones() -> None:
    p = Probe()

    def boom(v: tuple[Any, ...]) -> None:
        raise RuntimeError("boom")

    p.link.add_fast_handler(105, IMU_FIELDS, boom)
    mav = _mav()
    p.feed(_imu(mav, 1, (0, 0, 0)), _imu(mav, 2, (0, 0, 0)))
    assert p.link.counters["callback_errors"] == 2
    assert len(p.raw) == 2  # still recorded


@pytest.mark.parametrize(
    ("msg_id", "fields", "why"),
    [
        (99999, ("x",), "not in the common dialect"),
        (105, ("time_usec", "nope"), "no field"),
        (105, ("xgyro", "time_usec"), "wire order"),
        (105, (), "at least one"),
        (139, ("controls",), "scalar"),
    ],
)
def test_bad_registrations_are_refused(msg_id: int, fields: tuple[str, ...], why: str) -> None:
    with pytest.raises(ValueError, match=why):
        Probe(fast=False).link.add_fast_handler(msg_id, fields, lambda v: None)


def test_a_single_field_handler_gets_a_one_tuple() -> None:
    p = Probe(fast=False)
    got: list[tuple[Any, ...]] = []
    p.link.add_fast_handler(105, ("zgyro",), got.append)
    p.feed(_imu(_mav(), 1, (0.0, 0.0, 0.5)))
    assert got == [(0.5,)]
