"""The SITL's ArduPilot personality: an ArduCopter-like autopilot and its MAVLink face.

``sitl run --autopilot ardupilot`` shows the vehicle as ArduCopter 4.x would
(``docs/ardupilot.md`` lists what was checked against ArduPilot's source and what
is assumed). Like :mod:`sitl.autopilot`, the autopilot logic here has no sockets
and no clock: :class:`ArduCopter` is driven with simulation time by the runner,
and :class:`ArduPilotFace` turns MAVLink into calls on it.

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
  thrust semantics back to climb rate, staying in the mode (``angle_control_run``).

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
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, cast

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink

from companion.control.mixer import Mixer
from companion.profile import VehicleProfile
from sitl.autopilot import Event, MavResult, MessageStreams, StreamSpec
from sitl.mavlink_face import (
    ID_ATTITUDE,
    ID_ATTITUDE_QUATERNION,
    ID_AUTOPILOT_VERSION,
    ID_EXTENDED_SYS_STATE,
    ID_HEARTBEAT,
    ID_HIGHRES_IMU,
    ID_HOME_POSITION,
    ID_LOCAL_POSITION_NED,
    ID_RC_CHANNELS,
    ID_SYS_STATUS,
    Endpoint,
    MavlinkFace,
    _as_int,
)

__all__ = [
    "FORCE_ARM_MAGIC",
    "FORCE_DISARM_MAGIC",
    "MAV_AUTOPILOT_ARDUPILOTMEGA",
    "PARAM_SPECS",
    "SITL_RATE_TUNE",
    "ApRatePid",
    "ArduCopter",
    "ArduCopterConfig",
    "ArduParams",
    "ArduPilotFace",
    "ArduStreams",
    "CopterMode",
    "GyroLowPass",
    "ParamSpec",
    "ardupilot_streams",
    "climb_rate_from_thrust",
    "max_stream_rate_hz",
]

logger = logging.getLogger(__name__)

MAV_AUTOPILOT_ARDUPILOTMEGA = 3
FORCE_ARM_MAGIC = 2989
"""``MAV_CMD_COMPONENT_ARM_DISARM`` param2 that skips the arming checks (ArduPilot)."""
FORCE_DISARM_MAGIC = 21196
"""param2 that forces a disarm in the air."""

ID_RAW_IMU = mavlink.MAVLINK_MSG_ID_RAW_IMU
ID_SCALED_IMU = mavlink.MAVLINK_MSG_ID_SCALED_IMU
ID_STATUSTEXT = mavlink.MAVLINK_MSG_ID_STATUSTEXT

MAV_SEVERITY_CRITICAL = 2
MAV_SEVERITY_WARNING = 4
MAV_SEVERITY_INFO = 6

PARAM_INT8 = mavlink.MAV_PARAM_TYPE_INT8
PARAM_INT16 = mavlink.MAV_PARAM_TYPE_INT16
PARAM_INT32 = mavlink.MAV_PARAM_TYPE_INT32
PARAM_REAL32 = mavlink.MAV_PARAM_TYPE_REAL32
_INT_RANGE = {
    PARAM_INT8: (-128, 127),
    PARAM_INT16: (-32768, 32767),
    PARAM_INT32: (-(2**31), 2**31 - 1),
}

GUID_OPTION_THRUST_AS_THRUST = 8
"""``GUID_OPTIONS`` bit 3: SET_ATTITUDE_TARGET's thrust is thrust, not a climb rate."""

GRAVITY_M_S2 = 9.80665


class CopterMode(IntEnum):
    """ArduCopter mode numbers (``ArduCopter/mode.h``, ``Mode::Number``)."""

    STABILIZE = 0
    ACRO = 1
    ALT_HOLD = 2
    AUTO = 3
    GUIDED = 4
    LOITER = 5
    RTL = 6
    LAND = 9
    BRAKE = 17
    GUIDED_NOGPS = 20

    @property
    def custom_mode(self) -> int:
        return int(self)


_FLYABLE = {
    CopterMode.STABILIZE,
    CopterMode.ACRO,
    CopterMode.ALT_HOLD,
    CopterMode.GUIDED,
    CopterMode.LOITER,
    CopterMode.LAND,
    CopterMode.BRAKE,
    CopterMode.GUIDED_NOGPS,
}
_GUIDED = {CopterMode.GUIDED, CopterMode.GUIDED_NOGPS}
_MANUAL_THROTTLE = {CopterMode.STABILIZE, CopterMode.ACRO}
_NEEDS_POSITION = {CopterMode.LOITER, CopterMode.BRAKE}
_FS_OPTION_CONTINUE_GUIDED = 4


# ------------------------------------------------------------------ parameters


@dataclass(frozen=True)
class ParamSpec:
    """One ArduPilot parameter: name, default, MAVLink type, documented range."""

    name: str
    default: float
    param_type: int
    min_value: float = -math.inf
    max_value: float = math.inf
    doc: str = ""


def _rate_pid_specs(axis: str, p: float, i: float, d: float, flte: float) -> list[ParamSpec]:
    r32 = PARAM_REAL32
    return [
        ParamSpec(f"ATC_RAT_{axis}_P", p, r32, 0.0, 2.0, "rate P, output per rad/s"),
        ParamSpec(f"ATC_RAT_{axis}_I", i, r32, 0.0, 2.0, "rate I, output per rad"),
        ParamSpec(f"ATC_RAT_{axis}_D", d, r32, 0.0, 0.05, "rate D, output per rad/s^2"),
        ParamSpec(f"ATC_RAT_{axis}_FF", 0.0, r32, 0.0, 0.5, "rate feed-forward"),
        ParamSpec(f"ATC_RAT_{axis}_IMAX", 0.5, r32, 0.0, 1.0, "integrator limit"),
        ParamSpec(f"ATC_RAT_{axis}_FLTT", 20.0, r32, 0.0, 100.0, "target LPF, Hz (0 off)"),
        ParamSpec(f"ATC_RAT_{axis}_FLTE", flte, r32, 0.0, 100.0, "error LPF, Hz (0 off)"),
        ParamSpec(f"ATC_RAT_{axis}_FLTD", 20.0, r32, 0.0, 100.0, "D-term LPF, Hz (0 off)"),
    ]


