"""Loop latency benchmark: a harness plays the autopilot over real UDP.

The harness sends HIGHRES_IMU at a fixed rate (plus heartbeats showing
OFFBOARD and armed, RC_CHANNELS, and an ACCEPTED answer to every command)
and times each IMU datagram until the command carrying its ``time_usec``
comes back. The same harness measures a *floor*: a bare asyncio server that
parses with pymavlink and answers every HIGHRES_IMU with a fixed command.
The ratio of the two is what the companion's own work costs, on this
machine, in this run.

How the harness keeps the two comparable (each rule applies to every target
alike):

* Targets are served alternately in ``block_s`` blocks, so both see the same
  background load, and each gets the same number of whole blocks (a quick
  5 s run measures 3 blocks of 2 s each, not 3 against 2).
* A sample's time runs from just before the harness's ``sendto`` (the frame
  is packed first: the harness's own encoding is not timed) to the kernel's
  receive stamp of the command (``SO_TIMESTAMPNS``, CLOCK_REALTIME like the
  send stamp; on loopback the stamp is taken inside the server's ``sendto``),
  not to when the harness gets round to reading it. The harness's own wake-up
  is left out: with two cores it often waits for the CPU the answering server
  is still running on, so it charged that server's after-the-command work
  (logging, the identifier) to its latency, which is not what "datagram
  arrival to command leaving" means (server's send to harness's read, median
  / p90: floor 16-17 / 21 us, companion 20-26 / 40-49 us in 10 s runs with
  load < 1; with the kernel stamp both are 4-5 / 6-10 us). (The stamp needs
  Linux; elsewhere, or for the first packets while the kernel switches
  stamping on, it is the time of the read, as before.)
* Housekeeping (heartbeat and RC_CHANNELS, 50 Hz) goes to the target being
  timed right before one of its IMU samples, as an autopilot may send them
  together; the other targets get theirs half a period later. They used to
  go to every target at once in port order, floor first: the floor then
  worked through its heartbeat and RC while the harness was still sending
  the companion's, and met its IMU sample ready (arrival to the server's
  read, median over those samples: floor 6 us, companion 220-260 us in 20 s
  runs on a quiet machine); sending them all right before the sample instead
  made the idle server's work compete with the timed one for the two cores.
  Now both see the same order and nothing of the other's.
* A sample is *missed* when no command carrying its ``time_usec`` ever
  comes back (the harness waits ``_STRAGGLER_S`` after the run for the last
  ones). A command that comes back later than 20 ms (``_LATE_AFTER_US``, by
  the same stamps) is counted as *late* as well as timed (so a stall shows in
  the p99 and the ratio too, of whichever target it hit): on this shared
  2-core VM the whole machine stalls now and then for 20-40 ms (an
  independent 1 ms sleeper process sees the same gaps), and a sample sent
  just before such a stall comes back late from the floor and from the
  companion alike. Until November 2026 such answers counted as missed, which
  mixed "the companion dropped a sample" with "the machine stopped".
* The IMU keeps time like an autopilot's: when the harness is woken a whole
  period or more late (descheduled on a loaded machine), it skips the slots
  that passed instead of sending them in a burst, and counts them
  (``skipped``). A burst measured the harness's own backlog, not the server:
  on a machine loaded by other jobs the old catch-up fell seconds behind,
  sent thousands of samples back to back (the receiving socket dropped some,
  counted as misses) and starved the companion of IMU long enough for its
  stale-IMU failsafe. Skipped slots were never offered, so they are neither
  samples nor misses.
* The harness runs with its cyclic garbage collector off (frozen, then
  disabled): its full collections took 10-15 ms, long enough to skip slots.
"""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")

import asyncio
import contextlib
import gc
import json
import math
import select
import signal
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from sitl.lab import children
from sitl.lab.fly import free_tcp_port, free_udp_ports

__all__ = ["echo_server", "run_harness", "run_loop_bench"]

ROOT = Path(__file__).resolve().parents[2]

