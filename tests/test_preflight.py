"""``companion preflight``'s judgement, against exact answers: a well set-up
autopilot of each stack passes every line; each misconfiguration fails or warns
on its own line, with its fix. (The integration tests run the command against
the SITL: tests/integration/test_preflight.py.)"""

from __future__ import annotations

import dataclasses
import math
import struct
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from companion.fly_check import FlyCheck
from companion.link.requests import param_value
from companion.link.timesync import LinkStats
from companion.preflight import Check, CoreCost, Observed, Plan, judge, summary

GOOD_PX4_PARAMS: dict[str, float | None] = {
    "COM_OF_LOSS_T": 0.3,
    "COM_OBL_RC_ACT": 0,
    "COM_RC_LOSS_T": 0.5,
    "NAV_RCL_ACT": 2,
    "COM_RCL_EXCEPT": 0,
    "COM_RC_IN_MODE": 0,
    "RC_MAP_ROLL": 1,
    "RC_MAP_PITCH": 2,
    "RC_MAP_THROTTLE": 3,
    "RC_MAP_YAW": 4,
    "RC_MAP_FLTMODE": 6,
    "IMU_GYRO_RATEMAX": 400,
    "MC_ROLLRATE_K": 1.0,
    "MC_ROLLRATE_P": 0.15,
    "MC_PITCHRATE_K": 1.0,
    "MC_PITCHRATE_P": 0.15,
}
GOOD_ARDU_PARAMS: dict[str, float | None] = {
    "GUID_OPTIONS": 8,
    "GUID_TIMEOUT": 0.5,
    "MAV_GCS_SYSID": 255,
    "SYSID_MYGCS": None,
    "FS_THR_ENABLE": 1,
    "FS_OPTIONS": 16,
    "RC_FS_TIMEOUT": 1.0,
    "SCHED_LOOP_RATE": 400,
    "RCMAP_ROLL": 1,
    "RCMAP_PITCH": 2,
    "RCMAP_THROTTLE": 3,
    "RCMAP_YAW": 4,
    "FLTMODE_CH": 6,
}
GOOD_CORE = CoreCost(compiled=True, median_us=20.0, p99_us=40.0, updates=3000)


def observed(stack: str = "px4", **changes: Any) -> Observed:
    """A well set-up autopilot, seen for 3 s: disarmed, engage switch flipped."""
    px4 = stack == "px4"
    obs = Observed(
        heartbeat=True,
        autopilot_id=12 if px4 else 3,
        target=(1, 1),
        version=(1, 13, 3) if px4 else (4, 6, 0),
        capabilities=64 | 1024 if px4 else 64,
        params=dict(GOOD_PX4_PARAMS if px4 else GOOD_ARDU_PARAMS),
        imu_message="HIGHRES_IMU" if px4 else "ATTITUDE",
        imu_asked_hz=250.0,
        imu_result=0,
        imu_count=750,
        imu_window_s=3.0,
        imu_max_gap_s=0.005,
        link=LinkStats(30, 2.0, 1.8, 2.0, 2.6),
        timesync_requests=30,
        rc_messages=150,
        rc_chancount=8,
        rc_min_us=[1000, 1000, 1000, 1000, 1000, 1000, 1000, 1000],
        rc_max_us=[2000, 2000, 2000, 2000, 2000, 1000, 1000, 1000],
        rc_last_us=[1500, 1500, 1000, 1500, 1000, 1000, 1000, 1000],
        landed_states=[1, 1, 1],
        position_messages=12,
        frames_signed=900,
    )
    for name, value in changes.items():
        if name == "params":
            obs.params.update(value)
        else:
            setattr(obs, name, value)
    return obs


def plan(stack: str = "px4", **changes: Any) -> Plan:
    base = Plan(output="actuator" if stack == "px4" else "rates", signing=True)
    return dataclasses.replace(base, **changes)


