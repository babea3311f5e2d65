"""The autopilot's parameters preflight checks: one table of rules per stack.

Each :class:`Rule` names the parameters it reads and judges their values against
the planned run; preflight reads exactly the parameters its stack's rules name
(:func:`params_read`), and a parameter the autopilot did not answer for is a
warning naming it. Pure (no I/O, no clock): tested against exact answers
(tests/test_preflight.py). Each parameter's meaning and default: PX4's parameter
reference and ArduPilot Copter's full parameter list.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from companion.control import AXES
from companion.preflight.model import Check, Plan
from companion.rate_loop import PX4_RATE_GAINS, STIFF
from companion.stacks import ARDUPILOT, PX4, FlightStack
from companion.step import law_axes_names

__all__ = [
    "OLDER_NAMES",
    "PARAM_RULES",
    "Context",
    "Rule",
    "judge_params",
    "params_read",
]

Params = dict[str, float | None]


@dataclass(frozen=True)
class Context:
    """What a rule judges against: the planned run and how the pilot flies."""

    plan: Plan
    joystick: bool
    """The pilot is a ground station's joystick (no radio): the autopilot maps its
    axes itself."""


@dataclass(frozen=True)
class Rule:
    """One line (or a few) of the checklist from some of the autopilot's parameters."""

    reads: tuple[str, ...]
    """The parameters it needs; the first is the line's name."""
    judge: Callable[[Params, Context], list[Check]]
    """Called with every parameter of :attr:`reads` answered (see :attr:`partial`)."""
    when: Callable[[Context], bool] | None = None
    """The rule applies only when this holds (None: always)."""
    partial: bool = False
    """The rule judges its parameters itself, present or not (no warning for a
    missing one here)."""


def _missing(name: str, label: str = "") -> Check:
    return Check(
        label or name,
        "warn",
        f"{name} not read (no PARAM_VALUE)",
        f"check {name} in a ground station",
    )


def _one(name: str, judge: Callable[[float, Plan], Check]) -> Rule:
    """A rule on one parameter, judged from its value alone."""
    return Rule((name,), lambda p, ctx: [judge(_value(p, name), ctx.plan)])


def _value(p: Params, name: str) -> float:
    v = p[name]
    assert v is not None
    return v


# ----------------------------------------------------------------------------- PX4

_PX4_LOSS_S = 0.3
"""PX4 holds the companion's last setpoint for ``COM_OF_LOSS_T`` after the companion
dies or its link is lost: 0.3 s is the most it should be with either output (a
body rate held 1 s from a roll cost up to 26 m; docs/failsafes.md, "The companion
dies")."""
_PX4_LOSS_FAIL_S = {"actuator": 0.9, "rates": 3.0}
"""Beyond these it fails: a torque held 1 s from a roll ran away to thousands of
deg/s; a body rate held stays bounded by PX4's rate loop."""
_RC_LOSS_MAX_S = 1.0
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


def _offboard_loss(t: float, plan: Plan) -> Check:
    what = "torque" if plan.output == "actuator" else "body rate"
    fail_s = _PX4_LOSS_FAIL_S["actuator" if plan.output == "actuator" else "rates"]
    if t <= _PX4_LOSS_S + 1e-6:
        return Check("COM_OF_LOSS_T", "pass", f"{t:g} s (<= {_PX4_LOSS_S:g} s)")
    return Check(
        "COM_OF_LOSS_T",
        "fail" if t > fail_s + 1e-6 else "warn",
        f"{t:g} s: a companion that dies, or whose link is lost, leaves the last {what} "
        "held that long",
        f"set COM_OF_LOSS_T to {_PX4_LOSS_S:g}",
    )


def _offboard_loss_action(v: float, _plan: Plan) -> Check:
    act = int(v)
    label = _PX4_OBL_ACTIONS.get(act, f"value {act}")
    if act in (6, 7):
        return Check(
            "COM_OBL_RC_ACT",
            "fail",
            f"{act} ({label}): a lost companion link drops the vehicle",
            "set COM_OBL_RC_ACT to 0 (Position mode) or 1 (Altitude mode)",
        )
    if act not in _PX4_OBL_ACTIONS:
        return Check("COM_OBL_RC_ACT", "warn", f"{label}: not a known action", "set it to 0")
    return Check("COM_OBL_RC_ACT", "pass", f"{act} ({label}) on offboard loss")


