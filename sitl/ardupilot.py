"""The SITL's ArduPilot personality: an ArduCopter-like autopilot.

``sitl run --autopilot ardupilot`` shows the vehicle as ArduCopter 4.x would
(``docs/research/ardupilot.md`` lists what was checked against ArduPilot's source and what
is assumed). Like :mod:`sitl.autopilot`, the autopilot logic here has no sockets
and no clock: :class:`ArduCopter` is driven with simulation time by the runner,
and :class:`sitl.ardupilot_face.ArduPilotFace` turns MAVLink into calls on it.
What it shares with the PX4 personality (arming, disarming, mode bookkeeping,
events, RC presence) is :class:`sitl.personality.Personality`; its parameters
are :mod:`sitl.ardupilot_params`, its other tunables :mod:`sitl.ardupilot_config`,
its filter, rate PID and thrust curve :mod:`sitl.ardupilot_control`.

Modes (Copter ``custom_mode`` = mode number, ``ArduCopter/mode.h``)
--------------------------------------------------------------------
============= == ===========================================================
mode          no what this autopilot does
============= == ===========================================================
STABILIZE     0  angles + yaw rate from the sticks, manual throttle
ACRO          1  body rates from the sticks, manual throttle
ALT_HOLD      2  angles from the sticks, throttle stick = climb rate
GUIDED        4  SET_ATTITUDE_TARGET body rates; without them level + hold altitude
LOITER        5  as ALT_HOLD (no horizontal hold here); needs a position estimate
LAND          9  level, descend at ``LAND_SPEED``, disarm on touchdown
BRAKE         17 level, hold altitude and heading, sticks ignored; needs a position
GUIDED_NOGPS  20 SET_ATTITUDE_TARGET body rates (the companion's way in)
============= == ===========================================================

AUTO 3 and RTL 6 need navigation this SITL does not have: asking for them (or
any other number) answers ``MAV_RESULT_FAILED``, as ArduPilot's
``GCS_MAVLINK::_set_mode_common`` does when ``set_mode`` fails. Armed without a
position estimate (``--no-position``, fault ``position-lost``), LOITER and
BRAKE fail the same way ("requires position"); losing it in them is the EKF
failsafe: LAND.

Radio failsafe (``Copter::read_radio``, ``events.cpp``)
-------------------------------------------------------
RC is lost after ``RC_FS_TIMEOUT`` (1 s) without a frame, once RC has been seen
or the vehicle is armed, with ``FS_THR_ENABLE`` set (default 1). On that edge:
in GUIDED / GUIDED_NOGPS with ``FS_OPTIONS`` bit 2 (4) it carries on; landed, it
disarms; otherwise ``FS_THR_ENABLE`` 1 RTL, 3 Land, 4/5 SmartRTL are flown as
LAND (no navigation here), 7 as BRAKE with a position, else LAND. Without RC the
pilot's inputs read zero (level, no climb, no yaw rate); STABILIZE and ACRO are
refused during the failsafe (as ArduCopter 4.7 does).

GUIDED attitude targets (``GCS_MAVLINK_Copter::handle_message_set_attitude_target``)
------------------------------------------------------------------------------------
* Ignored outside GUIDED / GUIDED_NOGPS.
* The thrust field must be given; body rates all three or none (a partial mask,
  or an ignored thrust, is rejected: ArduPilot calls ``mode_guided.init(true)``,
  which in GUIDED stops the vehicle and in GUIDED_NOGPS leaves the previous target
  running until the timeout). An attitude quaternion is not supported here
  (rejected and counted).
* ``thrust`` is a climb-rate request unless ``GUID_OPTIONS`` bit 3 (8) is set:
  clipped to [0, 1]; 0.5 -> 0; above, ``(t - 0.5) * 2 * WPNAV_SPEED_UP``;
  below, ``-(0.5 - t) * 2 * WPNAV_SPEED_DN`` (2.5 and 1.5 m/s by default).
  With bit 3 it is collective thrust, clipped to [-1, 1] then [0, 1] by the motors,
  with ArduPilot's angle boost (``AC_AttitudeControl_Multi::get_throttle_boosted``).
* After ``GUID_TIMEOUT`` s without a target: level (yaw held), climb rate 0, and
  thrust semantics back to climb rate, staying in the mode, silently
  (``angle_control_run``).

Rate loop (``AC_AttitudeControl_Multi`` + ``AC_PID`` defaults)
--------------------------------------------------------------
Runs at ``SCHED_LOOP_RATE`` (400 Hz) on the gyro low-passed by a 2nd-order
Butterworth at ``INS_GYRO_FILTER`` (20 Hz) at the IMU rate; per axis
``out = P e + I + D de/dt + FF target`` with the target low-passed at ``FLTT``,
the error at ``FLTE`` and the derivative at ``FLTD`` (ATC_RAT_* parameters).
Outputs are mixed in thrust space (roll and pitch first, as ``Mixer`` does),
then linearised per motor with ``MOT_THST_EXPO`` and scaled into
[``MOT_SPIN_MIN``, ``MOT_SPIN_MAX``]; armed on the ground at zero throttle the
motors turn at ``MOT_SPIN_ARM``.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink

from companion.profile import VehicleProfile
from sitl.ardupilot_config import ArduCopterConfig
from sitl.ardupilot_control import (
    ApAxisGains,
    ApRatePid,
    AttitudeControl,
    AttitudeGains,
    GyroLowPass,
    MotorsMatrix,
    actuator_to_thrust,
    climb_rate_from_thrust,
)
from sitl.ardupilot_laws import AngleTarget, CopterLaws
from sitl.ardupilot_modes import FLYABLE, GUIDED, MANUAL_THROTTLE, NEEDS_POSITION, CopterMode
from sitl.ardupilot_params import ArduParams
from sitl.personality import (
    MAV_SEVERITY_CRITICAL,
    MAV_SEVERITY_WARNING,
    MavResult,
    clip,
)

__all__ = ["ArduCopter", "ArduCopterConfig"]

logger = logging.getLogger(__name__)

GUID_OPTION_THRUST_AS_THRUST = 8
"""``GUID_OPTIONS`` bit 3: SET_ATTITUDE_TARGET's thrust is thrust, not a climb rate."""
_FS_OPTION_CONTINUE_GUIDED = 4
"""``FS_OPTIONS`` bit 2: carry on in GUIDED / GUIDED_NOGPS on RC loss."""
_ARMING_CHECK_ALL, _ARMING_CHECK_RC = 1, 64
"""``ARMING_CHECK`` bits: all checks; the RC checks (bit 6)."""
_RC_OPTION_ARMING_CHECK_THROTTLE = 32
"""``RC_OPTIONS`` bit 5: the throttle must be at idle to arm (ArduCopter's default)."""
INTERNAL_ERROR_FLOW_OF_CTRL = 0x100000
"""``AP_InternalError::error_t::flow_of_ctrl`` (bit 20)."""
_FLOW_OF_CTRL_LINE = 57
"""Where ArduCopter 4.5 raises it: ``land_detector.cpp`` line 57 (the pre-arm text's ``l:``)."""