PARAM_SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("ARMING_CHECK", 1, PARAM_INT32, doc="0: skip the pre-arm checks"),
    ParamSpec("FS_OPTIONS", 16, PARAM_INT32, 0, 1023, "bit 2 (4): continue guided on RC loss"),
    ParamSpec("FS_THR_ENABLE", 1, PARAM_INT8, 0, 7, "RC loss: 0 off, 1 RTL, 3 land, 7 brake"),
    ParamSpec("GUID_OPTIONS", 0, PARAM_INT32, 0, 255, "bit 3 (8): thrust is thrust"),
    ParamSpec("GUID_TIMEOUT", 3.0, PARAM_REAL32, 0.1, 5.0, "s without targets before levelling"),
    ParamSpec("INS_GYRO_FILTER", 20, PARAM_INT16, 0, 256, "gyro LPF, Hz"),
    ParamSpec("LAND_SPEED", 50, PARAM_INT16, 30, 200, "final descent speed, cm/s"),
    ParamSpec("MAV_GCS_SYSID", 255, PARAM_INT16, 1, 255, "ground station sysid"),
    ParamSpec("MOT_SPIN_ARM", 0.10, PARAM_REAL32, 0.0, 0.2, "armed idle"),
    ParamSpec("MOT_SPIN_MAX", 0.95, PARAM_REAL32, 0.9, 1.0, "top of the output range"),
    ParamSpec("MOT_SPIN_MIN", 0.15, PARAM_REAL32, 0.0, 0.3, "bottom of the output range"),
    ParamSpec("MOT_THST_EXPO", 0.65, PARAM_REAL32, -1.0, 1.0, "thrust curve expo"),
    ParamSpec("RC_FS_TIMEOUT", 1.0, PARAM_REAL32, 0.1, 10.0, "s without RC before failsafe"),
    ParamSpec("SCHED_LOOP_RATE", 400, PARAM_INT16, 50, 2000, "main loop, Hz (at boot)"),
    ParamSpec("WPNAV_SPEED_DN", 150.0, PARAM_REAL32, 10, 500, "guided max descent, cm/s"),
    ParamSpec("WPNAV_SPEED_UP", 250.0, PARAM_REAL32, 10, 1000, "guided max climb, cm/s"),
    # AC_AttitudeControl_Multi.h defaults (AC_ATC_MULTI_RATE_*).
    *_rate_pid_specs("RLL", 0.135, 0.135, 0.0036, 0.0),
    *_rate_pid_specs("PIT", 0.135, 0.135, 0.0036, 0.0),
    *_rate_pid_specs("YAW", 0.180, 0.018, 0.0, 2.5),
)


class ArduParams:
    """ArduPilot-style parameter store (``PARAM_REQUEST_*`` / ``PARAM_SET``).

    Values are kept as the type says: integer types are rounded and saturated to
    the type's range (ArduPilot stores what it is sent; the documented range is
    not enforced, as in ``GCS_MAVLINK::handle_param_set``).
    """

    def __init__(self, specs: Sequence[ParamSpec] = PARAM_SPECS) -> None:
        self.specs = tuple(sorted(specs, key=lambda s: s.name))
        self._by_name = {s.name: s for s in self.specs}
        self._values = {s.name: float(s.default) for s in self.specs}
        self._listeners: list[Callable[[str, float], None]] = []

    def __contains__(self, name: str) -> bool:
        return name in self._by_name

    def __len__(self) -> int:
        return len(self.specs)

    def __getitem__(self, name: str) -> float:
        return self._values[name]

    def index(self, name: str) -> int:
        return self.specs.index(self._by_name[name])

    def by_index(self, index: int) -> ParamSpec | None:
        return self.specs[index] if 0 <= index < len(self.specs) else None

    def spec(self, name: str) -> ParamSpec | None:
        return self._by_name.get(name)

    def on_change(self, fn: Callable[[str, float], None]) -> None:
        """Call ``fn(name, value)`` after every successful :meth:`set`."""
        self._listeners.append(fn)

    def set(self, name: str, value: float) -> float:
        """Store ``value``; return what was stored.

        Raises
        ------
        KeyError
            For an unknown name.
        ValueError
            For a non-finite value.
        """
        spec = self._by_name[name]
        if not math.isfinite(value):
            raise ValueError(f"{name}: expected a finite value, got {value!r}")
        if spec.param_type in _INT_RANGE:
            lo, hi = _INT_RANGE[spec.param_type]
            value = float(min(hi, max(lo, round(value))))
        self._values[name] = float(value)
        for fn in self._listeners:
            fn(name, self._values[name])
        return self._values[name]


# -------------------------------------------------------------------- filters


def _lowpass_alpha(dt_s: float, cutoff_hz: float) -> float:
    """ArduPilot ``calc_lowpass_alpha_dt``: 1 (no filtering) when the cutoff is 0."""
    if cutoff_hz <= 0.0 or dt_s <= 0.0:
        return 1.0
    rc = 1.0 / (2.0 * math.pi * cutoff_hz)
    return dt_s / (dt_s + rc)


class GyroLowPass:
    r"""Three-axis 2nd-order Butterworth low-pass (ArduPilot ``LowPassFilter2p``).

    Coefficients for sample rate :math:`f_s` and cutoff :math:`f_c`, with
    :math:`\Omega = \tan(\pi f_c / f_s)` and :math:`c = 1 + \sqrt2\,\Omega + \Omega^2`:
    :math:`b_0 = b_2 = \Omega^2/c`, :math:`b_1 = 2 b_0`,
    :math:`a_1 = 2(\Omega^2 - 1)/c`, :math:`a_2 = (1 - \sqrt2\,\Omega + \Omega^2)/c`.
    A cutoff of 0 passes the signal through.
    """

    def __init__(self, cutoff_hz: float) -> None:
        self.cutoff_hz = float(cutoff_hz)
        self._fs_hz = 0.0
        self._coef = (1.0, 0.0, 0.0, 0.0, 0.0)
        self._d1 = [0.0, 0.0, 0.0]
        self._d2 = [0.0, 0.0, 0.0]
        self._primed = False

    def _design(self, fs_hz: float) -> None:
        self._fs_hz = fs_hz
        fc = self.cutoff_hz
        if fc <= 0.0 or fc >= 0.5 * fs_hz:
            self._coef = (1.0, 0.0, 0.0, 0.0, 0.0)
            return
        ohm = math.tan(math.pi * fc / fs_hz)
        c = 1.0 + 2.0 * math.cos(math.pi / 4.0) * ohm + ohm * ohm
        b0 = ohm * ohm / c
        a1 = 2.0 * (ohm * ohm - 1.0) / c
        a2 = (1.0 - 2.0 * math.cos(math.pi / 4.0) * ohm + ohm * ohm) / c
        self._coef = (b0, 2.0 * b0, b0, a1, a2)

    def apply(self, x: Sequence[float], dt_s: float) -> tuple[float, float, float]:
        """Filter one sample taken ``dt_s`` after the previous one."""
        fs = 1.0 / dt_s if dt_s > 0.0 else self._fs_hz
        if fs > 0.0 and (self._fs_hz <= 0.0 or abs(fs - self._fs_hz) > 0.1 * self._fs_hz):
            self._design(fs)
        b0, b1, b2, a1, a2 = self._coef
        if not self._primed:
            # Start at steady state on the first sample (no start-up transient).
            for i in range(3):
                d = x[i] / (1.0 + a1 + a2) if b1 else 0.0
                self._d1[i] = self._d2[i] = d
            self._primed = True
        out = [0.0, 0.0, 0.0]
        for i in range(3):
            d0 = x[i] - self._d1[i] * a1 - self._d2[i] * a2
            out[i] = d0 * b0 + self._d1[i] * b1 + self._d2[i] * b2 if b1 else x[i]
            self._d2[i] = self._d1[i]
            self._d1[i] = d0
        return (out[0], out[1], out[2])

    def reset(self) -> None:
        self._primed = False


@dataclass(frozen=True)
class ApAxisGains:
    """``AC_PID`` gains of one axis (ATC_RAT_{RLL,PIT,YAW}_*)."""

    kp: float
    ki: float
    kd: float
    kff: float = 0.0
    imax: float = 0.5
    filt_t_hz: float = 20.0
    filt_e_hz: float = 0.0
    filt_d_hz: float = 20.0


