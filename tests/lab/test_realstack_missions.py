"""The real-stack mission flight's pieces that need no stack: the waypoints as the
stacks take them, the figures, and the mission protocol against a fake autopilot."""

from __future__ import annotations

import itertools
import math
import threading
import time
from typing import Any

import numpy as np
import pytest

from sitl.lab.fly import free_udp_port
from sitl.lab.realstack.gcs import GroundStation
from sitl.lab.realstack.missions import (
    ARRIVED_M,
    EARTH_RADIUS_M,
    STACK_MISSIONS,
    MissionFlight,
    completed_at,
    load_square,
    mission_figures,
    offset_lat_lon,
)


def test_the_square_is_a_10_m_square_with_one_climb() -> None:
    m = load_square()
    corners = [(w.north_m, w.east_m) for w in m.waypoints]
    assert corners == [(10, 0), (10, 10), (0, 10), (0, 0)]
    assert [w.up_m for w in m.waypoints] == [0, 0, 3, 3]


def test_offsets_become_latitude_and_longitude_on_the_tangent_plane() -> None:
    lat, lon = offset_lat_lon(60.0, 10.0, 10.0, 10.0)
    assert lat - 60.0 == pytest.approx(math.degrees(10.0 / EARTH_RADIUS_M))
    # A degree of longitude at 60 deg is half of one at the equator.
    assert lon - 10.0 == pytest.approx(2.0 * math.degrees(10.0 / EARTH_RADIUS_M))


def test_each_stack_gets_the_waypoints_its_way() -> None:
    m = load_square()
    origin = (47.0, 8.0, 15.0)
    px4 = STACK_MISSIONS["px4"].items(origin, m)
    ardu = STACK_MISSIONS["ardupilot"].items(origin, m)
    assert len(px4) == 4 and len(ardu) == 5  # ArduPilot's item 0 is home
    assert (ardu[0].lat_deg, ardu[0].lon_deg) == (47.0, 8.0)
    assert ardu[1:] == [
        type(it)(it.command, it.lat_deg, it.lon_deg, it.alt_m, (0.0, 0.0, 0.0, 0.0)) for it in px4
    ]
    assert [it.alt_m for it in px4] == [15.0, 15.0, 18.0, 18.0]
    assert all(it.frame == 6 and it.command == 16 for it in px4)
    assert all(math.isnan(it.params[3]) for it in px4)


_PLAN = np.array([(0, 0, -15), (10, 0, -15), (10, 10, -15), (0, 10, -18), (0, 0, -18)], float)


def _flown(offset_m: float = 0.0, *, stop_short: bool = False) -> MissionFlight:
    """The plan flown at 2 m/s, ``offset_m`` to the left of each leg, 10 Hz."""
    rows: list[tuple[float, ...]] = []
    t = 1.0
    legs = list(itertools.pairwise(_PLAN))
    for i, (a, b) in enumerate(legs):
        d = b - a
        n = int(np.linalg.norm(d[:2]) / 0.2)
        side = np.array([-d[1], d[0], 0.0]) / np.linalg.norm(d[:2])
        last = i == len(legs) - 1
        for k in range(n + 1):
            if stop_short and last and k > n // 2:
                break
            p = a + d * k / n + (offset_m * side if 0 < k < n else 0.0)
            v = d / np.linalg.norm(d[:2]) * 2.0
            rows.append((t, *p, *v))
            t += 0.1
    att = [(r[0], 0.0, math.radians(10.0)) for r in rows]
    return MissionFlight("test", 0.5, 1.0, _PLAN, True, att, rows)


