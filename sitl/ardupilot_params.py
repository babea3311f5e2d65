"""The ArduPilot personality's parameters: their specs, defaults and the store.

``PARAM_REQUEST_READ`` / ``PARAM_REQUEST_LIST`` / ``PARAM_SET`` reach
:class:`ArduParams` through the face (``sitl.ardupilot_face``); the autopilot
(``sitl.ardupilot``) reads its values and listens for changes.

Names are ArduCopter 4.7's, the version the face reports by default
(``4.7.0-dev``): 4.7 moved the MAVLink settings into the ``MAV_`` group
(ArduPilot PR #29617, "PARAMETER_CONVERSION - Added: Mar-2025 for
ArduPilot-4.7"), so the ground station's sysid is ``MAV_GCS_SYSID`` (formerly
``SYSID_MYGCS``) and this vehicle's is ``MAV_SYSID`` (formerly
``SYSID_THISMAV``); the table keeps these names whatever ``--firmware`` says.
The per-port stream rates (``MAVn_*``, formerly ``SRn_*``) are not in the
table: the face's streams do not follow them (``sitl.ardupilot_face``).

Values ride in ``PARAM_VALUE`` C-cast (the number as a float, integers too),
as ArduPilot's ``GCS_MAVLINK`` sends them (``cast_to_float``).

Defaults are ArduCopter's; the SITL vehicle is then set up at boot with
:data:`SITL_RATE_TUNE` and :data:`SITL_AIRFRAME` (flight-mode switch on channel 6),
before ``sitl run --param``. Followed by the autopilot: ``ARMING_CHECK``,
``FS_THR_ENABLE``, ``FS_OPTIONS``, ``RC_FS_TIMEOUT``, ``GUID_OPTIONS``,
``GUID_TIMEOUT``, ``INS_GYRO_FILTER``, ``LAND_SPEED``, ``MOT_*``,
``WPNAV_SPEED_*``, ``ATC_RAT_*``; ``RC3_MIN``, ``RC3_MAX``, ``RC3_DZ``,
``RC_OPTIONS`` and ``THR_DZ`` (the throttle's arming checks); at boot only
``SCHED_LOOP_RATE`` and ``MAV_SYSID``; ``MOT_THST_HOVER`` is set at boot to the
vehicle's hover throttle, as ArduCopter learns it in flight (``MOT_HOVER_LEARN``
2). Stored only: the stick limits (``ANGLE_MAX``, ``PILOT_*``, ``LOIT_*``,
``PSC_ANGLE_MAX``, ``PSC_VELXY_P``, ``ATC_INPUT_TC``, ``RC1_DZ``: what the
companion's flight modes read, ``THR_DZ`` too), ``MAV_GCS_SYSID``, ``FS_GCS_*``,
``RCMAP_*`` (the SITL radio sends AETR), ``FLTMODE_CH`` (modes change over MAVLink).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink

from sitl.personality import ParamSpec, ParamStore

__all__ = ["PARAM_SPECS", "SITL_AIRFRAME", "SITL_RATE_TUNE", "ArduParams", "ParamSpec"]

PARAM_INT8 = mavlink.MAV_PARAM_TYPE_INT8
PARAM_INT16 = mavlink.MAV_PARAM_TYPE_INT16
PARAM_INT32 = mavlink.MAV_PARAM_TYPE_INT32
PARAM_REAL32 = mavlink.MAV_PARAM_TYPE_REAL32
_INT_RANGE = {
    PARAM_INT8: (-128, 127),
    PARAM_INT16: (-32768, 32767),
    PARAM_INT32: (-(2**31), 2**31 - 1),
}


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
    # AC_AttitudeControl.cpp, ArduCopter Parameters.cpp, AC_Loiter.cpp, AC_PosControl.cpp
    # (Copter-4.5 defaults): what the sticks may ask in STABILIZE, ALT_HOLD and LOITER
    # (stored only: the companion's flight modes read them).
    ParamSpec("ANGLE_MAX", 3000, PARAM_INT16, 1000, 8000, "lean angle max, cdeg"),
    ParamSpec("ARMING_CHECK", 1, PARAM_INT32, doc="0: skip the pre-arm checks"),
    # AC_AttitudeControl.cpp / AC_AttitudeControl_Multi.cpp (Copter-4.5 defaults).
    ParamSpec("ATC_ACCEL_P_MAX", 110000.0, PARAM_REAL32, 0, 180000, "pitch accel, cdeg/s^2"),
    ParamSpec("ATC_ACCEL_R_MAX", 110000.0, PARAM_REAL32, 0, 180000, "roll accel, cdeg/s^2"),
    ParamSpec("ATC_ACCEL_Y_MAX", 27000.0, PARAM_REAL32, 0, 72000, "yaw accel, cdeg/s^2"),
    ParamSpec("ATC_ANG_PIT_P", 4.5, PARAM_REAL32, 3.0, 12.0, "pitch angle P"),
    ParamSpec("ATC_ANG_RLL_P", 4.5, PARAM_REAL32, 3.0, 12.0, "roll angle P"),
    ParamSpec("ATC_ANG_YAW_P", 4.5, PARAM_REAL32, 3.0, 12.0, "yaw angle P"),
    ParamSpec("ATC_INPUT_TC", 0.15, PARAM_REAL32, 0.0, 1.0, "attitude input time constant, s"),
    ParamSpec("ATC_RATE_FF_ENAB", 1, PARAM_INT8, 0, 1, "1: shape rate input, feed it forward"),
    ParamSpec("ATC_THR_MIX_MAN", 0.1, PARAM_REAL32, 0.1, 0.9, "throttle mix, manual throttle"),
    ParamSpec("ATC_THR_MIX_MAX", 0.5, PARAM_REAL32, 0.5, 0.9, "throttle mix, in the air"),
    ParamSpec("ATC_THR_MIX_MIN", 0.1, PARAM_REAL32, 0.1, 0.25, "throttle mix, landed"),
    ParamSpec("FLTMODE_CH", 5, PARAM_INT8, 0, 16, "flight-mode channel (0 none)"),
    ParamSpec("FS_GCS_ENABLE", 0, PARAM_INT8, 0, 7, "GCS loss: 0 off (stored only)"),
    ParamSpec("FS_GCS_TIMEOUT", 5.0, PARAM_REAL32, 2.0, 120.0, "s without GCS (stored only)"),
    ParamSpec("FS_OPTIONS", 16, PARAM_INT32, 0, 1023, "bit 2 (4): continue guided on RC loss"),
    ParamSpec("FS_THR_ENABLE", 1, PARAM_INT8, 0, 7, "RC loss: 0 off, 1 RTL, 3 land, 7 brake"),
    ParamSpec("GUID_OPTIONS", 0, PARAM_INT32, 0, 255, "bit 3 (8): thrust is thrust"),
    ParamSpec("GUID_TIMEOUT", 3.0, PARAM_REAL32, 0.1, 5.0, "s without targets before levelling"),
    ParamSpec("INS_GYRO_FILTER", 20, PARAM_INT16, 0, 256, "gyro LPF, Hz"),
    ParamSpec("LAND_SPEED", 50, PARAM_INT16, 30, 200, "final descent speed, cm/s"),
    ParamSpec("LOIT_ANG_MAX", 0.0, PARAM_REAL32, 0.0, 45.0, "deg; 0: 2/3 of ANGLE_MAX"),
    ParamSpec("LOIT_BRK_ACCEL", 250.0, PARAM_REAL32, 25.0, 250.0, "braking, cm/s^2"),
    ParamSpec("LOIT_BRK_DELAY", 1.0, PARAM_REAL32, 0.0, 2.0, "brake start delay, s"),
    ParamSpec("LOIT_BRK_JERK", 500.0, PARAM_REAL32, 500.0, 5000.0, "braking jerk, cm/s^3"),
    ParamSpec("LOIT_SPEED", 1250.0, PARAM_REAL32, 20.0, 3500.0, "max speed, cm/s"),
    # GCS.cpp (4.7): MAV_GCS_SYSID (was SYSID_MYGCS), MAV_SYSID (was SYSID_THISMAV).
    ParamSpec("MAV_GCS_SYSID", 255, PARAM_INT16, 1, 255, "ground station sysid"),
    ParamSpec("MAV_SYSID", 1, PARAM_INT16, 1, 255, "this vehicle's sysid (at boot)"),
    ParamSpec("MOT_SPIN_ARM", 0.10, PARAM_REAL32, 0.0, 0.2, "armed idle"),
    ParamSpec("MOT_SPIN_MAX", 0.95, PARAM_REAL32, 0.9, 1.0, "top of the output range"),
    ParamSpec("MOT_SPIN_MIN", 0.15, PARAM_REAL32, 0.0, 0.3, "bottom of the output range"),
    ParamSpec("MOT_THST_EXPO", 0.65, PARAM_REAL32, -1.0, 1.0, "thrust curve expo"),
    ParamSpec("MOT_THST_HOVER", 0.35, PARAM_REAL32, 0.2, 0.8, "hover throttle (learnt)"),
    ParamSpec("MOT_YAW_HEADROOM", 200, PARAM_INT16, 0, 500, "yaw headroom, PWM us"),
    ParamSpec("PILOT_ACCEL_Z", 250, PARAM_INT16, 50, 500, "climb acceleration, cm/s^2"),
    ParamSpec("PILOT_SPEED_DN", 0, PARAM_INT16, 0, 500, "descent, cm/s; 0: PILOT_SPEED_UP"),
    ParamSpec("PILOT_SPEED_UP", 250, PARAM_INT16, 50, 500, "climb, cm/s"),
    ParamSpec("PSC_ANGLE_MAX", 0.0, PARAM_REAL32, 0.0, 45.0, "deg; 0: ANGLE_MAX"),
    ParamSpec("PSC_VELXY_P", 2.0, PARAM_REAL32, 0.1, 6.0, "velocity P, 1/s"),
    ParamSpec("RC1_DZ", 20, PARAM_INT16, 0, 200, "roll dead zone, us"),
    # The throttle channel as the real SITL's copter.parm calibrates it (ArduPilot's
    # RC3_MIN default is 1100); Copter's throttle dead zone; RC_OPTIONS bit 5 (32,
    # the default): the throttle must be at idle to arm.
    ParamSpec("RC3_DZ", 30, PARAM_INT16, 0, 200, "throttle dead zone above RC3_MIN, us"),
    ParamSpec("RC3_MAX", 2000, PARAM_INT16, 800, 2200, "throttle channel maximum, us"),
    ParamSpec("RC3_MIN", 1000, PARAM_INT16, 800, 2200, "throttle channel minimum, us"),
    ParamSpec("RC_FS_TIMEOUT", 1.0, PARAM_REAL32, 0.1, 10.0, "s without RC before failsafe"),
    ParamSpec("RC_OPTIONS", 32, PARAM_INT32, 0, 2**31 - 1, "bit 5 (32): throttle idle to arm"),
    # AP_RCMapper.cpp; the SITL radio sends AETR whatever they say (stored only).
    ParamSpec("RCMAP_PITCH", 2, PARAM_INT8, 1, 16, "pitch channel"),
    ParamSpec("RCMAP_ROLL", 1, PARAM_INT8, 1, 16, "roll channel"),
    ParamSpec("RCMAP_THROTTLE", 3, PARAM_INT8, 1, 16, "throttle channel"),
    ParamSpec("RCMAP_YAW", 4, PARAM_INT8, 1, 16, "yaw channel"),
    ParamSpec("SCHED_LOOP_RATE", 400, PARAM_INT16, 50, 2000, "main loop, Hz (at boot)"),
    ParamSpec("THR_DZ", 100, PARAM_INT16, 0, 300, "mid-throttle dead zone, us"),
    ParamSpec("WPNAV_ACCEL", 250.0, PARAM_REAL32, 50.0, 500.0, "AUTO's acceleration, cm/s^2"),
    ParamSpec("WPNAV_JERK", 1.0, PARAM_REAL32, 1.0, 20.0, "AUTO's jerk, m/s^3"),
    ParamSpec("WPNAV_SPEED_DN", 150.0, PARAM_REAL32, 10, 500, "guided max descent, cm/s"),
    ParamSpec("WPNAV_SPEED_UP", 250.0, PARAM_REAL32, 10, 1000, "guided max climb, cm/s"),
    # AC_AttitudeControl_Multi.h defaults (AC_ATC_MULTI_RATE_*).
    *_rate_pid_specs("RLL", 0.135, 0.135, 0.0036, 0.0),
    *_rate_pid_specs("PIT", 0.135, 0.135, 0.0036, 0.0),
    *_rate_pid_specs("YAW", 0.180, 0.018, 0.0, 2.5),
)


class ArduParams(ParamStore):
    """ArduPilot-style parameter store (``PARAM_REQUEST_*`` / ``PARAM_SET``).

    Values are kept as the type says: integer types are rounded and saturated to
    the type's range (ArduPilot stores what it is sent; the documented range is
    not enforced, as in ``GCS_MAVLINK::handle_param_set``).
    """

    def __init__(self, specs: Sequence[ParamSpec] = PARAM_SPECS) -> None:
        super().__init__(specs)

    def _coerce(self, spec: ParamSpec, value: float) -> float:
        if not math.isfinite(value):
            raise ValueError(f"{spec.name}: expected a finite value, got {value!r}")
        if spec.param_type in _INT_RANGE:
            lo, hi = _INT_RANGE[spec.param_type]
            value = float(min(hi, max(lo, round(value))))
        return float(value)


SITL_RATE_TUNE: tuple[tuple[str, float], ...] = ()
"""The SITL airframe's rate-loop tune over ArduPilot's defaults: none.

Until the personality shaped its rate input and flew an attitude target as
ArduCopter does (:class:`sitl.ardupilot_control.AttitudeControl`), roll and pitch
ran P 0.17, FLTT 9 Hz, FLTD 10 Hz here to make up for the missing shaping; with the
shaping in, ArduPilot's own defaults stand (``docs/research/ardupilot.md``).
"""

SITL_AIRFRAME: tuple[tuple[str, float], ...] = (("FLTMODE_CH", 6),)
"""How the SITL vehicle is set up beyond its tune (the runner applies it at boot,
before ``--param``): the flight-mode switch on channel 6 (ArduCopter's default
is 5), as channel 5 of the SITL radio is the companion's engage switch (the
pilot's first aux channel, ``companion run --engage-channel`` 5)."""
