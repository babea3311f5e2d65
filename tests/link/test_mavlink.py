"""MavlinkLink over the in-memory transport against a pymavlink "autopilot"."""

from __future__ import annotations

import asyncio
import socket
import time
from collections.abc import AsyncIterator
from typing import Any

import pytest

from companion.errors import LinkError
from companion.link.mavlink import MavlinkLink, mavlink2
from companion.link.transport import MemoryTransport, open_transport

from .peer import FakeAutopilot, settle

ACCEPTED = mavlink2.MAV_RESULT_ACCEPTED


class Setup:
    def __init__(self, link: MavlinkLink, ap: FakeAutopilot, ap_end: MemoryTransport) -> None:
        self.link = link
        self.ap = ap
        self.ap_end = ap_end
        self.messages: list[Any] = []


@pytest.fixture
async def pair() -> AsyncIterator[Setup]:
    ours, theirs = MemoryTransport.pair()
    messages: list[Any] = []
    link = MavlinkLink(ours, heartbeat_hz=0, on_message=messages.append)
    ap = await FakeAutopilot(theirs).open()
    s = Setup(link, ap, theirs)
    s.messages = messages
    await link.start()
    yield s
    await link.close()


async def test_learns_target_from_autopilot_heartbeat(pair: Setup) -> None:
    link, ap = pair.link, pair.ap
    assert link.target is None
    t0 = time.monotonic()
    ap.heartbeat()
    hb = await link.wait_heartbeat(1.0)
    assert link.target == (1, 1)
    assert hb.autopilot == mavlink2.MAV_AUTOPILOT_PX4
    assert link.last_heartbeat is hb
    assert link.last_heartbeat_monotonic_s is not None
    assert link.last_heartbeat_monotonic_s >= t0
    assert [m.get_type() for m in pair.messages] == ["HEARTBEAT"]
    assert link.counters["accepted"] == 1 and link.counters["received"] == 1


async def test_gcs_and_onboard_heartbeats_do_not_become_target(pair: Setup) -> None:
    link = pair.link
    gcs = FakeAutopilot(pair.ap_end, sysid=255, compid=190)
    gcs.heartbeat(mavlink2.MAV_TYPE_GCS, mavlink2.MAV_AUTOPILOT_INVALID)
    other = FakeAutopilot(pair.ap_end, sysid=1, compid=191)
    other.heartbeat(mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_AUTOPILOT_PX4)
    await settle()
    assert link.target is None
    assert link.counters["foreign_ignored"] == 2
    assert pair.messages == []
    pair.ap.heartbeat()
    await link.wait_heartbeat(1.0)
    assert link.target == (1, 1)


async def test_foreign_messages_are_counted_and_ignored(pair: Setup) -> None:
    link, ap = pair.link, pair.ap
    ap.heartbeat()
    await link.wait_heartbeat(1.0)
    intruder = FakeAutopilot(pair.ap_end, sysid=2, compid=1)
    intruder.heartbeat()
    intruder.mav.highres_imu_send(1, 0, 0, -9.8, 0.5, 0, 0, 0, 0, 0, 0, 0, 0, 0, 63)
    sibling = FakeAutopilot(pair.ap_end, sysid=1, compid=154)  # same system, other component
    sibling.mav.highres_imu_send(2, 0, 0, -9.8, 0.6, 0, 0, 0, 0, 0, 0, 0, 0, 0, 63)
    ap.mav.highres_imu_send(3, 0, 0, -9.8, 0.1, 0.2, 0.3, 0, 0, 0, 0, 0, 0, 0, 63)
    await settle()
    assert link.counters["foreign_ignored"] == 3
    imus = [m for m in pair.messages if m.get_type() == "HIGHRES_IMU"]
    assert len(imus) == 1 and imus[0].time_usec == 3
    assert imus[0].xgyro == pytest.approx(0.1)
    assert link.target == (1, 1)


async def test_pinned_target_ignores_other_autopilots() -> None:
    ours, theirs = MemoryTransport.pair()
    got: list[Any] = []
    link = MavlinkLink(ours, target_system=7, heartbeat_hz=0, on_message=got.append)
    await link.start()
    ap1 = await FakeAutopilot(theirs, sysid=1).open()
    ap7 = FakeAutopilot(theirs, sysid=7, compid=1)
    ap1.heartbeat()
    await settle()
    assert link.target is None
    ap7.heartbeat()
    await link.wait_heartbeat(1.0)
    assert link.target == (7, 1)
    assert link.counters["foreign_ignored"] == 1
    await link.close()


