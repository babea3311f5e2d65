"""Fixtures for integration tests: free UDP ports and the SITL as a separate process."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from sitl.lab import children

ROOT = Path(__file__).resolve().parents[2]
PROFILE = ROOT / "vehicle_profiles" / "f450.yaml"


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class SitlProcess:
    """A running ``python -m sitl run`` and where its outputs go."""

    proc: subprocess.Popen[bytes]
    log_path: Path
    stderr_path: Path

    def stop(self, timeout_s: float = 10.0) -> int:
        """SIGTERM, wait, and SIGKILL as a last resort; returns the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=timeout_s)
        return int(self.proc.returncode)

    def stderr(self) -> str:
        return self.stderr_path.read_text(encoding="utf-8", errors="replace")


@pytest.fixture
def udp_port() -> int:
    return free_udp_port()


@pytest.fixture
def start_sitl(tmp_path: Path) -> Iterator[Callable[..., SitlProcess]]:
    """Factory: ``start_sitl(port, "--clock", "lockstep", ...)`` -> :class:`SitlProcess`.

    The SITL sends (udpout) to 127.0.0.1:``port`` where the test's client listens.
    Every process started is terminated at teardown.
    """
    started: list[SitlProcess] = []

    def start(port: int, *args: str, duration_s: float = 60.0) -> SitlProcess:
        n = len(started)
        log_path = tmp_path / f"sitl{n}.npz"
        stderr_path = tmp_path / f"sitl{n}.stderr"
        cmd = [
            sys.executable,
            "-m",
            "sitl",
            "-v",
            "run",
            "--profile",
            str(PROFILE),
            "--mavlink",
            f"udpout:127.0.0.1:{port}",
            "--seed",
            "1",
            "--duration",
            str(duration_s),
            "--log",
            str(log_path),
            *args,
        ]
        env = dict(os.environ, MAVLINK20="1", PYTHONUNBUFFERED="1")
        with stderr_path.open("wb") as err:
            proc = children.start(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=err)
        sp = SitlProcess(proc, log_path, stderr_path)
        started.append(sp)
        return sp

    yield start
    for sp in started:
        sp.stop()