def line(checks: list[Check], name: str) -> Check:
    found = [c for c in checks if c.name == name]
    assert len(found) == 1, f"{name}: {[c.name for c in checks]}"
    return found[0]


@pytest.mark.parametrize("stack", ["px4", "ardupilot"])
def test_a_well_set_autopilot_passes_every_line(stack: str) -> None:
    checks = judge(observed(stack), plan(stack), GOOD_CORE)
    assert [c for c in checks if c.status != "pass"] == []
    assert summary(checks)["pass"] == len(checks) > 15


@pytest.mark.parametrize(
    ("stack", "obs", "run", "name", "status", "fix"),
    [
        # The stack and the output.
        ("px4", {"version": (1, 14, 0)}, {}, "output", "fail", "--output rates"),
        ("px4", {"version": (1, 15, 2)}, {}, "output", "fail", "--output rates"),
        ("ardupilot", {}, {"output": "actuator"}, "output", "fail", "--output rates"),
        ("px4", {"version": None}, {}, "output", "warn", "PX4 <= 1.13"),
        ("px4", {"capabilities": 64}, {}, "output", "warn", "--output rates"),
        ("px4", {"armed": True}, {}, "armed", "warn", "disarmed"),
        # PX4's parameters.
        ("px4", {"params": {"COM_OF_LOSS_T": 0.5}}, {}, "COM_OF_LOSS_T", "warn", "to 0.3"),
        ("px4", {"params": {"COM_OF_LOSS_T": 1.0}}, {}, "COM_OF_LOSS_T", "fail", "to 0.3"),
        ("px4", {"params": {"COM_OF_LOSS_T": 5.0}}, {}, "COM_OF_LOSS_T", "fail", "to 0.3"),
        # A body rate held from a roll (a companion killed mid-manoeuvre) costs
        # altitude too: PX4's default of 1 s is a warning with rates, 3 s the limit.
        (
            "px4",
            {"params": {"COM_OF_LOSS_T": 1.0}},
            {"output": "rates"},
            "COM_OF_LOSS_T",
            "warn",
            "to 0.3",
        ),
        (
            "px4",
            {"params": {"COM_OF_LOSS_T": 2.0}},
            {"output": "rates"},
            "COM_OF_LOSS_T",
            "warn",
            "to 0.3",
        ),
        (
            "px4",
            {"params": {"COM_OF_LOSS_T": 5.0}},
            {"output": "rates"},
            "COM_OF_LOSS_T",
            "fail",
            "to 0.3",
        ),
        ("px4", {"params": {"COM_OF_LOSS_T": None}}, {}, "COM_OF_LOSS_T", "warn", "ground station"),
        ("px4", {"params": {"COM_OBL_RC_ACT": 6}}, {}, "COM_OBL_RC_ACT", "fail", "Position"),
        ("px4", {"params": {"COM_OBL_RC_ACT": 7}}, {}, "COM_OBL_RC_ACT", "fail", "Position"),
        ("px4", {"params": {"COM_RC_LOSS_T": 3.0}}, {}, "COM_RC_LOSS_T", "warn", "at most 1"),
        ("px4", {"params": {"NAV_RCL_ACT": 0}}, {}, "NAV_RCL_ACT", "fail", "2 (Return)"),
        ("px4", {"params": {"NAV_RCL_ACT": 5}}, {}, "NAV_RCL_ACT", "fail", "2 (Return)"),
        ("px4", {"params": {"RC_MAP_ROLL": 0}}, {}, "RC map", "fail", "calibrate the radio"),
        (
            "px4",
            {"params": {"COM_RCL_EXCEPT": 5}},
            {},
            "COM_RCL_EXCEPT",
            "warn",
            "COM_RCL_EXCEPT = 1",
        ),
        ("px4", {"params": {"COM_RC_IN_MODE": 4}}, {}, "COM_RC_IN_MODE", "fail", "RC only"),
        (
            "px4",
            {"params": {"RC_MAP_PITCH": 3, "RC_MAP_THROTTLE": 2}},
            {},
            "RC map",
            "fail",
            "sticks.channels",
        ),
        (
            "px4",
            {"params": {"RC_MAP_FLTMODE": 5}},
            {},
            "RC_MAP_FLTMODE",
            "fail",
            "--engage-channel",
        ),
        (
            "px4",
            {"params": {"IMU_GYRO_RATEMAX": 200}},
            {},
            "IMU_GYRO_RATEMAX",
            "warn",
            "--rate-hz 200",
        ),
        (
            "px4",
            {"params": {"MC_PITCHRATE_K": 3.0}},
            {"output": "rates", "rates_law_axes": (True, True, True)},
            "MC_ROLLRATE_K",
            "warn",
            "--rates-law-axes auto",
        ),
        # ArduPilot's.
        (
            "ardupilot",
            {"params": {"GUID_OPTIONS": 0}},
            {},
            "GUID_OPTIONS",
            "fail",
            "GUID_OPTIONS to 8",
        ),
        (
            "ardupilot",
            {"params": {"GUID_OPTIONS": 1}},
            {},
            "GUID_OPTIONS",
            "fail",
            "GUID_OPTIONS to 9",
        ),
        ("ardupilot", {"params": {"GUID_TIMEOUT": 3.0}}, {}, "GUID_TIMEOUT", "warn", "to 1"),
        ("ardupilot", {"params": {"MAV_GCS_SYSID": 1}}, {}, "MAV_GCS_SYSID", "warn", "255"),
        (
            "ardupilot",
            {"params": {"MAV_GCS_SYSID": None, "SYSID_MYGCS": 1}},
            {},
            "SYSID_MYGCS",
            "warn",
            "255",
        ),
        ("ardupilot", {"params": {"FS_THR_ENABLE": 0}}, {}, "FS_THR_ENABLE", "fail", "1 (RTL)"),
        ("ardupilot", {"params": {"FS_OPTIONS": 20}}, {}, "FS_OPTIONS", "warn", "FS_OPTIONS = 16"),
        ("ardupilot", {"params": {"RC_FS_TIMEOUT": 5.0}}, {}, "RC_FS_TIMEOUT", "warn", "at most 1"),
        (
            "ardupilot",
            {"params": {"SCHED_LOOP_RATE": 200}},
            {},
            "SCHED_LOOP_RATE",
            "warn",
            "--rate-hz 160",
        ),
        (
            "ardupilot",
            {"params": {"RCMAP_YAW": 1, "RCMAP_ROLL": 4}},
            {},
            "RC map",
            "fail",
            "RCMAP_ROLL",
        ),
        ("ardupilot", {"params": {"FLTMODE_CH": 5}}, {}, "FLTMODE_CH", "fail", "--engage-channel"),
        # The streams and the link.
        ("px4", {"imu_result": 2}, {}, "IMU rate", "fail", "lower --rate-hz"),
        ("px4", {"imu_count": 0}, {}, "IMU rate", "fail", "MAV_n_RATE"),
        ("px4", {"imu_count": 300}, {}, "IMU rate", "fail", "--rate-hz (e.g. 100)"),
        ("px4", {"imu_count": 690}, {}, "IMU rate", "warn", "bandwidth"),
        ("px4", {"imu_count": 600}, {}, "IMU rate", "warn", "IMU_INTEG_RATE (200 Hz"),
        ("px4", {"imu_count": 597}, {}, "IMU rate", "fail", "set it to at least --rate-hz"),
        ("px4", {"imu_max_gap_s": 0.05}, {}, "IMU rate", "warn", "bandwidth"),
        (
            "px4",
            {"link": LinkStats(30, 30.0, 28.0, 30.0, 33.0)},
            {},
            "round trip",
            "warn",
            "faster link",
        ),
        ("px4", {"link": LinkStats(30, 3.0, 1.0, 3.0, 15.0)}, {}, "round trip", "warn", "busy USB"),
        ("px4", {"link": LinkStats(0, *[float("nan")] * 4)}, {}, "round trip", "warn", "TIMESYNC"),
        ("px4", {"rc_messages": 0, "rc_chancount": 0}, {}, "RC", "fail", "bind"),
        ("px4", {"rc_messages": 0, "rc_chancount": 0}, {"engage": "auto"}, "RC", "warn", "radio"),
        ("px4", {}, {"engage_channel": 9}, "engage switch", "fail", "--engage-channel"),
        (
            "px4",
            {"rc_last_us": [1500, 1500, 1000, 1500, 1900, 1000, 1000, 1000]},
            {},
            "engage switch",
            "warn",
            "switch low",
        ),
        (
            "px4",
            {"rc_max_us": [2000] * 4 + [1000] * 4},
            {},
            "engage switch",
            "warn",
            "flip the engage switch",
        ),
        # Signing, the landed state, the position.
        ("px4", {"frames_signed": 0, "frames_unsigned": 900}, {}, "signing", "warn", "same key"),
        (
            "px4",
            {"frames_signed": 0, "frames_unsigned": 900},
            {"signing": False},
            "signing",
            "warn",
            "signing on both sides",
        ),
        ("px4", {"landed_states": []}, {}, "landed state", "warn", "collective alone"),
        ("px4", {"landed_states": [0, 0]}, {}, "landed state", "warn", "collective alone"),
        ("px4", {"position_messages": 0}, {}, "position", "warn", "GPS"),
    ],
)
def test_each_misconfiguration_is_named_with_its_fix(
    stack: str, obs: dict[str, Any], run: dict[str, Any], name: str, status: str, fix: str
) -> None:
    checks = judge(observed(stack, **obs), plan(stack, **run), GOOD_CORE)
    c = line(checks, name)
    assert (c.status, fix in c.fix) == (status, True), c
    # Every other line still passes: each check judges one thing.
    others = [x for x in checks if x.name != name and x.status != "pass"]
    assert others == [], others


