"""The real-stack tier: the real PX4 v1.16 and ArduCopter 4.5.6 SITL, flown in real time.

``scripts/test --realstack`` runs this tier alone, in one process (one stack at a
time: both in real time on two cores would load each other). The stacks' launchers
are found at ``../shared/stacks`` or where ``MFC_PX4_SITL`` and
``MFC_ARDUCOPTER_SITL`` point (sitl/lab/realstack/launch.py); without them the
tier stops at once with one line saying so and a non-zero exit: it is not
counted as passed.

Each module boots its stack once and flies its tests on it in order; a test
that needs the vehicle in the air puts it there (the stack's own take-off). The
figures each test measured (the closing notes quote them) are printed at the
end of the run and written to ``$MFC_REALSTACK_FIGURES`` (default
``runs/realstack/figures.jsonl``).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from sitl.lab.realstack.flights import Session
from sitl.lab.realstack.launch import StackMissingError, find_launcher

ROOT = Path(__file__).resolve().parents[2]
_FIGURES: list[dict[str, Any]] = []


def _figures_path() -> Path:
    return Path(
        os.environ.get("MFC_REALSTACK_FIGURES", ROOT / "runs" / "realstack" / "figures.jsonl")
    )


@pytest.fixture(scope="session")
def figures() -> Iterator[list[dict[str, Any]]]:
    """Append ``{"test": ..., **what it measured}``; printed and written at the end."""
    yield _FIGURES


def pytest_terminal_summary(terminalreporter: Any) -> None:
    if not _FIGURES:
        return
    path = _figures_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", encoding="utf-8") as f:
        for row in _FIGURES:
            f.write(json.dumps(row) + "\n")
    terminalreporter.section("real-stack figures")
    for row in _FIGURES:
        terminalreporter.write_line(json.dumps(row))
    terminalreporter.write_line(f"(written to {path})")


RERUNS = 1
"""A failed real-stack test is flown again this many times (pytest-rerunfailures).

The stacks fly in real time on a shared 2-core machine, and one flight can stand
apart: in the tier at 44aa4a8, 3 of 49 tests failed (the preflight's IMU rate at
PX4's start, a roll 1.08x on the stiff loop where both laws send the pilot's
roll, an engagement sag 0.25 m against 0.2), each a flight the same code flew
within its bound in other runs. A law or a failsafe that is wrong fails both
tries; each try's figures are recorded, and pytest reports a test flown again
as ``rerun``."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    here = Path(__file__).parent
    for item in items:
        if here in Path(item.path).parents:
            item.add_marker(pytest.mark.flaky(reruns=RERUNS))


def boot(stack: str, workdir: Path) -> Session:
    """A stack booted and its ground station connected; the tier stops (exit 3)
    with one line if the stack is not installed."""
    try:
        find_launcher(stack)
    except StackMissingError as exc:
        pytest.exit(f"real-stack tier not run: {exc}", returncode=3)
    session = Session(stack, workdir)
    try:
        session.connect(90.0)
    except BaseException:
        session.close()
        raise
    return session