def _rc_loss_time(name: str, fix: str) -> Callable[[float, Plan], Check]:
    def judge(t: float, _plan: Plan) -> Check:
        if t <= _RC_LOSS_MAX_S + 1e-6:
            return Check(name, "pass", f"{t:g} s")
        return Check(name, "warn", f"{t:g} s before a lost radio counts", fix)

    return judge


def _rc_loss_action(v: float, _plan: Plan) -> Check:
    act = int(v)
    label = _PX4_RCL_ACTIONS.get(act, f"value {act}")
    if act in (0, 5, 6):
        return Check(
            "NAV_RCL_ACT",
            "fail",
            f"{act} ({label}) on RC loss",
            "set NAV_RCL_ACT to 2 (Return), 3 (Land) or 1 (Hold)",
        )
    return Check("NAV_RCL_ACT", "pass", f"{act} ({label}) on RC loss")


def _bit_clear(name: str, bit: int, when_set: str, fix: str, when_clear: str) -> Rule:
    """A warning while ``bit`` of an options bitmask is set. The texts are formats of
    ``v`` (the value) and ``cleared`` (the value with the bit cleared)."""

    def judge(value: float, _plan: Plan) -> Check:
        v = int(value)
        if v & bit:
            cleared = v & ~bit
            return Check(name, "warn", when_set.format(v=v), fix.format(v=v, cleared=cleared))
        return Check(name, "pass", when_clear.format(v=v))

    return _one(name, judge)


def _stick_input(p: Params, ctx: Context) -> list[Check]:
    mode = int(_value(p, "COM_RC_IN_MODE"))
    label = _PX4_RC_IN_MODES.get(mode, f"value {mode}")
    if mode in (1, 4) and ctx.plan.engage == "rc-switch" and not ctx.joystick:
        return [
            Check(
                "COM_RC_IN_MODE",
                "fail",
                f"{mode} ({label}): no radio reaches the autopilot and no joystick was seen, "
                "so no engage switch",
                "set COM_RC_IN_MODE to 0 (RC only), or fly a joystick from a ground station "
                "with a button on aux1",
            )
        ]
    return [Check("COM_RC_IN_MODE", "pass", f"{mode} ({label})")]


def _gyro_rate(gyro: float, plan: Plan) -> Check:
    if gyro + 1e-6 < plan.rate_hz:
        return Check(
            "IMU_GYRO_RATEMAX",
            "warn",
            f"{gyro:g} Hz: below the loop rate asked ({plan.rate_hz:g} Hz)",
            f"set IMU_GYRO_RATEMAX to at least {plan.rate_hz:g}, or run with --rate-hz {gyro:g}",
        )
    return Check("IMU_GYRO_RATEMAX", "pass", f"{gyro:g} Hz")


def _rate_gains(p: Params, ctx: Context) -> list[Check]:
    """PX4's rate gains against where the law's roll and pitch correction pays
    (:mod:`companion.rate_loop`): said with ``--rates-law-axes auto``, which chooses
    from them at start-up; a warning where the axes asked correct a stiff loop."""
    values, unusable = PX4_RATE_GAINS.usable(p)
    if unusable:
        return [
            Check(
                "MC_ROLLRATE_K",
                "warn",
                f"{', '.join(unusable)} not read or not positive: the rate loop's stiffness "
                "is not known (--rates-law-axes auto then corrects every axis)",
                f"check {', '.join(unusable)} in a ground station",
            )
        ]
    said = PX4_RATE_GAINS.said(values)
    chosen = PX4_RATE_GAINS.law_axes(values)
    asked = ctx.plan.rates_law_axes
    if asked is None:
        what = law_axes_names(chosen).replace(",", ", ")
        return [
            Check(
                "MC_ROLLRATE_K", "pass", f"{said}; --rates-law-axes auto: the law corrects {what}"
            )
        ]
    stiff = [a for a, on, pays in zip(AXES, asked, chosen, strict=False) if on and not pays]
    if stiff:
        return [
            Check(
                "MC_ROLLRATE_K",
                "warn",
                f"{said}: a rate loop {STIFF:g}x PX4's default or stiffer on "
                f"{' and '.join(stiff)}, where correcting yaw alone measured no worse than "
                "the full law, and at 3x the full law worse than passing the pilot's rates "
                "through",
                "fly --rates-law-axes auto (it leaves those axes to the pilot's rate), or fly "
                "both and keep the better (docs/controller.md)",
            )
        ]
    return [Check("MC_ROLLRATE_K", "pass", said)]


