"""The app tier's harness: a Companion run against a FakeAutopilot over a MemoryTransport.

:class:`Flight` is one running companion and its fake autopilot; the ``start``
fixture (``conftest.py``) makes them; the helpers below drive the common steps.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import math
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from companion.app import Companion, RunOptions
from companion.config import DEFAULT_CONTROLLER, load_controller
from companion.failsafe import FailsafeConfig
from companion.link.transport import MemoryTransport
from companion.profile import load_profile
from tests.app.fakes import (
    CMD_ARM,
    CMD_DO_SET_MODE,
    CMD_SET_MESSAGE_INTERVAL,
    HANG_SLACK,
    PX4_MANUAL,
    PX4_OFFBOARD,
    FakeAutopilot,
    mavlink2,
    settle,
)

ROOT = Path(__file__).resolve().parents[2]
PROFILE_PATH = ROOT / "vehicle_profiles" / "f450.yaml"
PROFILE = load_profile(PROFILE_PATH)
CONTROLLER = load_controller(DEFAULT_CONTROLLER)

PX4 = mavlink2.MAV_AUTOPILOT_PX4
ARDUPILOT = mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA
MSG_ATTITUDE = 30
MSG_RC_CHANNELS = 65
MSG_HIGHRES_IMU = 105
MSG_EXTENDED_SYS_STATE = 245
DENIED = mavlink2.MAV_RESULT_DENIED
ACCEPTED = mavlink2.MAV_RESULT_ACCEPTED

# Watchdogs loose enough that a test's own pauses do not trip them; a test about
# one failsafe tightens that one.
LOOSE = FailsafeConfig(stale_imu_s=2.0, rc_timeout_s=5.0, link_timeout_s=5.0, hand_back_watch_s=0.3)
FEED_PERIOD_S = 0.004
""":meth:`Flight.feed_until` sends once per this (at most: a loaded machine is slower)."""


class StepClock:
    """The engagement's clock in this tier (its ``clock`` and ``sleep``): time
    passes only while the engagement waits, and by exactly what it asked to wait,
    however long a loaded machine took to wake it. Its retries, deadlines and
    safe-mode watch are so counted in its own waits, the same on any machine.

    Each wait still lasts that long on the wall: what runs on the wall clock (the
    fake autopilot, the shell's watchdogs) goes on beside it as in flight, and
    this clock never runs ahead of the wall's (waits that overlap, a hand-back
    beside an engagement, take it to the later end, not to their sum)."""

    def __init__(self) -> None:
        self._ns = 0

    def __call__(self) -> float:
        """Now, s (0 when the run was made)."""
        return self._ns * 1e-9

    async def sleep(self, dt_s: float) -> None:
        wake_ns = self._ns + round(dt_s * 1e9)
        await asyncio.sleep(dt_s)
        self._ns = max(self._ns, wake_ns)


@dataclass
class Flight:
    """One running companion and its fake autopilot; ``clock`` is its engagement's."""

    companion: Companion
    fake: FakeAutopilot
    task: asyncio.Task[int]
    clock: StepClock = field(default_factory=StepClock)
    t_us: int = 10_000_000
    t_ms: int = 10_000

    def imu(self, gyro: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> int:
        """Send the next HIGHRES_IMU sample (250 Hz); returns its time_usec."""
        self.t_us += 4000
        self.fake.highres_imu(self.t_us, gyro)
        return self.t_us

    def att(self, rates: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> int:
        """Send the next ATTITUDE sample (~333 Hz); returns its time_boot_ms."""
        self.t_ms += 3
        self.fake.attitude(self.t_ms, rates)
        return self.t_ms

    async def feed_until(
        self,
        cond: Callable[[], Any],
        *,
        send: Callable[[], Any] | None = None,
        timeout_s: float = 2.0,
        what: str = "condition",
    ) -> None:
        """Stream samples (as an autopilot does) until ``cond()`` holds.

        Gives up (a guard against a hang) after ``timeout_s`` times ``HANG_SLACK``
        of samples: that many ``FEED_PERIOD_S`` apart, each send followed by a wait
        of ``FEED_PERIOD_S``, so at least as long on the wall too, however slowly a
        loaded machine makes them."""
        send = send or self.imu
        limit_s = HANG_SLACK * timeout_s
        for _ in range(math.ceil(limit_s / FEED_PERIOD_S)):
            if cond():
                return
            if self.task.done():
                raise AssertionError(f"run() ended ({self.task.result()}) waiting for {what}")
            send()
            await asyncio.sleep(FEED_PERIOD_S)
        if not cond():
            raise AssertionError(f"not within {limit_s:g} s of samples waiting for {what}")

    async def finish(self, timeout_s: float = 2.0) -> int:
        """The run's exit code, once it ends (``asyncio.TimeoutError`` if it has not
        after ``timeout_s`` times ``HANG_SLACK``: a guard against a hang)."""
        return await asyncio.wait_for(asyncio.shield(self.task), HANG_SLACK * timeout_s)

    def kinds(self) -> list[str]:
        return [e["kind"] for e in self.companion.events]

    def details(self, kind: str) -> list[str]:
        return [e["detail"] for e in self.companion.events if e["kind"] == kind]


Start = Callable[..., Awaitable[Flight]]


async def streams_requested(f: Flight, imu_id: int = MSG_HIGHRES_IMU) -> None:
    def both() -> bool:
        ids = {int(m.param1) for m in f.fake.commands(CMD_SET_MESSAGE_INTERVAL)}
        return {imu_id, MSG_RC_CHANNELS} <= ids

    await f.fake.wait_until(both, 2.0)


async def started_up(f: Flight) -> None:
    """Start-up over: the engage switch is read from then on."""
    await f.fake.wait_until(lambda: f.companion.started_up, 2.0)


async def engage_px4_auto(f: Flight) -> None:
    """Start-up, setpoints, OFFBOARD, ARM, and the heartbeat that shows them applied."""
    await streams_requested(f)
    # Valid sticks, half throttle: a few frames (an auto engagement waits for a stream).
    pilot_frames(f)
    await f.feed_until(lambda: f.fake.commands(CMD_ARM), what="ARM")
    await settle()
    assert not f.companion.engaged, "engaged on the ACKs alone, before the heartbeat said so"
    f.fake.set_state(PX4_OFFBOARD, armed=True)
    await f.fake.wait_until(lambda: f.companion.engaged, 1.0)


def pilot_frames(f: Flight, ch5_us: int = 1000, n: int = 3) -> None:
    """The pilot's radio streaming (``n`` RC_CHANNELS frames: valid sticks, half
    throttle): an auto engagement waits for a stream, not one frame."""
    for _ in range(n):
        f.fake.rc(ch5_us, sticks=(1500, 1500, 1500, 1500))


def index_of(fake: FakeAutopilot, pred: Callable[[Any], bool]) -> int:
    for i, m in enumerate(fake.received):
        if pred(m):
            return i
    raise AssertionError("no such message received")


def is_mode(m: Any, param2: float) -> bool:
    return m.get_type() == "COMMAND_LONG" and m.command == CMD_DO_SET_MODE and m.param2 == param2


def setpoint_times(msgs: list[Any]) -> list[int]:
    return [m.time_usec if hasattr(m, "time_usec") else m.time_boot_ms for m in msgs]


async def switch_flicked_high(start: Start) -> Flight:
    """An armed PX4 in MANUAL with ``--engage rc-switch``: streams up, switch low, then high.

    The fake shows a mode only when the test says so (``follow_modes=False``)."""
    f = await start(
        engage="rc-switch", output="actuator", custom_mode=PX4_MANUAL, armed=True,
        follow_modes=False,
    )  # fmt: skip
    await streams_requested(f)
    await started_up(f)
    f.fake.rc(1000)
    await settle()
    f.fake.rc(2000)
    return f


async def flights() -> AsyncIterator[Start]:
    """Factory: ``await start(autopilot=..., engage=..., **run_options)`` -> Flight.

    The run's engagement is timed on a :class:`StepClock` (``clock``, a new one
    unless given)."""
    flights: list[Flight] = []

    async def _start(
        *,
        autopilot: int = PX4,
        custom_mode: int = PX4_MANUAL,
        armed: bool = False,
        results: dict[int, Any] | None = None,
        params: dict[str, float | None] | None = None,
        heartbeat: bool = True,
        position: bool = True,
        follow_modes: bool = True,
        clock: StepClock | None = None,
        **opts: Any,
    ) -> Flight:
        ours, theirs = MemoryTransport.pair()
        fake = await FakeAutopilot(
            theirs,
            autopilot=autopilot,
            custom_mode=custom_mode,
            armed=armed,
            results=results,
            params=params,
            heartbeat_period_s=0.2 if heartbeat else 3600.0,
            position=position,
            follow_modes=follow_modes,
        ).open()
        opts.setdefault("failsafe", LOOSE)
        opts.setdefault("controller", CONTROLLER)
        options = RunOptions(connect="memory", profile=PROFILE, **opts)
        companion = Companion(options, transport=ours)
        clock = clock or StepClock()
        companion.engagement.clock = clock
        companion.engagement.sleep = clock.sleep
        task = asyncio.get_running_loop().create_task(companion.run(), name="companion")
        flight = Flight(companion, fake, task, clock)
        flights.append(flight)
        await fake.wait_until(lambda: ours.is_open, 1.0)
        if heartbeat:
            fake.heartbeat()
            if position:
                fake.local_position()
        return flight

    yield _start
    for f in flights:
        if not f.task.done():
            f.companion._stop.set()
            with contextlib.suppress(asyncio.TimeoutError, asyncio.CancelledError):
                await asyncio.wait_for(f.task, 2.0)
        await f.fake.close()
    gc.unfreeze()  # run() freezes what start-up built; do not pile it up across tests