# Linux's SO_TIMESTAMPNS (asm-generic value; the socket module does not name it):
# each datagram carries the CLOCK_REALTIME time the kernel received it.
_SO_TIMESTAMPNS = 35
_TIMESPEC = struct.Struct("@qq")
_LATE_AFTER_US = 20_000.0
"""A command that comes back later than this after its sample is late."""
_STRAGGLER_S = 1.0
"""After the run, how long the harness waits for commands still on their way."""


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
        with contextlib.suppress(OSError):  # without it: stamped after recv
            sk.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        socks.append(sk)
    parser = mavlink2.MAVLink(_Sink(), srcSystem=255, srcComponent=0)
    period = 1.0 / rate_hz
    period_us = round(period * 1e6)
    n = len(ports)
    # time_usec -> (sent at, ns CLOCK_REALTIME; sent while measuring)
    sent: list[dict[int, tuple[int, bool]]] = [{} for _ in ports]
    lat: list[list[float]] = [[] for _ in ports]
    measured = [0] * n
    skipped = [0] * n
    late = [0] * n
    # Late samples at most 20 ms plus one period apart are one episode (a stall).
    late_episodes = [0] * n
    last_late = [-2] * n  # time_usec slot of the last late sample
    # Every target gets the same number of whole blocks.
    blocks_each = max(1, math.ceil(seconds_each / block_s - 1e-9))
    wall_ns = time.time_ns  # the clock of the kernel's receive stamps
    cmsg_size = socket.CMSG_SPACE(_TIMESPEC.size)
    addrs = [("127.0.0.1", p) for p in ports]

    def send(i: int, msg: Any) -> None:
        socks[i].sendto(msg.pack(mav), addrs[i])

    def housekeeping(i: int) -> None:
        send(i, mavlink2.MAVLink_heartbeat_message(2, 12, 128 | 1, 6 << 16, 4, 3))
        ch = [1500, 1500, 1500, 1500, 1000] + [65535] * 13
        send(i, mavlink2.MAVLink_rc_channels_message(0, 5, *ch, 254))

    def drain(i: int) -> None:
        sk = socks[i]
        while True:
            try:
                data, anc, _flags, _addr = sk.recvmsg(4096, cmsg_size)
            except BlockingIOError:
                return
            t_rx = 0
            for level, kind, value in anc:
                if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS:
                    sec, nsec = _TIMESPEC.unpack_from(value)
                    t_rx = sec * 1_000_000_000 + nsec
            if not t_rx:
                t_rx = wall_ns()
            for m in parser.parse_buffer(data) or []:
                mid = m.get_msgId()
                if mid == mavlink2.MAVLINK_MSG_ID_SET_ACTUATOR_CONTROL_TARGET:
                    entry = sent[i].pop(m.time_usec, None)
                    if entry is not None and entry[1]:
                        dt_us = (t_rx - entry[0]) / 1000.0
                        lat[i].append(dt_us)
                        if dt_us > _LATE_AFTER_US:
                            late[i] += 1
                            slot = round(m.time_usec / period_us)
                            if slot - last_late[i] > 1 + round(_LATE_AFTER_US / period_us):
                                late_episodes[i] += 1
                            last_late[i] = slot
                elif mid == mavlink2.MAVLINK_MSG_ID_COMMAND_LONG:
                    send(i, mavlink2.MAVLink_command_ack_message(
                        m.command, 0, 0, 0, m.get_srcSystem(), m.get_srcComponent()))  # fmt: skip

    # The harness's own pauses: no cyclic collection during the run (what it
    # allocates per sample is freed by reference counting).
    gc_was_enabled = gc.isenabled()
    gc.collect()
    gc.freeze()
    gc.disable()
    try:
        t_start = time.perf_counter()
        k = 0
        next_hk = t_start
        idle_hk: list[int] = []  # targets whose housekeeping is due at idle_hk_at
        idle_hk_at = t_start
        total = warmup_s * n + blocks_each * block_s * n
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
                # The target being timed gets its heartbeat and RC right before an IMU
                # sample (as an autopilot may send them); the others, which only need
                # them to keep their watchdogs fed, half a period later (see the
                # module docstring).
                housekeeping(target)
                idle_hk = [i for i in range(n) if i != target]
                idle_hk_at = now + 0.5 * period
                next_hk += 0.02 * (1 + int((now - next_hk) / 0.02))  # no catch-up burst either
            if idle_hk and now >= idle_hk_at:
                for i in idle_hk:
                    housekeeping(i)
                idle_hk = []
            due = t_start + k * period
            if now >= due:
                # Woken a whole period or more late (descheduled): skip the slots that
                # passed rather than send them in a burst (see the module docstring).
                behind = int((now - due) / period)
                if behind:
                    k += behind
                    if measuring:
                        skipped[target] += behind
                k += 1
                time_usec = k * period_us
                buf = mavlink2.MAVLink_highres_imu_message(
                    time_usec, 0, 0, -9.81, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0b111111
                ).pack(mav)
                # Stamped after packing: the harness's own work is not timed.
                sent[target][time_usec] = (wall_ns(), measuring)
                socks[target].sendto(buf, addrs[target])
                if measuring:
                    measured[target] += 1
            for i in range(n):
                drain(i)
            wake = min(t_start + k * period, next_hk)
            if idle_hk:
                wake = min(wake, idle_hk_at)
            wait = wake - time.perf_counter()
            if wait > 0.0:
                r, _, _ = select.select(socks, [], [], wait)
                for sk in r:
                    drain(socks.index(sk))
        # Stragglers: heartbeat and RC go on (as from an autopilot), so no
        # server's lost-link or lost-RC watchdog ends it while it is awaited.
        deadline = time.perf_counter() + _STRAGGLER_S
        while (now := time.perf_counter()) < deadline:
            if now >= next_hk:
                for i in range(n):
                    housekeeping(i)
                next_hk = now + 0.02
            r, _, _ = select.select(socks, [], [], max(0.0, min(deadline, next_hk) - now))
            for sk in r:
                drain(socks.index(sk))
    finally:
        if gc_was_enabled:
            gc.enable()
        gc.unfreeze()
    out = []
    for i in range(n):
        socks[i].close()
        xs = lat[i]
        stats: dict[str, Any] = {
            "samples": measured[i],
            "answered": len(xs),
            "missed": max(0, measured[i] - len(xs)),
            "late": late[i],
            "late_episodes": late_episodes[i],
            "skipped": skipped[i],
        }
        if xs:
            stats["p50_us"] = statistics.median(xs)
            stats["p99_us"] = _percentile(xs, 0.99)
            stats["max_us"] = max(xs)
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