@pytest.mark.parametrize(
    ("gap_s", "late", "status"),
    [
        (0.023, 1, "pass"),  # one hiccup of a busy companion (seen on the real PX4)
        (0.039, 7, "pass"),  # under ten periods, and under 1 % of 750 late
        (0.041, 1, "warn"),  # a stall: over ten periods (40 ms at 250 Hz)
        (0.012, 8, "warn"),  # short gaps, but over 1 % of the stream late
    ],
)
def test_the_imu_stream_warns_on_a_stall_not_on_one_hiccup(
    gap_s: float, late: int, status: str
) -> None:
    obs = observed(imu_max_gap_s=gap_s, imu_late=late)
    c = line(judge(obs, plan(), GOOD_CORE), "IMU rate")
    assert c.status == status, c
    assert c.detail.endswith(f"longest gap {gap_s * 1e3:.0f} ms, {late} of 750 over 16 ms"), c


def test_a_simulator_behind_real_time_is_named_as_the_streams_cause() -> None:
    # The real PX4 SITL on a loaded machine: 224 Hz of 250, its clock at 0.93.
    obs = observed(imu_count=672, imu_clock_ratio=0.93)
    c = line(judge(obs, plan(), GOOD_CORE), "IMU rate")
    assert c.status == "warn", c
    assert c.detail.endswith("the autopilot's clock runs at 0.93 of real time"), c
    assert "a simulator behind real time" in c.fix, c
    # A real autopilot's clock keeps real time: the link is the suspect.
    c = line(judge(observed(imu_count=672, imu_clock_ratio=1.0), plan(), GOOD_CORE), "IMU rate")
    assert "of real time" not in c.detail and "bandwidth" in c.fix, c


