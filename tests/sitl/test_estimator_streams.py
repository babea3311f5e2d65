"""ATTITUDE, ATTITUDE_QUATERNION and LOCAL_POSITION_NED carry the estimator's output.

The SITL runs in a thread (lockstep clock: outside OFFBOARD it never waits, so
a few simulated seconds take a fraction of one) and sends to a real UDP socket;
pymavlink parses what arrives. The truth is the run's own log. On the ground
the vehicle sits still at the origin, level and heading north, so every
difference from it is the estimator's error, whatever its lag.
"""

from __future__ import annotations

import dataclasses
import math
import socket
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.control.quaternion import quat_conj, quat_log, quat_mul
from companion.profile import VehicleProfile, load_profile
from sitl.estimator_model import EKF_GPS, EstimatorSpec
from sitl.flight_log import read_log
from sitl.mavlink_link import parse_endpoint
from sitl.runner import RunConfig, Runner
from tests.sitl.udp_client import Client, mavlink2

ROOT = Path(__file__).resolve().parents[2]

FAST = dataclasses.replace(
    EKF_GPS,
    attitude_tau_s=(0.01, 0.01, 0.01),
    attitude_bias_sigma_rad=(0.0, 0.0, 0.0),
    position_tau_s=(0.01, 0.01, 0.01),
    position_smoothing_s=(0.0, 0.0, 0.0),
    velocity_tau_s=(0.01, 0.01, 0.01),
)
"""EKF_GPS's sigmas with errors that forget within a message period (no smoothing,
no bias): a few seconds of streams are many independent draws of each error."""


@pytest.fixture(scope="module")
def profile() -> VehicleProfile:
    return load_profile(ROOT / "vehicle_profiles" / "f450.yaml")


@dataclasses.dataclass
class Flight:
    msgs: list[Any]
    log: dict[str, np.ndarray]
    t_start_s: float
    """When the pilot started (arming, with ``arm_after_s``), s."""

    def of(self, mtype: str) -> list[Any]:
        return [m for m in self.msgs if m.get_type() == mtype]


def fly(
    profile: VehicleProfile,
    tmp_path: Path,
    *,
    seed: int = 1,
    estimator: EstimatorSpec | None = EKF_GPS,
    autopilot: str = "px4",
    pilot: str | None = None,
    duration_s: float = 3.0,
    arm_after_s: float | None = None,
) -> Flight:
    """Run the SITL for ``duration_s`` simulated seconds; what a client received.

    ``arm_after_s``: the pilot starts at arming (``pilot_from_arm``). The client's
    arm command reaches the SITL's socket before the SITL reads it at the first step
    at or after that simulated time (the SITL's thread sends it and waits for it to
    arrive), so arming falls on that step however loaded the machine is.
    """
    client = Client()
    try:
        # Room for every datagram should the reader fall behind the loop.
        client.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        log_path = tmp_path / f"sitl-{seed}-{autopilot}-{estimator is None}.npz"
        config = RunConfig(
            mavlink=parse_endpoint(f"udpout:127.0.0.1:{client.port}"),
            clock="lockstep",
            seed=seed,
            duration_s=duration_s,
            pilot=pilot,
            log_path=log_path,
            estimator=estimator,
            autopilot=autopilot,  # type: ignore[arg-type]
            pilot_from_arm=arm_after_s is not None,
            auto_arm=arm_after_s is None,
        )
        runner = Runner(profile, config, profile_name="f450")
        if arm_after_s is not None:
            _arm_at(runner, client, arm_after_s)
        summaries = []
        thread = threading.Thread(target=lambda: summaries.append(runner.run()))
        thread.start()
        msgs: list[Any] = []
        client.sock.settimeout(0.05)
        while True:
            try:
                data = client.sock.recv(65536)
            except TimeoutError:
                if not thread.is_alive():
                    break
                continue
            msgs += client.parser.parse_buffer(data) or []
        thread.join()
    finally:
        client.close()
    assert summaries and summaries[0].status == "completed"
    log = read_log(log_path)
    starts = [e["t_s"] for e in log.events if e["kind"] == "pilot_start"]
    t_start_s = starts[0] if starts else 0.0
    return Flight([m for m in msgs if m.get_type() != "BAD_DATA"], log.arrays, t_start_s)


def _arm_at(runner: Runner, client: Client, t_s: float) -> None:
    """Have ``client`` command arming so that the SITL reads it at its first step at or
    after ``t_s`` (simulated): the command is sent from the SITL's own thread just
    before that step's read, which waits until it is on the socket."""
    face = runner.face
    poll = face.poll
    sent = False

    def poll_after_arming(now_s: float, *, defer_commands: bool = False) -> int:
        nonlocal sent
        if not sent and now_s >= t_s - 1e-9:
            client.mav.command_long_send(
                1, 1, mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0
            )
            client.send_last(face)
            sent = True
        return poll(now_s, defer_commands=defer_commands)

    face.poll = poll_after_arming  # type: ignore[method-assign]