class ApRatePid:
    r"""Three-axis ArduPilot rate controller (``AC_PID::update_all``), a pure object.

    Per axis, at the loop period ``dt_s``:

    .. math::  T_f \leftarrow T_f + \alpha_T (T - T_f), \qquad
               e \leftarrow e + \alpha_E ((T_f - \omega) - e), \\
               \dot e_f \leftarrow \dot e_f + \alpha_D (\tfrac{e - e_{prev}}{dt} - \dot e_f), \\
               I \leftarrow \operatorname{clip}(I + K_I e\,dt, \pm I_{max}), \qquad
               u = K_P e + I + K_D \dot e_f + K_{FF} T_f

    (D on the error, as ArduPilot does: a target step kicks D through the FLTT
    filter). The integrator does not grow while ``limit`` says the output
    saturated in the direction of the error. Outputs are normalised torques.
    """

    def __init__(self, gains: Sequence[ApAxisGains]) -> None:
        self.gains = tuple(gains)
        self._target = [0.0, 0.0, 0.0]
        self._error = [0.0, 0.0, 0.0]
        self._deriv = [0.0, 0.0, 0.0]
        self._integ = [0.0, 0.0, 0.0]
        self._reset = True

    @property
    def integrator(self) -> tuple[float, float, float]:
        i = self._integ
        return (i[0], i[1], i[2])

    def reset(self) -> None:
        """Forget the filters and the integrator."""
        self._integ = [0.0, 0.0, 0.0]
        self._reset = True

    def reset_integrator(self) -> None:
        self._integ = [0.0, 0.0, 0.0]

    def update(
        self,
        dt_s: float,
        target_rad_s: Sequence[float],
        measured_rad_s: Sequence[float],
        limit: Sequence[bool] = (False, False, False),
    ) -> tuple[float, float, float]:
        out = [0.0, 0.0, 0.0]
        for i in range(3):
            g = self.gains[i]
            tgt = target_rad_s[i]
            meas = measured_rad_s[i]
            if self._reset:
                self._target[i] = tgt
                self._error[i] = tgt - meas
                self._deriv[i] = 0.0
            else:
                prev_err = self._error[i]
                self._target[i] += _lowpass_alpha(dt_s, g.filt_t_hz) * (tgt - self._target[i])
                err = self._target[i] - meas
                self._error[i] += _lowpass_alpha(dt_s, g.filt_e_hz) * (err - self._error[i])
                raw_d = (self._error[i] - prev_err) / dt_s
                self._deriv[i] += _lowpass_alpha(dt_s, g.filt_d_hz) * (raw_d - self._deriv[i])
            e = self._error[i]
            integ = self._integ[i]
            if g.ki > 0.0 and (not limit[i] or integ * e < 0.0):
                integ = min(g.imax, max(-g.imax, integ + e * g.ki * dt_s))
            self._integ[i] = integ
            out[i] = g.kp * e + integ + g.kd * self._deriv[i] + g.kff * self._target[i]
        self._reset = False
        return (out[0], out[1], out[2])


def climb_rate_from_thrust(thrust: float, speed_up_m_s: float, speed_dn_m_s: float) -> float:
    """SET_ATTITUDE_TARGET thrust as a climb-rate request (``GCS_MAVLINK_Copter``).

    Clipped to [0, 1]; 0.5 holds altitude; 1 climbs at ``speed_up_m_s``; 0
    descends at ``speed_dn_m_s``. Returns m/s, positive up.
    """
    t = min(1.0, max(0.0, thrust))
    if t == 0.5:
        return 0.0
    if t > 0.5:
        return (t - 0.5) * 2.0 * speed_up_m_s
    return -(0.5 - t) * 2.0 * speed_dn_m_s


def thrust_to_actuator(thrust: float, expo: float) -> float:
    """``AP_Motors_Thrust_Linearization::apply_thrust_curve_and_volt_scaling`` (no battery)."""
    t = min(1.0, max(0.0, thrust))
    if abs(expo) < 1e-6:
        return t
    return ((expo - 1.0) + math.sqrt((1.0 - expo) ** 2 + 4.0 * expo * t)) / (2.0 * expo)


def actuator_to_thrust(actuator: float, expo: float) -> float:
    """Inverse of :func:`thrust_to_actuator`: ``(1 - expo) a + expo a^2``."""
    a = min(1.0, max(0.0, actuator))
    return (1.0 - expo) * a + expo * a * a


def max_stream_rate_hz(loop_rate_hz: float) -> float:
    """Fastest stream ArduPilot accepts: 0.8 x loop rate, in whole ms (333 Hz at 400)."""
    loop_period_us = 1e6 / loop_rate_hz
    return 1000.0 / max(1, int(loop_period_us / 800.0))


# ------------------------------------------------------------------ autopilot


SITL_RATE_TUNE: tuple[tuple[str, float], ...] = tuple(
    (f"ATC_RAT_{axis}_{name}", value)
    for axis in ("RLL", "PIT")
    for name, value in (("P", 0.17), ("FLTT", 9.0), ("FLTD", 10.0))
)
"""Roll/pitch tune of the SITL airframe (ArduPilot defaults: P 0.135, FLTT 20, FLTD 20 Hz).

Chosen so a +1 rad/s roll-rate step on the F450 profile reaches 0.38 / 0.89 /
0.99 rad/s after 40 / 80 / 120 ms, as ArduCopter's own loop did (facts.md 10:
0.38 / 0.90 / 0.98); I, D, IMAX, FF and the yaw axis keep ArduPilot's defaults.
"""


@dataclass(frozen=True)
class ArduCopterConfig:
    """Tunables of the ArduCopter personality that are not ArduPilot parameters.

    Attributes
    ----------
    test_stand
        On a gimbal rig: LAND never touches down (it only levels).
    hover_motor_cmd
        Motor command that hovers this vehicle (the runner's ``hover_motor_command``);
        turned into ArduPilot's hover throttle (``MOT_THST_HOVER``) through the
        output stage, so the climb-rate loops start from the right collective.
    prearm_fail
        Text of a pre-arm check that fails (``--prearm-fail``), or None.
    tune
        This airframe's rate-loop tune, applied over ArduPilot's defaults at boot
        (:data:`SITL_RATE_TUNE`).
    params
        Parameter overrides at boot, ``(name, value)`` pairs, applied last.
    acro_rate_max_rad_s
        Full-stick ACRO rates; the bundled pilot's map (720, 720, 360 deg/s), not
        ArduPilot's ``ACRO_RP_RATE`` 360 deg/s, so scripted maneuvers fly as written.
    angle_max_rad
        Full-stick tilt in STABILIZE / ALT_HOLD (``ANGLE_MAX`` 30 deg).
    pilot_yaw_rate_rad_s
        Full-stick yaw rate in the angle modes (``PILOT_Y_RATE`` 202.5 deg/s).
    angle_p
        Angle P (``ATC_ANG_RLL_P``, ``ATC_ANG_PIT_P``, ``ATC_ANG_YAW_P``: 4.5).
    pilot_speed_m_s
        Full-stick climb rate in ALT_HOLD (``PILOT_SPEED_UP`` 2.5 m/s).
    climb_p, climb_i
        Vertical-speed PI, thrust per m/s (and per m); stands in for
        ``PSC_VELZ_*`` / ``PSC_ACCZ_*``.
    """

    test_stand: bool = False
    hover_motor_cmd: float = 0.5
    prearm_fail: str | None = None
    tune: tuple[tuple[str, float], ...] = SITL_RATE_TUNE
    params: tuple[tuple[str, float], ...] = ()
    acro_rate_max_rad_s: tuple[float, float, float] = (
        math.radians(720.0),
        math.radians(720.0),
        math.radians(360.0),
    )
    angle_max_rad: float = math.radians(30.0)
    pilot_yaw_rate_rad_s: float = math.radians(202.5)
    angle_p: tuple[float, float, float] = (4.5, 4.5, 4.5)
    pilot_speed_m_s: float = 2.5
    climb_p: float = 0.15
    climb_i: float = 0.08


