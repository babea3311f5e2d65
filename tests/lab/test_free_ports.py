"""The UDP ports the lab hands its processes: free, distinct, and never ones the
kernel may give another socket in the meantime (the cause of a CI failure: a
companion could not bind the port chosen for it, ``address already in use``)."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from sitl.lab import fly
from sitl.lab.fly import free_udp_ports


def test_ports_are_distinct_bindable_and_below_the_ephemeral_range() -> None:
    lo, _hi = fly._ephemeral_ports()
    ports = free_udp_ports(8)
    assert len(set(ports)) == 8
    assert all(1024 <= p < lo for p in ports)
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in ports]
    try:
        for s, p in zip(socks, ports, strict=True):
            s.bind(("127.0.0.1", p))
    finally:
        for s in socks:
            s.close()


def test_a_range_that_leaves_no_room_below_draws_above_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "range").write_text("1024\t50000\n")
    monkeypatch.setattr(fly, "EPHEMERAL_RANGE_FILE", tmp_path / "range")
    assert all(p > 50000 for p in free_udp_ports(4))


def test_an_unreadable_range_falls_back_to_linux_default(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(fly, "EPHEMERAL_RANGE_FILE", tmp_path / "missing")
    assert fly._ephemeral_ports() == (32768, 60999)
    assert all(20000 <= p < 32768 for p in free_udp_ports(4))
