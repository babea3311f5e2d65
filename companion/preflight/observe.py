"""Watching the autopilot: the only part of preflight on the link; and the
control law's cost per update on this computer."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import math
import time
from dataclasses import asdict
from typing import Any

from companion.control import RateController
from companion.control.sticks import joystick_channels
from companion.errors import LinkError
from companion.link.timesync import LinkClock
from companion.preflight.judge import summary
from companion.preflight.model import LATE_PERIODS, Check, CoreCost, Observed, Plan
from companion.preflight.rules import OLDER_NAMES, params_read
from companion.step import LANDED_STATE_RATE_HZ

__all__ = ["as_data", "measure_core", "observe"]

# MAVLink numbers (common.xml).
_MSG_ATTITUDE = 30
_MSG_LOCAL_POSITION_NED = 32
_MSG_RC_CHANNELS = 65
_MSG_MANUAL_CONTROL = 69
_MSG_HIGHRES_IMU = 105
_MSG_AUTOPILOT_VERSION = 148
_MSG_EXTENDED_SYS_STATE = 245
_CMD_SET_MESSAGE_INTERVAL = 511
_CMD_REQUEST_MESSAGE = 512
_RESULT_ACCEPTED = 0
_BASE_MODE_ARMED = 128
_RC_RATE_HZ = 50.0
"""RC_CHANNELS as ``companion run`` asks for it."""
_POSITION_RATE_HZ = 4.0


def measure_core(
    controller: RateController, compiled: bool, rate_hz: float, updates: int = 3000
) -> CoreCost:
    """Time the law's update and learning on a made-up flight (a slow sine on
    every axis), after a warm-up."""
    dt = 1.0 / rate_hz
    times: list[float] = []
    clock = time.perf_counter
    for k in range(updates + 200):
        t = k * dt
        w = 2.0 * math.pi * 0.7 * t
        gyro = (0.5 * math.sin(w), 0.4 * math.cos(w), 0.2 * math.sin(0.5 * w))
        ref = (0.5 * math.sin(w + 0.1), 0.4 * math.cos(w + 0.1), 0.2 * math.sin(0.5 * w + 0.1))
        t0 = clock()
        controller.update(dt, gyro, ref, 0.5)
        controller.learn()
        if k >= 200:
            times.append(clock() - t0)
    times.sort()
    return CoreCost(
        compiled=compiled,
        median_us=times[len(times) // 2] * 1e6,
        p99_us=times[int(0.99 * (len(times) - 1))] * 1e6,
        updates=len(times),
    )


async def observe(
    link: Any,
    plan: Plan,
    *,
    watch_s: float = 3.0,
    heartbeat_timeout_s: float = 5.0,
) -> Observed:
    """Connect, read, ask for the streams, watch them for ``watch_s``; the link is
    started here and left open (the caller closes it).

    ``link`` is a :class:`~companion.link.mavlink.MavlinkLink` whose ``on_message``
    and ``on_raw`` this replaces."""
    obs = Observed()
    watcher = _Watcher(obs, plan.sticks_channels)
    link.on_message = watcher.on_message
    link.on_raw = watcher.on_raw
    await link.start()
    try:
        hb = await link.wait_heartbeat(heartbeat_timeout_s)
    except LinkError as exc:
        obs.error = str(exc)
        obs.frames_rejected_unsigned = int(link.counters.get("unsigned_rejected", 0))
        return obs
    obs.heartbeat = True
    obs.autopilot_id = int(hb.autopilot)
    obs.target = link.target
    obs.armed = bool(hb.base_mode & _BASE_MODE_ARMED)
    stack = obs.stack
    if stack is None:
        return obs
    await _read_version(link, watcher)
    names = params_read(stack)
    if obs.frames_signed and not plan.signing:
        # It would refuse everything we send: nothing more to learn.
        return obs
    for name in names:
        obs.params[name] = await _param(link, name)
        older = OLDER_NAMES.get(name)
        if older is not None and obs.params[name] is None:
            obs.params[older] = await _param(link, older)
    imu_id = _MSG_HIGHRES_IMU if stack.imu_message == "highres_imu" else _MSG_ATTITUDE
    obs.imu_message = "HIGHRES_IMU" if imu_id == _MSG_HIGHRES_IMU else "ATTITUDE"
    obs.imu_asked_hz = min(plan.rate_hz, stack.max_imu_rate_hz)
    obs.imu_result = await link.command_long(
        _CMD_SET_MESSAGE_INTERVAL, imu_id, 1e6 / obs.imu_asked_hz
    )
    for msg_id, hz in (
        (_MSG_RC_CHANNELS, _RC_RATE_HZ),
        (_MSG_MANUAL_CONTROL, _RC_RATE_HZ),
        (_MSG_EXTENDED_SYS_STATE, LANDED_STATE_RATE_HZ),
        (_MSG_LOCAL_POSITION_NED, _POSITION_RATE_HZ),
    ):
        with contextlib.suppress(LinkError):
            await link.command_long(_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)
    await watcher.watch(link, imu_id, watch_s)
    obs.frames_rejected_unsigned = int(link.counters.get("unsigned_rejected", 0))
    # Leave the IMU stream as the autopilot had it: interval 0 restores its default.
    with contextlib.suppress(LinkError):
        await link.command_long(_CMD_SET_MESSAGE_INTERVAL, imu_id, 0.0, retries=1)
    return obs


async def _param(link: Any, name: str) -> float | None:
    try:
        value: float = await link.param_read(name, timeout_s=0.3, retries=2)
    except LinkError:
        return None
    return value


async def _read_version(link: Any, watcher: _Watcher) -> None:
    watcher.version_seen.clear()
    with contextlib.suppress(LinkError):
        res = await link.command_long(_CMD_REQUEST_MESSAGE, _MSG_AUTOPILOT_VERSION)
        if res == _RESULT_ACCEPTED:
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(watcher.version_seen.wait(), 1.0)


def _note_channels(chans: list[int], lo: list[int], hi: list[int]) -> None:
    """Widen the per-channel ranges seen (``lo``, ``hi``, grown as needed) by ``chans``."""
    if len(chans) > len(lo):
        grow = len(chans) - len(lo)
        lo += [65535] * grow
        hi += [0] * grow
    for i, v in enumerate(chans):
        lo[i] = min(lo[i], v)
        hi[i] = max(hi[i], v)


class _Watcher:
    """Counts what the autopilot streams into an :class:`Observed`."""

    def __init__(self, obs: Observed, stick_channels: tuple[int, int, int, int]) -> None:
        self.obs = obs
        self.stick_channels = stick_channels
        self.version_seen = asyncio.Event()
        self.clock = LinkClock()
        self.imu_id = -1
        self.imu_times: list[float] = []
        self.imu_stamps: list[float] = []
        self.watching = False

    def on_raw(self, _t: float, frame: bytes, outgoing: bool) -> None:
        if outgoing or len(frame) < 3 or frame[0] != 0xFD:
            return
        if frame[2] & 0x01:
            self.obs.frames_signed += 1
        else:
            self.obs.frames_unsigned += 1

    def on_message(self, msg: Any) -> None:
        obs = self.obs
        mid = msg.get_msgId()
        if mid == _MSG_AUTOPILOT_VERSION:
            v = int(msg.flight_sw_version)
            obs.version = ((v >> 24) & 0xFF, (v >> 16) & 0xFF, (v >> 8) & 0xFF)
            obs.capabilities = int(msg.capabilities)
            self.version_seen.set()
            return
        if not self.watching:
            return
        if mid == self.imu_id:
            self.imu_times.append(time.perf_counter())
            self.imu_stamps.append(_stamp_s(msg))
        elif mid == _MSG_RC_CHANNELS:
            count = int(msg.chancount)
            obs.rc_messages += 1
            obs.rc_chancount = max(obs.rc_chancount, count)
            if count:
                chans = [int(getattr(msg, f"chan{i}_raw")) for i in range(1, min(count, 18) + 1)]
                _note_channels(chans, obs.rc_min_us, obs.rc_max_us)
                obs.rc_last_us = chans
        elif mid == _MSG_MANUAL_CONTROL:
            obs.joystick_messages += 1
            fields = (msg.x, msg.y, msg.z, msg.r, msg.enabled_extensions,
                      *(getattr(msg, f"aux{i}") for i in range(1, 7)))  # fmt: skip
            chans = list(joystick_channels(tuple(int(v) for v in fields), self.stick_channels))
            _note_channels(chans, obs.joystick_min_us, obs.joystick_max_us)
            obs.joystick_last_us = chans
        elif mid == _MSG_EXTENDED_SYS_STATE:
            obs.landed_states.append(int(msg.landed_state))
        elif mid == _MSG_LOCAL_POSITION_NED:
            obs.position_messages += 1
        elif msg.get_type() == "TIMESYNC" and msg.tc1 != 0:
            self.clock.reply(int(msg.tc1), int(msg.ts1), time.perf_counter())

    async def watch(self, link: Any, imu_id: int, watch_s: float) -> None:
        """Watch the streams for ``watch_s``, asking the autopilot's time 10 times a second."""
        self.imu_id = imu_id
        self.watching = True
        start = time.perf_counter()
        end = start + watch_s
        try:
            while (now := time.perf_counter()) < end:
                link.send(link.mav.timesync_encode(0, self.clock.request(now)))
                self.obs.timesync_requests += 1
                await asyncio.sleep(min(0.1, max(0.0, end - now)))
            await asyncio.sleep(0.05)  # the last answers
        finally:
            self.watching = False
        obs = self.obs
        ts = self.imu_times
        # The stream's own rate: from its first sample on (a new interval takes a
        # moment to apply), over the rest of the window.
        if len(ts) >= 2:
            obs.imu_count = len(ts) - 1
            obs.imu_window_s = end - ts[0]
            gaps = [b - a for a, b in itertools.pairwise(ts)] + [end - ts[-1]]
            obs.imu_max_gap_s = max(gaps)
            obs.imu_late = sum(g > LATE_PERIODS / obs.imu_asked_hz for g in gaps)
            stamps = self.imu_stamps
            if stamps[-1] > stamps[0]:
                obs.imu_clock_ratio = (stamps[-1] - stamps[0]) / (ts[-1] - ts[0])
        else:
            obs.imu_count = len(ts)
        obs.link = self.clock.stats()


