"""The SITL face tests' ground station (tests/sitl/udp_client.py), one per test."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.sitl.udp_client import Client


@pytest.fixture
def client() -> Iterator[Client]:
    c = Client()
    yield c
    c.close()
