"""The PX4-like autopilot logic of the SITL: modes, arming, offboard rules, failsafe, loops.

No sockets and no clock live here: :class:`Autopilot` is driven by the simulation
loop (``sitl.runner``) with simulation time, and the MAVLink face
(``sitl.px4_face``) turns messages into calls on it. That keeps every rule
testable without a network. What it shares with the ArduPilot personality
(arming, disarming, mode bookkeeping, events, RC presence) is
:class:`sitl.personality.Personality`.

Modes (PX4 ``custom_mode``: main mode in bits 16-23, sub mode in bits 24-31, ``sitl.px4_modes``)
--------------------------------------------------------------------------------------------------
========== ==== =====================================================================
mode       main what this autopilot does
========== ==== =====================================================================
MANUAL     1    stabilized from the sticks (what PX4 MANUAL does on a multicopter)
ALTCTL     2    same as STABILIZED here (no altitude hold: documented simplification)
POSCTL     3    same as STABILIZED here
AUTO       4    sub 3 LOITER (HOLD): level, hold climb rate 0 (test stand: level only);
                sub 6 LAND: level, descend at ``land_speed_m_s``, disarm when landed
ACRO       5    body rates from the sticks through the rate loop
OFFBOARD   6    follows the companion's setpoints (actuator controls or body rates)
STABILIZED 7    roll/pitch angle and yaw rate from the sticks
========== ==== =====================================================================

Offboard rules (as PX4)
-----------------------
* Switching to OFFBOARD is refused with ``MAV_RESULT_TEMPORARILY_REJECTED`` unless a
  setpoint arrived within ``offboard_entry_window_s`` (0.5 s: the ">= 2 Hz" rule).
* In OFFBOARD, if no setpoint arrives for ``offboard_timeout_s`` (parameter
  ``COM_OF_LOSS_T``) the vehicle fails safe. Default 1.0 s, PX4's
  ``COM_OF_LOSS_T`` default since v1.9 (commander_params.c; older releases had 0).
  As PX4's mode fallback (``Failsafe::checkModeFallback``, v1.14 and later) it
  says "Failsafe activated" (CRITICAL), shows CRITICAL while the fallback lasts and
  flies ``COM_OBL_RC_ACT``'s mode: 0 Position mode (POSCTL; ALTCTL without a
  position estimate, PX4's default), 1 Altitude (ALTCTL), 2 Stabilized (MANUAL up to
  1.13), 3 Return (flown as Land), 4 Land, 5 Hold (Land without a position),
  6 Terminate and 7 Disarm (motors off). The manual modes need stick input: without
  it PX4 >= 1.14 falls through to Hold; PX4 1.13 flies ``COM_OBL_ACT`` instead (0
  Land, 1 Hold, 2 Return, 3 Terminate, 4 Lockdown; -1 nothing). The real PX4 v1.16
  SIH, its companion killed with the joystick there, went to POSCTL. The fallback
  lasts while the setpoints do not come and the mode is not changed: a setpoint
  brings OFFBOARD back, a mode command ends it. On the test stand it switches to
  AUTO LOITER (main 4, sub 3) whatever the parameters: hold level with the last
  offboard thrust, clamped to [``failsafe_thrust_min``, hover thrust].
* Actuator setpoints (``SET_ACTUATOR_CONTROL_TARGET`` group 0, PX4 <= 1.13) are
  mixed directly; body-rate setpoints (``SET_ATTITUDE_TARGET`` with ``type_mask``
  bit 128) go through the internal rate loop first (PX4 >= 1.14). Non-finite
  setpoints are ignored and counted (:attr:`Autopilot.rejected_setpoints`).

RC and position (as PX4 >= 1.15, ``commander/failsafe``)
-------------------------------------------------------
* RC is the pilot's sticks reaching the autopilot, from a radio or from a ground
  station's joystick (``MANUAL_CONTROL`` from any sysid, taken when
  ``COM_RC_IN_MODE`` is 1, 2 or 3, :meth:`Autopilot.on_manual_control`; the face
  streams it back as PX4's own ``MANUAL_CONTROL`` while it is the stick input);
  lost after ``COM_RC_LOSS_T`` (0.5 s) without a frame. Armed, with RC lost, ACRO
  is refused (``TEMPORARILY_REJECTED``); MANUAL, STABILIZED, ALTCTL and POSCTL are
  taken as the real PX4 v1.16 SIH takes them: shown as POSCTL, in a failsafe
  (CRITICAL, STATUSTEXT "Failsafe activated") that descends at ``MPC_LAND_SPEED``
  and disarms on touchdown, until stick input comes back. In any mode but LAND and
  those ``COM_RCL_EXCEPT`` exempts (bit 1 hold, bit 2
  offboard; default none) the RC-loss failsafe acts: ``NAV_RCL_ACT`` 1 Hold
  (Land without a position), 2 Return (PX4's default; flown as Land: this SITL
  does not fly home), 3 Land, 5 Terminate and 6 Disarm (motors off where it is),
  0 nothing ("Disabled" in PX4 <= 1.13's list; PX4's failsafe maps 0 to no
  action, as for ``NAV_DLL_ACT``). RC already lost when arming (a vehicle flown with
  no radio) does not trigger it until RC has come back once. The hold before
  the action (``COM_FAIL_ACT_T``) is not modelled.
* A position estimate (``--no-position``, fault ``position-lost``): without one,
  POSCTL and AUTO.LOITER are refused; in POSCTL the autopilot falls back to
  ALTCTL, in AUTO.LOITER to LAND. AUTO.LAND is always accepted (from 1.15 it
  is forced through and flown as a descent without a position).

Parameters (``sitl.px4_params``)
--------------------------------
:attr:`Autopilot.params` is the PX4 parameter table the face serves. The
parameters this autopilot models (:data:`PX4_PARAMS`) start from
:class:`AutopilotConfig` and follow ``PARAM_SET`` at once, as PX4's commander
does; a value it cannot fly (``NAV_RCL_ACT`` 4, ``COM_OF_LOSS_T`` 0...) is
refused with the same error :class:`AutopilotConfig` gives. ``MC_ROLLRATE_K``,
``MC_PITCHRATE_K`` and ``MC_YAWRATE_K`` set the rate loop's gain per axis, and
``MC_*RATE_P`` its proportional term, as PX4's rate controller takes them,
keeping its integrator.

Arming rules
------------
* Arming is ``DENIED`` when the vehicle has crashed.
* Arming while not landed is ``DENIED`` except in OFFBOARD (a hand-over in flight).
* Arming in OFFBOARD is ``DENIED`` without recent setpoints.
* Disarming in the air is ``DENIED`` unless forced (param2 = 21196, as PX4).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

from companion.profile import VehicleProfile
from sitl.personality import (
    MAV_SEVERITY_CRITICAL,
    PILOT_ACRO_RATE_MAX_RAD_S,
    MavResult,
    Personality,
    clip,
    stick_unit,
    throttle_unit,
)
from sitl.px4_control import ControlAllocator, Px4RateLoop
from sitl.px4_modes import (
    AUTO_SUB_LAND,
    AUTO_SUB_LOITER,
    MODE_LAND,
    MODE_LOITER,
    MODE_OFFBOARD,
    FlightMode,
    MainMode,
)
from sitl.px4_params import Px4Params

__all__ = ["PX4_PARAMS", "Autopilot", "AutopilotConfig", "Joystick", "joystick_channels"]

logger = logging.getLogger(__name__)


_STICK_MODES = {
    MainMode.MANUAL,
    MainMode.ALTCTL,
    MainMode.POSCTL,
    MainMode.ACRO,
    MainMode.STABILIZED,
}


@dataclass(frozen=True)
class AutopilotConfig:
    """Tunables of the simulated autopilot (PX4 parameter names in the docs).

    Attributes
    ----------
    offboard_timeout_s
        ``COM_OF_LOSS_T``: setpoint silence in OFFBOARD before failsafe (PX4 default 1.0 s).
    offboard_entry_window_s
        A setpoint must be this recent to enter OFFBOARD (PX4 wants >= 2 Hz).
    test_stand
        The vehicle is on a test stand: the failsafe holds level instead of landing.
    hover_thrust
        Normalised collective thrust that hovers (``MPC_THR_HOVER``), in the
        allocator's units (0 armed idle, 1 full: :func:`sitl.px4_control.thrust_for_command`),
        used by the LAND/LOITER vertical loop and the test-stand failsafe.
    acro_rate_max_rad_s
        Full-stick body rates in ACRO (roll, pitch, yaw); the same linear map as the
        simulated pilot (``sitl.pilot``: 720, 720, 360 deg/s, ch2 > 1500 µs = nose up).
    tilt_max_rad
        Full-stick tilt in the stabilized modes (``MPC_MAN_TILT_MAX``, 35 deg).
    yaw_rate_max_rad_s
        Full-stick yaw rate in the stabilized modes (``MPC_MAN_Y_MAX``, 150 deg/s).
    attitude_p
        Attitude P gains roll, pitch (``MC_ROLL_P``, ``MC_PITCH_P``: 6.5), rad/s per rad.
    attitude_rate_max_rad_s
        Rate setpoint limit of the attitude loop (``MC_ROLLRATE_MAX`` 220 deg/s).
    land_speed_m_s
        Descent speed in AUTO LAND (``MPC_LAND_SPEED`` 0.7 m/s).
    climb_p, climb_i
        Vertical-speed loop gains, normalised thrust per m/s (and per m).
    failsafe_thrust_min
        Lowest thrust of the test-stand hold.
    rc_loss_timeout_s
        ``COM_RC_LOSS_T``: RC silence before it counts as lost (0.5 s).
    rc_loss_action
        ``NAV_RCL_ACT``: 0 none, 1 Hold, 2 Return (flown as Land), 3 Land,
        5 Terminate, 6 Disarm; default 2.
    rc_loss_exceptions
        ``COM_RCL_EXCEPT`` bits: 2 (bit 1) hold, 4 (bit 2) offboard; default 0.
    """

    offboard_timeout_s: float = 1.0
    offboard_entry_window_s: float = 0.5
    test_stand: bool = False
    hover_thrust: float = 0.5
    acro_rate_max_rad_s: tuple[float, float, float] = PILOT_ACRO_RATE_MAX_RAD_S
    tilt_max_rad: float = math.radians(35.0)
    yaw_rate_max_rad_s: float = math.radians(150.0)
    attitude_p: tuple[float, float] = (6.5, 6.5)
    attitude_rate_max_rad_s: float = math.radians(220.0)
    land_speed_m_s: float = 0.7
    climb_p: float = 0.25
    climb_i: float = 0.1
    failsafe_thrust_min: float = 0.1
    rc_loss_timeout_s: float = 0.5
    rc_loss_action: int = 2
    rc_loss_exceptions: int = 0

    def __post_init__(self) -> None:
        if not (self.offboard_timeout_s > 0.0 and math.isfinite(self.offboard_timeout_s)):
            raise ValueError(f"offboard_timeout_s must be > 0, got {self.offboard_timeout_s}")
        if not 0.0 < self.hover_thrust < 1.0:
            raise ValueError(f"hover_thrust must be in (0, 1), got {self.hover_thrust}")
        if not (self.rc_loss_timeout_s > 0.0 and math.isfinite(self.rc_loss_timeout_s)):
            raise ValueError(f"COM_RC_LOSS_T must be > 0, got {self.rc_loss_timeout_s}")
        if self.rc_loss_action not in _RCL_ACTIONS:
            raise ValueError(
                f"NAV_RCL_ACT {self.rc_loss_action} is not modelled: expected 0, 1, 2, 3, 5 or 6"
            )
        if not 0 <= self.rc_loss_exceptions <= 31:
            raise ValueError(f"COM_RCL_EXCEPT must be in 0..31, got {self.rc_loss_exceptions}")


PX4_PARAMS = {
    "COM_OF_LOSS_T": "offboard_timeout_s",
    "COM_RC_LOSS_T": "rc_loss_timeout_s",
    "NAV_RCL_ACT": "rc_loss_action",
    "COM_RCL_EXCEPT": "rc_loss_exceptions",
}
"""The PX4 parameters this autopilot follows, by the :class:`AutopilotConfig` field
each sets (the rest of :class:`~sitl.px4_params.Px4Params` is stored only)."""

_RATE_GAIN_PARAMS = {
    f"MC_{axis}RATE_{term}": (i, term.lower())
    for i, axis in enumerate(("ROLL", "PITCH", "YAW"))
    for term in ("K", "P")
}
"""The rate loop's global gain and proportional term per axis: the axis, and the
:class:`sitl.px4_control.Px4AxisGains` field each sets."""

_RCL_EXCEPT_HOLD = 2
_RCL_EXCEPT_OFFBOARD = 4
_RCL_NONE, _RCL_HOLD, _RCL_TERMINATE, _RCL_DISARM = 0, 1, 5, 6
_RCL_ACTIONS = (_RCL_NONE, _RCL_HOLD, 2, 3, _RCL_TERMINATE, _RCL_DISARM)
_JOYSTICK_IN_MODES = (1, 2, 3)
"""``COM_RC_IN_MODE`` values that take a ground station's joystick: 1 joystick only,
2 RC and joystick with fallback, 3 RC or joystick, the first kept (0 RC only, 4 no
stick input)."""
MANUAL_LOSS = "manual_control_loss"
"""The failsafe of a manual mode entered without stick input."""
OFFBOARD_LOSS = "offboard_loss"
"""The failsafe of OFFBOARD without setpoints for ``COM_OF_LOSS_T``."""
_OBL_POSITION, _OBL_ALTITUDE, _OBL_STABILIZED, _OBL_RETURN, _OBL_LAND, _OBL_HOLD = range(6)
_OBL_TERMINATE, _OBL_DISARM, _OBL_NONE = 6, 7, -1
_OBL_LEGACY = {0: _OBL_LAND, 1: _OBL_HOLD, 2: _OBL_RETURN, 3: _OBL_TERMINATE, 4: _OBL_DISARM}
"""PX4 1.13's ``COM_OBL_ACT`` (offboard lost without RC) as ``COM_OBL_RC_ACT`` values."""


