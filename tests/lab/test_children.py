"""A lab process killed with SIGKILL takes its SITL and companion children with it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's"
)

# A parent that starts a long-lived child the way fly_mavlink does, prints its pid
# and waits on it (as fly_mavlink waits on the companion).
PARENT = """
import subprocess, sys
from sitl.lab import children
child = children.start(
    [sys.executable, "-c", "import time; time.sleep(60)"], stdout=subprocess.DEVNULL
)
print(child.pid, flush=True)
child.wait()
"""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A zombie (dead, not yet reaped by init) counts as gone.
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_child_dies_when_its_parent_is_killed() -> None:
    with subprocess.Popen(
        [sys.executable, "-c", PARENT], stdout=subprocess.PIPE, text=True
    ) as parent:
        assert parent.stdout is not None
        child_pid = int(parent.stdout.readline())
        try:
            assert _alive(child_pid)
            parent.send_signal(signal.SIGKILL)
            parent.wait(timeout=10)
            deadline = time.monotonic() + 10.0
            while _alive(child_pid) and time.monotonic() < deadline:
                time.sleep(0.05)
            assert not _alive(child_pid), "the child outlived its SIGKILLed parent"
        finally:
            if _alive(child_pid):
                os.kill(child_pid, signal.SIGKILL)


def test_start_passes_popen_arguments_through(tmp_path: os.PathLike[str]) -> None:
    from sitl.lab import children

    out = os.path.join(tmp_path, "out.txt")
    with open(out, "wb") as f:
        p = children.start([sys.executable, "-c", "print('hello')"], stdout=f)
        assert p.wait(timeout=30) == 0
    with open(out, encoding="utf-8") as f:
        assert f.read() == "hello\n"