def run_loop_bench(
    *,
    seconds: float = 60.0,
    rate_hz: float = 1000.0,
    profile: Path | None = None,
    viewer: bool = False,
) -> dict[str, Any]:
    """Companion (logging on) and floor, served alternately by one harness in one run.

    ``profile``: the vehicle profile the companion is given (default: the source
    tree's F450, for a run from a checkout). ``viewer``: a third target, the
    companion with ``--live`` and a viewer (:mod:`sitl.lab.live_viewer`, its own
    process) subscribed to every topic and reading all it is sent; its figures
    are the ``viewer_*`` keys, its ratios against the floor and against the
    companion without a viewer, all three measured in the same blocks.
    """
    py = sys.executable
    profile = profile or ROOT / "vehicle_profiles" / "f450.yaml"
    fport, cport, vport = free_udp_ports(3)
    wport = free_tcp_port()

    def companion(port: int, logs: str, *extra: str) -> list[str]:
        return [py, "-m", "companion", "run", "--connect", f"udpin:127.0.0.1:{port}",
                "--profile", str(profile), "--engage", "auto",
                "--rate-hz", str(rate_hz), "--log-dir", logs,
                # The harness serves the other targets most of the time: gaps of
                # one block per other target are expected here (4 s of three), more
                # when the harness is descheduled on a loaded machine.
                "--stale-imu-s", "10", "--beyond-bounds", "--stale-imu-s",
                "--link-timeout-s", "10", *extra]  # fmt: skip

    with tempfile.TemporaryDirectory() as logs:
        cmds = [
            [py, "-c", f"from sitl.lab.loopbench import echo_server; echo_server({fport})"],
            companion(cport, str(Path(logs) / "plain")),
        ]
        if viewer:
            cmds.append(
                companion(vport, str(Path(logs) / "viewed"), "--live", f"127.0.0.1:{wport}")
            )
        # stderr to files, not pipes: a pipe nobody reads fills up at 64 KiB and
        # blocks the writer in the middle of the measurement.
        errs = [Path(logs) / f"server{i}.stderr" for i in range(len(cmds))]
        procs = []
        for c, e in zip(cmds, errs, strict=True):
            with e.open("wb") as f:
                procs.append(children.start(c, stdout=subprocess.DEVNULL, stderr=f))
        watcher = None
        try:
            time.sleep(1.5)  # imports and socket set-up
            for p, e in zip(procs, errs, strict=True):
                if p.poll() is not None:
                    err = e.read_text(errors="replace")
                    raise RuntimeError(f"a benchmark server exited: {err}")
            if viewer:
                # Subscribed before the first sample; reads until the server goes.
                watch_cmd = [py, "-m", "sitl.lab.live_viewer", f"ws://127.0.0.1:{wport}",
                             str(4.0 * seconds + 60.0)]  # fmt: skip
                watcher = children.start(
                    watch_cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL
                )
                time.sleep(1.0)
            ports = [fport, cport, vport] if viewer else [fport, cport]
            timed = run_harness(ports, rate_hz=rate_hz, seconds_each=seconds)
            floor, comp = timed[0], timed[1]
            # A server that ended by itself (a failsafe) missed everything after: say so.
            ended_early = [p.poll() is not None for p in procs]
        finally:
            for p in procs:
                p.send_signal(signal.SIGTERM)
                try:
                    p.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
    nan = float("nan")
    out: dict[str, Any] = {
        "rate_hz": rate_hz,
        "seconds": seconds,
        "logging": True,
        "latency_us_p50": round(comp.get("p50_us", nan), 1),
        "latency_us_p99": round(comp.get("p99_us", nan), 1),
        "floor_us_p50": round(floor.get("p50_us", nan), 1),
        "floor_us_p99": round(floor.get("p99_us", nan), 1),
        "latency_us_max": round(comp.get("max_us", nan), 1),
        "floor_us_max": round(floor.get("max_us", nan), 1),
        "samples": comp["samples"],
        "floor_missed": floor["missed"],
        "late": comp["late"],
        "floor_late": floor["late"],
        "late_episodes": comp["late_episodes"],
        "floor_late_episodes": floor["late_episodes"],
        "skipped": comp["skipped"],
        "floor_skipped": floor["skipped"],
        "ended_early": ended_early[1],
        "floor_ended_early": ended_early[0],
    }
    missed_key = "missed_at_1khz" if rate_hz == 1000.0 else f"missed_at_{int(rate_hz)}hz"
    out[missed_key] = comp["missed"]
    out["ratio_p50"] = round(out["latency_us_p50"] / out["floor_us_p50"], 3)
    out["ratio_p99"] = round(out["latency_us_p99"] / out["floor_us_p99"], 3)
    out["targets_met"] = bool(
        out["ratio_p50"] <= 1.3 and out["ratio_p99"] <= 1.5 and comp["missed"] == 0
    )
    if viewer:
        seen: dict[str, Any] = {}
        if watcher is not None:
            try:
                text, _ = watcher.communicate(timeout=30)
                seen = json.loads(text.decode().strip().splitlines()[-1])
            except (subprocess.TimeoutExpired, ValueError, IndexError):
                watcher.kill()
                watcher.wait()
        v = timed[2]
        out.update(
            viewer=True,
            viewer_latency_us_p50=round(v.get("p50_us", nan), 1),
            viewer_latency_us_p99=round(v.get("p99_us", nan), 1),
            viewer_latency_us_max=round(v.get("max_us", nan), 1),
            viewer_samples=v["samples"],
            viewer_late=v["late"],
            viewer_skipped=v["skipped"],
            viewer_ended_early=ended_early[2],
            viewer_topics=len(seen.get("topics", [])),
            viewer_messages=sum(seen.get("counts", {}).values()),
        )
        out[f"viewer_{missed_key}"] = v["missed"]
        out["viewer_ratio_p50"] = round(out["viewer_latency_us_p50"] / out["floor_us_p50"], 3)
        out["viewer_ratio_p99"] = round(out["viewer_latency_us_p99"] / out["floor_us_p99"], 3)
        out["viewer_over_plain_p50"] = round(
            out["viewer_latency_us_p50"] / out["latency_us_p50"], 3
        )
        out["viewer_over_plain_p99"] = round(
            out["viewer_latency_us_p99"] / out["latency_us_p99"], 3
        )
        out["viewer_targets_met"] = bool(
            out["viewer_ratio_p50"] <= 1.3 and out["viewer_ratio_p99"] <= 1.5 and v["missed"] == 0
        )
    return out