def test_an_autopilot_that_signs_against_a_companion_without_a_key_is_one_failed_line() -> None:
    # (It would refuse every request: preflight stops after the heartbeat.)
    checks = judge(observed(), plan(signing=False), GOOD_CORE)
    assert [(c.name, c.status) for c in checks] == [
        ("link", "pass"),
        ("signing", "fail"),
        ("control core", "pass"),
    ]
    assert "--signing-key" in checks[1].fix


def test_an_unsigned_serial_link_passes() -> None:
    obs = observed(frames_signed=0, frames_unsigned=900)
    c = line(judge(obs, plan(signing=False, serial=True)), "signing")
    assert c.status == "pass"


@pytest.mark.parametrize(
    ("core", "status"),
    [
        (CoreCost(True, 900.0, 3000.0, 3000), "pass"),  # median 900 us of 4000; p99 is noise
        (CoreCost(True, 1100.0, 1500.0, 3000), "warn"),  # over a quarter of the period
        (CoreCost(True, 2100.0, 2500.0, 3000), "fail"),  # over half
        (CoreCost(False, 60.0, 100.0, 3000), "warn"),  # pure Python: build the compiled one
    ],
)
def test_the_control_core_against_the_loop_period(core: CoreCost, status: str) -> None:
    c = line(judge(observed(), plan(), core), "control core")
    assert c.status == status
    assert ("compiled" in c.detail) == core.compiled