async def test_our_heartbeat_goes_out_at_the_configured_rate() -> None:
    ours, theirs = MemoryTransport.pair()
    ap = await FakeAutopilot(theirs).open()
    link = MavlinkLink(ours, heartbeat_hz=20.0)
    t0 = time.monotonic()
    async with link:
        first = (await ap.wait_for("HEARTBEAT", 1, timeout_s=1.0))[0]
        t_first = time.monotonic() - t0
        await asyncio.sleep(0.5)
    hbs = ap.of_type("HEARTBEAT")
    assert t_first < 0.05  # the first goes out at start, not one period later
    assert first.type == mavlink2.MAV_TYPE_ONBOARD_CONTROLLER
    assert first.autopilot == mavlink2.MAV_AUTOPILOT_INVALID
    assert (first.get_srcSystem(), first.get_srcComponent()) == (1, 191)
    # 0.5 s at 20 Hz after the first: ~10 more (scheduler jitter allowed, a stall is not).
    assert 8 <= len(hbs) - 1 <= 12
    assert link.counters["sent"] == len(hbs)


async def test_command_long_returns_ack_result(pair: Setup) -> None:
    link, ap = pair.link, pair.ap
    ap.ack_policy = lambda m: mavlink2.MAV_RESULT_DENIED if m.command == 400 else ACCEPTED
    ap.heartbeat()
    await link.wait_heartbeat(1.0)
    result = await link.command_long(mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, 105, 4000)
    assert result == ACCEPTED
    cmd = ap.of_type("COMMAND_LONG")[0]
    assert (cmd.target_system, cmd.target_component) == (1, 1)
    assert (cmd.param1, cmd.param2, cmd.param3, cmd.param7) == (105, 4000, 0, 0)
    assert cmd.confirmation == 0
    assert await link.command_long(400, 1) == mavlink2.MAV_RESULT_DENIED


async def test_command_long_retries_when_first_ack_is_lost(pair: Setup) -> None:
    link, ap = pair.link, pair.ap
    seen: list[int] = []

    def drop_first(msg: Any) -> int | None:
        seen.append(msg.confirmation)
        return None if len(seen) == 1 else ACCEPTED

    ap.ack_policy = drop_first
    ap.heartbeat()
    await link.wait_heartbeat(1.0)
    t0 = time.monotonic()
    assert await link.command_long(176, 1, 6 << 16, timeout_s=0.1, retries=3) == ACCEPTED
    assert seen == [0, 1]  # confirmation counts the retransmission: sent twice, no more
    assert time.monotonic() - t0 > 0.09  # the resend waited for the ACK's timeout


async def test_command_long_raises_after_all_retries(pair: Setup) -> None:
    link, ap = pair.link, pair.ap
    ap.ack_policy = lambda m: None
    ap.heartbeat()
    await link.wait_heartbeat(1.0)
    with pytest.raises(LinkError, match=r"no COMMAND_ACK for command 400.*3 attempts"):
        await link.command_long(400, 1, timeout_s=0.05, retries=2)
    assert [m.confirmation for m in ap.of_type("COMMAND_LONG")] == [0, 1, 2]


async def test_command_long_ignores_acks_for_someone_else(pair: Setup) -> None:
    link, ap = pair.link, pair.ap

    def ack_elsewhere_then_us(msg: Any) -> int | None:
        ap.mav.command_ack_send(msg.command, mavlink2.MAV_RESULT_FAILED, 0, 0, 255, 190)
        return ACCEPTED

    ap.ack_policy = ack_elsewhere_then_us
    ap.heartbeat()
    await link.wait_heartbeat(1.0)
    assert await link.command_long(400, 1) == ACCEPTED


async def test_command_long_waits_through_in_progress(pair: Setup) -> None:
    link, ap = pair.link, pair.ap

    def progress_then_done(msg: Any) -> int | None:
        ap.mav.command_ack_send(msg.command, mavlink2.MAV_RESULT_IN_PROGRESS, 50, 0, 1, 191)
        asyncio.get_running_loop().call_later(
            0.08, ap.mav.command_ack_send, msg.command, ACCEPTED, 0, 0, 1, 191
        )
        return None

    ap.ack_policy = progress_then_done
    ap.heartbeat()
    await link.wait_heartbeat(1.0)
    assert await link.command_long(241, timeout_s=0.05, retries=0) == ACCEPTED
    assert len(ap.of_type("COMMAND_LONG")) == 1  # no resend while in progress


async def test_command_long_needs_a_target(pair: Setup) -> None:
    with pytest.raises(LinkError, match="autopilot not known"):
        await pair.link.command_long(400, 1)


async def test_wait_heartbeat_timeout_raises(pair: Setup) -> None:
    t0 = time.monotonic()
    with pytest.raises(LinkError, match=r"no HEARTBEAT .* within 0\.1 s"):
        await pair.link.wait_heartbeat(0.1)
    assert time.monotonic() - t0 > 0.09  # it waited its timeout before it gave up


async def test_request_message_interval(pair: Setup) -> None:
    pair.ap.heartbeat()
    await pair.link.wait_heartbeat(1.0)
    assert await pair.link.request_message_interval(105, 4000) == ACCEPTED
    cmd = pair.ap.of_type("COMMAND_LONG")[0]
    assert cmd.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL
    assert (cmd.param1, cmd.param2) == (105, 4000)


