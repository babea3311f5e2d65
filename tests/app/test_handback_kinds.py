"""Every failsafe kind ends in the safe mode the vehicle can fly, on both stacks.

For each kind (brought about as it happens in flight: the IMU stops, the gyro
reads NaN, the rates leave the envelope, RC stops, the autopilot leaves
OFFBOARD, a signal, the run's end), with and without the pilot's radio, on PX4
and ArduPilot: the mode asked, and that it is asked at once: on the engagement's
own clock (``Flight.clock``, tests/app/flight.py), no wait between the failsafe
and the mode asked but the one for the autopilot's next SYS_STATUS where it took
over by itself. Without a radio the flight is a reference file with its own
collective (it needs no RC).
"""

from __future__ import annotations

import signal
from dataclasses import replace
from typing import Any

import pytest

from companion import engagement
from companion.reference import ReferenceScript
from tests.app.fakes import APM_GUIDED_NOGPS, CMD_ARM, CMD_DO_SET_MODE, PX4_OFFBOARD
from tests.app.flight import (
    ACCEPTED,
    ARDUPILOT,
    LOOSE,
    MSG_ATTITUDE,
    MSG_HIGHRES_IMU,
    PX4,
    Flight,
    Start,
    StepClock,
    streams_requested,
)

HOVER = ReferenceScript(t_s=(0.0,), rates_rad_s=((0.0, 0.0, 0.0),), thrust=(0.5,))
FS = replace(LOOSE, stale_imu_s=0.2, rc_timeout_s=0.3, hand_back_watch_s=0.3)
PX4_MANUAL_MODE = 1 << 16
APM_STABILIZE_MODE = 0

# DO_SET_MODE (param2, param3)
POSCTL, HOLD = (3.0, 0.0), (4.0, 3.0)
ALT_HOLD, LOITER = (2.0, 0.0), (5.0, 0.0)

KINDS = ("stale_imu", "invalid_imu", "envelope", "rc_lost", "took_over", "signal", "run_end")
# (stack, radio, kind): every kind on both stacks with and without a radio, but
# RC loss, which needs a radio to lose.
CASES = [
    pytest.param(stack, radio, kind, id=f"{name}-{'rc' if radio else 'no-rc'}-{kind}")
    for stack, name in ((PX4, "px4"), (ARDUPILOT, "ardupilot"))
    for radio in (True, False)
    for kind in KINDS
    if radio or kind != "rc_lost"
]


class Asked:
    """The fake's DO_SET_MODE answer: ACCEPTED, each asked kept with its time on
    ``clock`` (the engagement's: give it to ``start``)."""

    def __init__(self) -> None:
        self.clock = StepClock()
        self.modes: list[tuple[float, tuple[float, float]]] = []

    def __call__(self, m: Any) -> int:
        self.modes.append((self.clock(), (m.param2, m.param3)))
        return int(ACCEPTED)


def expected(stack: int, kind: str, radio: bool) -> tuple[float, float] | None:
    """The mode the companion asks for; None: it keeps the autopilot's own."""
    manual, hold = (POSCTL, HOLD) if stack == PX4 else (ALT_HOLD, LOITER)
    if kind == "took_over":
        return None if radio else hold  # the pilot's mode with RC; nobody flies it without
    return manual if radio and kind != "rc_lost" else hold


@pytest.mark.parametrize(("stack", "radio", "kind"), CASES)
async def test_each_failsafe_kind_hands_back_to_a_mode_the_vehicle_can_fly(
    start: Start, stack: int, radio: bool, kind: str
) -> None:
    asked = Asked()
    px4 = stack == PX4
    f = await start(
        autopilot=stack,
        custom_mode=PX4_MANUAL_MODE if px4 else APM_STABILIZE_MODE,
        engage="auto",
        output="actuator" if px4 else "rates",
        params=None if px4 else {"GUID_OPTIONS": 8.0},
        failsafe=FS,
        reference=None if radio else HOVER,
        results={CMD_DO_SET_MODE: asked},
        clock=asked.clock,
    )
    await engage(f, px4=px4, radio=radio)
    n_engage = len(asked.modes)

    t0 = f.clock()  # engaged: nothing waits on the engagement's clock until the failsafe
    fed_s = await bring_about(f, kind, px4=px4, radio=radio)
    want_exit = 0 if kind in ("signal", "run_end") else 3
    assert await f.finish(timeout_s=3.0) == want_exit
    hand_back = asked.modes[n_engage:]
    want = expected(stack, kind, radio)
    if want is None:
        assert hand_back == []
        assert f.details("handed_back")[-1].endswith("kept (the autopilot's mode)")
        return
    assert [m for _, m in hand_back] == [want], (kind, f.details("handed_back"))
    assert hand_back[0][0] - t0 <= wait_before_asking_s(kind)
    if kind in IN_SAMPLE_TIME:  # the failsafe itself, judged on the samples: that soon
        # (give or take the few samples sent before the companion had read the last)
        assert fed_s <= IN_SAMPLE_TIME[kind] + 5 * (0.004 if px4 else 0.003), fed_s
    assert f.details("handed_back")[-1].endswith("accepted")
    assert len(f.details("safe_mode_held")) == 1


