"""The lockstep clock ends each wait on the answer to the sample it gave, not on
a late answer to an older one.

Seen in CI: a companion that fell behind before OFFBOARD (the clock does not
wait there, and runs as fast as it can) still had older samples to answer when
OFFBOARD began; counting setpoints, the clock took those answers for the
current sample's, so the autopilot flew a setpoint some samples old, by an
amount that depended on the wall clock. Reproduced with a companion stopped
for a moment before OFFBOARD (``SIGSTOP``); here with a client that sleeps.
"""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import common as mavlink

from companion.profile import load_profile
from sitl.answers import ECHO_RUN, AnswerJudge
from sitl.mavlink_link import parse_endpoint
from sitl.runner import RunConfig, Runner

ROOT = Path(__file__).resolve().parents[2]
US = 1e-6


def code(time_usec: int) -> float:
    """What the client puts in the roll control: its sample's time, recognisably."""
    return (time_usec // 1000 % 1000) * 1e-5


# ------------------------------------------------------------------ the judge


def test_a_client_stamping_samples_times_is_recognised_and_its_late_answers_not_counted() -> None:
    judge = AnswerJudge()
    for k in range(40):
        judge.sample_given(k * 0.004)
    # Answers to samples 0..ECHO_RUN: consecutive, so the client stamps sample times.
    for k in range(ECHO_RUN + 1):
        assert judge.counts(round(k * 0.004 / US), US)
    assert judge.echoes_stamps
    judge.await_from(39 * 0.004)
    late = [judge.counts(round(k * 0.004 / US), US) for k in range(ECHO_RUN + 1, 39)]
    assert not any(late) and judge.stale == len(late)
    assert judge.counts(round(39 * 0.004 / US), US)  # the awaited sample's answer


def test_a_client_stamping_its_own_clock_is_counted_as_before() -> None:
    judge = AnswerJudge()
    for k in range(2000):
        judge.sample_given(k * 0.001)  # every millisecond is a sample's
    judge.await_from(1.999)
    # MAVSDK's time_boot_ms: its own uptime, 20 ms apart, behind the simulation.
    assert all(judge.counts(ms, 1e-3) for ms in range(100, 1000, 20))
    assert not judge.echoes_stamps and judge.stale == 0
    # A time never given forgets what was learnt.
    for k in range(ECHO_RUN + 1):
        judge.counts(1000 + k, 1e-3)
    assert judge.echoes_stamps
    assert judge.counts(5000, 1e-3) and not judge.echoes_stamps


def test_a_lockstep_timeout_makes_the_judge_count_everything_again() -> None:
    judge = AnswerJudge()
    for k in range(20):
        judge.sample_given(k * 0.004)
    for k in range(ECHO_RUN + 1):
        judge.counts(round(k * 0.004 / US), US)
    judge.await_from(19 * 0.004)
    assert not judge.counts(round(10 * 0.004 / US), US)
    judge.forget()
    assert judge.counts(round(11 * 0.004 / US), US)


# ------------------------------------------------------- a SITL and a client


def _client_and_lockstep_sitl(**config: Any) -> tuple[socket.socket, Runner]:
    """A UDP client and a lockstep SITL (1 s, MANUAL, disarmed, unless ``config``
    says otherwise) streaming HIGHRES_IMU to it at 250 Hz."""
    client = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    client.bind(("127.0.0.1", 0))
    client.settimeout(0.5)
    port = client.getsockname()[1]
    profile = load_profile(ROOT / "vehicle_profiles" / "f450.yaml")
    settings: dict[str, Any] = {
        "mavlink": parse_endpoint(f"udpout:127.0.0.1:{port}"),
        "pilot": "paper-acro",
        "clock": "lockstep",
        "seed": 1,
        "duration_s": 1.0,
        "initial_mode": "MANUAL",
        "auto_arm": False,
        "log_path": None,
    }
    cfg = RunConfig(**{**settings, **config})
    runner = Runner(profile, cfg, profile_name="f450")
    runner.face.streams.set_interval(mavlink.MAVLINK_MSG_ID_HIGHRES_IMU, 4000.0, t_s=0.0)
    return client, runner


def _imu_received(client: socket.socket, mav: Any) -> list[tuple[Any, Any]]:
    """The HIGHRES_IMU messages in the client's next datagram, with its sender
    (none within the client's timeout: none)."""
    try:
        data, addr = client.recvfrom(4096)
    except TimeoutError:
        return []
    return [(m, addr) for m in mav.parse_buffer(data) or [] if m.get_type() == "HIGHRES_IMU"]


def test_the_first_offboard_steps_fly_their_own_samples_answers_after_a_client_stall() -> None:
    client, runner = _client_and_lockstep_sitl()
    ap = runner.autopilot
    offboard_step = 300  # t = 0.3 s: the client sleeps through it

    poll = runner.face.poll

    def poll_then_engage(t_s: float, *, defer_commands: bool = False) -> int:
        n = poll(t_s, defer_commands=defer_commands)
        if runner.quad.steps == offboard_step:
            assert ap.set_mode(t_s, 6) == 0  # type: ignore[attr-defined]  # OFFBOARD
            assert ap.arm(t_s) == 0
        return n

    runner.face.poll = poll_then_engage  # type: ignore[method-assign]
    flown: list[tuple[float, float]] = []  # (sample time, roll control flown)
    update = ap.update

    def recording_update(t_s: float, *args: object, **kwargs: object) -> tuple[float, ...]:
        motors = update(t_s, *args, **kwargs)  # type: ignore[arg-type]
        if ap.armed:
            flown.append((t_s, ap.last_torque_thrust[0]))
        return motors

    ap.update = recording_update  # type: ignore[method-assign]
    sitl = threading.Thread(target=runner.run, daemon=True)
    sitl.start()

    mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    slept = False
    answered = 0
    try:
        while sitl.is_alive():
            for msg, addr in _imu_received(client, mav):
                if not slept and msg.time_usec >= 100_000:
                    slept = True
                    time.sleep(0.3)  # the SITL runs on, OFFBOARD begins meanwhile
                sp = mavlink.MAVLink_set_actuator_control_target_message(
                    msg.time_usec, 0, 1, 1, [code(msg.time_usec), 0, 0, 0, 0, 0, 0, 0]
                )
                client.sendto(sp.pack(mav), addr)
                answered += 1
    finally:
        runner.stop.set()
        sitl.join(10)
        client.close()

    assert slept and answered > 100
    assert runner.face.answers.echoes_stamps
    assert runner.face.stale_setpoints > 10  # the samples answered after the sleep
    # The autopilot's own IMU runs at 1 kHz: the steps that sent HIGHRES_IMU (250 Hz).
    sent = [(t, roll) for t, roll in flown if round(t / US) % 4000 == 0]
    assert len(sent) > 100
    wrong = [(t, roll) for t, roll in sent if roll != pytest.approx(code(round(t / US)), abs=1e-9)]
    assert not wrong, f"{len(wrong)} of {len(sent)} samples flew another's answer: {wrong[:3]}"


@pytest.mark.parametrize("how", ["mode", "land"])
def test_a_hand_back_ends_the_lockstep_wait_without_a_timeout(how: str) -> None:
    """A client handing back answers no more samples: its mode or land command,
    kept for the next step, ends the wait there rather than the timeout (seen
    costing every lockstep flight its timeout at its end)."""
    # A wait that times out fails the test's bound.
    client, runner = _client_and_lockstep_sitl(lockstep_timeout_s=60.0)
    ap = runner.autopilot
    poll = runner.face.poll

    engaged: list[float] = []

    def poll_then_engage(t_s: float, *, defer_commands: bool = False) -> int:
        n = poll(t_s, defer_commands=defer_commands)
        # OFFBOARD once the client's setpoints stream (PX4 wants them first), once.
        ready = runner.quad.steps >= 100 and not defer_commands and not engaged
        if ready and ap.set_mode(t_s, 6) == 0:  # type: ignore[attr-defined]  # OFFBOARD
            assert ap.arm(t_s) == 0
            engaged.append(t_s)
        return n

    runner.face.poll = poll_then_engage  # type: ignore[method-assign]
    summary: list[object] = []
    sitl = threading.Thread(target=lambda: summary.append(runner.run()), daemon=True)
    mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    answered = 0
    handed_back_at: float | None = None
    try:
        sitl.start()
        while sitl.is_alive() and handed_back_at is None:
            for msg, addr in _imu_received(client, mav):
                if handed_back_at is not None:
                    continue
                if not ap.external_control or answered < 50:
                    sp = mavlink.MAVLink_set_actuator_control_target_message(
                        msg.time_usec, 0, 1, 1, [0.0] * 3 + [0.5] + [0.0] * 4
                    )
                    client.sendto(sp.pack(mav), addr)
                    answered += 1
                    continue
                # The sample the clock now waits on goes unanswered: hand back.
                if how == "mode":  # POSCTL
                    cmd = mavlink.MAVLink_command_long_message(
                        1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 3, 0, 0, 0, 0, 0
                    )
                else:
                    cmd = mavlink.MAVLink_command_long_message(
                        1, 1, mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, 0, 0, 0, 0, 0
                    )
                client.sendto(cmd.pack(mav), addr)
                handed_back_at = time.monotonic()
        sitl.join(10)
        finished_alone = not sitl.is_alive()
    finally:
        runner.stop.set()
        sitl.join(10)
        client.close()

    assert handed_back_at is not None and finished_alone
    assert summary, "the SITL did not finish"
    run = summary[0]
    assert run.lockstep_timeouts == 0  # type: ignore[attr-defined]
    assert not ap.external_control
    assert run.sim_time_s == pytest.approx(1.0, abs=0.01)  # type: ignore[attr-defined]


def test_a_client_streaming_setpoints_outside_offboard_is_not_outrun() -> None:
    """Run free, the clock overfilled a streaming client's socket: the datagrams the
    kernel dropped left jumps in IMU time the wall did not take, and the companion
    held the sample after such a jump back (a possibly corrupt stamp) while the
    first wait in OFFBOARD waited for its answer (CI: a 0.5 s lockstep timeout at
    engagement). While a client streams setpoints the autopilot does not fly yet,
    the clock keeps to the wall's; when they stop, it runs free again."""
    client, runner = _client_and_lockstep_sitl(duration_s=3.0)
    sitl = threading.Thread(target=runner.run, daemon=True)
    mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    clocks: list[tuple[float, float]] = []  # (wall, simulation time), while streaming
    answered = 0
    try:
        sitl.start()
        wall0 = time.monotonic()
        while sitl.is_alive() and len(clocks) < 2:
            for msg, addr in _imu_received(client, mav):
                sp = mavlink.MAVLink_set_actuator_control_target_message(
                    msg.time_usec, 0, 1, 1, [0.0] * 8
                )
                client.sendto(sp.pack(mav), addr)
                answered += 1
            since = time.monotonic() - wall0
            if since >= (0.2, 0.7)[len(clocks)]:
                clocks.append((time.monotonic(), runner.quad.t_s))
        # Silent now: the clock runs free to the end of the run.
        sitl.join(10)
        finished = not sitl.is_alive()
    finally:
        runner.stop.set()
        sitl.join(10)
        client.close()

    assert finished and answered > 50 and len(clocks) == 2
    (w0, s0), (w1, s1) = clocks
    # Simulation time kept to the wall's (it may only fall behind), where it ran
    # several times faster before.
    assert s1 - s0 <= (w1 - w0) + 0.02, (s1 - s0, w1 - w0)
    assert runner.quad.t_s == pytest.approx(3.0, abs=0.01)