def rotation_error(msg: Any) -> tuple[float, float, float]:
    """The rotation from the truth (identity on the ground) to the streamed attitude."""
    return quat_log(quat_mul((msg.q1, msg.q2, msg.q3, msg.q4), quat_conj((1.0, 0.0, 0.0, 0.0))))


def test_the_vehicle_on_the_ground_is_still_at_the_origin(
    profile: VehicleProfile, tmp_path: Path
) -> None:
    """What the other tests take as the truth."""
    log = fly(profile, tmp_path, duration_s=1.0).log
    assert np.all(log["pos_ned_m"] == 0.0) and np.all(log["vel_ned_m_s"] == 0.0)
    assert np.all(log["q_wxyz"] == (1.0, 0.0, 0.0, 0.0))


def test_local_position_errors_are_the_specs_size(profile: VehicleProfile, tmp_path: Path) -> None:
    flight = fly(profile, tmp_path, estimator=FAST, duration_s=4.0)
    lp = flight.of("LOCAL_POSITION_NED")
    assert len(lp) >= 35  # PX4's 10 Hz
    pos = np.array([(m.x, m.y, m.z) for m in lp])  # the truth is 0
    vel = np.array([(m.vx, m.vy, m.vz) for m in lp])
    for err, sigma in ((pos, FAST.position_sigma_m), (vel, FAST.velocity_sigma_m_s)):
        rms = np.sqrt(np.mean(err**2, axis=0))
        assert np.all(rms > 0.6 * np.array(sigma)), (rms, sigma)
        assert np.all(rms < 1.5 * np.array(sigma)), (rms, sigma)
        assert np.all(np.abs(np.mean(err, axis=0)) < 0.6 * np.array(sigma))


def test_with_ekf_gps_position_errors_wander_within_a_few_sigma(
    profile: VehicleProfile, tmp_path: Path
) -> None:
    """EKF_GPS's errors are slow (their driver's tau 3.5-6.5 s, smoothed over 1-1.5 s):
    bounded, and they drift, they do not jump."""
    lp = fly(profile, tmp_path, seed=2, duration_s=4.0).of("LOCAL_POSITION_NED")
    pos = np.array([(m.x, m.y, m.z) for m in lp])
    sigma = np.array(EKF_GPS.position_sigma_m)
    assert np.all(np.abs(pos) < 5.0 * sigma)
    assert np.all(np.abs(pos).max(axis=0) > 0.02 * sigma)  # not the truth
    # 0.1 s apart: even an unsmoothed driver with tau 3.5 s steps by
    # sqrt(2 (1 - e^-0.1/3.5)) = 0.24 sigma; the smoothing makes it less.
    steps = np.diff(pos[1:], axis=0)  # from the second: the first is 70 ms before the next
    assert np.all(np.sqrt(np.mean(steps**2, axis=0)) < 0.5 * sigma)


@pytest.mark.parametrize(("autopilot", "first_ms"), [("px4", 30), ("ardupilot", 250)])
def test_no_local_position_before_the_first_estimate(
    profile: VehicleProfile, tmp_path: Path, autopilot: str, first_ms: int
) -> None:
    """The position estimate comes 30 ms late: PX4's stream, due at 0, goes out
    when it arrives (its slot held); ArduPilot's slot at 0 passes (4 Hz: 250 ms)."""
    flight = fly(profile, tmp_path, autopilot=autopilot, duration_s=0.6)
    lp = flight.of("LOCAL_POSITION_NED")
    assert lp and lp[0].time_boot_ms == first_ms
    truth = fly(profile, tmp_path, autopilot=autopilot, duration_s=0.6, estimator=None)
    assert truth.of("LOCAL_POSITION_NED")[0].time_boot_ms == 0  # --true-state: as before


def test_attitude_quaternion_is_a_unit_quaternion_near_the_truth(
    profile: VehicleProfile, tmp_path: Path
) -> None:
    flight = fly(profile, tmp_path, duration_s=3.0)
    aq = flight.of("ATTITUDE_QUATERNION")
    assert len(aq) >= 145  # 50 Hz
    # Identity until the first estimate (10 ms late), then the estimate.
    assert aq[0].time_boot_ms == 0 and (aq[0].q1, aq[0].q2, aq[0].q3, aq[0].q4) == (1, 0, 0, 0)
    est = aq[1:]
    norms = [math.sqrt(m.q1**2 + m.q2**2 + m.q3**2 + m.q4**2) for m in est]
    assert np.allclose(norms, 1.0, atol=1e-6)  # float32 on the wire
    err = np.array([rotation_error(m) for m in est])
    sigma = np.array(EKF_GPS.attitude_sigma_rad)
    assert np.all(np.abs(err) < 5.0 * sigma)
    assert np.all(np.abs(err).max(axis=0) > 0.02 * sigma)  # not the truth
    # The ATTITUDE message carries the same estimate as Euler angles.
    att = {m.time_boot_ms: m for m in flight.of("ATTITUDE")}
    for m in est:
        a = att[m.time_boot_ms]
        w, x, y, z = m.q1, m.q2, m.q3, m.q4
        roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
        yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
        assert a.roll == pytest.approx(roll, abs=1e-6) and a.yaw == pytest.approx(yaw, abs=1e-6)