IN_SAMPLE_TIME = {"invalid_imu": FS.invalid_imu_s, "envelope": FS.envelope_time_s}
"""The failsafes judged on the samples' own time: their bound, s of samples."""


def wait_before_asking_s(kind: str) -> float:
    """How long the hand-back may wait, on the engagement's clock, before it asks
    for a mode: not at all (it starts in the failsafe's own call), but where the
    autopilot took over by itself, for its next SYS_STATUS (what failed: its RC
    receiver?), polled every 10 ms."""
    return engagement._SYS_STATUS_WAIT_S + 0.01 if kind == "took_over" else 0.0


async def engage(f: Flight, *, px4: bool, radio: bool) -> None:
    await streams_requested(f, MSG_HIGHRES_IMU if px4 else MSG_ATTITUDE)

    def feed() -> None:
        sample(f, px4)
        if radio:
            f.fake.rc(1000)

    await f.feed_until(lambda: f.fake.commands(CMD_ARM), send=feed, what="ARM")
    f.fake.set_state(PX4_OFFBOARD if px4 else APM_GUIDED_NOGPS, armed=True)
    await f.feed_until(lambda: f.companion.engaged, send=feed, what="engaged")


def sample(f: Flight, px4: bool, gyro: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
    if px4:
        f.imu(gyro)
    else:
        f.att(gyro)


async def bring_about(f: Flight, kind: str, *, px4: bool, radio: bool) -> float:
    """Bring ``kind`` about, then feed the run to its end; how long the samples fed
    until the failsafe span, s (their own time)."""

    def now_s() -> float:
        return f.t_us * 1e-6 if px4 else f.t_ms * 1e-3

    t_fault = now_s()

    def feed(gyro: tuple[float, float, float] = (0.0, 0.0, 0.0), rc: bool = radio) -> None:
        sample(f, px4, gyro)
        if rc:
            f.fake.rc(1000)

    def failed() -> bool:
        return f.task.done() or any(k.startswith("failsafe") for k in f.kinds())

    if kind == "stale_imu":
        await f.feed_until(failed, send=lambda: f.fake.rc(1000) if radio else None, what=kind)
    elif kind == "invalid_imu":
        nan = float("nan")
        await f.feed_until(failed, send=lambda: feed((nan, nan, nan)), what=kind)
    elif kind == "envelope":
        await f.feed_until(failed, send=lambda: feed((25.0, 0.0, 0.0)), what=kind)  # 1432 deg/s
    elif kind == "rc_lost":
        await f.feed_until(failed, send=lambda: feed(rc=False), what=kind)
    elif kind == "took_over":
        f.fake.set_state(PX4_MANUAL_MODE if px4 else APM_STABILIZE_MODE, armed=True)
        await f.feed_until(failed, send=feed, what=kind)
    elif kind == "signal":
        f.companion._on_signal(signal.SIGTERM)
    else:
        f.companion._stop.set()
    if kind not in ("signal", "run_end"):
        assert [k for k in f.kinds() if k.startswith("failsafe")] == [
            "failsafe_autopilot_took_over" if kind == "took_over" else f"failsafe_{kind}"
        ]
    fed_s = now_s() - t_fault
    # Samples (and RC, with a radio) go on during the hand-back, as in flight.
    await f.feed_until(f.task.done, send=feed, timeout_s=2.5, what="the run's end")
    return fed_s