def _law_on_roll_or_pitch(ctx: Context) -> bool:
    axes = ctx.plan.rates_law_axes
    return ctx.plan.output == "rates" and (axes is None or axes[0] or axes[1])


# ----------------------------------------------------------------------- both stacks


def _chans(c: tuple[int, ...]) -> str:
    return "/".join(str(x) for x in c)


def _rc_map(
    names: tuple[str, str, str, str], mode_name: str, when: Callable[[Context], bool] | None = None
) -> Rule:
    """The autopilot's stick channels against the controller's, and the flight-mode
    channel against the engage channel."""

    def judge(p: Params, ctx: Context) -> list[Check]:
        plan = ctx.plan
        out: list[Check] = []
        seen = [p.get(n) for n in names]
        if any(v is None for v in seen):
            missing = ", ".join(n for n, v in zip(names, seen) if v is None)
            out.append(_missing(missing, "RC map"))
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
                        f"move the engage switch (--engage-channel) or {mode_name} to another "
                        "channel",
                    )
                )
            elif fm is not None and 1 <= int(fm) <= 18 and int(fm) in plan.sticks_channels:
                out.append(
                    Check(
                        mode_name, "fail", f"channel {int(fm)} is also a stick", f"fix {mode_name}"
                    )
                )
        return out

    return Rule((*names, mode_name), judge, when=when, partial=True)


# ------------------------------------------------------------------------ ArduPilot

_GUID_TIMEOUT_S = 1.0
"""ArduPilot's ``GUID_TIMEOUT``: it holds the last rate that long, then levels."""
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


def _guided_thrust(v: float, plan: Plan) -> Check:
    g = int(v)
    if plan.output == "rates" and not g & 8:
        return Check(
            "GUID_OPTIONS",
            "fail",
            f"{g}: bit 3 clear, SET_ATTITUDE_TARGET thrust is read as a climb rate",
            f"set GUID_OPTIONS to {g | 8} (add 8: thrust is thrust); companion run refuses "
            "to start otherwise",
        )
    return Check("GUID_OPTIONS", "pass", f"{g}: thrust is a normalised thrust")


def _guided_timeout(t: float, _plan: Plan) -> Check:
    if t <= _GUID_TIMEOUT_S + 1e-6:
        return Check("GUID_TIMEOUT", "pass", f"{t:g} s")
    return Check(
        "GUID_TIMEOUT",
        "warn",
        f"{t:g} s: a lost companion link holds the last body rate that long before the "
        "vehicle levels",
        f"set GUID_TIMEOUT to {_GUID_TIMEOUT_S:g}",
    )


def _ground_station_id(p: Params, ctx: Context) -> list[Check]:
    """``MAV_GCS_SYSID`` (ArduPilot 4.7), ``SYSID_MYGCS`` before it."""
    name = "MAV_GCS_SYSID" if p.get("MAV_GCS_SYSID") is not None else "SYSID_MYGCS"
    gcs = p.get(name)
    if gcs is None:
        return [_missing("MAV_GCS_SYSID or SYSID_MYGCS", "MAV_GCS_SYSID")]
    if int(gcs) == ctx.plan.source_system:
        return [
            Check(
                name,
                "warn",
                f"{int(gcs)}: the companion's system id is the ground station's, so its "
                "heartbeat hides a lost ground station",
                f"set {name} to the ground station's id (255 by default)",
            )
        ]
    return [Check(name, "pass", f"{int(gcs)}: RC overrides and GCS failsafe from that system")]


def _radio_failsafe(v: float, _plan: Plan) -> Check:
    fs = int(v)
    if fs == 0:
        return Check(
            "FS_THR_ENABLE",
            "fail",
            "0: no radio failsafe",
            "set FS_THR_ENABLE to 1 (RTL) or 3 (land)",
        )
    label = _ARDU_FS_THR.get(fs, f"value {fs}")
    return Check("FS_THR_ENABLE", "pass", f"{fs} ({label}) on RC loss")


def _radio_timeout(p: Params, ctx: Context) -> list[Check]:
    """Older ArduCopter has no ``RC_FS_TIMEOUT``: nothing is said then."""
    t = p.get("RC_FS_TIMEOUT")
    if t is None:
        return []
    judge = _rc_loss_time("RC_FS_TIMEOUT", f"set RC_FS_TIMEOUT to at most {_RC_LOSS_MAX_S:g}")
    return [judge(t, ctx.plan)]