def _stamp_s(msg: Any) -> float:
    """An IMU message's time on the autopilot's clock, s."""
    if hasattr(msg, "time_usec"):
        return float(msg.time_usec) * 1e-6
    return float(msg.time_boot_ms) * 1e-3


def as_data(obs: Observed, checks: list[Check], core: CoreCost | None) -> dict[str, Any]:
    """``--json``'s document."""
    counts = summary(checks)
    stack = obs.stack
    return {
        "ok": counts["fail"] == 0,
        "counts": counts,
        "stack": stack.name if stack else None,
        "version": ".".join(map(str, obs.version)) if obs.version else None,
        "target": list(obs.target) if obs.target else None,
        "checks": [asdict(c) for c in checks],
        "params": obs.params,
        "link": obs.link.as_dict() if obs.link else None,
        "imu_rate_hz": round(obs.imu_count / obs.imu_window_s, 1) if obs.imu_window_s else None,
        "imu_longest_gap_ms": round(obs.imu_max_gap_s * 1e3, 1) if obs.imu_count else None,
        "imu_late": obs.imu_late,
        "autopilot_clock_ratio": (
            round(obs.imu_clock_ratio, 4) if math.isfinite(obs.imu_clock_ratio) else None
        ),
        "core": asdict(core) if core else None,
    }
