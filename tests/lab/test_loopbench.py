"""The loop benchmark's harness against its floor server, briefly, over real UDP."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

from sitl.lab.fly import free_udp_port
from sitl.lab.loopbench import run_harness


def wait_until_bound(server: subprocess.Popen[bytes], port: int, timeout_s: float = 60.0) -> None:
    """Until the server's UDP socket is bound to 127.0.0.1:``port``.

    Read from the kernel's socket table, which cannot race the server's own bind
    the way a probing bind could; a fixed sleep was too short on a loaded machine
    (the server's imports took over a second, and every sample went unanswered).
    """
    want = f"0100007F:{port:04X}"
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert server.poll() is None, "the server exited before binding its socket"
        table = Path("/proc/net/udp").read_text().splitlines()[1:]
        if any(line.split()[1] == want for line in table):
            return
        time.sleep(0.05)
    raise AssertionError(f"nothing bound 127.0.0.1:{port} within {timeout_s} s")


def test_harness_times_the_echo_server_and_accounts_for_every_sample() -> None:
    port = free_udp_port()
    cmd = f"from sitl.lab.loopbench import echo_server; echo_server({port})"
    server = subprocess.Popen([sys.executable, "-c", cmd])
    try:
        wait_until_bound(server, port)
        (stats,) = run_harness([port], rate_hz=200.0, seconds_each=0.5, block_s=0.25, warmup_s=0.2)
    finally:
        server.send_signal(signal.SIGTERM)
        server.wait(timeout=10)
    # 0.5 s in whole 0.25 s blocks at 200 Hz: about 100 slots, each sent or skipped.
    assert 90 <= stats["samples"] + stats["skipped"] <= 102
    assert stats["samples"] == stats["answered"] + stats["missed"]
    assert stats["answered"] > 0
    assert 0.0 < stats["p50_us"] <= stats["p99_us"]


_PICKY_SERVER = """
import asyncio, os
os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as m2

class Sink:
    def write(self, b): pass

async def main(port):
    loop = asyncio.get_running_loop()
    mav = m2.MAVLink(Sink(), srcSystem=1, srcComponent=191)

    class P(asyncio.DatagramProtocol):
        def connection_made(self, t): self.t = t
        def datagram_received(self, data, addr):
            for m in mav.parse_buffer(data) or []:
                if m.get_msgId() != m2.MAVLINK_MSG_ID_HIGHRES_IMU:
                    continue
                slot = m.time_usec // 5000  # 200 Hz
                out = m2.MAVLink_set_actuator_control_target_message(
                    m.time_usec, 0, 1, 1, [0.0] * 8).pack(mav)
                if slot % 5 == 0:
                    continue  # dropped: never answered
                if slot % 5 == 1:
                    loop.call_later(0.05, self.t.sendto, out, addr)  # late
                else:
                    self.t.sendto(out, addr)

    await loop.create_datagram_endpoint(P, local_addr=("127.0.0.1", port))
    await asyncio.sleep(30)

asyncio.run(main(PORT))
"""


def test_harness_tells_a_dropped_sample_from_a_late_one() -> None:
    port = free_udp_port()
    server = subprocess.Popen([sys.executable, "-c", _PICKY_SERVER.replace("PORT", str(port))])
    try:
        wait_until_bound(server, port)
        (stats,) = run_harness([port], rate_hz=200.0, seconds_each=1.0, block_s=0.5, warmup_s=0.2)
    finally:
        server.kill()
        server.wait(timeout=10)
    n = stats["samples"]
    assert n >= 150
    # One slot in five is dropped, one in five answered 50 ms late (and timed).
    assert abs(stats["missed"] - n / 5) <= 0.05 * n
    assert abs(stats["late"] - n / 5) <= 0.05 * n
    # Late samples 25 ms apart (under 20 ms plus a period) make one episode.
    # (A slot the harness skipped while descheduled can split one into two.)
    assert 1 <= stats["late_episodes"] <= 1 + stats["skipped"]
    assert stats["samples"] == stats["answered"] + stats["missed"]
    assert stats["p99_us"] > 20_000.0