def test_attitude_errors_are_the_specs_size(profile: VehicleProfile, tmp_path: Path) -> None:
    aq = fly(profile, tmp_path, estimator=FAST, duration_s=3.0).of("ATTITUDE_QUATERNION")[1:]
    err = np.array([rotation_error(m) for m in aq])
    sigma = np.array(FAST.attitude_sigma_rad)  # about north, east (tilt), down (heading)
    rms = np.sqrt(np.mean(err**2, axis=0))
    assert np.all(rms > 0.7 * sigma) and np.all(rms < 1.4 * sigma), (np.degrees(rms), sigma)


def estimates(flight: Flight) -> list[tuple[Any, ...]]:
    return [
        (m.get_type(), m.time_boot_ms, m.q1, m.q2, m.q3, m.q4)
        if m.get_type() == "ATTITUDE_QUATERNION"
        else (m.get_type(), m.time_boot_ms, m.x, m.y, m.z, m.vx, m.vy, m.vz)
        for m in flight.msgs
        if m.get_type() in ("ATTITUDE_QUATERNION", "LOCAL_POSITION_NED")
    ]


def test_one_seed_streams_the_same_estimates_another_seed_others(
    profile: VehicleProfile, tmp_path: Path
) -> None:
    a, b, c = (estimates(fly(profile, tmp_path, seed=s, duration_s=1.0)) for s in (7, 7, 8))
    assert len(a) > 50
    assert a == b
    assert len(a) == len(c)
    differ = [x != y for x, y in zip(a[1:], c[1:], strict=True)]  # the first is the identity
    assert all(differ)


def test_after_arming_the_estimates_do_not_depend_on_when(
    profile: VehicleProfile, tmp_path: Path
) -> None:
    """With the pilot started at arming, the estimator starts again from the seed
    then (as the IMU, wind and pilot do): what it streams after arming is the same
    whenever the vehicle was armed, from the first message on."""
    flights = [
        fly(profile, tmp_path / str(i), seed=9, pilot="step-roll", duration_s=1.0,
            arm_after_s=arm_s)
        for i, arm_s in enumerate((0.2, 0.5))
    ]  # fmt: skip
    after = []
    for f in flights:
        t0_ms = round(f.t_start_s * 1e3)
        after.append([(m[0], m[1] - t0_ms, *m[2:]) for m in estimates(f) if m[1] >= t0_ms])
    # Armed at the steps asked for, whatever the machine's load.
    assert [f.t_start_s for f in flights] == pytest.approx([0.2, 0.5], abs=0.0015)
    assert len(after[0]) > 50
    assert after[0] == after[1]
    # The first go out at arming (the position, then the attitude, ahead of the
    # step's IMU sample), and are the new model's, not the last of the one before.
    firsts = [m for m in after[0] if m[1] == 0]
    assert [m[0] for m in firsts] == ["LOCAL_POSITION_NED", "ATTITUDE_QUATERNION"]
    before = [m for m in estimates(flights[0]) if m[1] < round(flights[0].t_start_s * 1e3)]
    for first in firsts:
        last = [b for b in before if b[0] == first[0]][-1]
        assert first[2:] != last[2:], first[0]


IMU_MESSAGES = ("HIGHRES_IMU", "RAW_IMU", "SCALED_IMU")


def body_rates(flight: Flight) -> list[tuple[Any, ...]]:
    """Every IMU message whole, and the rates of ATTITUDE / ATTITUDE_QUATERNION."""
    out: list[tuple[Any, ...]] = []
    for m in flight.msgs:
        mtype = m.get_type()
        if mtype in IMU_MESSAGES:
            out.append((mtype, *m.to_dict().values()))
        elif mtype in ("ATTITUDE", "ATTITUDE_QUATERNION"):
            out.append((mtype, m.time_boot_ms, m.rollspeed, m.pitchspeed, m.yawspeed))
    return out


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_the_estimator_changes_no_body_rate_and_no_motor(
    profile: VehicleProfile, tmp_path: Path, autopilot: str
) -> None:
    """A flight (the pilot takes off and rolls, in acro) is the same bit for bit with the
    estimator as with the true state: the gyro streams, the plant, the motors."""
    est, truth = (
        fly(profile, tmp_path, seed=5, autopilot=autopilot, pilot="step-roll",
            duration_s=5.6, estimator=spec)
        for spec in (EKF_GPS, None)
    )  # fmt: skip
    assert np.ptp(truth.log["rate_frd_rad_s"][:, 0]) > 0.5  # it flew
    rates = body_rates(est)
    assert len(rates) > 40
    assert rates == body_rates(truth)
    for key, col in truth.log.items():
        assert np.array_equal(est.log[key], col), key
    # ... while the attitude each streams differs.
    att = [(m.time_boot_ms, m.roll) for m in est.of("ATTITUDE")]
    assert att[1:] != [(m.time_boot_ms, m.roll) for m in truth.of("ATTITUDE")][1:]
