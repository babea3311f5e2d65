"""The SITL's MAVLink face through a modelled link, on a real UDP socket: what it
sends reaches the socket, and what it reads is handled, when the link delivers it."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v10 import common as mavlink1
from pymavlink.dialects.v20 import common as mavlink2

from companion.profile import load_profile
from sitl.autopilot import Autopilot, AutopilotConfig
from sitl.link_model import LINK_PROFILES, LinkModel, parse_link
from sitl.mavlink_link import frame_msgid, parse_endpoint
from sitl.px4_face import Px4Face, px4_streams
from tests.sitl.udp_client import Client, Collect

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def face(client: Client) -> Iterator[Px4Face]:
    profile = load_profile(ROOT / "vehicle_profiles" / "f450.yaml")
    f = Px4Face(
        parse_endpoint(f"udpout:127.0.0.1:{client.port}"),
        Autopilot(profile, AutopilotConfig()),
        px4_streams(250.0),
    )
    with f:
        yield f


def _imu_step(face: Px4Face, t_s: float) -> bool:
    face.snapshot.t_s = face.snapshot.imu_t_s = t_s
    return face.publish(t_s, imu_sample=True, wall_s=time.monotonic())


def _highres_us(msgs: list[Any]) -> list[int]:
    return [m.time_usec for m in msgs if m.get_type() == "HIGHRES_IMU"]


def test_the_message_id_is_read_from_mavlink_1_and_2_frames() -> None:
    v2, v1 = Collect(), Collect()
    mavlink2.MAVLink(v2).highres_imu_send(1, *[0.0] * 13, 0)
    mavlink2.MAVLink(v2).set_actuator_control_target_send(1, 0, 1, 1, [0.0] * 8)
    mavlink1.MAVLink(v1).heartbeat_send(2, 12, 0, 0, 0)
    mavlink1.MAVLink(v1).rc_channels_send(0, 0, *[0] * 18, 0)
    assert [frame_msgid(f) for f in v2.frames] == [105, 139]
    assert [frame_msgid(f) for f in v1.frames] == [0, 65]
    assert frame_msgid(b"\x00garbage") == -1


def test_the_ideal_link_sends_at_once(face: Px4Face, client: Client) -> None:
    face.set_link(LinkModel(LINK_PROFILES["ideal"], 0))
    assert face.link_model is None
    assert _imu_step(face, 0.0)
    assert _highres_us(client.received()) == [0]


def test_what_is_sent_reaches_the_socket_when_the_link_delivers_it(
    face: Px4Face, client: Client
) -> None:
    face.set_link(LinkModel(parse_link("up_delay_ms=5"), 0))
    assert not _imu_step(face, 0.0)
    assert client.received() == []
    for t in (0.001, 0.002, 0.003, 0.004):
        assert not face.publish(t, imu_sample=False, wall_s=time.monotonic())
    assert client.received() == []
    assert face.publish(0.005, imu_sample=False, wall_s=time.monotonic())
    assert face.samples_delivered == [pytest.approx(0.005)]
    msgs = client.received()
    assert _highres_us(msgs) == [0]
    assert "HEARTBEAT" in [m.get_type() for m in msgs]
    assert face.link_model is not None and face.link_model.counts()["up_sent"] == len(msgs)


def test_only_a_sample_newer_than_any_delivered_is_waited_for(
    face: Px4Face, client: Client
) -> None:
    # Duplicates and reordering: the lockstep clock must not wait for the copies
    # and the late samples, which a client drops without answering.
    face.set_link(LinkModel(parse_link("delay_ms=6,jitter_ms=5,duplicate=0.3,fifo=false"), 4))
    face.streams.set_interval(105, 4000.0)
    new = 0
    for k in range(300):
        t = k * 0.001
        if k % 4 == 0:
            waits = _imu_step(face, t)
        else:
            waits = face.publish(t, imu_sample=False, wall_s=time.monotonic())
        assert waits == bool(face.samples_delivered)
        new += len(face.samples_delivered)
    stamps = _highres_us(client.received(0.2))
    newer = [s for i, s in enumerate(stamps) if all(s > p for p in stamps[:i])]
    assert len(stamps) > len(set(stamps)) > len(newer) + 5  # copies and late samples came
    assert new == len(newer)


def _send_setpoint(client: Client, face: Px4Face) -> None:
    client.mav.set_actuator_control_target_send(0, 0, 1, 1, [0.1, 0.0, 0.0, 0.5] + [0.0] * 4)
    client.send_last(face)


def test_a_setpoint_is_handled_when_the_link_delivers_it(face: Px4Face, client: Client) -> None:
    face.set_link(LinkModel(parse_link("down_delay_ms=5"), 0))
    _send_setpoint(client, face)
    face.poll(0.0, defer_commands=True)
    assert (face.setpoints_arrived, face.setpoints_received) == (1, 0)
    face.poll(0.004)
    assert face.setpoints_received == 0
    face.poll(0.005)
    assert face.setpoints_received == 1
    assert face.autopilot.setpoint_age_s(0.005) == pytest.approx(0.0)


def test_an_answer_counts_as_sent_when_its_sample_arrived(face: Px4Face, client: Client) -> None:
    face.set_link(LinkModel(parse_link("down_delay_ms=5"), 0))
    face.expect_answers([0.0005])  # the sample it answers arrived at 0.5 ms
    _send_setpoint(client, face)
    face.poll(0.004, defer_commands=True)  # read at 4 ms: sent at 0.5 ms all the same
    face.expect_answers(())
    face.poll(0.005)
    assert face.setpoints_received == 0
    face.poll(0.006)
    assert face.setpoints_received == 1
    # The next one, outside a wait, counts as sent when read.
    _send_setpoint(client, face)
    face.poll(0.006)
    face.poll(0.010)
    assert face.setpoints_received == 1
    face.poll(0.011)
    assert face.setpoints_received == 2


def test_a_command_delivered_during_a_wait_takes_effect_at_the_next_step(
    face: Px4Face, client: Client
) -> None:
    face.set_link(LinkModel(parse_link("down_delay_ms=2"), 0))
    handled: list[tuple[str, float]] = []
    handle = face._handle

    def spy(msg: Any, t_s: float) -> None:
        handled.append((msg.get_type(), t_s))
        handle(msg, t_s)

    face._handle = spy  # type: ignore[method-assign]
    client.mav.command_long_send(1, 1, 511, 0, 105, 10000.0, 0, 0, 0, 0, 0)
    client.send_last(face)
    face.poll(0.0, defer_commands=True)
    face.poll(0.002, defer_commands=True)  # due, but the lockstep clock is waiting
    assert handled == []
    face.poll(0.003)
    assert handled == [("COMMAND_LONG", 0.003)]
    assert face.streams.interval_s(105) == pytest.approx(0.01)


def test_a_restarted_link_loses_the_samples_and_setpoints_on_their_way(
    face: Px4Face, client: Client
) -> None:
    face.set_link(LinkModel(parse_link("delay_ms=5"), 0))
    _imu_step(face, 0.0)
    _send_setpoint(client, face)
    face.poll(0.0)
    face.set_link(LinkModel(parse_link("delay_ms=5"), 0), restart=True)
    face.poll(0.005)
    assert face.setpoints_received == 0
    assert not face.publish(0.005, imu_sample=False, wall_s=time.monotonic())
    msgs = client.received()
    assert _highres_us(msgs) == []
    assert "HEARTBEAT" in [m.get_type() for m in msgs]  # the rest arrives as drawn


def test_a_muted_link_loses_what_is_on_its_way(face: Px4Face, client: Client) -> None:
    face.set_link(LinkModel(parse_link("delay_ms=5"), 0))
    _imu_step(face, 0.0)
    face.muted = True
    assert not face.publish(0.005, imu_sample=False, wall_s=time.monotonic())
    assert client.received() == []
