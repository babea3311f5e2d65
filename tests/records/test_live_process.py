"""The live view's own process (companion/live.py, companion/live_publisher.py)."""

from __future__ import annotations

import os
import signal
import socket
import time

import pytest

from companion.live import NICE, LiveView
from companion.records import columns


def _rows(view: LiveView, t0: float, n: int) -> None:
    cols = columns(4)
    t = cols.index("t_s")
    for k in range(n):
        row = [0.5] * len(cols)
        row[t] = t0 + k * 0.005
        view.append(row)


def _published_all(view: LiveView, timeout_s: float = 20.0) -> None:
    view.flush()
    end = time.monotonic() + timeout_s
    while view.pending:
        assert time.monotonic() < end, "timed out"
        time.sleep(0.01)


def test_the_server_runs_in_another_process_and_ends_with_the_view() -> None:
    view = LiveView(columns(4), port=0, flush_interval_s=1.0)
    view.start()
    try:
        child = view._child
        assert child is not None and child.pid not in (None, os.getpid())
        # Nicer than the companion: the scheduler gives a contested core to the loop.
        mine = os.getpriority(os.PRIO_PROCESS, 0)
        assert os.getpriority(os.PRIO_PROCESS, child.pid) == min(mine + NICE, 19)
        with socket.create_connection(("127.0.0.1", view.port), timeout=5.0):
            pass  # it listens where it says
        _rows(view, 1.0, 100)
        _published_all(view)
        c = view.counters
        assert c["dropped_rows"] == 0 and c["publish_errors"] == 0
        assert c["published"] == 0  # nobody subscribed: nothing formatted or sent
    finally:
        view.close()
    assert child.pid is None  # ended


def test_a_live_view_process_that_dies_costs_the_caller_nothing_and_is_counted() -> None:
    view = LiveView(columns(4), port=0, flush_interval_s=0.0)
    view.start()
    try:
        _rows(view, 1.0, 20)
        _published_all(view)
        assert view._child is not None and view._child.pid is not None
        os.kill(view._child.pid, signal.SIGKILL)
        _rows(view, 2.0, 50)  # never raises
        view.event({"kind": "x", "detail": "after"})
        _published_all(view)
    finally:
        view.close()
    c = view.counters
    assert c["publish_errors"] == 1, c
    assert c["dropped_rows"] == 50 and c["dropped_events"] == 1, c


def test_a_port_in_use_is_refused_naming_it() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        view = LiveView(columns(4), port=port)
        with pytest.raises(OSError, match=f"cannot serve the live view on 127.0.0.1:{port}"):
            view.start()
    view.close()  # harmless


def test_a_live_view_process_that_hangs_does_not_hold_the_close() -> None:
    """Stopped (alive, answering nothing), the live view's process is killed when
    the view closes, rather than keeping the companion from ending."""
    view = LiveView(columns(4), port=0, flush_interval_s=0.0)
    view.start()
    child = view._child
    assert child is not None and child.pid is not None
    os.kill(child.pid, signal.SIGSTOP)
    _rows(view, 1.0, 20)  # the publishing thread now waits on it
    start = time.monotonic()
    view.close(timeout_s=0.5)
    assert time.monotonic() - start < 5.0
    assert child.pid is None
