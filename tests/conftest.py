"""The tiers: each test gets one marker from where it lives (``pytest -m TIER``).

- ``unit``: pure and fast (control laws, link parsing, records, the plant's parts,
  the command line's input checks);
- ``app``: the companion app on the in-memory transport;
- ``lab``: in-process flights, campaigns, the envelope, tuning, the scripts;
- ``integration``: separate processes over real UDP (the SITL, mosquitto, MAVSDK);
  also any test elsewhere marked so;
- ``regression``: pinned flight figures (tests/regression, and tests marked so).

Across the tiers, the ``long`` checks (marked so: the wheel built and installed,
the envelope's corners with a PID tuned for each, the paper reproduction, the
fuzzer's real-time run, the heaviest lab and app flights, and the other
vehicles' cases of flights the default run flies on the F450) take minutes or half a
minute or more of a core each, or would take the default run past ten minutes on two
cores. The default run leaves them out (they are *deselected*, and the header says
so); ``--long`` runs them alone. CI runs both (``.ci/run``).

The ``realstack`` tier (``tests/realstack``) flies the real PX4 and ArduCopter
SITL in real time, one stack at a time, about 25 minutes on 2 cores: the default run
leaves it out too; ``--realstack`` runs it alone (``.ci/run`` does).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
_BY_FOLDER = {
    "control": "unit",
    "link": "unit",
    "records": "unit",
    "sitl": "unit",
    "app": "app",
    "lab": "lab",
    "integration": "integration",
    "regression": "regression",
    "realstack": "realstack",
}


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--long",
        action="store_true",
        help="run the long checks alone (marked long); the default run leaves them out",
    )
    parser.addoption(
        "--realstack",
        action="store_true",
        help="run the real-stack tier alone (tests/realstack: the real PX4 and ArduCopter "
        "SITL); the default run leaves it out",
    )


def pytest_report_header(config: pytest.Config) -> str:
    if config.getoption("--realstack"):
        return "real-stack tier: only this (--realstack)"
    if config.getoption("--long"):
        return "long checks: only these (--long)"
    return "long checks and the real-stack tier: deselected (--long, --realstack run them)"


def _in_realstack(item: pytest.Item) -> bool:
    parts = Path(str(item.path)).resolve().relative_to(HERE).parts
    return len(parts) > 1 and parts[0] == "realstack"


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    long = bool(config.getoption("--long"))
    realstack = bool(config.getoption("--realstack"))
    kept, dropped = [], []
    for item in items:
        if realstack:
            wanted = _in_realstack(item)
        else:
            wanted = not _in_realstack(item) and (
                (item.get_closest_marker("long") is not None) == long
            )
        (kept if wanted else dropped).append(item)
    if dropped:
        config.hook.pytest_deselected(items=dropped)
        items[:] = kept
    for item in items:
        parts = Path(str(item.path)).resolve().relative_to(HERE).parts
        tier = _BY_FOLDER.get(parts[0], "unit") if len(parts) > 1 else "unit"
        if item.get_closest_marker("integration") is not None:
            tier = "integration"
        elif item.get_closest_marker("regression") is not None:
            tier = "regression"
        item.add_marker(tier)


@pytest.fixture(autouse=True, scope="session")
def _own_fly_check_record(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The controller fly-check record (companion.fly_check) in a folder of the test
    session's own, for the commands run in process and as subprocesses: no test reads
    or writes the user's, and none passes a file because of it."""
    from companion.fly_check import STATE_DIR_ENV

    before = os.environ.get(STATE_DIR_ENV)
    os.environ[STATE_DIR_ENV] = str(tmp_path_factory.mktemp("mfc-state"))
    yield
    if before is None:
        del os.environ[STATE_DIR_ENV]
    else:
        os.environ[STATE_DIR_ENV] = before