async def test_send_encodes_and_on_raw_sees_both_directions() -> None:
    ours, theirs = MemoryTransport.pair()
    raw: list[tuple[float, bytes, bool]] = []
    link = MavlinkLink(ours, heartbeat_hz=0, on_raw=lambda t, b, out: raw.append((t, b, out)))
    ap = await FakeAutopilot(theirs).open()
    async with link:
        ap.heartbeat()
        await link.wait_heartbeat(1.0)
        msg = link.mav.set_actuator_control_target_encode(
            123, 0, 1, 1, [0.1, -0.2, 0.3, 0.5, 0, 0, 0, 0]
        )
        link.send(msg)
        got = (await ap.wait_for("SET_ACTUATOR_CONTROL_TARGET"))[0]
    assert got.controls[:4] == pytest.approx([0.1, -0.2, 0.3, 0.5])
    assert (got.get_srcSystem(), got.get_srcComponent()) == (1, 191)
    incoming = [b for _, b, out in raw if not out]
    outgoing = [b for _, b, out in raw if out]
    assert len(incoming) == 1 and incoming[0][0] == 0xFD  # the heartbeat, as on the wire
    assert outgoing == [bytes(msg.get_msgbuf())]
    assert all(abs(t - time.time()) < 5 for t, _, _ in raw)
    assert ap.raw_received == outgoing


async def test_garbage_is_counted_as_bad_data(pair: Setup) -> None:
    pair.ap_end.write(b"\x00\x01\x02 definitely not mavlink")
    frame = bytearray(pair.ap.mav.heartbeat_encode(2, 12, 0, 0, 3).pack(pair.ap.mav))
    frame[-3] ^= 0xFF  # break the CRC
    pair.ap_end.write(bytes(frame))
    await settle()
    assert pair.link.counters["bad_data"] == 2
    assert pair.link.counters["accepted"] == 0


async def test_on_message_exception_is_counted_not_fatal() -> None:
    ours, theirs = MemoryTransport.pair()
    calls: list[str] = []

    def flaky(msg: Any) -> None:
        calls.append(msg.get_type())
        if len(calls) == 1:
            raise RuntimeError("boom")

    link = MavlinkLink(ours, heartbeat_hz=0, on_message=flaky)
    ap = await FakeAutopilot(theirs).open()
    async with link:
        ap.heartbeat()
        ap.heartbeat()
        await settle()
    assert calls == ["HEARTBEAT", "HEARTBEAT"]
    assert link.counters["callback_errors"] == 1


async def test_close_fails_pending_command(pair: Setup) -> None:
    pair.ap.ack_policy = lambda m: None
    pair.ap.heartbeat()
    await pair.link.wait_heartbeat(1.0)
    task = asyncio.create_task(pair.link.command_long(400, 1, timeout_s=5.0))
    await asyncio.sleep(0.02)
    await pair.link.close()
    with pytest.raises(LinkError, match="closed"):
        await task


async def test_constructor_touches_nothing() -> None:
    ours, _ = MemoryTransport.pair()
    MavlinkLink(ours)
    assert not ours.is_open
    with pytest.raises(ValueError):
        MavlinkLink(ours, heartbeat_hz=-1)
    with pytest.raises(ValueError):
        MavlinkLink(ours, target_component=1)


async def test_udpin_answers_the_autopilot_not_whoever_sent_last() -> None:
    """Real UDP: junk and a ground station's heartbeat do not redirect our commands."""
    t = open_transport("udpin:127.0.0.1:0")
    link = MavlinkLink(t, heartbeat_hz=0)
    await link.start()
    try:
        assert t.local_address is not None
        port = t.local_address[1]
        ap, gcs = (socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2))
        for s in (ap, gcs):
            s.bind(("127.0.0.1", 0))
            s.settimeout(0.3)
        enc_ap = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
        enc_gcs = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
        hb = enc_ap.heartbeat_encode(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_PX4,
                                     0, 0, 0)  # fmt: skip
        ap.sendto(hb.pack(enc_ap), ("127.0.0.1", port))
        await link.wait_heartbeat(2.0)
        assert link.target == (1, 1)
        gcs.sendto(b"junk, not MAVLink", ("127.0.0.1", port))
        gcs_hb = enc_gcs.heartbeat_encode(mavlink2.MAV_TYPE_GCS, mavlink2.MAV_AUTOPILOT_INVALID,
                                          0, 0, 0)  # fmt: skip
        gcs.sendto(gcs_hb.pack(enc_gcs), ("127.0.0.1", port))
        await asyncio.sleep(0.1)
        link.send_actuator_controls(1, [0.1] * 8)
        got = ap.recv(1000)
        assert got and got[0] == 0xFD  # our MAVLink 2 frame went to the autopilot
        with pytest.raises(TimeoutError):
            gcs.recv(1000)
        assert t.counters["peer_changes"] == 0
        ap.close()
        gcs.close()
    finally:
        await link.close()
