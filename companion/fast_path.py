"""The messages on the control path, parsed straight from their frames.

The IMU sample, the attitude estimate and the pilot's frames skip pymavlink's
generic parser when their frame allows (the link's ``add_fast_handler``) and go
to the flight core with the time they arrived.
"""

from __future__ import annotations

import time
from typing import Any

from companion.core import FlightCore

__all__ = ["add_fast_handlers"]

# MAVLink numbers used here (common.xml).
_MSG_ATTITUDE = 30
_MSG_ATTITUDE_QUATERNION = 31
_MSG_RC_CHANNELS = 65
_MSG_MANUAL_CONTROL = 69
_MSG_HIGHRES_IMU = 105
_RC_FIELDS = (*(f"chan{i}_raw" for i in range(1, 19)), "chancount")
_JOYSTICK_FIELDS = ("x", "y", "z", "r", "enabled_extensions", *(f"aux{i}" for i in range(1, 7)))


def add_fast_handlers(link: Any, core: FlightCore) -> None:
    """The messages on the control path skip pymavlink's generic parser when
    their frame allows: the IMU sample, the estimates, the pilot's frames."""

    # The IMU's message is the stack's, known once it is recognised (startup).
    def on_highres_imu(v: tuple[Any, ...]) -> None:
        """HIGHRES_IMU ``(time_usec, xgyro, ygyro, zgyro)``."""
        if core.imu_source == "highres_imu":
            t_usec, g0, g1, g2 = v
            core.on_imu(t_usec * 1e-6, (g0, g1, g2), link.rx_perf_s)

    def on_attitude(v: tuple[Any, ...]) -> None:
        """ATTITUDE ``(time_boot_ms, rollspeed, pitchspeed, yawspeed)``."""
        if core.imu_source == "attitude":
            t_ms, g0, g1, g2 = v
            core.on_imu(t_ms * 1e-3, (g0, g1, g2), link.rx_perf_s)

    def on_rc(v: tuple[Any, ...]) -> None:
        core.on_rc(v, time.perf_counter())

    def on_manual_control(v: tuple[Any, ...]) -> None:
        core.on_manual_control(v, time.perf_counter())

    link.add_fast_handler(
        _MSG_HIGHRES_IMU, ("time_usec", "xgyro", "ygyro", "zgyro"), on_highres_imu
    )
    link.add_fast_handler(
        _MSG_ATTITUDE, ("time_boot_ms", "rollspeed", "pitchspeed", "yawspeed"), on_attitude
    )
    if core.needs_attitude:
        link.add_fast_handler(
            _MSG_ATTITUDE_QUATERNION,
            ("time_boot_ms", "q1", "q2", "q3", "q4"),
            core.modes.on_attitude_quaternion,
        )
    # RC_CHANNELS often shares the IMU sample's datagram: keep it short too.
    link.add_fast_handler(_MSG_RC_CHANNELS, _RC_FIELDS, on_rc)
    link.add_fast_handler(_MSG_MANUAL_CONTROL, _JOYSTICK_FIELDS, on_manual_control)