# ------------------------------------------------------------------ autopilot


class ArduCopter(CopterLaws):
    """An ArduCopter-like multicopter autopilot: modes, arming, guided rules, failsafes.

    The main loop and the parameters are here; what each mode flies is
    :class:`~sitl.ardupilot_laws.CopterLaws`. The runner and the face use the
    surface of :class:`sitl.personality.Personality` (``arm``, ``disarm``,
    ``update``, ``events``, ``custom_mode``...), as for
    :class:`sitl.autopilot.Autopilot`, so one simulation loop drives either personality.

    Parameters
    ----------
    profile
        The vehicle (frame -> mixer, rate limits).
    config
        See :class:`ArduCopterConfig`.
    initial_mode
        Mode at boot (STABILIZE by default, as ArduCopter boots).
    """

    refusal = MavResult.FAILED
    land_mode = CopterMode.LAND
    log = logger

    def __init__(
        self,
        profile: VehicleProfile,
        config: ArduCopterConfig | None = None,
        *,
        initial_mode: CopterMode = CopterMode.STABILIZE,
    ) -> None:
        super().__init__(profile, initial_mode=initial_mode)
        self.config = config or ArduCopterConfig()
        self.params = ArduParams()
        for name, value in (*self.config.tune, *self.config.params):
            if name not in self.params:
                raise ValueError(f"unknown ArduPilot parameter {name!r}")
            self.params.set(name, value)
        self.loop_rate_hz = float(self.params["SCHED_LOOP_RATE"])
        """Main-loop rate fixed at boot (SCHED_LOOP_RATE needs a reboot in ArduPilot)."""
        self.loop_dt_s = 1.0 / self.loop_rate_hz
        self.rate_pid = ApRatePid(self._gains())
        self.attitude = AttitudeControl(self._attitude_gains())
        self.motors_matrix = MotorsMatrix.from_profile(profile)
        self.motors_matrix.yaw_headroom = self.params["MOT_YAW_HEADROOM"]
        self.gyro_lpf = GyroLowPass(self.params["INS_GYRO_FILTER"])
        self.params.on_change(self._param_changed)
        self.failsafe_radio = False
        """The radio failsafe is on (RC lost); cleared when RC comes back."""
        self.ignored_setpoints = 0
        self.gyro_filtered_rad_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self.rate_target_rad_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
        """Body-rate target of the last rate-loop run (rad/s)."""
        self.hover_throttle = self._hover_throttle(self.config.hover_motor_cmd)
        # What ArduCopter would have learnt (MOT_HOVER_LEARN 2) and a ground station reads.
        self.params.set("MOT_THST_HOVER", self.hover_throttle)
        self._target: AngleTarget | None = None
        self._timed_out = False
        self._yaw_hold: float | None = None
        self._last_imu_t_s: float | None = None
        self._next_loop_s: float | None = None
        self._limit = [False, False, False]
        self.internal_errors = 0
        """``AP_InternalError``'s bitmask: kept until a reboot (a new SITL)."""

    # ---------------------------------------------------------------- status

    @property
    def base_mode(self) -> int:
        """``GCS_MAVLINK_Copter::base_mode``: STABILIZE | MANUAL_INPUT | CUSTOM (+GUIDED, ARMED)."""
        flags = 16 | 64 | 1  # STABILIZE_ENABLED | MANUAL_INPUT_ENABLED | CUSTOM_MODE_ENABLED
        if self.mode == CopterMode.GUIDED:
            flags |= 8  # GUIDED_ENABLED: the position controller is active in GUIDED
        if self.armed:
            flags |= 128
        return flags

    @property
    def system_status(self) -> int:
        """``MAV_STATE``: CRITICAL (5) while any failsafe is on (armed or not, as
        ``GCS_MAVLINK_Copter::vehicle_system_status``), STANDBY (3) landed, else ACTIVE (4)."""
        if self.failsafe is not None or self.failsafe_radio:
            return 5
        return 3 if (self.landed or not self.armed) else 4

    def rc_receiver(self, t_s: float) -> tuple[bool, bool, bool]:
        """SYS_STATUS's RC bit: once a radio was seen it stays present and enabled;
        healthy until ``RC_FS_TIMEOUT`` passes without a frame."""
        if self._rc_t_s is None:
            return (False, False, False)
        return (True, True, not self.rc_lost(t_s))

    def prearm_ok(self, t_s: float) -> bool:
        """The pre-arm checks pass (``SYS_STATUS`` pre-arm bit healthy)."""
        return not self.crashed and not self._arming_problem(t_s, force=False)

    @property
    def external_control(self) -> bool:
        """In GUIDED / GUIDED_NOGPS: a companion's setpoints drive the vehicle."""
        return self.mode in GUIDED

    @property
    def rc_timeout_s(self) -> float:
        """``RC_FS_TIMEOUT``."""
        return self.params["RC_FS_TIMEOUT"]

    @property
    def guided_thrust_is_thrust(self) -> bool:
        return bool(int(self.params["GUID_OPTIONS"]) & GUID_OPTION_THRUST_AS_THRUST)

    def setpoint_age_s(self, t_s: float) -> float:
        return math.inf if self._target is None else t_s - self._target.t_s

    # ------------------------------------------------------------ parameters

    def _gains(self) -> tuple[ApAxisGains, ApAxisGains, ApAxisGains]:
        p = self.params

        def axis(a: str) -> ApAxisGains:
            return ApAxisGains(
                kp=p[f"ATC_RAT_{a}_P"],
                ki=p[f"ATC_RAT_{a}_I"],
                kd=p[f"ATC_RAT_{a}_D"],
                kff=p[f"ATC_RAT_{a}_FF"],
                imax=p[f"ATC_RAT_{a}_IMAX"],
                filt_t_hz=p[f"ATC_RAT_{a}_FLTT"],
                filt_e_hz=p[f"ATC_RAT_{a}_FLTE"],
                filt_d_hz=p[f"ATC_RAT_{a}_FLTD"],
            )

        return (axis("RLL"), axis("PIT"), axis("YAW"))

    def _attitude_gains(self) -> AttitudeGains:
        p = self.params
        cds2 = math.radians(0.01)  # centideg/s^2 -> rad/s^2
        return AttitudeGains(
            accel_max_rad_s2=(
                p["ATC_ACCEL_R_MAX"] * cds2,
                p["ATC_ACCEL_P_MAX"] * cds2,
                p["ATC_ACCEL_Y_MAX"] * cds2,
            ),
            angle_p=(p["ATC_ANG_RLL_P"], p["ATC_ANG_PIT_P"], p["ATC_ANG_YAW_P"]),
            rate_ff=int(p["ATC_RATE_FF_ENAB"]) != 0,
        )

    def _param_changed(self, name: str, value: float) -> None:
        if name.startswith("ATC_RAT_"):
            self.rate_pid.gains = self._gains()
        elif name.startswith(("ATC_ACCEL_", "ATC_ANG_", "ATC_RATE_FF_ENAB")):
            self.attitude.gains = self._attitude_gains()
        elif name == "MOT_YAW_HEADROOM":
            self.motors_matrix.yaw_headroom = value
        elif name == "INS_GYRO_FILTER":
            self.gyro_lpf.cutoff_hz = value
            self.gyro_lpf._fs_hz = 0.0  # redesign on the next sample
        elif name.startswith("MOT_"):
            self.hover_throttle = self._hover_throttle(self.config.hover_motor_cmd)

    def _hover_throttle(self, hover_motor_cmd: float) -> float:
        p = self.params
        lo, hi = p["MOT_SPIN_MIN"], p["MOT_SPIN_MAX"]
        a = (hover_motor_cmd - lo) / (hi - lo) if hi > lo else 0.5
        return clip(actuator_to_thrust(a, p["MOT_THST_EXPO"]), 0.1, 0.8)

    # -------------------------------------------------------------- commands

    def prearm_failures(self) -> list[str]:
        """Pre-arm checks that fail now (only run when ``ARMING_CHECK`` != 0): the
        ``--prearm-fail`` text; an internal error since boot (``AP_Arming::system_checks``,
        a check no ``ARMING_CHECK`` bit turns off)."""
        fails = []
        if self.config.prearm_fail:
            fails.append(self.config.prearm_fail)
        if self.internal_errors:
            fails.append(
                f"Internal errors 0x{self.internal_errors:x} l:{_FLOW_OF_CTRL_LINE} flow_of_ctrl"
            )
        return fails

    def _arming_problem(self, t_s: float, *, force: bool) -> str | None:
        """The text of the first failing check (``"Arm: ..."`` or ``"PreArm: ..."``), or None."""
        if self.crashed:
            return "Arm: Crashed"
        if self.mode == CopterMode.LAND:
            # Mode::allows_arming is a mandatory check: ARMING_CHECK=0 does not skip it.
            return "Arm: Mode not armable"
        if force or int(self.params["ARMING_CHECK"]) == 0:
            return None
        fails = self.prearm_failures()
        if fails:
            return f"PreArm: {fails[0]}"
        cfg = self.config
        if self.mode in NEEDS_POSITION | {CopterMode.GUIDED} and (
            t_s < cfg.ekf_position_ready_s or not self.position_valid
        ):
            return "PreArm: Need Position Estimate"
        if t_s < cfg.ekf_alt_ready_s:
            # AP_Arming_Copter::mandatory_checks (ekf alt), after the pre-arm checks.
            return "Arm: Need Alt Estimate"
        return None

    def _arming_checks(self, t_s: float, *, force: bool) -> MavResult | None:
        """ArduCopter's checks; ``force`` (param2 2989) skips the pre-arm ones.

        A refusal answers FAILED (``GCS_MAVLINK::handle_command_component_arm_disarm``)
        and is reported as ``STATUSTEXT "Arm: ..."`` / ``"PreArm: ..."`` (severity
        CRITICAL): a crash, LAND, a failing ``--prearm-fail`` check or an internal
        error since boot, no position estimate yet in a mode that needs one
        (``ekf_position_ready_s`` after boot, or none), no altitude estimate yet
        (``ekf_alt_ready_s``); then the radio's throttle above idle
        (:meth:`_throttle_problem`).
        """
        problem = self._arming_problem(t_s, force=force)
        if problem is None and not force:
            problem = self._throttle_problem(t_s)
        if problem is None:
            return None
        if problem.startswith("PreArm: ") and problem[8:] in self.prearm_failures():
            for f in self.prearm_failures():
                self._text(MAV_SEVERITY_CRITICAL, f"PreArm: {f}")
        else:
            self._text(MAV_SEVERITY_CRITICAL, problem)
        reason = problem.split(": ", 1)[1]
        return self._arm_denied(t_s, reason.lower() if problem.startswith("Arm: ") else reason)

    def throttle_control_in(self, pwm_us: int) -> int:
        """The throttle channel's ``control_in`` (0..1000) for a pulse of ``pwm_us``:
        ``RC_Channel::pwm_to_range_dz``, zero up to ``RC3_MIN + RC3_DZ``, in integers."""
        p = self.params
        lo, hi = int(p["RC3_MIN"]), int(p["RC3_MAX"])
        low = lo + int(p["RC3_DZ"])
        r_in = min(max(pwm_us, lo), hi)
        return 1000 * (r_in - low) // (hi - low) if r_in > low and hi > low else 0

    def _throttle_problem(self, t_s: float) -> str | None:
        """ArduCopter 4.5's arming checks on the throttle stick (arm checks, not
        pre-arm: SYS_STATUS's pre-arm bit does not see them), with a radio whose
        frames came within ``RC_FS_TIMEOUT`` (``rc_arm_checks`` needs input within
        the last second) and the RC checks on (``ARMING_CHECK`` 1 or bit 6).

        * ``AP_Arming_Copter::arm_checks``, skipped when arming from a ground station
          in GUIDED / GUIDED_NOGPS: a climb asked (``control_in`` above mid-stick +
          ``THR_DZ``, ``get_pilot_desired_climb_rate`` > 0) or, with a manual
          throttle (STABILIZE, ACRO), any throttle: "Arm: Throttle too high".
        * ``AP_Arming::rc_arm_checks``, with ``RC_OPTIONS`` bit 5: the throttle not at
          idle (``control_in`` != 0), in any mode: "Arm: Throttle (RC3) is not neutral"
          (the real 4.5.6 in GUIDED_NOGPS: 1100 to 1500 us refused, 1000 us armed).
        """
        checks = int(self.params["ARMING_CHECK"])
        sticks = self._last_sticks
        if not checks & (_ARMING_CHECK_ALL | _ARMING_CHECK_RC) or sticks is None or len(sticks) < 3:
            return None
        if self.rc_lost(t_s) or self.failsafe_radio:
            return None
        thr = self.throttle_control_in(sticks[2])
        if self.mode not in GUIDED:
            p = self.params
            lo, hi = int(p["RC3_MIN"]), int(p["RC3_MAX"])
            mid = self.throttle_control_in((lo + hi) // 2)
            if thr > mid + int(p["THR_DZ"]) or (self.mode in MANUAL_THROTTLE and thr > 0):
                return "Arm: Throttle too high"
        if int(self.params["RC_OPTIONS"]) & _RC_OPTION_ARMING_CHECK_THROTTLE and thr != 0:
            return "Arm: Throttle (RC3) is not neutral"
        return None

    def _on_armed(self, t_s: float) -> None:
        # The flight starts here: the filters, the rate loop and its schedule too,
        # so what follows does not depend on how long the vehicle sat disarmed.
        self._yaw_hold = None
        self.gyro_lpf.reset()
        self.gyro_filtered_rad_s = (0.0, 0.0, 0.0)  # what ATTITUDE shows until the next sample
        self.rate_pid.reset()
        self._last_imu_t_s = None
        self._next_loop_s = None
        self._limit = [False, False, False]

    def set_mode(self, t_s: float, number: int, sub: int = 0) -> MavResult:
        """``MAV_CMD_DO_SET_MODE`` param2 = Copter mode number (param3 unused)."""
        try:
            mode = CopterMode(number)
        except ValueError:
            self._event(t_s, "mode_denied", number=number, reason="no such mode")
            return MavResult.FAILED
        if mode not in FLYABLE:
            self._event(t_s, "mode_denied", mode=mode.name, reason="needs navigation")
            return MavResult.FAILED
        if self.armed and mode in NEEDS_POSITION and not self.position_valid:
            self._text(MAV_SEVERITY_WARNING, f"Flight mode change failed {mode.name}")
            self._event(t_s, "mode_denied", mode=mode.name, reason="requires position")
            return MavResult.FAILED
        if self.armed and mode in MANUAL_THROTTLE and self.failsafe_radio:
            self._event(t_s, "mode_denied", mode=mode.name, reason="in RC failsafe")
            return MavResult.FAILED
        if mode != self.mode:
            self._change_mode(t_s, mode, reason="command")
        return MavResult.ACCEPTED

    def _on_mode_change(self, new: CopterMode) -> None:
        self._yaw_hold = None
        self.failsafe = None
        if new in GUIDED:
            # ModeGuided::init / angle_control_start: no target until one arrives.
            self._target = None
            self._timed_out = False

    # ------------------------------------------------------------- setpoints

    def on_actuator_target(self, t_s: float, controls: Sequence[float]) -> bool:
        """ArduPilot has no actuator interface: ignored."""
        self.ignored_setpoints += 1
        return False

    def on_attitude_target(
        self,
        t_s: float,
        type_mask: int,
        rates_frd_rad_s: Sequence[float],
        thrust: float,
    ) -> bool:
        """``SET_ATTITUDE_TARGET`` with ArduCopter's rules (see the module docs).

        Returns
        -------
        bool
            True when the target was taken.
        """
        if self.mode not in GUIDED:
            self.ignored_setpoints += 1
            return False
        ignore = (bool(type_mask & 1), bool(type_mask & 2), bool(type_mask & 4))
        valid = (
            not type_mask & mavlink.ATTITUDE_TARGET_TYPEMASK_THROTTLE_IGNORE
            and type_mask & mavlink.ATTITUDE_TARGET_TYPEMASK_ATTITUDE_IGNORE
            and (all(ignore) or not any(ignore))
        )
        rates = (0.0, 0.0, 0.0) if all(ignore) else tuple(float(r) for r in rates_frd_rad_s[:3])
        if not valid or not all(math.isfinite(v) for v in (*rates, thrust)):
            self.rejected_setpoints += 1
            if self.mode == CopterMode.GUIDED:
                self._target = None  # mode_guided.init(true): stop and hold
            return False
        rm = self.rate_max_rad_s
        clipped = (
            clip(rates[0], -rm[0], rm[0]),
            clip(rates[1], -rm[1], rm[1]),
            clip(rates[2], -rm[2], rm[2]),
        )
        p = self.params
        if self.guided_thrust_is_thrust:
            value, use_thrust = clip(thrust, -1.0, 1.0), True
        else:
            up = p["WPNAV_SPEED_UP"] * 0.01
            dn = p["WPNAV_SPEED_DN"] * 0.01
            value, use_thrust = climb_rate_from_thrust(thrust, up, dn), False
        prev = self._target
        if prev is not None and prev.use_thrust and not use_thrust:
            self._climb_integral = 0.0  # init_U_controller on thrust -> climb rate
        self._target = AngleTarget(t_s, clipped, value, use_thrust)
        if self._timed_out:
            self._timed_out = False
            self._event(t_s, "guided_resumed")
        self.accepted_setpoints += 1
        return True

    # ------------------------------------------------------------------ loop

    def _step(
        self,
        t_s: float,
        gyro_frd_rad_s: Sequence[float],
        euler_rad: Sequence[float],
        climb_rate_m_s: float,
    ) -> tuple[float, ...]:
        """Filter an IMU sample; run the main loop when it is due (``SCHED_LOOP_RATE``).

        Between loop runs the motor outputs are held.
        """
        # In whole microseconds: the difference of two large times would carry their
        # rounding into the filter, and a flight would depend on when it began.
        dt_imu = (
            0.001 if self._last_imu_t_s is None else round((t_s - self._last_imu_t_s) * 1e6) * 1e-6
        )
        self._last_imu_t_s = t_s
        self.gyro_filtered_rad_s = self.gyro_lpf.apply(gyro_frd_rad_s, dt_imu)
        if self._next_loop_s is not None and t_s + 1e-9 < self._next_loop_s:
            return self.motors
        nxt = (t_s if self._next_loop_s is None else self._next_loop_s) + self.loop_dt_s
        self._next_loop_s = nxt if nxt > t_s else t_s + self.loop_dt_s
        self._check_guided_timeout(t_s)
        self._check_radio(t_s)
        self._check_position(t_s)
        if not self.armed:
            return self._disarmed()
        sticks = None if self.failsafe_radio or self.rc_lost(t_s) else self._last_sticks
        motors = self._run(t_s, self.gyro_filtered_rad_s, euler_rad, climb_rate_m_s, sticks)
        self._check_take_off(t_s)
        return motors

    def _check_take_off(self, t_s: float) -> None:
        """ArduCopter 4.5's land detector on the ground: a throttle above half the
        hover throttle that no mode announced as a take-off is a bug it reports,
        ``INTERNAL_ERROR(flow_of_ctrl)``, once per boot ("Internal Errors 0x100000",
        CRITICAL) before flying on; the error then fails the pre-arm checks until a
        reboot. GUIDED / GUIDED_NOGPS with ``GUID_OPTIONS`` bit 3 does not announce
        its take-off (``ModeGuided::angle_control_run`` calls ``set_land_complete``
        only on a climb rate: ArduPilot issue 26865, fixed after 4.5.7); STABILIZE,
        ACRO and the climb-rate modes do."""
        tgt = self._target
        if (
            not self.landed
            or self.mode not in GUIDED
            or tgt is None
            or not tgt.use_thrust
            or self._timed_out
            or self.last_torque_thrust[3] <= self.hover_throttle / 2.0
            or self.internal_errors & INTERNAL_ERROR_FLOW_OF_CTRL
        ):
            return
        self.internal_errors |= INTERNAL_ERROR_FLOW_OF_CTRL
        self._text(MAV_SEVERITY_CRITICAL, f"Internal Errors 0x{self.internal_errors:x}")
        self._event(t_s, "internal_error", errors=f"0x{self.internal_errors:x}", cause="take-off")

    def _check_radio(self, t_s: float) -> None:
        """The radio failsafe: on when RC is lost (``RC_FS_TIMEOUT``), acting once."""
        stale = self.rc_lost(t_s)
        if not stale:
            if self.failsafe_radio:
                self.failsafe_radio = False
                self._text(MAV_SEVERITY_WARNING, "Radio Failsafe Cleared")
                self._event(t_s, "failsafe_cleared", cause="radio")
            return
        action = int(self.params["FS_THR_ENABLE"])
        if self.failsafe_radio or action == 0 or (self._rc_t_s is None and not self.armed):
            return
        self.failsafe_radio = True
        if not self.armed:
            self._text(MAV_SEVERITY_WARNING, "Radio Failsafe")
            return
        fs_options = int(self.params["FS_OPTIONS"])
        if self.mode in GUIDED and fs_options & _FS_OPTION_CONTINUE_GUIDED:
            self._text(MAV_SEVERITY_WARNING, "Radio Failsafe - Continuing Guided Mode")
            self._event(t_s, "failsafe", cause="radio", action="continue")
            return
        if self.landed:
            # events.cpp: on the ground the failsafe disarms.
            self._text(MAV_SEVERITY_WARNING, "Radio Failsafe - Disarming")
            self._event(t_s, "failsafe", cause="radio", action="disarm")
            self.disarm(t_s, reason="radio failsafe")
            return
        self._text(MAV_SEVERITY_WARNING, "Radio Failsafe")
        if action == 7 and self.position_valid:
            new = CopterMode.BRAKE
        elif action == 1 and self.position_valid:
            new = CopterMode.RTL  # shown as RTL; flown as LAND (no navigation here)
        else:
            new = CopterMode.LAND
        self._enter_failsafe(t_s, "radio", new, reason="radio failsafe")

    def _check_position(self, t_s: float) -> None:
        """Losing the position in LOITER or BRAKE: the EKF failsafe (FS_EKF_ACTION 1, land)."""
        if self.position_valid or not self.armed or self.mode not in NEEDS_POSITION:
            return
        self._enter_failsafe(t_s, "ekf", CopterMode.LAND, reason="position lost")

    def _check_guided_timeout(self, t_s: float) -> None:
        tgt = self._target
        if self.mode not in GUIDED or tgt is None or self._timed_out:
            return
        timeout_s = max(self.params["GUID_TIMEOUT"], 0.1)
        if t_s - tgt.t_s <= timeout_s:
            return
        self._timed_out = True
        self._climb_integral = 0.0 if tgt.use_thrust else self._climb_integral
        # ArduCopter says nothing (ModeGuided::angle_control_run): an event only.
        self._event(t_s, "guided_timeout", age_s=round(t_s - tgt.t_s, 3), action="level, hold alt")
