"""A personality flown on the bundled physics, one IMU sample at a time (unit tests)."""

from __future__ import annotations

from typing import Any

from sitl.frames import quat_to_euler_rad
from sitl.imu import Imu
from sitl.personality import Personality
from sitl.physics import Quadrotor

__all__ = ["autopilot_on_imu"]


def autopilot_on_imu(ap: Personality[Any], imu: Imu, quad: Quadrotor) -> tuple[float, ...] | None:
    """Run ``ap`` on the IMU sample due at ``quad``'s time, as the runner does (true
    attitude, climb rate, land and crash flags): its motor commands, or None when no
    sample is due (the motors hold)."""
    st = quad.state
    s = imu.update(quad.t_s, st.rate_frd_rad_s, st.specific_force_frd_m_s2)
    if s is None:
        return None
    return ap.update(
        s.time_s,
        s.gyro_frd_rad_s,
        quat_to_euler_rad(st.q_wxyz),
        climb_rate_m_s=-st.vel_ned_m_s[2],
        landed=st.landed,
        crashed=st.crashed,
    )