@dataclass(frozen=True)
class Joystick:
    """A ground station's ``MANUAL_CONTROL`` as PX4 takes it: ``x`` pitch (stick
    forward +), ``y`` roll (right +), ``r`` yaw (right +), each -1000..1000; ``z``
    thrust 0..1000; ``aux`` aux1..aux6 (-1000..1000), present where
    ``enabled_extensions`` bits 2..7 say so."""

    x: int
    y: int
    z: int
    r: int
    enabled_extensions: int = 0
    aux: tuple[int, int, int, int, int, int] = (0, 0, 0, 0, 0, 0)


def joystick_channels(j: Joystick) -> tuple[int, ...]:
    """The joystick as the SITL's AETR channels in us: roll ``1500 + y/2``, pitch
    ``1500 - x/2`` (stick forward is nose down, a low channel here), throttle
    ``1000 + z``, yaw ``1500 + r/2``, then aux1..aux6 as ``1500 + aux/2`` (centred
    where absent)."""
    chans = [1500 + j.y // 2, 1500 - j.x // 2, 1000 + j.z, 1500 + j.r // 2]
    for i in range(6):
        chans.append(1500 + j.aux[i] // 2 if j.enabled_extensions & (4 << i) else 1500)
    return tuple(chans)


@dataclass
class _Setpoint:
    kind: Literal["actuator", "rates"]
    t_s: float
    values: tuple[float, float, float, float]  # (roll, pitch, yaw, thrust)


class Autopilot(Personality[FlightMode]):
    """A PX4-like multicopter autopilot: commander + rate loop + allocation.

    The rate loop and the allocation are PX4 v1.16's (:mod:`sitl.px4_control`):
    ``RateControl`` on the filtered gyro, the yaw-torque low-pass, and the
    sequential-desaturation allocator with ``MC_AIRMODE`` 0, whose [0, 1] spans
    the motors' armed idle to full.

    Parameters
    ----------
    profile
        The vehicle; its frame makes the allocation (``physics.mixer`` picks geometry or
        the paper's '+' frame) and ``limits`` gives the idle and the rate limits.
    config
        Tunables, see :class:`AutopilotConfig`; the parameters of :data:`PX4_PARAMS`
        start from it.
    initial_mode
        Mode at boot (PX4 SITL boots disarmed in a manual mode).
    params
        The parameter table (a new :class:`~sitl.px4_params.Px4Params` by default).
    """

    refusal = MavResult.DENIED
    land_mode = MODE_LAND
    log = logger
    rate_pid: Px4RateLoop
    params: Px4Params

    def __init__(
        self,
        profile: VehicleProfile,
        config: AutopilotConfig | None = None,
        *,
        initial_mode: FlightMode | None = None,
        params: Px4Params | None = None,
    ) -> None:
        self.motor_idle = profile.limits.motor_idle
        super().__init__(profile, initial_mode=initial_mode or FlightMode(MainMode.MANUAL))
        self.config = config or AutopilotConfig()
        self.params = params if params is not None else Px4Params()
        for name, field_name in PX4_PARAMS.items():
            self.params.set(name, getattr(self.config, field_name))
        # Only now: the seeds leave the config as given (COM_OF_LOSS_T's is a float32).
        self.params.add_check(self._check_param)
        self.params.on_change(self._param_changed)
        self.allocator = ControlAllocator.from_profile(profile)
        self.rate_pid = Px4RateLoop(self.allocator)
        self._setpoint: _Setpoint | None = None
        self._rc_lost_at_arming = False
        self._rc_loss_handled = False
        self._last_rate_t_s: float | None = None
        self._joystick: Joystick | None = None
        self._joystick_t_s: float | None = None
        self._offboard_fallback = False
        """OFFBOARD is what the user asked for, and its offboard-loss fallback is flown."""

    # ------------------------------------------------------------------ status

    @property
    def base_mode(self) -> int:
        """``MAV_MODE_FLAG``: custom mode enabled (1), armed (128), plus the usual PX4 bits."""
        flags = 1  # MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.mode.main in _STICK_MODES:
            flags |= 64  # MANUAL_INPUT_ENABLED
        if self.mode.main != MainMode.ACRO:
            flags |= 16  # STABILIZE_ENABLED
        if self.mode.main in (MainMode.AUTO, MainMode.OFFBOARD):
            flags |= 4 | 8  # AUTO_ENABLED | GUIDED_ENABLED
        if self.armed:
            flags |= 128  # MAV_MODE_FLAG_SAFETY_ARMED
        return flags

    @property
    def external_control(self) -> bool:
        """True in OFFBOARD: a companion's setpoints drive the vehicle (lockstep waits)."""
        return self.mode.main == MainMode.OFFBOARD

    @property
    def system_status(self) -> int:
        """``MAV_STATE``: CRITICAL (5) in a failsafe, else STANDBY (3) or ACTIVE (4, armed)."""
        if self.failsafe is not None:
            return 5
        return 4 if self.armed else 3

    def joystick(self, t_s: float) -> Joystick | None:
        """The ground station's joystick while it is PX4's stick input (frames within
        ``COM_RC_LOSS_T``), else None: what PX4 streams back as ``MANUAL_CONTROL``."""
        jt = self._joystick_t_s
        if jt is None or t_s - jt > self.rc_timeout_s:
            return None
        return self._joystick

    def rc_receiver(self, t_s: float) -> tuple[bool, bool, bool]:
        """SYS_STATUS's RC bit: a radio's (as the base), or the joystick's: present,
        enabled and healthy while it streams, not present once it stops."""
        if self._joystick_t_s is not None:
            on = self.joystick(t_s) is not None
            return (on, on, on)
        return super().rc_receiver(t_s)

    @property
    def rc_timeout_s(self) -> float:
        """``COM_RC_LOSS_T``."""
        return self.config.rc_loss_timeout_s

    def setpoint_age_s(self, t_s: float) -> float:
        """Seconds since the last accepted offboard setpoint (inf if none)."""
        return math.inf if self._setpoint is None else t_s - self._setpoint.t_s

    # ------------------------------------------------------------ parameters

    def _config_with(self, name: str, value: float) -> AutopilotConfig:
        field_name = PX4_PARAMS[name]
        v: Any = value if field_name.endswith("_s") else int(value)
        return dataclasses.replace(self.config, **{field_name: v})

    def _check_param(self, name: str, value: float) -> None:
        """Refuse a value the autopilot cannot fly (AutopilotConfig's ValueError)."""
        if name in PX4_PARAMS:
            self._config_with(name, value)

    def _param_changed(self, name: str, value: float) -> None:
        if name in PX4_PARAMS:
            self.config = self._config_with(name, value)
        elif name in _RATE_GAIN_PARAMS:
            control = self.rate_pid.control
            gains = list(control.gains)
            axis, term = _RATE_GAIN_PARAMS[name]
            gains[axis] = dataclasses.replace(gains[axis], **{term: value})
            control.set_gains(gains)

    # ---------------------------------------------------------------- commands

    def _arming_checks(self, t_s: float, *, force: bool) -> MavResult | None:
        if self.crashed:
            return self._arm_denied(t_s, "crashed")
        if self.mode == MODE_OFFBOARD:
            if self.setpoint_age_s(t_s) > self.config.offboard_entry_window_s:
                return self._arm_denied(t_s, "no offboard setpoints")
        elif not self.landed and not force:
            return self._arm_denied(t_s, "not landed")
        return None

    def _on_armed(self, t_s: float) -> None:
        self._rc_lost_at_arming = self.rc_lost(t_s)
        # The flight starts here: the gyro filters, the rate loop and its sample
        # clock too, so that it does not depend on how long the vehicle sat disarmed
        # nor on where between two samples the arm command came (PX4's filters run
        # on; at rest the difference is noise).
        self.rate_pid.filter.reset()
        self.rate_pid.reset()
        self._last_rate_t_s = None

    def set_mode(self, t_s: float, main: int, sub: int = 0) -> MavResult:
        """Request a mode (``MAV_CMD_DO_SET_MODE`` param2 = main, param3 = sub).

        An accepted one is the user's choice: an offboard-loss fallback ends there.
        """
        result = self._set_mode(t_s, main, sub)
        if result == MavResult.ACCEPTED and self._offboard_fallback:
            self._offboard_fallback = False
            if self.failsafe == OFFBOARD_LOSS:
                self.failsafe = None
        return result

    def _set_mode(self, t_s: float, main: int, sub: int) -> MavResult:
        try:
            main_mode = MainMode(main)
        except ValueError:
            return MavResult.DENIED
        if main_mode != MainMode.AUTO:
            sub = 0
        elif sub not in (AUTO_SUB_LAND, AUTO_SUB_LOITER):
            # Mission, RTL, takeoff... need navigation this SITL does not have.
            return MavResult.TEMPORARILY_REJECTED
        new = FlightMode(main_mode, sub)
        if new == self.mode:
            return MavResult.ACCEPTED
        if self.armed and main_mode in _STICK_MODES and self.rc_lost(t_s):
            if main_mode == MainMode.ACRO:
                self._event(t_s, "mode_denied", mode=new.name, reason="no manual control")
                return MavResult.TEMPORARILY_REJECTED
            # PX4 v1.16 takes the manual mode, shows POSCTL, and fails safe at once.
            return self._manual_mode_without_sticks(t_s)
        if (
            self.armed
            and (main_mode == MainMode.POSCTL or new == MODE_LOITER)
            and not self.position_valid
        ):
            self._event(t_s, "mode_denied", mode=new.name, reason="no position estimate")
            return MavResult.TEMPORARILY_REJECTED
        if (
            main_mode == MainMode.OFFBOARD
            and self.setpoint_age_s(t_s) > self.config.offboard_entry_window_s
        ):
            self._event(t_s, "mode_denied", mode=new.name, reason="no offboard setpoints")
            return MavResult.TEMPORARILY_REJECTED
        self._change_mode(t_s, new, reason="command")
        return MavResult.ACCEPTED

    def _manual_mode_without_sticks(self, t_s: float) -> MavResult:
        """A manual mode (MANUAL, STABILIZED, ALTCTL, POSCTL) asked for with no valid
        stick input: as the real PX4 v1.16 SITL did, the command is accepted, the
        vehicle shows POSCTL (ALTCTL without a position estimate), raises its
        failsafe (HEARTBEAT CRITICAL, STATUSTEXT "Failsafe activated") and
        descends (``MPC_LAND_SPEED``; about 0.6 m/s measured) until stick input
        comes back or it lands and disarms."""
        shown = FlightMode(MainMode.POSCTL if self.position_valid else MainMode.ALTCTL)
        if shown != self.mode:
            self._change_mode(t_s, shown, reason="command")
        if self.failsafe != MANUAL_LOSS:
            self.failsafe = MANUAL_LOSS
            self._text(MAV_SEVERITY_CRITICAL, "Failsafe activated")
            self._event(t_s, "failsafe", cause=MANUAL_LOSS, action="DESCEND")
        return MavResult.ACCEPTED

    def _on_mode_change(self, new: FlightMode) -> None:
        if new != MODE_LAND and new != MODE_LOITER:
            self.failsafe = None

    # --------------------------------------------------------------- setpoints

    def on_actuator_target(self, t_s: float, controls: Sequence[float]) -> bool:
        """``SET_ACTUATOR_CONTROL_TARGET`` group 0: roll, pitch, yaw torque, thrust.

        Returns
        -------
        bool
            False when the setpoint was rejected (non-finite first four controls).
        """
        if len(controls) < 4 or not all(math.isfinite(c) for c in controls[:4]):
            self.rejected_setpoints += 1
            return False
        self._setpoint = _Setpoint(
            "actuator",
            t_s,
            (
                clip(controls[0], -1.0, 1.0),
                clip(controls[1], -1.0, 1.0),
                clip(controls[2], -1.0, 1.0),
                clip(controls[3], 0.0, 1.0),
            ),
        )
        self.accepted_setpoints += 1
        return True

    def on_rates_target(self, t_s: float, rates_frd_rad_s: Sequence[float], thrust: float) -> bool:
        """``SET_ATTITUDE_TARGET`` with attitude ignored: body rates (rad/s) + thrust [0, 1].

        Rates are clipped to the profile's ``limits.rate_max_deg_s``.

        Returns
        -------
        bool
            False when the setpoint was rejected (non-finite values).
        """
        vals = (*rates_frd_rad_s[:3], thrust)
        if len(rates_frd_rad_s) < 3 or not all(math.isfinite(v) for v in vals):
            self.rejected_setpoints += 1
            return False
        rm = self.rate_max_rad_s
        self._setpoint = _Setpoint(
            "rates",
            t_s,
            (
                clip(vals[0], -rm[0], rm[0]),
                clip(vals[1], -rm[1], rm[1]),
                clip(vals[2], -rm[2], rm[2]),
                clip(thrust, 0.0, 1.0),
            ),
        )
        self.accepted_setpoints += 1
        return True

    # -------------------------------------------------------------------- loop

    def on_manual_control(self, t_s: float, joystick: Joystick) -> bool:
        """A ground station's ``MANUAL_CONTROL`` (from any sysid): PX4's stick input when
        ``COM_RC_IN_MODE`` takes a joystick (1, 2, 3), as RC frames are.

        Returns
        -------
        bool
            False when ignored (``COM_RC_IN_MODE`` 0 or 4, or a value out of range).
        """
        if int(self.params["COM_RC_IN_MODE"]) not in _JOYSTICK_IN_MODES:
            return False
        j = joystick
        if not (all(-1000 <= v <= 1000 for v in (j.x, j.y, j.r, *j.aux)) and 0 <= j.z <= 1000):
            self.rejected_setpoints += 1
            return False
        self._joystick, self._joystick_t_s = j, t_s
        self._rc_t_s = t_s
        self._last_sticks = joystick_channels(j)
        self._on_rc_frame()
        return True

    def _on_rc_frame(self) -> None:
        self._rc_lost_at_arming = False
        self._rc_loss_handled = False
        if self.failsafe == MANUAL_LOSS:
            self.failsafe = None  # stick input is back: PX4 leaves the failsafe

    def _step(
        self,
        t_s: float,
        gyro_frd_rad_s: Sequence[float],
        euler_rad: Sequence[float],
        climb_rate_m_s: float,
    ) -> tuple[float, ...]:
        """The commander checks and one rate-loop iteration.

        The rate loop's dt comes from consecutive samples, clamped to 0.125..20 ms
        as PX4 does.
        """
        self._check_offboard_loss(t_s)
        self._check_rc_loss(t_s)
        self._check_position(t_s)
        # In whole microseconds, as PX4's hrt_abstime: the difference of two large
        # times would carry their rounding, and a flight would depend on when it began.
        dt_s = (
            0.004
            if self._last_rate_t_s is None
            else round((t_s - self._last_rate_t_s) * 1e6) * 1e-6
        )
        self._last_rate_t_s = t_s
        dt_s = clip(dt_s, 0.000125, 0.02)
        # vehicle_angular_velocity runs on every sample, armed or not.
        self.rate_pid.filter_gyro(gyro_frd_rad_s, dt_s)

        if not self.armed:
            return self._disarmed()

        main = self.mode.main
        sp = self._setpoint
        if main == MainMode.OFFBOARD and sp is not None:
            if sp.kind == "actuator":
                torque_thrust = sp.values
            else:
                torque_thrust = self._rate_loop(dt_s, sp.values[:3], sp.values[3])
        elif self.mode in (MODE_LAND, MODE_LOITER):
            descend = self.mode == MODE_LAND
            torque_thrust = self._auto_loop(t_s, dt_s, euler_rad, climb_rate_m_s, descend=descend)
        elif self.failsafe == MANUAL_LOSS:
            torque_thrust = self._auto_loop(t_s, dt_s, euler_rad, climb_rate_m_s, descend=True)
        else:
            # Until RC counts as lost, the last frame holds (as PX4's manual_control_setpoint).
            sticks = None if self.rc_lost(t_s) else self._last_sticks
            torque_thrust = self._stick_loop(dt_s, euler_rad, sticks)
        return self._allocate(torque_thrust)

    def _check_offboard_loss(self, t_s: float) -> None:
        """PX4's offboard-loss mode fallback (see the module's docstring): entered
        after ``COM_OF_LOSS_T`` in OFFBOARD, its mode chosen again on each sample
        while it lasts (the stick input may go or come), left for OFFBOARD when a
        setpoint arrives."""
        if not self.armed:
            self._offboard_fallback = False
            return
        lost = self.setpoint_age_s(t_s) > self.config.offboard_timeout_s
        if self._offboard_fallback:
            if not lost:
                self._offboard_fallback = False
                self._change_mode(t_s, MODE_OFFBOARD, reason="offboard regained")
                self._event(t_s, "failsafe_cleared", cause=OFFBOARD_LOSS)
                return
            new = self._offboard_loss_mode(t_s)
            if new is not None and new != self.mode:
                self._enter_failsafe(t_s, OFFBOARD_LOSS, new, reason="offboard lost")
            return
        if self.mode != MODE_OFFBOARD or not lost:
            return
        action = self._offboard_loss_action(t_s)
        if action == _OBL_NONE:
            return
        self._text(MAV_SEVERITY_CRITICAL, "Failsafe activated")
        if action in (_OBL_TERMINATE, _OBL_DISARM):
            self.failsafe = OFFBOARD_LOSS
            name = "TERMINATE" if action == _OBL_TERMINATE else "DISARM"
            self._event(t_s, "failsafe", cause=OFFBOARD_LOSS, action=name)
            self.disarm(t_s, force=True, reason="offboard lost")
            return
        new = self._offboard_loss_mode(t_s)
        assert new is not None
        self._offboard_fallback = True
        self._enter_failsafe(t_s, OFFBOARD_LOSS, new, reason="offboard lost")

    def _offboard_loss_action(self, t_s: float) -> int:
        """The offboard-loss action as a ``COM_OBL_RC_ACT`` value: that parameter's,
        or with no stick input on PX4 1.13 (which has ``COM_OBL_ACT``) that one's;
        Hold on the test stand."""
        if self.config.test_stand:
            return _OBL_HOLD
        params = self.params
        if "COM_OBL_ACT" in params and self.rc_lost(t_s):
            return _OBL_LEGACY.get(int(params["COM_OBL_ACT"]), _OBL_NONE)
        return int(params["COM_OBL_RC_ACT"])

    def _offboard_loss_mode(self, t_s: float) -> FlightMode | None:
        """The mode the offboard-loss fallback flies now (None: no mode, it disarms
        or does nothing). The manual modes need stick input and fall through to Hold
        without it (PX4 >= 1.14's ``getSelectedAction``); Position mode needs a
        position estimate (else Altitude); Hold too (else Land); Return is flown as
        Land (no navigation here)."""
        if self.config.test_stand:
            return MODE_LOITER
        action = self._offboard_loss_action(t_s)
        if action in (_OBL_TERMINATE, _OBL_DISARM, _OBL_NONE):
            return None
        if action in (_OBL_POSITION, _OBL_ALTITUDE, _OBL_STABILIZED):
            if self.rc_lost(t_s):
                action = _OBL_HOLD
            elif action == _OBL_POSITION and self.position_valid:
                return FlightMode(MainMode.POSCTL)
            elif action != _OBL_STABILIZED:
                return FlightMode(MainMode.ALTCTL)
            elif "COM_OBL_ACT" in self.params:
                return FlightMode(MainMode.MANUAL)  # PX4 1.13's value 2: Manual
            else:
                return FlightMode(MainMode.STABILIZED)
        if action == _OBL_HOLD and self.position_valid:
            return MODE_LOITER
        return MODE_LAND

    def _check_rc_loss(self, t_s: float) -> None:
        """PX4's RC-loss failsafe (``NAV_RCL_ACT``), once per loss."""
        if not self.armed or self._rc_loss_handled or self._rc_lost_at_arming:
            return
        if not self.rc_lost(t_s):
            return
        exc = self.config.rc_loss_exceptions
        # What the user asked for: OFFBOARD while its offboard-loss fallback flies.
        mode = MODE_OFFBOARD if self._offboard_fallback else self.mode
        if (
            mode == MODE_LAND
            or (mode == MODE_LOITER and exc & _RCL_EXCEPT_HOLD)
            or (mode == MODE_OFFBOARD and exc & _RCL_EXCEPT_OFFBOARD)
        ):
            return
        self._rc_loss_handled = True
        action = self.config.rc_loss_action
        if action == _RCL_NONE:
            return
        self._offboard_fallback = False  # the worse action wins, and stays
        if action in (_RCL_TERMINATE, _RCL_DISARM):
            # Motors off where it is (Terminate also fires a parachute PX4 may have).
            self.failsafe = "rc_loss"
            name = "TERMINATE" if action == _RCL_TERMINATE else "DISARM"
            self._event(t_s, "failsafe", cause="rc_loss", action=name)
            self.disarm(t_s, force=True, reason="rc lost")
            return
        hold = action == _RCL_HOLD and self.position_valid
        new = MODE_LOITER if hold else MODE_LAND
        self._enter_failsafe(t_s, "rc_loss", new, reason="rc lost")

    def _check_position(self, t_s: float) -> None:
        """Without a position estimate POSCTL falls back to ALTCTL, AUTO.LOITER to LAND."""
        if self.position_valid or not self.armed:
            return
        if self.mode.main == MainMode.POSCTL:
            self._change_mode(t_s, FlightMode(MainMode.ALTCTL), reason="position lost")
        elif self.mode == MODE_LOITER and not self.config.test_stand:
            self._enter_failsafe(t_s, "position_loss", MODE_LAND, reason="position lost")

    def _rate_loop(
        self, dt_s: float, rate_sp_rad_s: Sequence[float], thrust: float
    ) -> tuple[float, float, float, float]:
        # The land detector's "landed" freezes the integrator (RateControl::update).
        tq = self.rate_pid.torque(rate_sp_rad_s, dt_s, landed=self.landed)
        return (tq[0], tq[1], tq[2], thrust)

    def _level_rates(
        self, euler_rad: Sequence[float], roll_sp: float, pitch_sp: float
    ) -> tuple[float, float]:
        cfg = self.config
        lim = cfg.attitude_rate_max_rad_s
        p = clip(cfg.attitude_p[0] * (roll_sp - euler_rad[0]), -lim, lim)
        q = clip(cfg.attitude_p[1] * (pitch_sp - euler_rad[1]), -lim, lim)
        return p, q

    def _stick_loop(
        self,
        dt_s: float,
        euler_rad: Sequence[float],
        sticks_us: Sequence[int] | None,
    ) -> tuple[float, float, float, float]:
        if sticks_us is None or len(sticks_us) < 4:
            roll_s, pitch_s, thr, yaw_s = 0.0, 0.0, 0.0, 0.0
        else:
            roll_s, pitch_s = stick_unit(sticks_us[0]), stick_unit(sticks_us[1])
            thr, yaw_s = throttle_unit(sticks_us[2]), stick_unit(sticks_us[3])
        cfg = self.config
        if self.mode.main == MainMode.ACRO:
            rm = cfg.acro_rate_max_rad_s
            # Project convention (sitl.pilot): ch2 > 1500 µs is "stick back" = +q, nose up.
            rates = (roll_s * rm[0], pitch_s * rm[1], yaw_s * rm[2])
        else:
            p, q = self._level_rates(
                euler_rad, roll_s * cfg.tilt_max_rad, pitch_s * cfg.tilt_max_rad
            )
            rates = (p, q, yaw_s * cfg.yaw_rate_max_rad_s)
        return self._rate_loop(dt_s, rates, thr)

    def _auto_loop(
        self,
        t_s: float,
        dt_s: float,
        euler_rad: Sequence[float],
        climb_rate_m_s: float,
        *,
        descend: bool,
    ) -> tuple[float, float, float, float]:
        cfg = self.config
        p, q = self._level_rates(euler_rad, 0.0, 0.0)
        hover = cfg.hover_thrust
        if cfg.test_stand:
            last = self.last_torque_thrust[3]
            thrust = clip(last, cfg.failsafe_thrust_min, hover)
        else:
            if descend and self.landed:
                self.disarm(t_s, reason="landed")
                return (0.0, 0.0, 0.0, 0.0)
            climb_sp = -cfg.land_speed_m_s if descend else 0.0
            err = climb_sp - climb_rate_m_s
            self._climb_integral = clip(self._climb_integral + err * dt_s, -2.0, 2.0)
            tilt = max(math.cos(euler_rad[0]) * math.cos(euler_rad[1]), 0.5)
            thrust = (hover + cfg.climb_p * err + cfg.climb_i * self._climb_integral) / tilt
            thrust = clip(thrust, 0.05, 0.95)
        return self._rate_loop(dt_s, (p, q, 0.0), thrust)

    def _allocate(self, torque_thrust: Sequence[float]) -> tuple[float, ...]:
        roll, pitch, yaw, thrust = (float(x) for x in torque_thrust)
        if not all(math.isfinite(v) for v in (roll, pitch, yaw, thrust)):
            # PX4 zeroes non-finite controller outputs rather than sending them out.
            roll = pitch = yaw = 0.0
            thrust = 0.0 if not math.isfinite(thrust) else thrust
        thrust = clip(thrust, 0.0, 1.0)
        self.last_torque_thrust = (roll, pitch, yaw, thrust)
        # The allocator's saturation reaches the integrator on the next sample.
        res = self.rate_pid.allocate((roll, pitch, yaw), thrust)
        # Armed, the allocator's 0 is the motors' idle (PWM_MAIN_MINn).
        self.motors = self.allocator.motor_commands(res.actuators)
        return self.motors
