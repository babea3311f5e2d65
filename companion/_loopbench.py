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
    port: int, *, rate_hz: float, seconds: float, warmup_s: float = 3.0
) -> dict[str, Any]:
    """Drive whatever listens on 127.0.0.1:``port``; return latency statistics (us)."""
    mav = mavlink2.MAVLink(_Sink(), srcSystem=1, srcComponent=1)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setblocking(False)
    dest = ("127.0.0.1", port)
    parser = mavlink2.MAVLink(_Sink(), srcSystem=255, srcComponent=0)
    period = 1.0 / rate_hz
    sent: dict[int, int] = {}
    lat_us: list[float] = []
    answered = 0
    pc = time.perf_counter_ns

    def send(msg: Any) -> None:
        sock.sendto(msg.pack(mav), dest)

    def heartbeat() -> None:
        send(mavlink2.MAVLink_heartbeat_message(2, 12, 128 | 1, 6 << 16, 4, 3))

    def rc() -> None:
        ch = [1500, 1500, 1500, 1500, 1000] + [65535] * 13
        send(mavlink2.MAVLink_rc_channels_message(0, 5, *ch, 254))

    def drain(measuring: bool) -> None:
        nonlocal answered
        while True:
            try:
                data = sock.recv(4096)
            except BlockingIOError:
                return
            t_rx = pc()
            for m in parser.parse_buffer(data) or []:
                mid = m.get_msgId()
                if mid == mavlink2.MAVLINK_MSG_ID_SET_ACTUATOR_CONTROL_TARGET:
                    t_tx = sent.pop(m.time_usec, None)
                    if t_tx is not None and measuring:
                        lat_us.append((t_rx - t_tx) / 1000.0)
                        answered += 1
                elif mid == mavlink2.MAVLINK_MSG_ID_COMMAND_LONG:
                    send(
                        mavlink2.MAVLink_command_ack_message(
                            m.command, 0, 0, 0, m.get_srcSystem(), m.get_srcComponent()
                        )
                    )

    t_start = time.perf_counter()
    k = 0
    n_measured = 0
    next_hb = next_rc = t_start
    total = warmup_s + seconds
    while True:
        now = time.perf_counter()
        elapsed = now - t_start
        if elapsed >= total:
            break
        if now >= next_hb:
            heartbeat()
            next_hb += 0.5
        if now >= next_rc:
            rc()
            next_rc += 0.02
        due = t_start + k * period
        if now >= due:
            k += 1
            time_usec = k * round(period * 1e6)
            msg = mavlink2.MAVLink_highres_imu_message(
                time_usec, 0, 0, -9.81, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0b111111
            )
            measuring = elapsed >= warmup_s
            sent[time_usec] = pc()
            send(msg)
            if measuring:
                n_measured += 1
            # Anything not answered within 20 ms is a miss.
            cutoff = time_usec - 20_000
            for key in [t for t in sent if t < cutoff]:
                del sent[key]
        drain(elapsed >= warmup_s)
        # Wait on the socket until the next event, so a reply is stamped when it lands.
        wait = min(t_start + k * period, next_rc, next_hb) - time.perf_counter()
        if wait > 0.0:
            r, _, _ = select.select([sock], [], [], wait)
            if r:
                drain(elapsed >= warmup_s)
    deadline = time.perf_counter() + 0.05
    while time.perf_counter() < deadline:
        drain(True)
    sock.close()
    if not lat_us:
        return {"samples": n_measured, "answered": 0, "missed": n_measured}
    return {
        "samples": n_measured,
        "answered": answered,
        "missed": max(0, n_measured - answered),
        "p50_us": statistics.median(lat_us),
        "p99_us": _percentile(lat_us, 0.99),
    }


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


def _measure(cmd: list[str], port: int, rate_hz: float, seconds: float) -> dict[str, Any]:
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        time.sleep(1.5)  # imports and socket setup
        if proc.poll() is not None:
            raise RuntimeError(
                f"{cmd[2:4]} exited: {proc.stderr.read().decode() if proc.stderr else ''}"
            )
        return run_harness(port, rate_hz=rate_hz, seconds=seconds)
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()


def run_loop_bench(
    *, seconds: float = 60.0, rate_hz: float = 1000.0, floor_seconds: float = 20.0
) -> dict[str, Any]:
    """Companion (logging on) and floor, measured by the same harness in one run."""
    py = sys.executable
    fport = _free_port()
    floor = _measure(
        [py, "-c", f"from companion._loopbench import echo_server; echo_server({fport})"],
        fport,
        rate_hz,
        floor_seconds,
    )
    cport = _free_port()
    with tempfile.TemporaryDirectory() as logs:
        comp = _measure(
            [py, "-m", "companion", "run", "--connect", f"udpin:127.0.0.1:{cport}",
             "--profile", str(ROOT / "vehicle_profiles" / "f450.yaml"), "--engage", "auto",
             "--rate-hz", str(rate_hz), "--log-dir", logs, "--stale-imu-s", "0.5"],
            cport, rate_hz, seconds,
        )  # fmt: skip
    out: dict[str, Any] = {
        "rate_hz": rate_hz,
        "seconds": seconds,
        "logging": True,
        "latency_us_p50": round(comp.get("p50_us", float("nan")), 1),
        "latency_us_p99": round(comp.get("p99_us", float("nan")), 1),
        "floor_us_p50": round(floor.get("p50_us", float("nan")), 1),
        "floor_us_p99": round(floor.get("p99_us", float("nan")), 1),
        "samples": comp["samples"],
        "missed_at_1khz" if rate_hz == 1000.0 else f"missed_at_{int(rate_hz)}hz": comp["missed"],
        "floor_missed": floor["missed"],
    }
    out["ratio_p50"] = round(out["latency_us_p50"] / out["floor_us_p50"], 3)
    out["ratio_p99"] = round(out["latency_us_p99"] / out["floor_us_p99"], 3)
    out["targets_met"] = bool(
        out["ratio_p50"] <= 1.3 and out["ratio_p99"] <= 1.5 and comp["missed"] == 0
    )
    return out