def _loop_rate(loop: float, plan: Plan) -> Check:
    if 0.8 * loop + 1e-6 < plan.rate_hz:
        return Check(
            "SCHED_LOOP_RATE",
            "warn",
            f"{loop:g} Hz: ArduPilot streams at most {0.8 * loop:g} Hz, below the "
            f"{plan.rate_hz:g} Hz asked",
            f"run with --rate-hz {math.floor(0.8 * loop):g}, or raise SCHED_LOOP_RATE",
        )
    return Check("SCHED_LOOP_RATE", "pass", f"{loop:g} Hz")


def _radio(ctx: Context) -> bool:
    return not ctx.joystick


PARAM_RULES: dict[FlightStack, tuple[Rule, ...]] = {
    PX4: (
        _one("COM_OF_LOSS_T", _offboard_loss),
        _one("COM_OBL_RC_ACT", _offboard_loss_action),
        _one(
            "COM_RC_LOSS_T",
            _rc_loss_time(
                "COM_RC_LOSS_T", f"set COM_RC_LOSS_T to at most {_RC_LOSS_MAX_S:g} (default 0.5)"
            ),
        ),
        _one("NAV_RCL_ACT", _rc_loss_action),
        _bit_clear(
            "COM_RCL_EXCEPT",
            4,
            "{v}: bit 2 set, PX4 ignores RC loss in OFFBOARD",
            "clear bit 2 so the autopilot acts on a lost radio too (the companion's own "
            "RC-loss failsafe is the only one otherwise): COM_RCL_EXCEPT = {cleared}",
            "{v}: RC loss acted on in OFFBOARD",
        ),
        Rule(("COM_RC_IN_MODE",), _stick_input),
        _rc_map(
            ("RC_MAP_ROLL", "RC_MAP_PITCH", "RC_MAP_THROTTLE", "RC_MAP_YAW"),
            "RC_MAP_FLTMODE",
            when=_radio,  # a joystick's axes PX4 maps itself
        ),
        _one("IMU_GYRO_RATEMAX", _gyro_rate),
        Rule(PX4_RATE_GAINS.names, _rate_gains, when=_law_on_roll_or_pitch, partial=True),
    ),
    ARDUPILOT: (
        _one("GUID_OPTIONS", _guided_thrust),
        _one("GUID_TIMEOUT", _guided_timeout),
        Rule(("MAV_GCS_SYSID",), _ground_station_id, partial=True),
        _one("FS_THR_ENABLE", _radio_failsafe),
        _bit_clear(
            "FS_OPTIONS",
            4,
            "{v}: bit 2 set, GUIDED continues on RC loss",
            "clear bit 2 (FS_OPTIONS = {cleared}) so a lost radio is acted on while the "
            "companion flies",
            "{v}: RC loss acted on in GUIDED",
        ),
        Rule(("RC_FS_TIMEOUT",), _radio_timeout, partial=True),
        _one("SCHED_LOOP_RATE", _loop_rate),
        _rc_map(("RCMAP_ROLL", "RCMAP_PITCH", "RCMAP_THROTTLE", "RCMAP_YAW"), "FLTMODE_CH"),
    ),
}
"""Each stack's parameter checks, in the order a pilot reads them."""


OLDER_NAMES = {"MAV_GCS_SYSID": "SYSID_MYGCS"}
"""A parameter's name before a release renamed it (ArduPilot 4.7's MAV_GCS_SYSID was
SYSID_MYGCS): read when the new name gets no answer."""


def params_read(stack: FlightStack) -> tuple[str, ...]:
    """The parameters preflight reads from ``stack``: what its rules name."""
    return tuple(name for rule in PARAM_RULES[stack] for name in rule.reads)


def judge_params(stack: FlightStack, p: Params, plan: Plan, *, joystick: bool) -> list[Check]:
    """Every rule of ``stack`` that applies, on the parameters read (``p``)."""
    ctx = Context(plan, joystick)
    out: list[Check] = []
    for rule in PARAM_RULES[stack]:
        if rule.when is not None and not rule.when(ctx):
            continue
        if not rule.partial and (missing := [n for n in rule.reads if p.get(n) is None]):
            out.extend(_missing(n) for n in missing)
            continue
        out.extend(rule.judge(p, ctx))
    return out