def test_a_flight_along_the_legs_has_no_path_error() -> None:
    f = mission_figures(_flown())
    assert f["completed"]
    assert f["path_rms_m"] == pytest.approx(0.0, abs=1e-9)
    assert f["alt_max_m"] == pytest.approx(0.0, abs=1e-9)
    assert f["tilt_max_deg"] == pytest.approx(10.0)
    assert f["speed_mean_m_s"] == pytest.approx(2.0)
    assert f["engage_after_s"] == 0.5
    # Arrived ARRIVED_M short of the end, at 2 m/s; the clock from the start (0.5 s).
    end_s = _flown().position[-1][0]
    assert f["time_to_complete_s"] == pytest.approx(end_s - ARRIVED_M / 2.0 - 0.5, abs=0.15)
    assert f["end_offset_m"] == pytest.approx(1.0, abs=0.15)  # closing at 2 m/s in its last 1 s


def test_the_path_error_is_the_distance_from_above_to_the_closest_leg() -> None:
    f = mission_figures(_flown(0.4))
    assert f["path_max_m"] == pytest.approx(0.4)
    assert 0.35 < f["path_rms_m"] < 0.4  # the waypoints themselves are on the legs


def test_a_flight_that_stops_short_is_not_complete() -> None:
    f = mission_figures(_flown(stop_short=True))
    assert not f["completed"] and math.isnan(f["time_to_complete_s"])
    rows = _flown().position
    t = np.array([r[0] for r in rows])
    p = np.array([r[1:4] for r in rows])
    # A flat square ends where it starts: at the start it counts only once the
    # others are passed.
    flat, p[:, 2] = _PLAN.copy(), -15.0
    flat[:, 2] = -15.0
    done = completed_at(t, p, flat)
    assert done == pytest.approx(t[-1] - ARRIVED_M / 2.0, abs=0.15)


class _FakeAutopilot:
    """Just enough of an autopilot for the mission protocol and GLOBAL_POSITION_INT."""

    def __init__(self, port: int) -> None:
        from pymavlink import mavutil

        self.conn: Any = mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{port}", source_system=1, source_component=1
        )
        self.items: dict[int, Any] = {}
        self._count = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        next_hb = 0.0
        while not self._stop.is_set():
            if time.monotonic() >= next_hb:  # (sent once a ground station was heard)
                next_hb = time.monotonic() + 0.2
                self.conn.mav.heartbeat_send(2, 12, 0, 0, 4)
            msg = self.conn.recv_match(blocking=True, timeout=0.02)
            if msg is None:
                continue
            mtype = msg.get_type()
            if mtype == "MISSION_COUNT":
                self._count, self.items = msg.count, {}
                self.conn.mav.mission_request_int_send(255, 190, 0, 0)
            elif mtype == "MISSION_ITEM_INT":
                self.items[msg.seq] = msg
                if msg.seq + 1 < self._count:
                    self.conn.mav.mission_request_send(255, 190, msg.seq + 1, 0)
                else:
                    self.conn.mav.mission_ack_send(255, 190, 0, 0)
            elif mtype == "COMMAND_LONG" and msg.command == 512 and msg.param1 == 33:
                self.conn.mav.global_position_int_send(0, 470000000, 80000000, 0, 15000, 0, 0, 0, 0)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.conn.close()


def test_the_mission_protocol_uploads_every_item_as_asked() -> None:
    port = free_udp_port()
    fake = _FakeAutopilot(port)
    g = GroundStation(f"udpout:127.0.0.1:{port}", stack="px4")
    try:
        g.wait_heartbeat(10.0)
        lat, lon, up = g.global_position()
        assert (lat, lon, up) == pytest.approx((47.0, 8.0, 15.0))
        items = STACK_MISSIONS["ardupilot"].items((lat, lon, up), load_square())
        # Asked with MISSION_REQUEST_INT and with MISSION_REQUEST: answered alike.
        assert g.upload_mission(items) == 0
        got = [fake.items[i] for i in range(len(items))]
        assert [m.seq for m in got] == list(range(5))
        assert [(m.x, m.y, m.z) for m in got] == [
            (round(it.lat_deg * 1e7), round(it.lon_deg * 1e7), pytest.approx(it.alt_m))
            for it in items
        ]
        assert all(m.frame == 6 and m.command == 16 for m in got)
    finally:
        g.close()
        fake.close()
