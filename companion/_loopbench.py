"""Loop latency benchmark: a harness plays the autopilot over real UDP.

The harness sends HIGHRES_IMU at a fixed rate (plus heartbeats showing
OFFBOARD and armed, RC_CHANNELS, and an ACCEPTED answer to every command)
and times each IMU datagram until the command carrying its ``time_usec``
comes back. The same harness measures a *floor*: a bare asyncio server that
parses with pymavlink and answers every HIGHRES_IMU with a fixed command.
The ratio of the two is what the companion's own work costs, on this
machine, in this run.
"""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

import asyncio
import select
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

__all__ = ["echo_server", "run_harness", "run_loop_bench"]

ROOT = Path(__file__).resolve().parents[1]


class _Sink:
    def write(self, b: bytes) -> None:  # pymavlink wants a file-like object
        pass


def _percentile(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, int(q * len(s)))]


def run_harness(
    ports: list[int],
    *,
    rate_hz: float,
    seconds_each: float,
    block_s: float = 2.0,
    warmup_s: float = 3.0,
) -> list[dict[str, Any]]:
    """Drive each server on 127.0.0.1:``ports[i]`` in turn, ``block_s`` at a time.

    Every target gets ``seconds_each`` of IMU at ``rate_hz`` after a warm-up in
    which all of them are served; alternating in short blocks means they share
    the machine's background load. Returns latency statistics (us) per target.
    """
    mav = mavlink2.MAVLink(_Sink(), srcSystem=1, srcComponent=1)
    socks = []
    for _ in ports:
        sk = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sk.setblocking(False)
        socks.append(sk)
    parser = mavlink2.MAVLink(_Sink(), srcSystem=255, srcComponent=0)
    period = 1.0 / rate_hz
    n = len(ports)
    sent: list[dict[int, int]] = [{} for _ in ports]
    lat: list[list[float]] = [[] for _ in ports]
    measured = [0] * n
    pc = time.perf_counter_ns

    def send(i: int, msg: Any) -> None:
        socks[i].sendto(msg.pack(mav), ("127.0.0.1", ports[i]))

    def housekeeping(i: int) -> None:
        send(i, mavlink2.MAVLink_heartbeat_message(2, 12, 128 | 1, 6 << 16, 4, 3))
        ch = [1500, 1500, 1500, 1500, 1000] + [65535] * 13
        send(i, mavlink2.MAVLink_rc_channels_message(0, 5, *ch, 254))

    def drain(i: int, measuring: bool) -> None:
        sk = socks[i]
        while True:
            try:
                data = sk.recv(4096)
            except BlockingIOError:
                return
            t_rx = pc()
            for m in parser.parse_buffer(data) or []:
                mid = m.get_msgId()
                if mid == mavlink2.MAVLINK_MSG_ID_SET_ACTUATOR_CONTROL_TARGET:
                    t_tx = sent[i].pop(m.time_usec, None)
                    if t_tx is not None and measuring:
                        lat[i].append((t_rx - t_tx) / 1000.0)
                elif mid == mavlink2.MAVLINK_MSG_ID_COMMAND_LONG:
                    send(i, mavlink2.MAVLink_command_ack_message(
                        m.command, 0, 0, 0, m.get_srcSystem(), m.get_srcComponent()))  # fmt: skip

    t_start = time.perf_counter()
    k = 0
    next_hk = t_start
    total = warmup_s * n + seconds_each * n
    while True:
        now = time.perf_counter()
        elapsed = now - t_start
        if elapsed >= total:
            break
        if elapsed < warmup_s * n:
            target = int(elapsed / warmup_s) % n  # warm every target up in turn
            measuring = False
        else:
            target = int((elapsed - warmup_s * n) / block_s) % n
            measuring = True
        if now >= next_hk:
            for i in range(n):
                housekeeping(i)
            next_hk += 0.02
        due = t_start + k * period
        if now >= due:
            k += 1
            time_usec = k * round(period * 1e6)
            msg = mavlink2.MAVLink_highres_imu_message(
                time_usec, 0, 0, -9.81, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0b111111
            )
            sent[target][time_usec] = pc()
            send(target, msg)
            if measuring:
                measured[target] += 1
            cutoff = time_usec - 20_000  # not answered within 20 ms: a miss
            for i in range(n):
                for key in [t for t in sent[i] if t < cutoff]:
                    del sent[i][key]
        for i in range(n):
            drain(i, measuring)
        wait = min(t_start + k * period, next_hk) - time.perf_counter()
        if wait > 0.0:
            r, _, _ = select.select(socks, [], [], wait)
            for sk in r:
                drain(socks.index(sk), measuring)
    deadline = time.perf_counter() + 0.05
    while time.perf_counter() < deadline:
        for i in range(n):
            drain(i, True)
    out = []
    for i in range(n):
        socks[i].close()
        xs = lat[i]
        stats: dict[str, Any] = {
            "samples": measured[i],
            "answered": len(xs),
            "missed": max(0, measured[i] - len(xs)),
        }
        if xs:
            stats["p50_us"] = statistics.median(xs)
            stats["p99_us"] = _percentile(xs, 0.99)
        out.append(stats)
    return out


