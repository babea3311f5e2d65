"""The bounds the real-stack tier judges the companion's modes by (tests/realstack/mode_checks.py),
on figures measured there: no stack needed."""

from __future__ import annotations

from typing import Any

from tests.realstack.mode_checks import failures, mission_failures


def _figures(**changes: float) -> dict[str, Any]:
    base = {
        "engage_tilt_deg": 1.0, "engage_sag_m": 0.0, "stick_tilt_deg": 36.0,
        "stick_speed_m_s": 5.2, "asked_speed_m_s": float("nan"), "hold_rms_m": 0.2,
        "alt_rms_m": 0.03,
    }  # fmt: skip
    return {**base, **changes}


def test_an_altitude_hold_within_the_stacks_own_spread_passes() -> None:
    # Measured on the real PX4 v1.16: ALTCTL held 0.029 m, the companion 0.17 m; in
    # other runs ALTCTL itself held 0.235 m.
    assert failures("altitude", _figures(alt_rms_m=0.17), _figures(alt_rms_m=0.029)) == []


def test_an_altitude_that_wanders_fails_naming_the_figure() -> None:
    (bad,) = failures("altitude", _figures(alt_rms_m=0.3), _figures(alt_rms_m=0.029))
    assert bad.startswith("alt_rms_m 0.3 against 0.029")


def test_the_horizontal_hold_keeps_its_tighter_allowance() -> None:
    ours, theirs = _figures(hold_rms_m=0.45), _figures(hold_rms_m=0.2)
    (bad,) = failures("position", ours, theirs)
    assert bad.startswith("hold_rms_m 0.45 against 0.2")


def test_a_jolt_on_engaging_fails() -> None:
    (bad,) = failures("angle", _figures(engage_tilt_deg=14.0), _figures())
    assert bad.startswith("engage tilt 14.0 deg")


def _mission(**changes: Any) -> dict[str, Any]:
    base = {"completed": True, "engage_tilt_deg": 2.0, "path_rms_m": 0.3}
    return {**base, **changes}


def test_a_mission_start_tilted_no_more_than_the_stacks_own_passes() -> None:
    # Measured on the real PX4 v1.16 (2026-12-01): the companion's start 7.243 deg,
    # PX4's AUTO.MISSION's own 7.98 deg on the same try.
    ours, theirs = _mission(engage_tilt_deg=7.243), _mission(engage_tilt_deg=7.98)
    assert mission_failures(ours, theirs) == []


def test_a_jolt_beyond_the_stacks_own_start_fails() -> None:
    # A jolt the bound is for (mode_checks' docstring: ArduCopter's vehicle tilted
    # 9.5 deg by a first leg at PX4's jerk), against a stack start of 4.45 deg.
    ours, theirs = _mission(engage_tilt_deg=9.5), _mission(engage_tilt_deg=4.45)
    (bad,) = mission_failures(ours, theirs)
    assert bad == "engage tilt 9.5 deg >= 7.0"
