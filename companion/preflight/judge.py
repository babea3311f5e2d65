"""The checklist: each line judged from what was observed and the planned run.

Pure (no I/O, no clock): tested against exact answers (tests/test_preflight.py).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

from companion.link.timesync import LINK_RTT_SHOWN_MS
from companion.preflight.model import (
    LATE_PERIODS,
    SLOW_CLOCK_RATIO,
    STALL_S,
    STALL_SHARE,
    Check,
    CoreCost,
    Observed,
    Plan,
)
from companion.preflight.rules import judge_params
from companion.stacks import FlightStack

__all__ = ["judge", "summary"]

_RESULT_ACCEPTED = 0
_CAP_SET_ATTITUDE_TARGET = 64  # MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
_CAP_SET_ACTUATOR_TARGET = 1024  # ..._SET_ACTUATOR_TARGET (RESERVED3 in today's common.xml)
_LANDED_STATES = {0: "undefined", 1: "on ground", 2: "in air", 3: "taking off", 4: "landing"}
_SWITCH_HIGH_US = (1700, 2200)
"""The engage switch counts as high in this range (companion.pilot.EngageSwitch)."""
_SWITCH_LOW_BELOW_US = 1300
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
    joystick = obs.joystick_messages > 0 and obs.rc_messages == 0
    checks.extend(judge_params(stack, obs.params, plan, joystick=joystick))
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
    name = obs.stack.display_name
    version = ".".join(map(str, obs.version)) if obs.version else "version unknown"
    return Check("link", "pass", f"{name} {version}, system {obs.target[0]} component "
                 f"{obs.target[1]}" if obs.target else f"{name} {version}")  # fmt: skip


def _check_output(obs: Observed, plan: Plan, stack: FlightStack) -> Check:
    name = stack.display_name
    if obs.version is None:
        shown = "no AUTOPILOT_VERSION answer"
    else:
        shown = f"{name} {'.'.join(map(str, obs.version))}"
    if plan.output == "actuator":
        if not stack.supports_actuator_output:
            return Check(
                "output",
                "fail",
                f"{stack.display_name} accepts no actuator setpoints over MAVLink",
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
    return Check(
        "output", "pass", f"{shown} takes body rates in {stack.engage_label} (--output rates)"
    )


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
    late_ms = LATE_PERIODS * 1e3 / asked
    text = (
        f"{obs.imu_message} at {got:.0f} Hz (asked {asked:g}), longest gap "
        f"{obs.imu_max_gap_s * 1e3:.0f} ms, {obs.imu_late} of {obs.imu_count} over {late_ms:.0f} ms"
    )
    slow_clock = obs.imu_clock_ratio < SLOW_CLOCK_RATIO
    if slow_clock:
        text += f"; the autopilot's clock runs at {obs.imu_clock_ratio:.2f} of real time"
    # One short hiccup (a busy companion) is not a stream the loop cannot fly on.
    stalls = (
        obs.imu_max_gap_s > min(10 / asked, STALL_S) or obs.imu_late > STALL_SHARE * obs.imu_count
    )
    capped = f" (the stack's limit {stack.max_imu_rate_hz:g} Hz)" if asked < plan.rate_hz else ""
    limit = f"; {stack.imu_rate_limit}" if stack.imu_rate_limit else ""
    if got < 0.8 * asked:
        return Check(
            "IMU rate",
            "fail",
            text + capped,
            "the link or the autopilot cannot stream this fast: a faster baud rate, a "
            "higher MAVLink rate limit on that port (PX4 MAV_n_RATE, ArduPilot SRn_*), or a "
            f"lower --rate-hz (e.g. {10 * math.floor(got / 10):g}){limit}",
        )
    if got < 0.95 * asked or stalls or capped:
        why = (
            "a simulator behind real time (a loaded machine)"
            if slow_clock
            else "see the link's bandwidth and load"
        )
        return Check(
            "IMU rate",
            "warn",
            text + capped,
            f"the loop runs at the rate the stream gives; {why}{limit}",
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