def test_no_heartbeat_is_one_failed_line_naming_signing_when_frames_were_refused() -> None:
    obs = Observed(error="udpin:0.0.0.0:14540: no HEARTBEAT from any autopilot within 5 s")
    (c,) = judge(obs, plan())
    assert (c.name, c.status) == ("link", "fail")
    assert "--connect" in c.fix
    obs.frames_rejected_unsigned = 12
    (c,) = judge(obs, plan())
    assert "does not sign" in c.fix


def test_an_unknown_autopilot_fails() -> None:
    (c,) = judge(Observed(heartbeat=True, autopilot_id=8, target=(1, 1)), plan())
    assert c.status == "fail"
    assert "not supported" in c.detail


@pytest.mark.parametrize(
    ("param_type", "value", "bytewise", "expected"),
    [
        (6, struct.unpack("<f", struct.pack("<i", 7))[0], True, 7.0),  # PX4 int32, bytewise
        (6, struct.unpack("<f", struct.pack("<i", -1))[0], True, -1.0),
        (9, 0.3, True, pytest.approx(0.3)),  # a float is a float
        (6, 7.0, False, 7.0),  # ArduPilot: C-cast
        (2, 255.0, False, 255.0),
    ],
)
def test_parameter_values_decode_by_encoding(
    param_type: int, value: float, bytewise: bool, expected: Any
) -> None:
    msg = SimpleNamespace(param_type=param_type, param_value=value)
    assert param_value(msg, bytewise=bytewise) == expected


_MINE = "my_gains.yaml"
_FIX = f"companion check-config --controller {_MINE} --fly"


@pytest.mark.parametrize(
    ("status", "engage", "skip", "expected"),
    [
        ("shipped", "rc-switch", False, ("pass", f"{_MINE}: a shipped controller", "")),
        ("passed", "rc-switch", False,
         ("pass", f"{_MINE}: passed the fly check on 2025-06-01 14:02 UTC", "")),
        ("unchecked", "rc-switch", False,
         ("fail", f"{_MINE}: not checked in the simulator on this computer; companion run "
          "refuses it", f"fly it in the simulator first: `{_FIX}` (or fly it with "
          "--skip-fly-check)")),
        ("failed", "auto", False,
         ("fail", f"{_MINE}: failed the fly check on 2025-06-01 14:02 UTC: heavy-weak: crashed; "
          "companion run refuses it", f"do not fly it as it is: change it, then check it again "
          f"with `{_FIX}` (or fly it with --skip-fly-check)")),
        ("unchecked", "rc-switch", True,
         ("warn", f"{_MINE}: not checked in the simulator on this computer; flown anyway "
          "(--skip-fly-check)", f"fly it in the simulator first: `{_FIX}`")),
        ("unchecked", "none", False,
         ("warn", f"{_MINE}: not checked in the simulator on this computer; shadow mode "
          "(--engage none) flies it, sending nothing",
          f"before it flies the vehicle, fly it in the simulator first: `{_FIX}`")),
    ],
)  # fmt: skip
def test_the_controller_line_says_whether_the_file_passed_the_fly_check(
    status: str, engage: str, skip: bool, expected: tuple[str, str, str]
) -> None:
    dated = status in ("passed", "failed")
    check = FlyCheck(
        Path(_MINE), "ab" * 32, status,  # type: ignore[arg-type]
        date="2025-06-01T14:02:07Z" if dated else "",
        problems=("heavy-weak: crashed",) if status == "failed" else (),
    )  # fmt: skip
    run = plan(fly_check=check, engage=engage, skip_fly_check=skip)
    c = line(judge(observed(), run, GOOD_CORE), "controller")
    assert (c.status, c.detail, c.fix) == expected
    # Judged whatever the autopilot showed: with no autopilot at all too.
    assert line(judge(Observed(), run), "controller") == c


