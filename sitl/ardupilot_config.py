"""The ArduCopter personality's tunables that are not ArduPilot parameters.

:class:`ArduCopterConfig` is read by the autopilot (:mod:`sitl.ardupilot`) and by
its flight laws (:mod:`sitl.ardupilot_laws`), so it sits below both.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sitl.ardupilot_params import SITL_RATE_TUNE
from sitl.personality import PILOT_ACRO_RATE_MAX_RAD_S

__all__ = ["ArduCopterConfig"]


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
    ekf_alt_ready_s, ekf_position_ready_s
        Seconds after boot at which the EKF has an altitude and a position
        estimate; before, arming is refused with ArduCopter's texts ("Arm: Need Alt
        Estimate"; "PreArm: Need Position Estimate" in a mode that needs one). The
        real 4.5.6 SITL: a few seconds and 40-50 s. 0: ready at boot.
    """

    test_stand: bool = False
    hover_motor_cmd: float = 0.5
    prearm_fail: str | None = None
    tune: tuple[tuple[str, float], ...] = SITL_RATE_TUNE
    params: tuple[tuple[str, float], ...] = ()
    acro_rate_max_rad_s: tuple[float, float, float] = PILOT_ACRO_RATE_MAX_RAD_S
    angle_max_rad: float = math.radians(30.0)
    pilot_yaw_rate_rad_s: float = math.radians(202.5)
    angle_p: tuple[float, float, float] = (4.5, 4.5, 4.5)
    pilot_speed_m_s: float = 2.5
    climb_p: float = 0.15
    climb_i: float = 0.08
    ekf_alt_ready_s: float = 0.0
    ekf_position_ready_s: float = 0.0
