"""The loop benchmark's harness against its floor server, briefly, over real UDP."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

from companion._loopbench import _free_port, run_harness


def test_harness_times_the_echo_server_and_accounts_for_every_sample() -> None:
    port = _free_port()
    cmd = f"from companion._loopbench import echo_server; echo_server({port})"
    server = subprocess.Popen([sys.executable, "-c", cmd])
    try:
        time.sleep(1.0)  # imports and socket set-up
        assert server.poll() is None
        (stats,) = run_harness([port], rate_hz=200.0, seconds_each=0.5, block_s=0.25, warmup_s=0.2)
    finally:
        server.send_signal(signal.SIGTERM)
        server.wait(timeout=10)
    # 0.5 s in whole 0.25 s blocks at 200 Hz: about 100 slots, each sent or skipped.
    assert 90 <= stats["samples"] + stats["skipped"] <= 102
    assert stats["samples"] == stats["answered"] + stats["missed"]
    assert stats["answered"] > 0
    assert 0.0 < stats["p50_us"] <= stats["p99_us"]
