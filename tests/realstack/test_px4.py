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
    FAILSAFE_KINDS,
    check_failsafe_case,
    flick_the_switch_while_preflight_watches,
    fly_failsafe_case,
    fly_rates_pair,
    fly_safe_mode_case,
    handback_cases,
    preflight,
    preflight_with,
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
    checks = preflight(px4, RATES, "--watch-s", "6")
    figures.append({"test": "px4 preflight", **{k: v["status"] for k, v in checks.items()}})
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
    assert checks["link"]["detail"].startswith("PX4 1.16")
    assert checks["landed state"]["detail"] == "on ground"
    assert checks["RC"]["detail"].startswith("no radio: the pilot's joystick")
    assert checks["engage switch"]["status"] == "pass", checks["engage switch"]
    assert checks["IMU rate"]["status"] == "pass"
    assert checks["position"]["status"] == "pass"


BAD_PX4 = {
    "COM_OF_LOSS_T": 5.0,  # fail: holds a rate 5 s
    "COM_OBL_RC_ACT": 6.0,  # fail: Disarm on offboard loss
    "COM_RC_LOSS_T": 10.0,  # warn
    "NAV_RCL_ACT": 0.0,  # fail: nothing on RC loss
    "COM_RCL_EXCEPT": 4.0,  # warn: RC loss ignored in OFFBOARD
    "IMU_GYRO_RATEMAX": 100.0,  # warn: below the loop rate asked
}


def test_preflight_flags_each_badly_set_px4_parameter_with_its_fix(
    px4: Session, figures: list[dict[str, Any]]
) -> None:
    checks = preflight_with(px4, RATES, BAD_PX4)
    got = {name: checks[name]["status"] for name in BAD_PX4}
    figures.append({"test": "px4 preflight, badly set", **got})
    assert got == {
        "COM_OF_LOSS_T": "fail", "COM_OBL_RC_ACT": "fail", "COM_RC_LOSS_T": "warn",
        "NAV_RCL_ACT": "fail", "COM_RCL_EXCEPT": "warn", "IMU_GYRO_RATEMAX": "warn",
    }  # fmt: skip
    for name in BAD_PX4:
        assert checks[name]["fix"], checks[name]


def test_mfc_flies_px4s_rate_loop_better_than_passing_the_pilots_rates(
    px4: Session, figures: list[dict[str, Any]]
) -> None:
    errs = fly_rates_pair(px4, RATES, seed=11)
    assert not errs["mfc"]["failsafes"] and not errs["pass-through"]["failsafes"], errs
    figures.append({"test": "px4 rates acro-mixed seed 11 MAE deg/s", **errs})
    for axis in ("roll", "pitch", "yaw"):
        assert errs["mfc"][axis] < errs["pass-through"][axis], (axis, errs)


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
