"""The companion against the real PX4 v1.16 SITL (SIH quadrotor), over MAVLink on UDP.

PX4's SIH has no radio: the pilot is a ground station's joystick (MANUAL_CONTROL,
``aux1`` the engage switch), which PX4 streams back to the companion. The tests
run in order on one booted PX4 (the cold start has its own).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sitl.lab.realstack.flights import Session
from sitl.pilot.factory import make_pilot
from tests.realstack.conftest import ROOT, boot
from tests.realstack.scenarios import (
    AXES,
    FAILSAFE_KINDS,
    check_failsafe_case,
    flick_the_switch_while_preflight_watches,
    fly_failsafe_case,
    fly_rates_pair,
    fly_safe_mode_case,
    handback_cases,
    median_of_pairs,
    params_set,
    preflight,
    preflight_document,
    preflight_with,
    real_time_factor,
    send_a_signing_key,
)

PROFILE = str(ROOT / "vehicle_profiles" / "px4_sih_quadx.yaml")
RATES = ("--output", "rates", "--profile", PROFILE)
PX4_POSCTL = 3 << 16
PX4_LOITER = (4 << 16) | (3 << 24)


@pytest.fixture(scope="module")
def px4(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Session]:
    session = boot("px4", tmp_path_factory.mktemp("px4"))
    yield session
    session.close()


def test_preflight_is_true_of_the_real_px4(px4: Session, figures: list[dict[str, Any]]) -> None:
    g = px4.gcs
    assert g is not None
    flick_the_switch_while_preflight_watches(px4)
    doc = preflight_document(px4, RATES, "--watch-s", "6")
    # Its watch: the 6 s before it closed the link and exited.
    now = g.clock()
    speed = real_time_factor(px4, now - 6.5, now - 0.5)
    checks = {c["name"]: c for c in doc["checks"]}
    imu = checks["IMU rate"]
    figures.append(
        {
            "test": "px4 preflight",
            **{k: v["status"] for k, v in checks.items()},
            "IMU rate detail": imu["detail"],
            "px4 real-time factor": round(speed, 3),
            "autopilot_clock_ratio": doc["autopilot_clock_ratio"],
        }
    )
    failed = {k: v for k, v in checks.items() if v["status"] == "fail"}
    assert not failed, failed
    # Every figure it quotes is the stack's own.
    for name in ("COM_OF_LOSS_T", "COM_RC_LOSS_T"):
        value = g.param_get(name)
        assert value is not None
        assert checks[name]["detail"].startswith(f"{value[0]:g} s"), checks[name]
    for name in ("NAV_RCL_ACT", "COM_OBL_RC_ACT", "COM_RCL_EXCEPT", "COM_RC_IN_MODE"):
        value = g.param_get(name)
        assert value is not None
        assert checks[name]["detail"].startswith(f"{int(value[0])}"), checks[name]
    gains = {n: g.param_get(n) for n in ("MC_ROLLRATE_K", "MC_ROLLRATE_P", "MC_PITCHRATE_K",
                                         "MC_PITCHRATE_P")}  # fmt: skip
    assert None not in gains.values(), gains
    assert checks["MC_ROLLRATE_K"]["detail"].startswith(
        ", ".join(f"{n} {v[0]:g}" for n, v in gains.items() if v is not None)
    ), checks["MC_ROLLRATE_K"]
    assert checks["MC_ROLLRATE_K"]["detail"].endswith(
        "--rates-law-axes auto: the law corrects roll, pitch, yaw"
    ), checks["MC_ROLLRATE_K"]
    assert checks["link"]["detail"].startswith("PX4 1.16")
    assert checks["landed state"]["detail"] == "on ground"
    assert checks["RC"]["detail"].startswith("no radio: the pilot's joystick")
    assert checks["engage switch"]["status"] == "pass", checks["engage switch"]
    # The check measures the stream on the wall clock, as the loop would fly it. In
    # real time on a loaded machine PX4 runs behind the wall clock, its stream with
    # it: the check says so, in PX4's own time stamps, and warns below 95 % of the
    # rate asked. Where PX4 keeps real time, it passes.
    assert doc["autopilot_clock_ratio"] == pytest.approx(speed, abs=0.02), (imu, speed)
    if imu["status"] == "warn":
        stalled = doc["imu_longest_gap_ms"] > 40 or doc["imu_late"] > 0.01 * 250 * 6
        assert doc["imu_rate_hz"] < 0.95 * 250 or stalled, imu
    if speed > 0.97:
        assert imu["status"] == "pass", (imu, speed)
    assert checks["position"]["status"] == "pass"


BAD_PX4 = {
    "COM_OF_LOSS_T": 5.0,  # fail: holds a rate 5 s
    "COM_OBL_RC_ACT": 6.0,  # fail: Disarm on offboard loss
    "COM_RC_LOSS_T": 10.0,  # warn
    "NAV_RCL_ACT": 0.0,  # fail: nothing on RC loss
    "COM_RCL_EXCEPT": 4.0,  # warn: RC loss ignored in OFFBOARD
    "IMU_GYRO_RATEMAX": 100.0,  # warn: below the loop rate asked
    "MC_ROLLRATE_K": 3.0,  # warn: the law's roll correction no longer pays
}


def test_preflight_flags_each_badly_set_px4_parameter_with_its_fix(
    px4: Session, figures: list[dict[str, Any]]
) -> None:
    # The law asked on every axis: on a stiff loop preflight warns (auto would not ask).
    checks = preflight_with(px4, (*RATES, "--rates-law-axes", "roll,pitch,yaw"), BAD_PX4)
    got = {name: checks[name]["status"] for name in BAD_PX4}
    figures.append({"test": "px4 preflight, badly set", **got})
    assert got == {
        "COM_OF_LOSS_T": "fail", "COM_OBL_RC_ACT": "fail", "COM_RC_LOSS_T": "warn",
        "NAV_RCL_ACT": "fail", "COM_RCL_EXCEPT": "warn", "IMU_GYRO_RATEMAX": "warn",
        "MC_ROLLRATE_K": "warn",
    }  # fmt: skip
    for name in BAD_PX4:
        assert checks[name]["fix"], checks[name]


TIE_BAND = 1.05
"""MFC's MAE on an axis it ties on, at most this times pass-through's."""


def _fly_judged(px4: Session, figures: list[dict[str, Any]], test: str) -> dict[str, Any]:
    """The rates pair, and where MFC is beyond :data:`TIE_BAND` of pass-through on an
    axis, two more pairs, judged on each law's median of the three. PX4 runs in real
    time beside the companion, and one flight can stand apart (since the engaged
    edge was fixed, one MFC roll in ten: docs/research/realstack.md#engaged-edge;
    before it, a yaw of 21-22 against 28-29 deg/s, the scoring starting with PX4's
    1 Hz heartbeat). A law worse by more than the band is worse in the median of
    three too."""
    pairs = [fly_rates_pair(px4, RATES, seed=11)]
    figures.append({"test": test, **pairs[0]})
    if any(pairs[0]["mfc"][a] > TIE_BAND * pairs[0]["pass-through"][a] for a in AXES):
        for k in (2, 3):
            pairs.append(fly_rates_pair(px4, RATES, seed=11))
            figures.append({"test": f"{test}, pair {k}", **pairs[-1]})
    return median_of_pairs(pairs)


def test_mfc_flies_px4s_rate_loop_better_than_passing_the_pilots_rates(
    px4: Session, figures: list[dict[str, Any]]
) -> None:
    errs = _fly_judged(px4, figures, "px4 rates acro-mixed seed 11 MAE deg/s")
    assert not errs["mfc"]["failsafes"] and not errs["pass-through"]["failsafes"], errs
    # PX4's default gains: auto corrects every axis.
    chose = errs["mfc"]["rates_law_axes"]
    assert chose and all(c.endswith("1x / 1x the default gain on roll / pitch: the law "
                                    "corrects roll, pitch, yaw") for c in chose), chose  # fmt: skip
    # Roll and pitch, MFC is well ahead (0.80-0.93 of pass-through over six runs).
    # Yaw is at parity: 0.964-1.000 over the same six (two cores), the pass-through's
    # yaw alone 28.47-29.12 deg/s between runs, and one run in six tied to the
    # hundredth (28.47 and 28.47), so a 5 % tie band that catches a law flying worse,
    # not the spread (docs/research/realstack.md).
    for axis in ("roll", "pitch"):
        assert errs["mfc"][axis] < errs["pass-through"][axis], (axis, errs)
    assert errs["mfc"]["yaw"] <= TIE_BAND * errs["pass-through"]["yaw"], errs


def test_on_a_stiffer_rate_loop_the_default_flies_no_worse_than_pass_through(
    px4: Session, figures: list[dict[str, Any]]
) -> None:
    """PX4's rate gains tripled, as an owner tuning the vehicle might: roll through
    ``MC_ROLLRATE_K``, pitch through ``MC_PITCHRATE_P``. The full law tracks roll
    1.13-1.25x worse than pass-through there; the default (``--rates-law-axes
    auto``) reads the gains, corrects yaw alone, and flew roll and pitch at most
    1.03x pass-through and yaw at parity (docs/research/realstack.md#law-axes-auto).
    A 5 % tie band, as on yaw above."""
    stiff = {"MC_ROLLRATE_K": 3.0, "MC_PITCHRATE_P": 0.45}
    with params_set(px4, stiff):
        errs = _fly_judged(px4, figures, "px4 roll K 3, pitch P 0.45, auto, acro-mixed seed 11")
    chose = errs["mfc"]["rates_law_axes"]
    assert not errs["mfc"]["failsafes"] and not errs["pass-through"]["failsafes"], errs
    yaw_only = "the law corrects yaw; roll and pitch: the pilot's rate and the lead"
    assert chose and all(c.endswith(yaw_only) for c in chose), chose
    for axis in AXES:
        assert errs["mfc"][axis] <= TIE_BAND * errs["pass-through"][axis], (axis, errs)


def test_the_control_log_lines_up_with_px4s_ulog(
    px4: Session, figures: list[dict[str, Any]]
) -> None:
    """Every sample in the companion's control log (read with ``mcap``) is one of
    PX4's own ``sensor_combined`` samples in its ULog (read with ``pyulog``), at the
    same time to the microsecond (HIGHRES_IMU carries its stamp): the two logs share
    one time axis. The gyro agrees up to the EKF's gyro bias, which PX4 takes off
    what it streams (its HIGHRES_IMU stream subtracts ``estimator_sensor_bias``) and
    which barely moves in seconds. Shadow mode (``--engage none``) while PX4 hovers."""
    import json
    import time

    from mcap.reader import make_reader
    from pyulog import ULog

    px4.ensure_airborne(15.0)  # PX4 logs while armed
    run = px4.start_companion(*RATES, "--engage", "none", name="aligned")
    time.sleep(5.0)
    run.stop()
    time.sleep(1.0)  # its logger writes in blocks: the last seconds reach the file
    ulogs = sorted((px4.stack.workdir / "log").glob("*/*.ulg"), key=lambda q: q.stat().st_mtime)
    assert ulogs, "PX4 wrote no ULog"
    combined = ULog(str(ulogs[-1]), ["sensor_combined"]).get_dataset("sensor_combined").data
    at = {int(t): i for i, t in enumerate(combined["timestamp"])}
    ulog_gyro = np.stack([combined[f"gyro_rad[{k}]"] for k in range(3)], axis=1)
    diffs, shifted = [], []
    with (run.log_dir / "control.mcap").open("rb") as f:
        for _s, _c, msg in make_reader(f).iter_messages(topics=["/rates"]):
            i = at.get(msg.log_time // 1000)
            if i is None:
                continue  # after the end of what PX4's logger has written yet
            got = json.loads(msg.data)
            ours = [got[f"meas_{a}_rad_s"] for a in ("roll", "pitch", "yaw")]
            diffs.append(np.asarray(ours) - ulog_gyro[i])
            if i + 1 < len(ulog_gyro):
                shifted.append(np.asarray(ours) - ulog_gyro[i + 1])
    d, d1 = np.asarray(diffs), np.asarray(shifted)
    period_us = float(np.median(np.diff(np.asarray(combined["timestamp"]))))
    bias = np.median(d, axis=0) if len(d) else np.full(3, np.nan)
    residual = float(np.max(np.abs(d - bias))) if len(d) else math.inf
    # The same against the next sample of PX4's: what one IMU period off would show.
    off_by_one = float(np.max(np.abs(d1 - np.median(d1, axis=0)))) if len(d1) else 0.0
    figures.append({
        "test": "px4 log alignment", "matched_samples": len(d), "ulog_period_us": period_us,
        "gyro_bias_rad_s": [round(float(b), 5) for b in bias], "residual_rad_s": residual,
        "off_by_one_residual_rad_s": off_by_one,
    })  # fmt: skip
    # At least 2 s of samples found at the same microsecond, every one the same reading
    # once the bias is off (a sample's neighbours differ by the vehicle's motion).
    assert len(d) > 2.0 / (period_us * 1e-6), (len(d), period_us)
    assert np.all(np.abs(bias) < 0.02), bias
    # (Measured: 0.35-1.0e-3 rad/s, the bias drifting; one sample off, 0.35 rad/s.)
    assert residual < 5e-3 and off_by_one > 10 * residual, (residual, off_by_one)


@pytest.mark.parametrize("case", handback_cases("px4"), ids=lambda c: c.id)
def test_each_safe_mode_with_the_pilot_present_and_absent(
    px4: Session, case: Any, figures: list[dict[str, Any]]
) -> None:
    out = fly_safe_mode_case(px4, case, RATES)
    figures.append({"test": f"px4 hand-back {case.id}", **out})
    case.check(out)


@pytest.mark.parametrize("kind", FAILSAFE_KINDS)
def test_each_failsafe_that_can_be_made_real_leaves_a_vehicle_that_flies(
    px4: Session, kind: str, figures: list[dict[str, Any]]
) -> None:
    out = fly_failsafe_case(px4, kind, RATES)
    figures.append({"test": f"px4 failsafe {kind}", **out})
    check_failsafe_case(px4, kind, out)


def test_px4_v1_16_does_not_sign_and_a_keyed_companion_says_so(
    px4: Session, tmp_path: Path, figures: list[dict[str, Any]]
) -> None:
    """PX4 v1.16 ignores SETUP_SIGNING (measured: nothing it sends is signed after
    it): a companion given a key refuses its unsigned frames, and preflight says why."""
    path = send_a_signing_key(px4, tmp_path)
    link = preflight(px4, RATES, "--signing-key", str(path), "--watch-s", "1")["link"]
    figures.append({"test": "px4 v1.16 signing", "link": link})
    assert link["status"] == "fail" and "does not sign" in link["fix"], link


def test_engage_auto_from_a_cold_start(tmp_path: Path, figures: list[dict[str, Any]]) -> None:
    session = Session("px4", tmp_path / "cold")
    try:
        run = session.start_companion(
            *RATES, "--engage", "auto", "--duration", "8", "--arm-timeout-s", "60"
        )
        # The companion starts while PX4 boots; the pilot's joystick comes with the GCS.
        g = session.connect(90.0)
        session.pilot.hover_throttle = 0.5
        session.pilot.pilot = make_pilot("hover", rng=np.random.default_rng(1))
        session.pilot.engage(g.clock())
        code = run.wait(120.0)
        kinds = run.kinds()
        figures.append({
            "test": "px4 engage auto, cold", "exit": code,
            "arm_refused": len(run.details("arm_refused")), "engaged": "engaged" in kinds,
            "climbed_m": max((-p[1] for p in g.series("LOCAL_POSITION_NED", "z")), default=0.0),
        })  # fmt: skip
        assert code == 0, (code, run.events())
        assert "engaged" in kinds and "duration" in kinds, run.events()
        assert not math.isnan(figures[-1]["climbed_m"]) and figures[-1]["climbed_m"] > 1.0
    finally:
        session.close()
