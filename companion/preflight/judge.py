"""The checklist: each line judged from what was observed and the planned run.

Pure (no I/O, no clock): tested against exact answers (tests/test_preflight.py).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

from companion.link.timesync import LINK_RTT_SHOWN_MS
from companion.preflight.model import Check, CoreCost, Observed, Plan
from companion.stacks import ARDUPILOT, PX4, FlightStack

__all__ = ["judge", "summary"]

_RESULT_ACCEPTED = 0
_CAP_SET_ATTITUDE_TARGET = 64  # MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
_CAP_SET_ACTUATOR_TARGET = 1024  # ..._SET_ACTUATOR_TARGET (RESERVED3 in today's common.xml)
_LANDED_STATES = {0: "undefined", 1: "on ground", 2: "in air", 3: "taking off", 4: "landing"}
_SWITCH_HIGH_US = (1700, 2200)
"""The engage switch counts as high in this range (companion.samples)."""
_SWITCH_LOW_BELOW_US = 1300

_PX4_OBL_ACTIONS = {
    0: "Position mode",
    1: "Altitude mode",
    2: "Manual",
    3: "Return",
    4: "Land",
    5: "Hold",
    6: "Terminate",
    7: "Disarm",
}
_PX4_RCL_ACTIONS = {0: "Disabled", 1: "Hold", 2: "Return", 3: "Land", 5: "Terminate", 6: "Disarm"}
_PX4_RC_IN_MODES = {
    0: "RC only",
    1: "MAVLink joystick only",
    2: "RC and joystick with fallback",
    3: "RC or joystick, first kept",
    4: "stick input disabled",
}
_ARDU_FS_THR = {
    0: "disabled",
    1: "RTL",
    2: "continue mission in auto",
    3: "land",
    4: "SmartRTL or RTL",
    5: "SmartRTL or land",
    6: "auto DO_LAND_START or RTL",
    7: "brake or land",
}

_PX4_LOSS_S = 0.3
"""PX4 holds the companion's last setpoint for ``COM_OF_LOSS_T`` after the companion
dies or its link is lost: 0.3 s is the most it should be with either output (a
body rate held 1 s from a roll cost up to 26 m; docs/failsafes.md, "The companion
dies")."""
_PX4_LOSS_FAIL_S = {"actuator": 0.9, "rates": 3.0}
"""Beyond these it fails: a torque held 1 s from a roll ran away to thousands of
deg/s; a body rate held stays bounded by PX4's rate loop."""
_GUID_TIMEOUT_S = 1.0
"""ArduPilot's ``GUID_TIMEOUT``: it holds the last rate that long, then levels."""
_RC_LOSS_MAX_S = 1.0
_CORE_WARN_SHARE = 0.25
"""The law's update may take this share of the loop period before it is a warning:
the sample path also decodes, gates, logs and sends."""
_CORE_FAIL_SHARE = 0.5


def judge(obs: Observed, plan: Plan, core: CoreCost | None = None) -> list[Check]:
    """The checklist for ``obs`` and the planned run, in the order a pilot reads it."""
    checks: list[Check] = []
    checks.append(_check_link_up(obs, plan))
    stack = obs.stack
    if stack is None:
        return checks + _here(plan, core)
    if obs.frames_signed and not plan.signing:
        checks.append(_check_signing(obs, plan))
        return checks + _here(plan, core)
    checks.append(_check_output(obs, plan, stack))
    checks.append(_check_armed(obs))
    checks.extend(_check_ids(obs, plan))
    if stack is PX4:
        joystick = obs.joystick_messages > 0 and obs.rc_messages == 0
        checks.extend(_px4_params(obs.params, plan, joystick=joystick))
    else:
        checks.extend(_ardupilot_params(obs.params, plan))
    checks.append(_check_imu_rate(obs, plan, stack))
    checks.append(_check_round_trip(obs))
    checks.extend(_check_rc(obs, plan))
    checks.append(_check_signing(obs, plan))
    checks.append(_check_landed_state(obs))
    checks.append(_check_position(obs))
    return checks + _here(plan, core)


def _here(plan: Plan, core: CoreCost | None) -> list[Check]:
    """The lines about this computer, whatever the autopilot showed: the controller
    file's fly check and the law's cost."""
    out = []
    if plan.fly_check is not None:
        out.append(_check_controller(plan))
    if core is not None:
        out.append(_check_core(core, plan))
    return out


def _check_controller(plan: Plan) -> Check:
    """Shipped, passed the fly check here, or not (companion run then refuses it)."""
    check = plan.fly_check
    assert check is not None
    if check.may_fly:
        return Check("controller", "pass", check.describe())
    if plan.engage == "none":
        text = f"{check.describe()}; shadow mode (--engage none) flies it, sending nothing"
        return Check("controller", "warn", text, f"before it flies the vehicle, {check.advice}")
    if plan.skip_fly_check:
        text = f"{check.describe()}; flown anyway (--skip-fly-check)"
        return Check("controller", "warn", text, check.advice)
    text = f"{check.describe()}; companion run refuses it"
    return Check("controller", "fail", text, f"{check.advice} (or fly it with --skip-fly-check)")


def summary(checks: Iterable[Check]) -> dict[str, int]:
    counts = {"pass": 0, "warn": 0, "fail": 0}
    for c in checks:
        counts[c.status] += 1
    return counts


def _check_link_up(obs: Observed, plan: Plan) -> Check:
    if not obs.heartbeat:
        fix = (
            "check the --connect URL, the baud rate and the wiring, and that the autopilot "
            "streams MAVLink on that port"
        )
        if obs.frames_rejected_unsigned:
            fix = (
                f"{obs.frames_rejected_unsigned} unsigned frames were refused: the autopilot "
                "does not sign; set up signing on it with the same key (docs: signing), or "
                "run without --signing-key"
            )
        return Check("link", "fail", obs.error or "no HEARTBEAT from an autopilot", fix)
    if obs.stack is None:
        return Check(
            "link",
            "fail",
            f"autopilot type {obs.autopilot_id} is not supported",
            "the companion flies PX4 (autopilot 12) and ArduPilot Copter (autopilot 3)",
        )
    name = "PX4" if obs.stack is PX4 else "ArduPilot"
    version = ".".join(map(str, obs.version)) if obs.version else "version unknown"
    return Check("link", "pass", f"{name} {version}, system {obs.target[0]} component "
                 f"{obs.target[1]}" if obs.target else f"{name} {version}")  # fmt: skip


def _check_output(obs: Observed, plan: Plan, stack: FlightStack) -> Check:
    name = "PX4" if stack is PX4 else "ArduPilot"
    if obs.version is None:
        shown = "no AUTOPILOT_VERSION answer"
    else:
        shown = f"{name} {'.'.join(map(str, obs.version))}"
    if plan.output == "actuator":
        if stack is ARDUPILOT:
            return Check(
                "output",
                "fail",
                "ArduPilot accepts no actuator setpoints over MAVLink",
                "run with --output rates (body rates, SET_ATTITUDE_TARGET)",
            )
        if obs.version is None:
            return Check(
                "output",
                "warn",
                f"{shown}: PX4 takes actuator setpoints only up to 1.13",
                "check the firmware is PX4 <= 1.13, or run with --output rates",
            )
        if obs.version >= (1, 14, 0):
            return Check(
                "output",
                "fail",
                f"{shown} ignores SET_ACTUATOR_CONTROL_TARGET (removed in PX4 1.14)",
                "run with --output rates (body rates, SET_ATTITUDE_TARGET)",
            )
        if obs.capabilities is not None and not obs.capabilities & _CAP_SET_ACTUATOR_TARGET:
            return Check(
                "output",
                "warn",
                f"{shown} does not advertise SET_ACTUATOR_TARGET",
                "run with --output rates, or check the firmware build",
            )
        return Check("output", "pass", f"{shown} takes actuator setpoints (--output actuator)")
    if obs.capabilities is not None and not obs.capabilities & _CAP_SET_ATTITUDE_TARGET:
        return Check(
            "output",
            "warn",
            f"{shown} does not advertise SET_ATTITUDE_TARGET",
            "check the firmware: body-rate setpoints need it",
        )
    mode = "OFFBOARD" if stack is PX4 else "GUIDED_NOGPS"
    return Check("output", "pass", f"{shown} takes body rates in {mode} (--output rates)")


def _check_armed(obs: Observed) -> Check:
    if obs.armed:
        return Check(
            "armed",
            "warn",
            "the vehicle is armed",
            "run preflight on the ground, disarmed, before each flight",
        )
    return Check("armed", "pass", "disarmed")


def _check_ids(obs: Observed, plan: Plan) -> list[Check]:
    ours = (plan.source_system, plan.source_component)
    if obs.target == ours:
        return [
            Check(
                "ids",
                "fail",
                f"the companion's system/component {ours[0]}/{ours[1]} is the autopilot's",
                "give the autopilot another component id (PX4 MAV_COMP_ID, ArduPilot is always 1)",
            )
        ]
    return [
        Check(
            "ids",
            "pass",
            f"companion {ours[0]}/{ours[1]} (onboard computer), autopilot "
            f"{obs.target[0]}/{obs.target[1]}"
            if obs.target
            else f"companion {ours[0]}/{ours[1]}",
        )
    ]


def _missing(name: str, label: str = "") -> Check:
    return Check(
        label or name,
        "warn",
        f"{name} not read (no PARAM_VALUE)",
        f"check {name} in a ground station",
    )


def _px4_params(p: dict[str, float | None], plan: Plan, *, joystick: bool = False) -> list[Check]:
    """PX4's parameters; ``joystick``: the pilot is a ground station's joystick (no
    radio), whose axes PX4 maps itself."""
    out: list[Check] = []
    t = p.get("COM_OF_LOSS_T")
    if t is None:
        out.append(_missing("COM_OF_LOSS_T"))
    else:
        bound = _PX4_LOSS_S
        what = "torque" if plan.output == "actuator" else "body rate"
        fail_s = _PX4_LOSS_FAIL_S["actuator" if plan.output == "actuator" else "rates"]
        if t <= bound + 1e-6:
            out.append(Check("COM_OF_LOSS_T", "pass", f"{t:g} s (<= {bound:g} s)"))
        else:
            out.append(
                Check(
                    "COM_OF_LOSS_T",
                    "fail" if t > fail_s + 1e-6 else "warn",
                    f"{t:g} s: a companion that dies, or whose link is lost, leaves the "
                    f"last {what} held that long",
                    f"set COM_OF_LOSS_T to {bound:g}",
                )
            )
    act = p.get("COM_OBL_RC_ACT")
    if act is None:
        out.append(_missing("COM_OBL_RC_ACT"))
    else:
        label = _PX4_OBL_ACTIONS.get(int(act), f"value {int(act)}")
        if int(act) in (6, 7):
            out.append(
                Check(
                    "COM_OBL_RC_ACT",
                    "fail",
                    f"{int(act)} ({label}): a lost companion link drops the vehicle",
                    "set COM_OBL_RC_ACT to 0 (Position mode) or 1 (Altitude mode)",
                )
            )
        elif int(act) not in _PX4_OBL_ACTIONS:
            out.append(
                Check("COM_OBL_RC_ACT", "warn", f"{label}: not a known action", "set it to 0")
            )
        else:
            out.append(Check("COM_OBL_RC_ACT", "pass", f"{int(act)} ({label}) on offboard loss"))
    t = p.get("COM_RC_LOSS_T")
    if t is None:
        out.append(_missing("COM_RC_LOSS_T"))
    elif t <= _RC_LOSS_MAX_S + 1e-6:
        out.append(Check("COM_RC_LOSS_T", "pass", f"{t:g} s"))
    else:
        out.append(
            Check(
                "COM_RC_LOSS_T",
                "warn",
                f"{t:g} s before a lost radio counts",
                f"set COM_RC_LOSS_T to at most {_RC_LOSS_MAX_S:g} (default 0.5)",
            )
        )
    act = p.get("NAV_RCL_ACT")
    if act is None:
        out.append(_missing("NAV_RCL_ACT"))
    else:
        label = _PX4_RCL_ACTIONS.get(int(act), f"value {int(act)}")
        if int(act) in (0, 5, 6):
            out.append(
                Check(
                    "NAV_RCL_ACT",
                    "fail",
                    f"{int(act)} ({label}) on RC loss",
                    "set NAV_RCL_ACT to 2 (Return), 3 (Land) or 1 (Hold)",
                )
            )
        else:
            out.append(Check("NAV_RCL_ACT", "pass", f"{int(act)} ({label}) on RC loss"))
    ex = p.get("COM_RCL_EXCEPT")
    if ex is None:
        out.append(_missing("COM_RCL_EXCEPT"))
    elif int(ex) & 4:
        out.append(
            Check(
                "COM_RCL_EXCEPT",
                "warn",
                f"{int(ex)}: bit 2 set, PX4 ignores RC loss in OFFBOARD",
                "clear bit 2 so the autopilot acts on a lost radio too (the companion's own "
                f"RC-loss failsafe is the only one otherwise): COM_RCL_EXCEPT = {int(ex) & ~4}",
            )
        )
    else:
        out.append(Check("COM_RCL_EXCEPT", "pass", f"{int(ex)}: RC loss acted on in OFFBOARD"))
    mode = p.get("COM_RC_IN_MODE")
    if mode is None:
        out.append(_missing("COM_RC_IN_MODE"))
    else:
        label = _PX4_RC_IN_MODES.get(int(mode), f"value {int(mode)}")
        if int(mode) in (1, 4) and plan.engage == "rc-switch" and not joystick:
            out.append(
                Check(
                    "COM_RC_IN_MODE",
                    "fail",
                    f"{int(mode)} ({label}): no radio reaches the autopilot and no joystick "
                    "was seen, so no engage switch",
                    "set COM_RC_IN_MODE to 0 (RC only), or fly a joystick from a ground "
                    "station with a button on aux1",
                )
            )
        else:
            out.append(Check("COM_RC_IN_MODE", "pass", f"{int(mode)} ({label})"))
    if not joystick:
        out.extend(
            _rc_map(
                p,
                plan,
                ("RC_MAP_ROLL", "RC_MAP_PITCH", "RC_MAP_THROTTLE", "RC_MAP_YAW"),
                "RC_MAP_FLTMODE",
            )
        )
    gyro = p.get("IMU_GYRO_RATEMAX")
    if gyro is None:
        out.append(_missing("IMU_GYRO_RATEMAX"))
    elif gyro + 1e-6 < plan.rate_hz:
        out.append(
            Check(
                "IMU_GYRO_RATEMAX",
                "warn",
                f"{gyro:g} Hz: below the loop rate asked ({plan.rate_hz:g} Hz)",
                f"set IMU_GYRO_RATEMAX to at least {plan.rate_hz:g}, or run with "
                f"--rate-hz {gyro:g}",
            )
        )
    else:
        out.append(Check("IMU_GYRO_RATEMAX", "pass", f"{gyro:g} Hz"))
    return out


def _rc_map(
    p: dict[str, float | None], plan: Plan, names: tuple[str, str, str, str], mode_name: str
) -> list[Check]:
    """The autopilot's stick channels against the controller's, and the flight-mode
    channel against the engage channel."""
    out: list[Check] = []
    seen = [p.get(n) for n in names]
    if any(v is None for v in seen):
        out.append(_missing(", ".join(n for n, v in zip(names, seen) if v is None), "RC map"))
    else:
        theirs = tuple(int(v) for v in seen if v is not None)
        unmapped = [n for n, c in zip(names, theirs) if c == 0]
        if unmapped:
            out.append(
                Check(
                    "RC map",
                    "fail",
                    f"{', '.join(unmapped)} 0: no channel mapped at the autopilot",
                    "calibrate the radio in a ground station (it sets "
                    + ", ".join(names)
                    + f" to channels {_chans(plan.sticks_channels)})",
                )
            )
        elif theirs != plan.sticks_channels:
            out.append(
                Check(
                    "RC map",
                    "fail",
                    f"roll/pitch/throttle/yaw on channels {_chans(theirs)} at the autopilot, "
                    f"{_chans(plan.sticks_channels)} in the controller config",
                    "make them the same: the controller config's sticks.channels, or "
                    + ", ".join(names),
                )
            )
        else:
            out.append(Check("RC map", "pass", f"roll/pitch/throttle/yaw on {_chans(theirs)}"))
    if plan.engage == "rc-switch":
        fm = p.get(mode_name)
        if fm is not None and int(fm) == plan.engage_channel:
            out.append(
                Check(
                    mode_name,
                    "fail",
                    f"channel {int(fm)} is the flight-mode switch and the engage switch",
                    f"move the engage switch (--engage-channel) or {mode_name} to another channel",
                )
            )
        elif fm is not None and 1 <= int(fm) <= 18 and int(fm) in plan.sticks_channels:
            out.append(
                Check(mode_name, "fail", f"channel {int(fm)} is also a stick", f"fix {mode_name}")
            )
    return out


def _chans(c: tuple[int, ...]) -> str:
    return "/".join(str(x) for x in c)


def _ardupilot_params(p: dict[str, float | None], plan: Plan) -> list[Check]:
    out: list[Check] = []
    g = p.get("GUID_OPTIONS")
    if g is None:
        out.append(_missing("GUID_OPTIONS"))
    elif plan.output == "rates" and not int(g) & 8:
        out.append(
            Check(
                "GUID_OPTIONS",
                "fail",
                f"{int(g)}: bit 3 clear, SET_ATTITUDE_TARGET thrust is read as a climb rate",
                f"set GUID_OPTIONS to {int(g) | 8} (add 8: thrust is thrust); companion run "
                "refuses to start otherwise",
            )
        )
    else:
        out.append(Check("GUID_OPTIONS", "pass", f"{int(g)}: thrust is a normalised thrust"))
    t = p.get("GUID_TIMEOUT")
    if t is None:
        out.append(_missing("GUID_TIMEOUT"))
    elif t <= _GUID_TIMEOUT_S + 1e-6:
        out.append(Check("GUID_TIMEOUT", "pass", f"{t:g} s"))
    else:
        out.append(
            Check(
                "GUID_TIMEOUT",
                "warn",
                f"{t:g} s: a lost companion link holds the last body rate that long "
                "before the vehicle levels",
                f"set GUID_TIMEOUT to {_GUID_TIMEOUT_S:g}",
            )
        )
    name = "MAV_GCS_SYSID" if p.get("MAV_GCS_SYSID") is not None else "SYSID_MYGCS"
    gcs = p.get(name)
    if gcs is None:
        out.append(_missing("MAV_GCS_SYSID or SYSID_MYGCS", "MAV_GCS_SYSID"))
    elif int(gcs) == plan.source_system:
        out.append(
            Check(
                name,
                "warn",
                f"{int(gcs)}: the companion's system id is the ground station's, so its "
                "heartbeat hides a lost ground station",
                f"set {name} to the ground station's id (255 by default)",
            )
        )
    else:
        out.append(
            Check(name, "pass", f"{int(gcs)}: RC overrides and GCS failsafe from that system")
        )
    fs = p.get("FS_THR_ENABLE")
    if fs is None:
        out.append(_missing("FS_THR_ENABLE"))
    elif int(fs) == 0:
        out.append(
            Check(
                "FS_THR_ENABLE",
                "fail",
                "0: no radio failsafe",
                "set FS_THR_ENABLE to 1 (RTL) or 3 (land)",
            )
        )
    else:
        label = _ARDU_FS_THR.get(int(fs), f"value {int(fs)}")
        out.append(Check("FS_THR_ENABLE", "pass", f"{int(fs)} ({label}) on RC loss"))
    opt = p.get("FS_OPTIONS")
    if opt is None:
        out.append(_missing("FS_OPTIONS"))
    elif int(opt) & 4:
        out.append(
            Check(
                "FS_OPTIONS",
                "warn",
                f"{int(opt)}: bit 2 set, GUIDED continues on RC loss",
                f"clear bit 2 (FS_OPTIONS = {int(opt) & ~4}) so a lost radio is acted on while "
                "the companion flies",
            )
        )
    else:
        out.append(Check("FS_OPTIONS", "pass", f"{int(opt)}: RC loss acted on in GUIDED"))
    t = p.get("RC_FS_TIMEOUT")
    if t is not None:
        if t <= _RC_LOSS_MAX_S + 1e-6:
            out.append(Check("RC_FS_TIMEOUT", "pass", f"{t:g} s"))
        else:
            out.append(
                Check(
                    "RC_FS_TIMEOUT",
                    "warn",
                    f"{t:g} s before a lost radio counts",
                    f"set RC_FS_TIMEOUT to at most {_RC_LOSS_MAX_S:g}",
                )
            )
    loop = p.get("SCHED_LOOP_RATE")
    if loop is None:
        out.append(_missing("SCHED_LOOP_RATE"))
    elif 0.8 * loop + 1e-6 < plan.rate_hz:
        out.append(
            Check(
                "SCHED_LOOP_RATE",
                "warn",
                f"{loop:g} Hz: ArduPilot streams at most {0.8 * loop:g} Hz, below the "
                f"{plan.rate_hz:g} Hz asked",
                f"run with --rate-hz {math.floor(0.8 * loop):g}, or raise SCHED_LOOP_RATE",
            )
        )
    else:
        out.append(Check("SCHED_LOOP_RATE", "pass", f"{loop:g} Hz"))
    out.extend(
        _rc_map(p, plan, ("RCMAP_ROLL", "RCMAP_PITCH", "RCMAP_THROTTLE", "RCMAP_YAW"), "FLTMODE_CH")
    )
    return out


def _check_imu_rate(obs: Observed, plan: Plan, stack: FlightStack) -> Check:
    asked = obs.imu_asked_hz
    if obs.imu_result is not None and obs.imu_result != _RESULT_ACCEPTED:
        return Check(
            "IMU rate",
            "fail",
            f"{obs.imu_message} at {asked:g} Hz refused (MAV_RESULT {obs.imu_result})",
            "lower --rate-hz, or check the autopilot's stream limits",
        )
    if obs.imu_count < 2 or obs.imu_window_s <= 0:
        return Check(
            "IMU rate",
            "fail",
            f"no {obs.imu_message} stream ({obs.imu_count} messages)",
            "check the port's MAVLink mode and bandwidth (PX4 MAV_n_MODE / MAV_n_RATE, "
            "ArduPilot SERIALn_PROTOCOL / baud)",
        )
    got = obs.imu_count / obs.imu_window_s
    gap_ms = obs.imu_max_gap_s * 1e3
    text = f"{obs.imu_message} at {got:.0f} Hz (asked {asked:g}), longest gap {gap_ms:.0f} ms"
    capped = f" (the stack's limit {stack.max_imu_rate_hz:g} Hz)" if asked < plan.rate_hz else ""
    if got < 0.8 * asked:
        return Check(
            "IMU rate",
            "fail",
            text + capped,
            "the link or the autopilot cannot stream this fast: a faster baud rate, a "
            "higher MAVLink rate limit on that port (PX4 MAV_n_RATE, ArduPilot SRn_*), or a "
            f"lower --rate-hz (e.g. {10 * math.floor(got / 10):g})",
        )
    if got < 0.95 * asked or gap_ms > 4e3 / asked or capped:
        return Check(
            "IMU rate",
            "warn",
            text + capped,
            "the loop runs at the rate the stream gives; see the link's bandwidth and load",
        )
    return Check("IMU rate", "pass", text)


def _check_round_trip(obs: Observed) -> Check:
    st = obs.link
    if st is None or st.n == 0:
        return Check(
            "round trip",
            "warn",
            f"no TIMESYNC answer to {obs.timesync_requests} requests",
            "the link cannot be measured in flight; PX4 and ArduPilot answer TIMESYNC on "
            "a MAVLink port in normal mode",
        )
    text = (
        f"TIMESYNC median {st.rtt_median_ms:.1f} ms, jitter {st.jitter_ms:.1f} ms ({st.n} answers)"
    )
    if st.rtt_median_ms > LINK_RTT_SHOWN_MS:
        return Check(
            "round trip",
            "warn",
            text + f": beyond the {LINK_RTT_SHOWN_MS:g} ms the controller is shown to fly",
            "use a faster link (UART at 921600 baud, or Ethernet), not Wi-Fi or a slow "
            "USB-serial adapter",
        )
    if st.jitter_ms > 0.5 * LINK_RTT_SHOWN_MS:
        return Check(
            "round trip",
            "warn",
            text + ": an uneven link",
            "look for a busy USB hub, Wi-Fi or a shared serial port",
        )
    return Check("round trip", "pass", text)


def _check_rc(obs: Observed, plan: Plan) -> list[Check]:
    if (obs.rc_messages == 0 or obs.rc_chancount == 0) and obs.joystick_messages:
        return _check_joystick(obs, plan)
    if obs.rc_messages == 0 or obs.rc_chancount == 0:
        if plan.engage == "rc-switch":
            return [
                Check(
                    "RC",
                    "fail",
                    "no RC channels from the autopilot: the engage switch cannot be read",
                    "bind and power the radio; check the autopilot sees it",
                )
            ]
        return [
            Check(
                "RC",
                "warn",
                "no RC channels: no pilot to take over, every hand-back lands or holds",
                "fly with a radio bound to the autopilot",
            )
        ]
    out = [Check("RC", "pass", f"{obs.rc_chancount} channels, {obs.rc_messages} messages")]
    if plan.engage != "rc-switch":
        return out
    ch = plan.engage_channel
    if ch > obs.rc_chancount or ch > len(obs.rc_last_us):
        out.append(
            Check(
                "engage switch",
                "fail",
                f"channel {ch} not among the {obs.rc_chancount} the radio sends",
                "assign a switch to that channel, or pick another with --engage-channel",
            )
        )
        return out
    out.append(_check_switch(ch, obs.rc_min_us, obs.rc_max_us, obs.rc_last_us, f"channel {ch}"))
    return out


def _check_joystick(obs: Observed, plan: Plan) -> list[Check]:
    """The pilot as a ground station's joystick (PX4 streams its MANUAL_CONTROL): the
    sticks as they are, ``aux1..6`` as channels 5..10 for the engage switch."""
    out = [
        Check(
            "RC",
            "pass",
            f"no radio: the pilot's joystick (MANUAL_CONTROL, {obs.joystick_messages} "
            "messages) flies",
        )
    ]
    if plan.engage != "rc-switch":
        return out
    ch = plan.engage_channel
    if not 5 <= ch <= 10:
        out.append(
            Check(
                "engage switch",
                "fail",
                f"channel {ch} is no joystick switch (aux1..aux6 are channels 5..10)",
                "pick the joystick button's aux channel with --engage-channel 5..10",
            )
        )
        return out
    name = f"aux{ch - 4} (channel {ch})"
    out.append(
        _check_switch(ch, obs.joystick_min_us, obs.joystick_max_us, obs.joystick_last_us, name)
    )
    return out


def _check_switch(
    ch: int, lo_us: list[int], hi_us: list[int], last_us: list[int], name: str
) -> Check:
    """The engage switch as seen: high (it would engage at once), seen low and high, or not."""
    lo, hi, last = lo_us[ch - 1], hi_us[ch - 1], last_us[ch - 1]
    if _SWITCH_HIGH_US[0] <= last <= _SWITCH_HIGH_US[1]:
        return Check(
            "engage switch",
            "warn",
            f"{name} is high ({last} us): companion run would engage as soon as it starts",
            "put the switch low before starting the companion",
        )
    if lo < _SWITCH_LOW_BELOW_US and _SWITCH_HIGH_US[0] <= hi <= _SWITCH_HIGH_US[1]:
        return Check("engage switch", "pass", f"{name} seen low and high ({lo}-{hi} us)")
    return Check(
        "engage switch",
        "warn",
        f"{name} not seen moving low and high ({lo}-{hi} us)",
        "flip the engage switch while preflight watches (longer with --watch-s); "
        f"high is {_SWITCH_HIGH_US[0]}-{_SWITCH_HIGH_US[1]} us, low below "
        f"{_SWITCH_LOW_BELOW_US} us",
    )


def _check_signing(obs: Observed, plan: Plan) -> Check:
    if plan.signing:
        if obs.frames_unsigned:
            return Check(
                "signing",
                "warn",
                f"{obs.frames_unsigned} unsigned frames from the autopilot accepted",
                "enable signing on the autopilot with the same key",
            )
        return Check("signing", "pass", f"both sign ({obs.frames_signed} signed frames checked)")
    if obs.frames_signed:
        return Check(
            "signing",
            "fail",
            "the autopilot signs but the companion has no key: its commands will be refused",
            "run with --signing-key FILE (the autopilot's key)",
        )
    if plan.serial:
        return Check("signing", "pass", "unsigned, on a serial port only the companion uses")
    return Check(
        "signing",
        "warn",
        "unsigned on a network link: anyone who reaches the port can command the vehicle",
        "set up MAVLink 2 signing on both sides (docs: signing), or use a serial link",
    )


def _check_landed_state(obs: Observed) -> Check:
    states = [s for s in obs.landed_states if s != 0]
    if not states:
        return Check(
            "landed state",
            "warn",
            "no landed state (EXTENDED_SYS_STATE)"
            + (" other than undefined" if obs.landed_states else ""),
            "the controller then stops learning on the ground by the collective alone; "
            "PX4 and ArduPilot Copter send it when asked",
        )
    return Check("landed state", "pass", _LANDED_STATES.get(states[-1], f"state {states[-1]}"))


def _check_position(obs: Observed) -> Check:
    if obs.position_messages:
        return Check("position", "pass", "a position estimate (LOCAL_POSITION_NED)")
    return Check(
        "position",
        "warn",
        "no position estimate: a hand-back without the pilot's radio lands",
        "a GPS or flow sensor gives the autopilot a hold mode to hand back to",
    )


def _check_core(core: CoreCost, plan: Plan) -> Check:
    period_us = 1e6 / plan.rate_hz
    which = "compiled" if core.compiled else "pure Python"
    text = (
        f"{which} core: {core.median_us:.0f} us per update (p99 {core.p99_us:.0f}), "
        f"{100 * core.median_us / period_us:.0f} % of the {period_us:.0f} us loop period"
    )
    fix = (
        "a lower --rate-hz"
        if core.compiled
        else "install with a C compiler and the Python headers (apt install build-essential "
        "python3-dev) so the compiled core is built, or a lower --rate-hz"
    )
    # Judged on the median: a p99 timed on a busy computer is mostly preemption.
    if core.median_us > _CORE_FAIL_SHARE * period_us:
        return Check("control core", "fail", text, fix)
    if core.median_us > _CORE_WARN_SHARE * period_us:
        return Check("control core", "warn", text, fix)
    if not core.compiled:
        return Check("control core", "warn", text, fix)
    return Check("control core", "pass", text)
