"""The ``start`` fixture of the app tier (see tests/app/flight.py)."""

from __future__ import annotations

from collections.abc import AsyncIterator

import pytest

from tests.app.flight import Start, flights


@pytest.fixture
async def start() -> AsyncIterator[Start]:
    """Factory: ``await start(autopilot=..., engage=..., **run_options)`` -> Flight."""
    async for factory in flights():
        yield factory
