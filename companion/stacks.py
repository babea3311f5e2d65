"""What differs between flight stacks, in one place.

The companion recognises the stack from the autopilot's HEARTBEAT
(``autopilot`` 12 = PX4, 3 = ArduPilot) and takes from here: which mode it
engages in, how it knows it is engaged, which modes it can hand back to, which
IMU message carries body rates, and whether the stack accepts actuator
setpoints at all.

=========================  ===========================  ==================================
                           PX4                          ArduPilot Copter
=========================  ===========================  ==================================
engage mode                OFFBOARD (main 6), after     GUIDED_NOGPS (20), then arm
                           setpoints stream, then arm
engaged when               main mode 6 and armed        custom mode 20 and armed
safe modes needing RC      posctl (3), altctl (2),      alt_hold (2), stabilize (0)
                           stabilized (7), manual (1)
... needing a position     hold (AUTO.LOITER: 4, sub 3) loiter (5), brake (17)
... needing neither        land (AUTO.LAND: 4, sub 6)   land (9)
auto's choice (in order)   posctl (altctl without a     alt_hold, loiter, land
                           position), hold, land
IMU message                HIGHRES_IMU (rad/s)          ATTITUDE (rad/s body rates)
actuator setpoints         yes (<= 1.13, bundled SITL)  no: body rates only
thrust (rates output)      normalised collective        climb rate unless GUID_OPTIONS
                                                        bit 3: checked at start-up
why it refused to arm      "Arming denied: ...",        "PreArm: ...", "Arm: ..."
(its STATUSTEXT)           "Preflight Fail: ..."
why it refused a mode      "Switching to ... is         "Mode change to ... failed: ..."
                           currently not available"
stick limits (--mode       ``MPC_*`` (Position mode     ``ANGLE_MAX``, ``PILOT_*``,
angle|altitude|position)   acceleration based, or       ``LOIT_*`` (LOITER), ``THR_DZ``
                           direct velocity)
hover thrust               ``MPC_THR_HOVER``            ``MOT_THST_HOVER``
=========================  ===========================  ==================================

The refusal texts are those of PX4 v1.16 (``src/modules/commander``:
``Commander.cpp``, ``HealthAndArmingChecks/``) and ArduCopter 4.5
(``libraries/AP_Arming/AP_Arming.cpp``, ``ArduCopter/mode.cpp``); :func:`said_why`
picks them out of what the autopilot said.

The stick limits (:class:`StickParams`) are the stacks' parameters with their
documented defaults: PX4 v1.16's parameter reference (Multicopter Position
Control), ArduCopter 4.5's (``ArduCopter/Parameters.cpp``,
``libraries/AC_WPNav/AC_Loiter.cpp``, ``libraries/AC_AttitudeControl/``). The
companion reads them at start-up and builds the laws'
:class:`~companion.control.stick_limits.StickLimits` from them; a parameter the
autopilot does not answer takes its default here, and an event says so. These
are the only defaults of the sticks' limits.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Literal

from companion.control.stick_limits import (
    ClimbLimits,
    HorizontalLimits,
    LoiterStickAcceleration,
    MissionLimits,
    Px4DirectVelocity,
    Px4StickAcceleration,
    StickLimits,
)
from companion.rate_loop import PX4_RATE_GAINS, RateLoopGains

__all__ = [
    "ARDUPILOT",
    "PX4",
    "FlightStack",
    "SafeMode",
    "StickParams",
    "said_why",
    "stack_for",
]

Needs = Literal["rc", "position", "nothing"]


@dataclass(frozen=True)
class SafeMode:
    """A mode the companion can hand the vehicle back to.

    ``needs`` is what the autopilot must have to fly it: ``"rc"`` a pilot's
    valid RC (PX4 refuses or fails safe out of its manual modes without one),
    ``"position"`` a position estimate (PX4 AUTO.LOITER, ArduPilot LOITER and
    BRAKE), ``"nothing"`` (land: both stacks descend level without a position).
    ``position_too`` marks a manual mode that also needs a position (POSCTL).
    """

    name: str
    param2: float
    param3: float
    needs: Needs
    position_too: bool = False


@dataclass(frozen=True)
class RateShapingParams:
    """The parameters with which a stack shapes body-rate setpoints
    (companion.control.shaping): a switch, and an acceleration limit per axis
    (roll, pitch, yaw) in centidegrees per second squared, 0 for none."""

    enable_param: str
    accel_params: tuple[str, str, str]
    default_accel_cdeg_s2: tuple[float, float, float]


_TILT_MAX_DEG = 60.0
"""The angle sticks' tilt is bounded here whatever the stack allows (PX4's
``MPC_MAN_TILT_MAX`` goes to 70): beyond it the attitude loop's tilt-first error
and the tilt compensation of the collective are no longer trusted."""


@dataclass(frozen=True)
class StickParams:
    """The parameters with which a stack limits what the sticks ask in its angle,
    altitude and position modes, each with its documented default (in the stack's
    units), and how they make the laws' limits.

    ``hover_thrust`` names the parameter holding the collective that hovers (the
    vertical loop's prior, and its take-over when nothing better is known); its
    default is in ``defaults`` too.
    """

    defaults: Mapping[str, float]
    build: Callable[[Mapping[str, float]], StickLimits]
    hover_thrust: str

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.defaults)

    def limits(self, values: Mapping[str, float] | None = None) -> StickLimits:
        """The limits from ``values`` (by name), the defaults for the rest.

        Raises
        ------
        ValueError
            For a value the limits cannot take (the limits' own message).
        """
        return self.build({**self.defaults, **(values or {})})


def _px4_stick_limits(p: Mapping[str, float]) -> StickLimits:
    """PX4 v1.16: Stabilized's tilt, Altitude's climb, Position's sticks
    (``MPC_POS_MODE`` 0 direct velocity, else acceleration based)."""
    dz = p["MPC_HOLD_DZ"]
    climb = ClimbLimits(
        dz, p["MPC_Z_MAN_EXPO"], p["MPC_Z_VEL_MAX_UP"], p["MPC_Z_VEL_MAX_DN"],
        p["MPC_ACC_UP_MAX"], p["MPC_ACC_DOWN_MAX"],
    )  # fmt: skip
    horizontal: HorizontalLimits
    if int(p["MPC_POS_MODE"]) == 0:
        horizontal = Px4DirectVelocity(dz, p["MPC_XY_MAN_EXPO"], p["MPC_VEL_MANUAL"])
    else:
        horizontal = Px4StickAcceleration(
            dz, p["MPC_XY_MAN_EXPO"], p["MPC_VEL_MANUAL"], p["MPC_ACC_HOR"],
            p["MPC_JERK_MAX"], p["MPC_TILTMAX_AIR"],
        )  # fmt: skip
    mission = MissionLimits(p["MPC_ACC_HOR"], p["MPC_JERK_AUTO"])
    return StickLimits(min(p["MPC_MAN_TILT_MAX"], _TILT_MAX_DEG), climb, horizontal, mission)


PX4_STICK_PARAMS = StickParams(
    # PX4 v1.16 parameter reference, Multicopter Position Control (the defaults).
    defaults={
        "MPC_MAN_TILT_MAX": 35.0,  # deg: Stabilized and Altitude modes' tilt
        "MPC_HOLD_DZ": 0.1,  # share of the stick's half-travel
        "MPC_Z_MAN_EXPO": 0.6,
        "MPC_Z_VEL_MAX_UP": 3.0,  # m/s
        "MPC_Z_VEL_MAX_DN": 1.5,  # m/s
        "MPC_ACC_UP_MAX": 4.0,  # m/s^2
        "MPC_ACC_DOWN_MAX": 3.0,  # m/s^2
        "MPC_POS_MODE": 4.0,  # 4 acceleration based, 0 direct velocity
        "MPC_XY_MAN_EXPO": 0.6,
        "MPC_VEL_MANUAL": 10.0,  # m/s
        "MPC_ACC_HOR": 3.0,  # m/s^2 (full stick asks twice this at rest)
        "MPC_JERK_MAX": 8.0,  # m/s^3
        "MPC_JERK_AUTO": 4.0,  # m/s^3: its missions'
        "MPC_TILTMAX_AIR": 45.0,  # deg
        "MPC_THR_HOVER": 0.5,  # normalised collective
    },
    build=_px4_stick_limits,
    hover_thrust="MPC_THR_HOVER",
)
"""PX4's stick limits; ``MPC_ACC_HOR_MAX`` is not read: v1.16 uses it in no
Position mode variant it still has ("4 not used, use MPC_ACC_HOR instead")."""


def _ardupilot_stick_limits(p: Mapping[str, float]) -> StickLimits:
    """ArduCopter 4.5: STABILIZE's and ALT_HOLD's lean angle, the pilot's climb,
    LOITER's sticks."""
    lean_max = p["ANGLE_MAX"] * 0.01  # cdeg
    psc = p["PSC_ANGLE_MAX"]  # deg; 0: ANGLE_MAX
    if psc > 0.0:
        lean_max = min(lean_max, psc)
    loit = p["LOIT_ANG_MAX"]  # deg; 0: 2/3 of the lean angle limit (AC_Loiter::get_angle_max_cd)
    loiter_angle = min(loit, lean_max) if loit > 0.0 else lean_max * 2.0 / 3.0
    up = p["PILOT_SPEED_UP"] * 0.01  # cm/s
    down = p["PILOT_SPEED_DN"] * 0.01 or up  # 0: PILOT_SPEED_UP
    accel = p["PILOT_ACCEL_Z"] * 0.01  # cm/s^2
    half_travel_us = 500.0
    climb = ClimbLimits(p["THR_DZ"] / half_travel_us, 0.0, up, down, accel, accel)
    horizontal = LoiterStickAcceleration(
        deadband=p["RC1_DZ"] / half_travel_us,
        speed_max_m_s=p["LOIT_SPEED"] * 0.01,
        angle_deg=loiter_angle,
        input_tc_s=p["ATC_INPUT_TC"],
        brake_accel_m_s2=p["LOIT_BRK_ACCEL"] * 0.01,
        brake_jerk_m_s3=p["LOIT_BRK_JERK"] * 0.01,
        brake_delay_s=p["LOIT_BRK_DELAY"],
        brake_gain_1_s=0.5 * p["PSC_VELXY_P"],
    )
    mission = MissionLimits(p["WPNAV_ACCEL"] * 0.01, p["WPNAV_JERK"])  # cm/s^2, m/s^3
    return StickLimits(min(lean_max, _TILT_MAX_DEG), climb, horizontal, mission)


ARDUPILOT_STICK_PARAMS = StickParams(
    # ArduCopter 4.5 defaults (ArduCopter/Parameters.cpp, AC_Loiter.cpp, AC_PosControl.cpp,
    # AC_AttitudeControl.cpp, RC_Channel: Copter's roll dead zone).
    defaults={
        "ANGLE_MAX": 3000.0,  # cdeg
        "PSC_ANGLE_MAX": 0.0,  # deg; 0: ANGLE_MAX
        "LOIT_ANG_MAX": 0.0,  # deg; 0: 2/3 of the lean angle limit
        "LOIT_SPEED": 1250.0,  # cm/s
        "LOIT_BRK_ACCEL": 250.0,  # cm/s^2
        "LOIT_BRK_JERK": 500.0,  # cm/s^3
        "LOIT_BRK_DELAY": 1.0,  # s
        "PSC_VELXY_P": 2.0,  # the brake's gain is half of it
        "ATC_INPUT_TC": 0.15,  # s
        "PILOT_SPEED_UP": 250.0,  # cm/s
        "PILOT_SPEED_DN": 0.0,  # cm/s; 0: PILOT_SPEED_UP
        "PILOT_ACCEL_Z": 250.0,  # cm/s^2
        "THR_DZ": 100.0,  # us around mid-throttle
        "RC1_DZ": 20.0,  # us around the roll stick's centre
        "WPNAV_ACCEL": 250.0,  # cm/s^2: AUTO's
        "WPNAV_JERK": 1.0,  # m/s^3: AUTO's
        "MOT_THST_HOVER": 0.35,  # normalised throttle (learnt in flight)
    },
    build=_ardupilot_stick_limits,
    hover_thrust="MOT_THST_HOVER",
)
"""ArduCopter's stick limits."""


@dataclass(frozen=True)
class ModeCodec:
    """How a stack shows a mode in HEARTBEAT ``custom_mode``, and sets it with
    ``MAV_CMD_DO_SET_MODE``'s param2 and param3.

    PX4 packs a main mode in bits 16-23 and a sub mode in bits 24-31 (its
    ``px4_custom_mode`` union); a mode is recognised by its main mode, and
    DO_SET_MODE takes the two as param2 and param3. ArduPilot's ``custom_mode``
    is the mode number itself, DO_SET_MODE's param2."""

    main_shift: int
    main_mask: int
    sub_shift: int | None
    """None: the stack has no sub modes."""

    def custom_mode(self, param2: float, param3: float) -> int:
        """The ``custom_mode`` a switch to (param2, param3) shows."""
        value = int(param2) << self.main_shift
        return value if self.sub_shift is None else value | int(param3) << self.sub_shift

    def main(self, custom_mode: int) -> int:
        """The main mode of a ``custom_mode``."""
        return (custom_mode >> self.main_shift) & self.main_mask

    def unnamed(self, custom_mode: int) -> str:
        """A label for a ``custom_mode`` the stack's tables do not name."""
        if self.sub_shift is None:
            return f"mode {custom_mode}"
        sub = (custom_mode >> self.sub_shift) & 0xFF
        main = self.main(custom_mode)
        return f"main {main} sub {sub}" if sub else f"main {main}"


PX4_MODES = ModeCodec(main_shift=16, main_mask=0xFF, sub_shift=24)
ARDUPILOT_MODES = ModeCodec(main_shift=0, main_mask=0xFFFFFFFF, sub_shift=None)


@dataclass(frozen=True, eq=False)
class FlightStack:
    """One flight stack's dialect (each exists once: compared and hashed by identity)."""

    name: str
    display_name: str
    """How the stack is named to a pilot ("PX4", "ArduPilot")."""
    autopilot_id: int
    modes: ModeCodec
    engage_mode: tuple[float, float]
    """DO_SET_MODE param2, param3 that engage the companion."""
    engage_label: str
    """The engage mode's name as the stack calls it."""
    safe_modes: dict[str, SafeMode] = field(default_factory=dict)
    auto_safe_modes: tuple[str, ...] = ()
    """``--safe-mode auto``'s candidates, most capable first (companion.handback)."""
    pilot_modes: frozenset[int] = frozenset()
    """``custom_mode`` values of every mode flown from the pilot's sticks (safe
    or not: ACRO too), for judging a mode the autopilot or the pilot chose."""
    throttle_modes: frozenset[int] = frozenset()
    """``custom_mode`` values of the modes whose throttle stick is the collective
    (PX4 MANUAL, ACRO, STABILIZED; ArduPilot STABILIZE, ACRO): engaged from one,
    the altitude and position modes take over at the pilot's throttle."""
    imu_message: str = "highres_imu"
    supports_actuator_output: bool = False
    max_imu_rate_hz: float = 1000.0
    """The fastest IMU stream worth asking for; the stack may still deny it."""
    imu_rate_limit: str = ""
    """What else caps the IMU stream below the rate asked, said where it falls short."""
    rate_shaping: RateShapingParams | None = None
    """How it shapes a body-rate setpoint before flying it; None: it flies it as sent."""
    rate_gains: RateLoopGains | None = None
    """Its rate loop's gain parameters, for ``--rates-law-axes auto``; None: not judged."""
    mode_names: dict[int, str] = field(default_factory=dict)
    """Names of its other modes by ``custom_mode`` (its failsafes' choices, for events)."""
    arm_refusals: tuple[str, ...] = ()
    """How the STATUSTEXTs begin with which the stack says why it refused to arm."""
    mode_refusals: tuple[str, ...] = ()
    """How the STATUSTEXTs begin with which it says why it refused a mode switch."""
    stick_params: StickParams = PX4_STICK_PARAMS
    """What limits the sticks in its angle, altitude and position modes."""
    thrust_param_bit: tuple[str, int] | None = None
    """The parameter and its bit without which ``SET_ATTITUDE_TARGET``'s thrust is
    not a normalised thrust (ArduPilot: GUID_OPTIONS bit 3, else a climb rate);
    None: it always is."""

    def is_engage_mode(self, custom_mode: int) -> bool:
        return self.modes.main(custom_mode) == int(self.engage_mode[0])

    def custom_mode(self, mode: SafeMode) -> int:
        """The HEARTBEAT ``custom_mode`` that shows ``mode``."""
        return self.modes.custom_mode(mode.param2, mode.param3)

    def safe_mode_shown(self, custom_mode: int) -> SafeMode | None:
        """The safe mode a HEARTBEAT ``custom_mode`` shows, or None."""
        for mode in self.safe_modes.values():
            if self.custom_mode(mode) == custom_mode:
                return mode
        return None

    def needs_rc(self, custom_mode: int) -> bool:
        """Whether the mode a HEARTBEAT shows is flown from the pilot's sticks."""
        return custom_mode in self.pilot_modes

    def mode_label(self, custom_mode: int) -> str:
        """A readable name of any ``custom_mode`` (for events)."""
        shown = self.safe_mode_shown(custom_mode)
        if shown is not None:
            return shown.name.upper()
        if self.is_engage_mode(custom_mode):
            return self.engage_label
        named = self.mode_names.get(custom_mode)
        if named is not None:
            return named
        return self.modes.unnamed(custom_mode)

    def mode(self, name: str) -> SafeMode:
        """A safe mode by name.

        Raises
        ------
        ValueError
            Naming the stack and the modes it has, for an unknown name.
        """
        try:
            return self.safe_modes[name]
        except KeyError:
            raise ValueError(
                f"{self.name} has no safe mode {name!r}: expected one of "
                f"{', '.join(sorted(self.safe_modes))}"
            ) from None


PX4 = FlightStack(
    name="px4",
    display_name="PX4",
    autopilot_id=12,
    modes=PX4_MODES,
    engage_mode=(6.0, 0.0),
    engage_label="OFFBOARD",
    safe_modes={
        m.name: m
        for m in (
            SafeMode("posctl", 3.0, 0.0, "rc", position_too=True),
            SafeMode("altctl", 2.0, 0.0, "rc"),
            SafeMode("stabilized", 7.0, 0.0, "rc"),
            SafeMode("manual", 1.0, 0.0, "rc"),
            SafeMode("hold", 4.0, 3.0, "position"),  # AUTO.LOITER
            SafeMode("land", 4.0, 6.0, "nothing"),  # AUTO.LAND
        )
    },
    auto_safe_modes=("posctl", "altctl", "hold", "land"),
    # MANUAL 1, ALTCTL 2, POSCTL 3, ACRO 5, STABILIZED 7 (main mode, bits 16-23)
    pilot_modes=frozenset(main << 16 for main in (1, 2, 3, 5, 7)),
    throttle_modes=frozenset(main << 16 for main in (1, 5, 7)),
    # PX4 main mode 5 ACRO; AUTO's sub modes (bits 24-31): 2 TAKEOFF, 4 MISSION, 5 RTL, 9 PRECLAND
    mode_names={
        5 << 16: "ACRO",
        4 << 16 | 2 << 24: "AUTO.TAKEOFF",
        4 << 16 | 4 << 24: "AUTO.MISSION",
        4 << 16 | 5 << 24: "AUTO.RTL",
        4 << 16 | 9 << 24: "AUTO.PRECLAND",
    },
    imu_message="highres_imu",
    supports_actuator_output=True,
    max_imu_rate_hz=1000.0,
    # HIGHRES_IMU is sensor_combined, published once per integration interval.
    imu_rate_limit="PX4 sends HIGHRES_IMU at most at IMU_INTEG_RATE (200 Hz by default): "
    "set it to at least --rate-hz",
    rate_gains=PX4_RATE_GAINS,
    # "Arming denied: Resolve system health failures first" follows the
    # "Preflight Fail: ..." that names the failing check; "Arm auth: Denied".
    arm_refusals=("Arming denied", "Preflight Fail", "Arm auth"),
    mode_refusals=("Switching to",),
    stick_params=PX4_STICK_PARAMS,
)

ARDUPILOT = FlightStack(
    name="ardupilot",
    # ArduCopter's GUID_OPTIONS bit 3 (value 8): SET_ATTITUDE_TARGET thrust is thrust.
    thrust_param_bit=("GUID_OPTIONS", 3),
    display_name="ArduPilot",
    autopilot_id=3,
    modes=ARDUPILOT_MODES,
    engage_mode=(20.0, 0.0),
    engage_label="GUIDED_NOGPS",
    safe_modes={
        m.name: m
        for m in (
            SafeMode("alt_hold", 2.0, 0.0, "rc"),
            SafeMode("stabilize", 0.0, 0.0, "rc"),
            SafeMode("loiter", 5.0, 0.0, "position"),
            SafeMode("brake", 17.0, 0.0, "position"),
            SafeMode("land", 9.0, 0.0, "nothing"),
        )
    },
    auto_safe_modes=("alt_hold", "loiter", "land"),
    # STABILIZE 0, ACRO 1, ALT_HOLD 2, DRIFT 11, SPORT 13, POSHOLD 16
    pilot_modes=frozenset((0, 1, 2, 11, 13, 16)),
    throttle_modes=frozenset((0, 1)),
    mode_names={
        1: "ACRO",
        3: "AUTO",
        4: "GUIDED",
        6: "RTL",
        7: "CIRCLE",
        11: "DRIFT",
        13: "SPORT",
        16: "POSHOLD",
        21: "SMART_RTL",
    },
    imu_message="attitude",
    supports_actuator_output=False,
    # ArduPilot denies intervals shorter than its loop period / 0.8 (~333 Hz at 400 Hz).
    max_imu_rate_hz=400.0,
    # AC_AttitudeControl::input_rate_bf_roll_pitch_yaw (Copter 4.5): the rate target slews
    # at ATC_ACCEL_*_MAX while ATC_RATE_FF_ENAB is set (defaults 110000/110000/27000).
    rate_shaping=RateShapingParams(
        "ATC_RATE_FF_ENAB",
        ("ATC_ACCEL_R_MAX", "ATC_ACCEL_P_MAX", "ATC_ACCEL_Y_MAX"),
        (110000.0, 110000.0, 27000.0),
    ),
    arm_refusals=("PreArm:", "Arm:"),
    # "Flight mode change failed": older ArduPilot's words, and the bundled SITL's.
    mode_refusals=("Mode change to", "Flight mode change failed"),
    stick_params=ARDUPILOT_STICK_PARAMS,
)

_BY_ID = {PX4.autopilot_id: PX4, ARDUPILOT.autopilot_id: ARDUPILOT}

_REASONS_QUOTED = 3
"""At most this many of the autopilot's reasons are quoted (PX4 names each failing
check in its own text)."""


def said_why(texts: Iterable[str], prefixes: tuple[str, ...]) -> str | None:
    """The texts among ``texts`` (the autopilot's STATUSTEXTs, oldest first) that
    begin with one of ``prefixes`` (a stack's :attr:`FlightStack.arm_refusals` or
    :attr:`FlightStack.mode_refusals`, compared without regard to case), each
    once, stripped (PX4 ends some with a tab), the first three joined by "; ";
    None if none does. Any other text, however recent, is not the reason."""
    wanted = tuple(p.casefold() for p in prefixes)
    found: list[str] = []
    for raw in texts:
        text = raw.strip()
        if text.casefold().startswith(wanted) and text not in found:
            found.append(text)
    return "; ".join(found[:_REASONS_QUOTED]) if found else None


def stack_for(autopilot_id: int) -> FlightStack | None:
    """The dialect for a HEARTBEAT ``autopilot`` value, or None if unsupported."""
    return _BY_ID.get(int(autopilot_id))