def test_no_controller_line_without_a_fly_check() -> None:
    assert "controller" not in [c.name for c in judge(observed(), plan(), GOOD_CORE)]


def joystick_only(**changes: Any) -> Observed:
    """PX4 with no radio, flown from a ground station's joystick (as SIH is)."""
    chans_lo = [1000, 1000, 1000, 1000, 1000] + [1500] * 13
    chans_hi = [2000, 2000, 2000, 2000, 2000] + [1500] * 13
    last = [1500, 1500, 1500, 1500, 1000] + [1500] * 13
    return observed(
        rc_messages=0, rc_chancount=0, rc_min_us=[], rc_max_us=[], rc_last_us=[],
        joystick_messages=120, joystick_min_us=chans_lo, joystick_max_us=chans_hi,
        joystick_last_us=last, params={"COM_RC_IN_MODE": 1}, **changes,
    )  # fmt: skip


def test_a_joystick_pilot_passes_where_px4_has_no_radio() -> None:
    checks = judge(joystick_only(), plan(), GOOD_CORE)
    assert line(checks, "RC") == Check(
        "RC", "pass", "no radio: the pilot's joystick (MANUAL_CONTROL, 120 messages) flies"
    )
    assert line(checks, "engage switch").status == "pass"
    assert "aux1 (channel 5)" in line(checks, "engage switch").detail
    assert line(checks, "COM_RC_IN_MODE").status == "pass"
    assert not [c for c in checks if c.name == "RC map"]  # PX4 maps a joystick's axes itself


def test_px4_in_joystick_mode_without_a_joystick_fails_naming_both_ways() -> None:
    obs = observed(rc_messages=0, rc_chancount=0, params={"COM_RC_IN_MODE": 1})
    check = line(judge(obs, plan(), GOOD_CORE), "COM_RC_IN_MODE")
    assert check.status == "fail"
    assert "no joystick was seen" in check.detail and "joystick" in check.fix


def test_a_joystick_engage_channel_must_be_an_aux_channel() -> None:
    check = line(judge(joystick_only(), plan(engage_channel=12), GOOD_CORE), "engage switch")
    assert check.status == "fail" and "aux1..aux6 are channels 5..10" in check.detail