@dataclass
class _AngleTarget:
    t_s: float
    rates_rad_s: tuple[float, float, float]
    value: float  # climb rate (m/s, up) or thrust [0, 1]
    use_thrust: bool


def _clip(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else hi if x > hi else x


def _stick(us: float) -> float:
    return _clip((us - 1500.0) / 500.0, -1.0, 1.0)


def _throttle(us: float) -> float:
    return _clip((us - 1000.0) / 1000.0, 0.0, 1.0)


def _wrap_pi(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


class ArduCopter:
    """An ArduCopter-like multicopter autopilot: modes, arming, guided rules, loops.

    The runner and the face use the same surface as :class:`sitl.autopilot.Autopilot`
    (``arm``, ``disarm``, ``update``, ``events``, ``custom_mode``...), so one
    simulation loop drives either personality.

    Parameters
    ----------
    profile
        The vehicle (frame -> mixer, rate limits).
    config
        See :class:`ArduCopterConfig`.
    initial_mode
        Mode at boot (STABILIZE by default, as ArduCopter boots).
    """

    def __init__(
        self,
        profile: VehicleProfile,
        config: ArduCopterConfig | None = None,
        *,
        initial_mode: CopterMode = CopterMode.STABILIZE,
    ) -> None:
        self.profile = profile
        self.config = config or ArduCopterConfig()
        self.n_motors = profile.n_motors
        if profile.physics.mixer == "paper":
            self.mixer = Mixer.paper(idle=0.0)
        else:
            self.mixer = Mixer.from_geometry(
                [m.position_frd_m for m in profile.frame.motors],
                [m.spin for m in profile.frame.motors],
                idle=0.0,
            )
        self.rate_max_rad_s = tuple(math.radians(x) for x in profile.limits.rate_max_deg_s)
        self.params = ArduParams()
        for name, value in (*self.config.tune, *self.config.params):
            if name not in self.params:
                raise ValueError(f"unknown ArduPilot parameter {name!r}")
            self.params.set(name, value)
        self.loop_rate_hz = float(self.params["SCHED_LOOP_RATE"])
        """Main-loop rate fixed at boot (SCHED_LOOP_RATE needs a reboot in ArduPilot)."""
        self.loop_dt_s = 1.0 / self.loop_rate_hz
        self.rate_pid = ApRatePid(self._gains())
        self.gyro_lpf = GyroLowPass(self.params["INS_GYRO_FILTER"])
        self.params.on_change(self._param_changed)
        self.mode = initial_mode
        self.armed = False
        self.crashed = False
        self.landed = True
        self.failsafe: str | None = None
        self.failsafe_radio = False
        """The radio failsafe is on (RC lost); cleared when RC comes back."""
        self.position_valid = True
        """A position estimate (the runner clears it for ``--no-position`` and faults)."""
        self.rejected_setpoints = 0
        self.accepted_setpoints = 0
        self.ignored_setpoints = 0
        self.events: list[Event] = []
        self.statustexts: list[tuple[int, str]] = []
        self.gyro_filtered_rad_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self.motors: tuple[float, ...] = (0.0,) * self.n_motors
        self.last_torque_thrust: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
        self.rate_target_rad_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
        """Body-rate target of the last rate-loop run (rad/s)."""
        self.hover_throttle = self._hover_throttle(self.config.hover_motor_cmd)
        self._target: _AngleTarget | None = None
        self._timed_out = False
        self._yaw_hold: float | None = None
        self._climb_integral = 0.0
        self._last_imu_t_s: float | None = None
        self._next_loop_s: float | None = None
        self._rc_t_s: float | None = None
        self._last_sticks: tuple[int, ...] | None = None
        self._limit = [False, False, False]

    # ---------------------------------------------------------------- status

    @property
    def custom_mode(self) -> int:
        return int(self.mode)

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
        """``MAV_STATE``: CRITICAL (5) in failsafe, STANDBY (3) landed, else ACTIVE (4)."""
        if self.failsafe is not None and self.armed:
            return 5
        return 3 if (self.landed or not self.armed) else 4

    @property
    def landed_state(self) -> int:
        if self.landed:
            return 1
        if self.armed and self.mode == CopterMode.LAND:
            return 4
        return 2

    @property
    def external_control(self) -> bool:
        """In GUIDED / GUIDED_NOGPS: a companion's setpoints drive the vehicle."""
        return self.mode in _GUIDED

    @property
    def guided_thrust_is_thrust(self) -> bool:
        return bool(int(self.params["GUID_OPTIONS"]) & GUID_OPTION_THRUST_AS_THRUST)

    def drain_events(self) -> list[Event]:
        out, self.events = self.events, []
        return out

    def drain_statustexts(self) -> list[tuple[int, str]]:
        out, self.statustexts = self.statustexts, []
        return out

    def _event(self, t_s: float, kind: str, **detail: Any) -> None:
        self.events.append(Event(t_s, kind, detail))
        logger.info("t=%.3f s %s %s", t_s, kind, detail or "")

    def _text(self, severity: int, text: str) -> None:
        self.statustexts.append((severity, text[:50]))

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

    def _param_changed(self, name: str, value: float) -> None:
        if name.startswith("ATC_RAT_"):
            self.rate_pid.gains = self._gains()
        elif name == "INS_GYRO_FILTER":
            self.gyro_lpf.cutoff_hz = value
            self.gyro_lpf._fs_hz = 0.0  # redesign on the next sample
        elif name.startswith("MOT_"):
            self.hover_throttle = self._hover_throttle(self.config.hover_motor_cmd)

    def _hover_throttle(self, hover_motor_cmd: float) -> float:
        p = self.params
        lo, hi = p["MOT_SPIN_MIN"], p["MOT_SPIN_MAX"]
        a = (hover_motor_cmd - lo) / (hi - lo) if hi > lo else 0.5
        return _clip(actuator_to_thrust(a, p["MOT_THST_EXPO"]), 0.1, 0.8)

    # -------------------------------------------------------------- commands

    def prearm_failures(self) -> list[str]:
        """Pre-arm checks that fail now (only run when ``ARMING_CHECK`` != 0)."""
        fails = []
        if self.config.prearm_fail:
            fails.append(self.config.prearm_fail)
        return fails

    def arm(self, t_s: float, *, force: bool = False) -> MavResult:
        """``MAV_CMD_COMPONENT_ARM_DISARM`` param1 = 1; ``force`` = param2 2989.

        Returns ACCEPTED or FAILED (``GCS_MAVLINK::handle_command_component_arm_disarm``);
        a failed check is reported as ``STATUSTEXT "PreArm: ..."`` (severity CRITICAL).
        """
        if self.armed:
            return MavResult.ACCEPTED
        if self.crashed:
            self._text(MAV_SEVERITY_CRITICAL, "Arm: Crashed")
            self._event(t_s, "arm_denied", reason="crashed")
            return MavResult.FAILED
        if self.mode == CopterMode.LAND:
            # Mode::allows_arming is a mandatory check: ARMING_CHECK=0 does not skip it.
            self._text(MAV_SEVERITY_CRITICAL, "Arm: Mode not armable")
            self._event(t_s, "arm_denied", reason="mode not armable")
            return MavResult.FAILED
        if not force and int(self.params["ARMING_CHECK"]) != 0:
            fails = self.prearm_failures()
            if fails:
                for f in fails:
                    self._text(MAV_SEVERITY_CRITICAL, f"PreArm: {f}")
                self._event(t_s, "arm_denied", reason=fails[0])
                return MavResult.FAILED
        self.armed = True
        self.failsafe = None
        self.rate_pid.reset()
        self._climb_integral = 0.0
        self._yaw_hold = None
        self._event(t_s, "armed", mode=self.mode.name)
        return MavResult.ACCEPTED

    def disarm(self, t_s: float, *, force: bool = False, reason: str = "command") -> MavResult:
        """param1 = 0; in the air only when forced (param2 = 21196), else FAILED."""
        if not self.armed:
            return MavResult.ACCEPTED
        if not self.landed and not force and not self.crashed:
            self._event(t_s, "disarm_denied", reason="in air")
            return MavResult.FAILED
        self.armed = False
        self.motors = (0.0,) * self.n_motors
        self._event(t_s, "disarmed", reason=reason)
        return MavResult.ACCEPTED

    def set_mode(self, t_s: float, number: int, sub: int = 0) -> MavResult:
        """``MAV_CMD_DO_SET_MODE`` param2 = Copter mode number (param3 unused)."""
        try:
            mode = CopterMode(number)
        except ValueError:
            self._event(t_s, "mode_denied", number=number, reason="no such mode")
            return MavResult.FAILED
        if mode not in _FLYABLE:
            self._event(t_s, "mode_denied", mode=mode.name, reason="needs navigation")
            return MavResult.FAILED
        if self.armed and mode in _NEEDS_POSITION and not self.position_valid:
            self._text(MAV_SEVERITY_WARNING, f"Flight mode change failed {mode.name}")
            self._event(t_s, "mode_denied", mode=mode.name, reason="requires position")
            return MavResult.FAILED
        if self.armed and mode in _MANUAL_THROTTLE and self.failsafe_radio:
            self._event(t_s, "mode_denied", mode=mode.name, reason="in RC failsafe")
            return MavResult.FAILED
        if mode != self.mode:
            self._change_mode(t_s, mode, reason="command")
        return MavResult.ACCEPTED

    def _change_mode(self, t_s: float, new: CopterMode, *, reason: str) -> None:
        old = self.mode
        self.mode = new
        self._climb_integral = 0.0
        self._yaw_hold = None
        self.failsafe = None
        if new in _GUIDED:
            # ModeGuided::init / angle_control_start: no target until one arrives.
            self._target = None
            self._timed_out = False
        self._event(t_s, "mode", old=old.name, new=new.name, reason=reason)

    # ------------------------------------------------------------- setpoints

    def on_actuator_target(self, t_s: float, controls: Sequence[float]) -> bool:
        """ArduPilot has no actuator interface: ignored."""
        self.ignored_setpoints += 1
        return False

    def reject_setpoint(self) -> None:
        self.rejected_setpoints += 1

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
        if self.mode not in _GUIDED:
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
            _clip(rates[0], -rm[0], rm[0]),
            _clip(rates[1], -rm[1], rm[1]),
            _clip(rates[2], -rm[2], rm[2]),
        )
        p = self.params
        if self.guided_thrust_is_thrust:
            value, use_thrust = _clip(thrust, -1.0, 1.0), True
        else:
            up = p["WPNAV_SPEED_UP"] * 0.01
            dn = p["WPNAV_SPEED_DN"] * 0.01
            value, use_thrust = climb_rate_from_thrust(thrust, up, dn), False
        prev = self._target
        if prev is not None and prev.use_thrust and not use_thrust:
            self._climb_integral = 0.0  # init_U_controller on thrust -> climb rate
        self._target = _AngleTarget(t_s, clipped, value, use_thrust)
        if self._timed_out:
            self._timed_out = False
            self._event(t_s, "guided_resumed")
        self.accepted_setpoints += 1
        return True

    # ------------------------------------------------------------------ loop

    def update(
        self,
        t_s: float,
        gyro_frd_rad_s: Sequence[float],
        euler_rad: Sequence[float],
        *,
        climb_rate_m_s: float = 0.0,
        landed: bool = False,
        crashed: bool = False,
        sticks_us: Sequence[int] | None = None,
    ) -> tuple[float, ...]:
        """Filter an IMU sample; run the main loop when it is due (``SCHED_LOOP_RATE``).

        Same arguments as :meth:`sitl.autopilot.Autopilot.update`. Between loop
        runs the motor outputs are held.
        """
        self.landed = landed
        if sticks_us is not None:
            self._rc_t_s = t_s
            self._last_sticks = tuple(sticks_us)
        if crashed and not self.crashed:
            self.crashed = True
            self._event(t_s, "crashed")
        if self.crashed:
            if self.armed:
                self.disarm(t_s, force=True, reason="crash")
            return self.motors
        dt_imu = 0.001 if self._last_imu_t_s is None else t_s - self._last_imu_t_s
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
            self.rate_pid.reset()
            self.motors = (0.0,) * self.n_motors
            return self.motors
        sticks = None if self.failsafe_radio or self._rc_stale(t_s) else self._last_sticks
        return self._run(t_s, self.gyro_filtered_rad_s, euler_rad, climb_rate_m_s, sticks)

    def _rc_stale(self, t_s: float) -> bool:
        return self._rc_t_s is None or t_s - self._rc_t_s > self.params["RC_FS_TIMEOUT"]

    def _check_radio(self, t_s: float) -> None:
        """The radio failsafe: on when RC is lost (``RC_FS_TIMEOUT``), acting once."""
        stale = self._rc_stale(t_s)
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
        self._text(MAV_SEVERITY_WARNING, "Radio Failsafe")
        if not self.armed:
            return
        fs_options = int(self.params["FS_OPTIONS"])
        if self.mode in _GUIDED and fs_options & _FS_OPTION_CONTINUE_GUIDED:
            self._text(MAV_SEVERITY_WARNING, "Radio Failsafe - Continuing Guided Mode")
            self._event(t_s, "failsafe", cause="radio", action="continue")
            return
        if self.landed:
            self._event(t_s, "failsafe", cause="radio", action="disarm")
            self.disarm(t_s, reason="radio failsafe")
            return
        new = CopterMode.BRAKE if action == 7 and self.position_valid else CopterMode.LAND
        if new != self.mode:
            self._change_mode(t_s, new, reason="radio failsafe")
        self.failsafe = "radio"
        self._event(t_s, "failsafe", cause="radio", action=new.name)

    def _check_position(self, t_s: float) -> None:
        """Losing the position in LOITER or BRAKE: the EKF failsafe (FS_EKF_ACTION 1, land)."""
        if self.position_valid or not self.armed or self.mode not in _NEEDS_POSITION:
            return
        self._change_mode(t_s, CopterMode.LAND, reason="position lost")
        self.failsafe = "ekf"
        self._event(t_s, "failsafe", cause="ekf", action=CopterMode.LAND.name)

    def _check_guided_timeout(self, t_s: float) -> None:
        tgt = self._target
        if self.mode not in _GUIDED or tgt is None or self._timed_out:
            return
        timeout_s = max(self.params["GUID_TIMEOUT"], 0.1)
        if t_s - tgt.t_s <= timeout_s:
            return
        self._timed_out = True
        self._climb_integral = 0.0 if tgt.use_thrust else self._climb_integral
        self._event(t_s, "guided_timeout", age_s=round(t_s - tgt.t_s, 3), action="level, hold alt")
        # SITL-only message: ArduCopter levels silently.
        self._text(MAV_SEVERITY_WARNING, "Guided: target timeout, levelling")

    def _run(
        self,
        t_s: float,
        gyro: Sequence[float],
        euler: Sequence[float],
        climb_rate_m_s: float,
        sticks_us: Sequence[int] | None,
    ) -> tuple[float, ...]:
        cfg = self.config
        dt = self.loop_dt_s
        mode = self.mode
        if sticks_us is None or len(sticks_us) < 4:
            # No RC: the pilot's inputs read zero (Mode::get_pilot_desired_*): level,
            # no yaw rate, no climb; a manual throttle reads zero.
            rs, ps, ys = 0.0, 0.0, 0.0
            thr_stick = 0.5 if mode in (CopterMode.ALT_HOLD, CopterMode.LOITER) else 0.0
        else:
            rs, ps = _stick(sticks_us[0]), _stick(sticks_us[1])
            thr_stick, ys = _throttle(sticks_us[2]), _stick(sticks_us[3])
        cos_tilt = math.cos(euler[0]) * math.cos(euler[1])

        rates: tuple[float, float, float]
        if mode == CopterMode.ACRO:
            rm = cfg.acro_rate_max_rad_s
            rates = (rs * rm[0], ps * rm[1], ys * rm[2])
            return self._output(dt, rates, gyro, self._manual_throttle(thr_stick), cos_tilt, False)
        if mode == CopterMode.BRAKE:
            rates = self._level_rates(euler, 0.0, 0.0, None)
            if self.landed:
                return self._ground_idle()
            thrust = self._climb_loop(dt, 0.0, climb_rate_m_s, cos_tilt)
            return self._output(dt, rates, gyro, thrust, cos_tilt, True)
        if mode in (CopterMode.STABILIZE, CopterMode.ALT_HOLD, CopterMode.LOITER):
            amax = cfg.angle_max_rad
            rates = self._level_rates(euler, rs * amax, ps * amax, ys * cfg.pilot_yaw_rate_rad_s)
            if mode == CopterMode.STABILIZE:
                thrust = self._manual_throttle(thr_stick)
                return self._output(dt, rates, gyro, thrust, cos_tilt, False)
            climb_sp = self._pilot_climb_rate(thr_stick)
            if self.landed and climb_sp <= 0.0:
                return self._ground_idle()
            thrust = self._climb_loop(dt, climb_sp, climb_rate_m_s, cos_tilt)
            return self._output(dt, rates, gyro, thrust, cos_tilt, True)
        if mode == CopterMode.LAND:
            if self.landed and not cfg.test_stand:
                self.disarm(t_s, reason="landed")
                return self.motors
            rates = self._level_rates(euler, 0.0, 0.0, 0.0)
            climb_sp = -self.params["LAND_SPEED"] * 0.01
            thrust = self._climb_loop(dt, climb_sp, climb_rate_m_s, cos_tilt)
            return self._output(dt, rates, gyro, thrust, cos_tilt, True)
        # GUIDED / GUIDED_NOGPS
        tgt = self._target
        if tgt is None or self._timed_out:
            rates = self._level_rates(euler, 0.0, 0.0, None)
            if self.landed:
                return self._ground_idle()
            thrust = self._climb_loop(dt, 0.0, climb_rate_m_s, cos_tilt)
            return self._output(dt, rates, gyro, thrust, cos_tilt, True)
        self._yaw_hold = None
        positive = tgt.value > 0.0
        if self.landed and not positive:
            return self._ground_idle()
        if tgt.use_thrust:
            # set_throttle_out(thrust, apply_angle_boost=true)
            inverted = _clip(10.0 * cos_tilt, 0.0, 1.0)
            boost = 1.0 / _clip(cos_tilt, 0.1, 1.0)
            thrust = _clip(tgt.value * inverted * boost, 0.0, 1.0)
        else:
            thrust = self._climb_loop(dt, tgt.value, climb_rate_m_s, cos_tilt)
        return self._output(dt, tgt.rates_rad_s, gyro, thrust, cos_tilt, not tgt.use_thrust)

    def _manual_throttle(self, stick: float) -> float:
        """``Mode::get_pilot_desired_throttle``: mid stick = hover throttle (expo curve)."""
        mid = self.hover_throttle
        expo = _clip(-(mid - 0.5) / 0.375, -0.5, 1.0)
        return stick * (1.0 - expo) + expo * stick**3

    def _pilot_climb_rate(self, stick: float) -> float:
        """ALT_HOLD throttle stick: 10 % dead zone around mid, full stick = PILOT_SPEED_UP."""
        dz = 0.05
        v = self.config.pilot_speed_m_s
        if stick > 0.5 + dz:
            return v * (stick - 0.5 - dz) / (0.5 - dz)
        if stick < 0.5 - dz:
            return v * (stick - 0.5 + dz) / (0.5 - dz)
        return 0.0

    def _level_rates(
        self,
        euler: Sequence[float],
        roll_sp: float,
        pitch_sp: float,
        yaw_rate_sp: float | None,
    ) -> tuple[float, float, float]:
        kp = self.config.angle_p
        if yaw_rate_sp is None:
            if self._yaw_hold is None:
                self._yaw_hold = euler[2]
            r = kp[2] * _wrap_pi(self._yaw_hold - euler[2])
        else:
            r = yaw_rate_sp
        return (kp[0] * (roll_sp - euler[0]), kp[1] * (pitch_sp - euler[1]), r)

    def _climb_loop(self, dt: float, climb_sp: float, climb: float, cos_tilt: float) -> float:
        cfg = self.config
        err = climb_sp - climb
        self._climb_integral = _clip(self._climb_integral + err * dt, -3.0, 3.0)
        thrust = self.hover_throttle + cfg.climb_p * err + cfg.climb_i * self._climb_integral
        return _clip(thrust / max(cos_tilt, 0.5), 0.0, 1.0)

    def _ground_idle(self) -> tuple[float, ...]:
        """Armed, landed, no climb request: motors at MOT_SPIN_ARM, controllers relaxed."""
        self.rate_pid.reset()
        self._climb_integral = 0.0
        self.last_torque_thrust = (0.0, 0.0, 0.0, 0.0)
        self.motors = (self.params["MOT_SPIN_ARM"],) * self.n_motors
        return self.motors

    def _output(
        self,
        dt: float,
        rates_sp: Sequence[float],
        gyro: Sequence[float],
        thrust: float,
        cos_tilt: float,
        auto_throttle: bool,
    ) -> tuple[float, ...]:
        if self.landed and thrust < self.hover_throttle * 0.5:
            self.rate_pid.reset_integrator()  # ArduPilot relaxes the I terms on the ground
        self.rate_target_rad_s = (rates_sp[0], rates_sp[1], rates_sp[2])
        tq = self.rate_pid.update(dt, rates_sp, gyro, self._limit)
        roll, pitch, yaw = (v if math.isfinite(v) else 0.0 for v in tq)
        thrust = thrust if math.isfinite(thrust) else 0.0
        self.last_torque_thrust = (roll, pitch, yaw, thrust)
        res = self.mixer.mix(thrust, roll, pitch, yaw)
        self._limit = list(res.saturated_axes)
        p = self.params
        lo, hi, expo = p["MOT_SPIN_MIN"], p["MOT_SPIN_MAX"], p["MOT_THST_EXPO"]
        span = hi - lo
        self.motors = tuple(lo + span * thrust_to_actuator(m, expo) for m in res.motors)
        return self.motors


# -------------------------------------------------------------------- streams


class ArduStreams(MessageStreams):
    """Message intervals with ArduPilot's rules (``GCS_MAVLINK::set_message_interval``).

    The interval is kept in whole milliseconds (``interval_us / 1000``, below 1 ms
    -> 1 ms); one faster than 0.8 x the main-loop rate
    (``interval_ms * 800 < loop_period_us``, ``cap_message_interval``) is
    DENIED (facts.md 10: what ArduCopter 4.7-dev answers); an unknown message or
    a reset-to-default of one without a default is FAILED.
    """

    def __init__(self, specs: Sequence[StreamSpec], *, loop_rate_hz: float) -> None:
        super().__init__(specs, imu_rate_hz=loop_rate_hz, max_rate_hz=loop_rate_hz)
        self.loop_rate_hz = loop_rate_hz

    def set_interval(self, msg_id: int, interval_us: float, *, t_s: float = 0.0) -> MavResult:
        st = self._streams.get(msg_id)
        if st is None or not math.isfinite(interval_us):
            return MavResult.FAILED
        us = int(interval_us)
        if us == -1:
            st.interval_s = 0.0
            return MavResult.ACCEPTED
        if us == 0:
            if st.spec.default_interval_s <= 0.0:
                return MavResult.FAILED
            st.interval_s = st.spec.default_interval_s
            st.next_due_s = t_s
            return MavResult.ACCEPTED
        if us < 0:
            return MavResult.FAILED
        interval_ms = 1 if us < 1000 else min(us // 1000, 60000)
        loop_period_us = 1e6 / self.loop_rate_hz
        if interval_ms * 800 < loop_period_us and int(loop_period_us / 800.0) > interval_ms:
            return MavResult.DENIED
        st.interval_s = interval_ms * 1e-3
        st.next_due_s = t_s
        return MavResult.ACCEPTED


def ardupilot_streams(loop_rate_hz: float = 400.0) -> ArduStreams:
    """Streams of the ArduPilot face and their defaults (0: off until requested).

    ArduPilot's defaults come from its ``SRn_*`` parameters; these are chosen
    for the SITL (assumed, not ArduPilot's).
    """
    return ArduStreams(
        [
            StreamSpec(ID_HEARTBEAT, "HEARTBEAT", 1.0),
            StreamSpec(ID_SYS_STATUS, "SYS_STATUS", 1.0),
            StreamSpec(ID_EXTENDED_SYS_STATE, "EXTENDED_SYS_STATE", 1.0),
            StreamSpec(ID_HOME_POSITION, "HOME_POSITION", 5.0),
            StreamSpec(ID_LOCAL_POSITION_NED, "LOCAL_POSITION_NED", 0.25),
            StreamSpec(ID_RC_CHANNELS, "RC_CHANNELS", 0.1),
            StreamSpec(ID_ATTITUDE, "ATTITUDE", 0.1, imu_based=True),
            StreamSpec(ID_RAW_IMU, "RAW_IMU", 0.1, imu_based=True),
            StreamSpec(ID_SCALED_IMU, "SCALED_IMU", 0.0, imu_based=True),
            StreamSpec(ID_HIGHRES_IMU, "HIGHRES_IMU", 0.0, imu_based=True),
            StreamSpec(ID_ATTITUDE_QUATERNION, "ATTITUDE_QUATERNION", 0.0, imu_based=True),
        ],
        loop_rate_hz=loop_rate_hz,
    )


# ----------------------------------------------------------------------- face

ARDUPILOT_CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
    | mavlink.MAV_PROTOCOL_CAPABILITY_FLIGHT_TERMINATION
    | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
)
# major << 24 | minor << 16 | patch << 8 | FIRMWARE_VERSION_TYPE_DEV (0)
ARDUPILOT_SW_VERSION = (4 << 24) | (7 << 16) | (0 << 8) | 0

_IMU_STREAMS = (ID_HIGHRES_IMU, ID_RAW_IMU, ID_SCALED_IMU, ID_ATTITUDE, ID_ATTITUDE_QUATERNION)
_EXTRA_ONE_SHOT = {ID_RAW_IMU, ID_SCALED_IMU, ID_HIGHRES_IMU, ID_ATTITUDE}


def _i16(x: float) -> int:
    return int(max(-32768, min(32767, round(x)))) if math.isfinite(x) else 0


class ArduPilotFace(MavlinkFace):
    """The MAVLink face of :class:`ArduCopter` (sysid 1, compid 1, autopilot 3).

    On top of :class:`~sitl.mavlink_face.MavlinkFace` (sockets, peers, streams):
    ArduPilot heartbeat and modes, ``SET_MODE``, parameters
    (``PARAM_REQUEST_READ`` / ``_LIST`` / ``PARAM_SET`` -> ``PARAM_VALUE``),
    ``STATUSTEXT``, ``RAW_IMU`` / ``SCALED_IMU`` / ``HIGHRES_IMU``, and
    ``SET_ATTITUDE_TARGET`` with ArduCopter's rules. ``SET_ACTUATOR_CONTROL_TARGET``
    is ignored, as ArduPilot does.

    IMU units: RAW_IMU and SCALED_IMU carry the INS-filtered gyro in mrad/s and
    the accelerometer in mG as int16 (ArduPilot's ``send_raw_imu`` scaling, the
    same in both); HIGHRES_IMU in rad/s and m/s^2 (floats). ATTITUDE rates are
    the filtered gyro too (ArduPilot sends the AHRS gyro).
    """

    def __init__(
        self,
        endpoint: Endpoint,
        autopilot: ArduCopter,
        streams: ArduStreams,
        *,
        sysid: int = 1,
        compid: int = 1,
    ) -> None:
        super().__init__(endpoint, cast(Any, autopilot), streams, sysid=sysid, compid=compid)
        self.ap = autopilot
        self.params_sent = 0

    # -------------------------------------------------------------- handling

    def _handle(self, msg: Any, t_s: float) -> None:
        mtype = msg.get_type()
        if mtype == "SET_ACTUATOR_CONTROL_TARGET":
            self.messages_received += 1
            self.ap.on_actuator_target(t_s, ())
            self._warn_once("act", "SET_ACTUATOR_CONTROL_TARGET ignored (ArduPilot)")
            return
        if mtype in ("PARAM_REQUEST_READ", "PARAM_REQUEST_LIST", "PARAM_SET", "SET_MODE"):
            self.messages_received += 1
            comp = None if mtype == "SET_MODE" else msg.target_component
            if not self._for_us(msg.target_system, comp):
                return
            if mtype == "PARAM_REQUEST_READ":
                self._param_read(msg.param_id, msg.param_index)
            elif mtype == "PARAM_REQUEST_LIST":
                for i in range(len(self.ap.params)):
                    self._send_param_index(i)
            elif mtype == "PARAM_SET":
                self._param_set(msg.param_id, msg.param_value)
            else:
                result = self._set_mode_common(msg.base_mode, msg.custom_mode, t_s)
                self.mav.command_ack_send(
                    mavlink.MAVLINK_MSG_ID_SET_MODE,
                    int(result),
                    0,
                    0,
                    msg.get_srcSystem(),
                    msg.get_srcComponent(),
                )
                if result == MavResult.ACCEPTED:
                    self._heartbeat_now = True
            return
        super()._handle(msg, t_s)

    def _handle_attitude_target(self, msg: Any, t_s: float) -> None:
        rates = (msg.body_roll_rate, msg.body_pitch_rate, msg.body_yaw_rate)
        self.ap.on_attitude_target(t_s, msg.type_mask, rates, msg.thrust)

    def _set_mode_common(self, base_mode: int, custom_mode: int, t_s: float) -> MavResult:
        if not base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return MavResult.UNSUPPORTED
        return self.ap.set_mode(t_s, custom_mode)

    def _command_result(self, command: int, p: Sequence[float], t_s: float) -> MavResult:
        ap = self.ap
        if command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            if p[0] == 1.0:
                return ap.arm(t_s, force=_as_int(p[1]) == FORCE_ARM_MAGIC)
            if p[0] == 0.0:
                return ap.disarm(t_s, force=_as_int(p[1]) == FORCE_DISARM_MAGIC)
            return MavResult.UNSUPPORTED
        if command == mavlink.MAV_CMD_DO_SET_MODE:
            return self._set_mode_common(_as_int(p[0]), _as_int(p[1]), t_s)
        if command == mavlink.MAV_CMD_NAV_LAND:
            return ap.set_mode(t_s, CopterMode.LAND)
        if command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self.streams.set_interval(_as_int(p[0]), float(p[1]), t_s=t_s)
        if command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            msg_id = _as_int(p[0])
            if msg_id in _EXTRA_ONE_SHOT:
                self._pending.add(msg_id)
                return MavResult.ACCEPTED
            return self._request(msg_id)
        if command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            return self._request(ID_AUTOPILOT_VERSION)
        if command == mavlink.MAV_CMD_GET_HOME_POSITION:
            return self._request(ID_HOME_POSITION)
        logger.debug("unsupported command %d", command)
        return MavResult.UNSUPPORTED

    # ------------------------------------------------------------ parameters

    def _param_read(self, param_id: str, index: int) -> None:
        params = self.ap.params
        if index >= 0:
            self._send_param_index(index)
        elif param_id in params:
            self._send_param_index(params.index(param_id))
        # Unknown names get no answer (ArduPilot ignores them).

    def _param_set(self, param_id: str, value: float) -> None:
        params = self.ap.params
        if param_id not in params:
            self._warn_once(f"param:{param_id}", "PARAM_SET of unknown parameter %s", param_id)
            return
        try:
            params.set(param_id, float(value))
        except ValueError as exc:
            logger.warning("PARAM_SET %s: %s", param_id, exc)
        self._send_param_index(params.index(param_id))

    def _send_param_index(self, index: int) -> None:
        params = self.ap.params
        spec = params.by_index(index)
        if spec is None:
            return
        self.mav.param_value_send(
            spec.name.encode(), params[spec.name], spec.param_type, len(params), index
        )
        self.params_sent += 1

    # -------------------------------------------------------------- streams

    def publish(self, t_s: float, *, imu_sample: bool, wall_s: float) -> bool:
        """As :meth:`MavlinkFace.publish`, with ArduPilot's IMU messages and STATUSTEXT.

        Returns True when the fastest body-rate stream (HIGHRES_IMU, RAW_IMU,
        SCALED_IMU, ATTITUDE or ATTITUDE_QUATERNION: whichever the client asked
        to be fast) went out: the lockstep clock waits after it in GUIDED /
        GUIDED_NOGPS.
        """
        for severity, text in self.ap.drain_statustexts():
            self.mav.statustext_send(severity, text.encode(), 0, 0)
        st = self.streams
        pending = self._pending
        if pending:
            self._pending = set()
            for msg_id in pending:
                self._send_one(msg_id)
        if (
            self._heartbeat_now
            or st.due(ID_HEARTBEAT, t_s)
            or wall_s - self._last_heartbeat_wall_s > 1.0
        ):
            self._heartbeat_now = False
            self._send_heartbeat(wall_s)
        if st.due(ID_RC_CHANNELS, t_s):
            self._send_one(ID_RC_CHANNELS)
        imu_sent = False
        if imu_sample and not self.imu_stopped:
            clock = st.lockstep_stream(_IMU_STREAMS)
            for msg_id in _IMU_STREAMS:
                if st.due(msg_id, t_s):
                    self._send_one(msg_id)
                    imu_sent = imu_sent or msg_id == clock
        for msg_id in (
            ID_LOCAL_POSITION_NED,
            ID_SYS_STATUS,
            ID_EXTENDED_SYS_STATE,
            ID_HOME_POSITION,
        ):
            if st.due(msg_id, t_s):
                self._send_one(msg_id)
        return imu_sent

    def _send_heartbeat(self, wall_s: float) -> None:
        ap = self.ap
        self.mav.heartbeat_send(
            mavlink.MAV_TYPE_QUADROTOR,
            MAV_AUTOPILOT_ARDUPILOTMEGA,
            ap.base_mode,
            ap.custom_mode,
            ap.system_status,
        )
        self._last_heartbeat_wall_s = wall_s

    def _gyro(self) -> tuple[float, float, float]:
        if self.imu_nan:
            return (math.nan, math.nan, math.nan)
        return self.ap.gyro_filtered_rad_s

    def _send_one(self, msg_id: int) -> None:
        s = self.snapshot
        mav = self.mav
        if msg_id in (ID_RAW_IMU, ID_SCALED_IMU):
            a, g = s.accel_frd_m_s2, self._gyro()
            acc_mg = [_i16(v * 1000.0 / GRAVITY_M_S2) for v in a]
            gyro_mrad = [_i16(v * 1000.0) for v in g]
            if msg_id == ID_RAW_IMU:
                mav.raw_imu_send(round(s.imu_t_s * 1e6), *acc_mg, *gyro_mrad, 0, 0, 0, 0, 4500)
            else:
                mav.scaled_imu_send(round(s.imu_t_s * 1e3), *acc_mg, *gyro_mrad, 0, 0, 0, 4500)
            self.imu_messages_sent += 1
        elif msg_id == ID_HIGHRES_IMU:
            a, g = s.accel_frd_m_s2, self._gyro()
            mav.highres_imu_send(
                round(s.imu_t_s * 1e6),
                a[0], a[1], a[2], g[0], g[1], g[2],
                0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 45.0,
                0b111111,
            )  # fmt: skip
            self.imu_messages_sent += 1
        elif msg_id == ID_ATTITUDE:
            e, g = s.euler_rad, self.ap.gyro_filtered_rad_s
            mav.attitude_send(round(s.imu_t_s * 1e3), e[0], e[1], e[2], g[0], g[1], g[2])
        elif msg_id == ID_AUTOPILOT_VERSION:
            mav.autopilot_version_send(
                ARDUPILOT_CAPABILITIES, ARDUPILOT_SW_VERSION, 0, 0, 0,
                [0] * 8, [0] * 8, [0] * 8, 0, 0, 1,
            )  # fmt: skip
        elif msg_id == ID_HEARTBEAT:
            self._send_heartbeat(self._last_heartbeat_wall_s)
        else:
            super()._send_one(msg_id)