async def _echo(port: int) -> None:
    loop = asyncio.get_running_loop()
    mav = mavlink2.MAVLink(_Sink(), srcSystem=1, srcComponent=191)
    reply_to: list[Any] = [None]

    class Proto(asyncio.DatagramProtocol):
        def connection_made(self, transport: Any) -> None:
            self.transport = transport

        def datagram_received(self, data: bytes, addr: Any) -> None:
            for m in mav.parse_buffer(data) or []:
                if m.get_msgId() == mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU:
                    out = mavlink2.MAVLink_set_actuator_control_target_message(
                        m.time_usec, 0, 1, 1, [0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 0.0]
                    )
                    self.transport.sendto(out.pack(mav), addr)
            reply_to[0] = addr

    await loop.create_datagram_endpoint(Proto, local_addr=("127.0.0.1", port))
    stop = asyncio.Event()
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    await stop.wait()


def echo_server(port: int) -> None:
    """The floor: parse with pymavlink, answer HIGHRES_IMU with a fixed command."""
    asyncio.run(_echo(port))


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def run_loop_bench(*, seconds: float = 60.0, rate_hz: float = 1000.0) -> dict[str, Any]:
    """Companion (logging on) and floor, served alternately by one harness in one run."""
    py = sys.executable
    fport, cport = _free_port(), _free_port()
    with tempfile.TemporaryDirectory() as logs:
        cmds = [
            [py, "-c", f"from companion._loopbench import echo_server; echo_server({fport})"],
            [py, "-m", "companion", "run", "--connect", f"udpin:127.0.0.1:{cport}",
             "--profile", str(ROOT / "vehicle_profiles" / "f450.yaml"), "--engage", "auto",
             "--rate-hz", str(rate_hz), "--log-dir", logs,
             # The harness serves the floor half the time: gaps are expected here.
             "--stale-imu-s", "5", "--link-timeout-s", "10"],
        ]  # fmt: skip
        procs = [
            subprocess.Popen(c, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE) for c in cmds
        ]
        try:
            time.sleep(1.5)  # imports and socket set-up
            for p in procs:
                if p.poll() is not None:
                    err = p.stderr.read().decode() if p.stderr else ""
                    raise RuntimeError(f"a benchmark server exited: {err}")
            floor, comp = run_harness([fport, cport], rate_hz=rate_hz, seconds_each=seconds)
        finally:
            for p in procs:
                p.send_signal(signal.SIGTERM)
                try:
                    p.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    p.kill()
    nan = float("nan")
    out: dict[str, Any] = {
        "rate_hz": rate_hz,
        "seconds": seconds,
        "logging": True,
        "latency_us_p50": round(comp.get("p50_us", nan), 1),
        "latency_us_p99": round(comp.get("p99_us", nan), 1),
        "floor_us_p50": round(floor.get("p50_us", nan), 1),
        "floor_us_p99": round(floor.get("p99_us", nan), 1),
        "samples": comp["samples"],
        "floor_missed": floor["missed"],
    }
    missed_key = "missed_at_1khz" if rate_hz == 1000.0 else f"missed_at_{int(rate_hz)}hz"
    out[missed_key] = comp["missed"]
    out["ratio_p50"] = round(out["latency_us_p50"] / out["floor_us_p50"], 3)
    out["ratio_p99"] = round(out["latency_us_p99"] / out["floor_us_p99"], 3)
    out["targets_met"] = bool(
        out["ratio_p50"] <= 1.3 and out["ratio_p99"] <= 1.5 and comp["missed"] == 0
    )
    return out