def test_preflight_reads_what_its_rules_judge_and_no_parameter_twice() -> None:
    """Regression check of the table (companion/preflight/rules.py): today's lists."""
    from companion.preflight import params_read
    from companion.stacks import ARDUPILOT, PX4

    assert params_read(PX4) == (
        "COM_OF_LOSS_T", "COM_OBL_RC_ACT", "COM_RC_LOSS_T", "NAV_RCL_ACT", "COM_RCL_EXCEPT",
        "COM_RC_IN_MODE", "RC_MAP_ROLL", "RC_MAP_PITCH", "RC_MAP_THROTTLE", "RC_MAP_YAW",
        "RC_MAP_FLTMODE", "IMU_GYRO_RATEMAX", "MC_ROLLRATE_K", "MC_ROLLRATE_P", "MC_PITCHRATE_K",
        "MC_PITCHRATE_P",
    )  # fmt: skip
    assert params_read(ARDUPILOT) == (
        "GUID_OPTIONS", "GUID_TIMEOUT", "MAV_GCS_SYSID", "FS_THR_ENABLE", "FS_OPTIONS",
        "RC_FS_TIMEOUT", "SCHED_LOOP_RATE", "RCMAP_ROLL", "RCMAP_PITCH", "RCMAP_THROTTLE",
        "RCMAP_YAW", "FLTMODE_CH",
    )  # fmt: skip
    for stack in (PX4, ARDUPILOT):
        assert len(set(params_read(stack))) == len(params_read(stack))


@pytest.mark.parametrize(
    ("run", "judged"),
    [
        ({"output": "rates", "rates_law_axes": (True, True, True)}, "warn"),
        ({"output": "rates", "rates_law_axes": (True, False, True)}, "warn"),
        ({"output": "rates", "rates_law_axes": (False, True, True)}, "pass"),
        ({"output": "rates"}, "pass"),  # auto: it leaves roll to the pilot's rate
        ({"output": "rates", "rates_law_axes": (False, False, True)}, None),
        ({"output": "actuator"}, None),
    ],
)
@pytest.mark.parametrize(
    "stiff_roll",
    [{"MC_ROLLRATE_K": 2.0}, {"MC_ROLLRATE_P": 0.3}, {"MC_ROLLRATE_K": 1.5, "MC_ROLLRATE_P": 0.2}],
)
def test_px4s_rate_gains_are_judged_only_where_the_law_corrects_roll_or_pitch_rates(
    run: dict[str, Any], judged: str | None, stiff_roll: dict[str, float]
) -> None:
    """A roll rate loop twice PX4's default gain (through its K, its P or both): a
    warning where the law is asked to correct roll, said where auto chooses."""
    obs = observed(params={**GOOD_PX4_PARAMS, **stiff_roll})
    checks = judge(obs, plan(**run), GOOD_CORE)
    found = [c for c in checks if c.name == "MC_ROLLRATE_K"]
    if judged is None:
        assert found == []
        return
    (c,) = found
    assert c.status == judged and "2x / 1x the default gain on roll / pitch" in c.detail, c
    if judged == "warn":
        assert "stiffer on roll," in c.detail and "--rates-law-axes auto" in c.fix, c
    elif "rates_law_axes" not in run:
        assert c.detail.endswith("--rates-law-axes auto: the law corrects pitch, yaw"), c
    at_default = judge(observed(), plan(**run), GOOD_CORE)
    (c,) = [c for c in at_default if c.name == "MC_ROLLRATE_K"]
    assert c.status == "pass" and "1x / 1x the default gain" in c.detail, c


@pytest.mark.parametrize("bad", [{"MC_ROLLRATE_P": None}, {"MC_PITCHRATE_K": math.nan},
                                 {"MC_ROLLRATE_K": 0.0}])  # fmt: skip
def test_px4s_rate_gains_unread_or_unusable_warn_as_the_start_up_falls_back(
    bad: dict[str, float | None],
) -> None:
    """The same gains the start-up's choice rests on (companion.rate_loop.usable):
    one missing, not finite or not positive, and auto corrects every axis."""
    checks = judge(observed(params=bad), plan(output="rates"), GOOD_CORE)
    (c,) = [c for c in checks if c.name == "MC_ROLLRATE_K"]
    (name,) = bad
    assert c.status == "warn" and c.detail.startswith(f"{name} not read or not positive"), c
    assert "auto then corrects every axis" in c.detail and name in c.fix, c
    assert [x for x in checks if name in x.name or name in x.detail] == [c], checks  # one line
