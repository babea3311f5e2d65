"""Tasks for the executor's tests: module-level, so Dask workers import them by name."""

from __future__ import annotations


def reciprocal(x: float) -> float:
    """``1 / x``; raises ZeroDivisionError for 0 (a task that fails)."""
    return 1.0 / x
