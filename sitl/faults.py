"""Faults the SITL injects in flight (``sitl run --fault KIND@T``).

:func:`parse_fault` reads them; the simulation loop (``sitl.runner``) applies
each once at its time; :class:`OutgoingFaults` is how the message faults
(``heartbeat-stop``, ``imu-range``) change what the face sends.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from sitl.mavlink_face import ID_HEARTBEAT, ID_HIGHRES_IMU

__all__ = ["FAULT_KINDS", "IMU_RANGE_GYRO_RAD_S", "Fault", "OutgoingFaults", "parse_fault"]

FAULT_KINDS = (
    "imu-stop",
    "imu-nan",
    "link-drop",
    "motor-fail",
    "heartbeat-stop",
    "imu-range",
    "rc-lost",
    "position-lost",
)

IMU_RANGE_GYRO_RAD_S = 40.0
"""The HIGHRES_IMU ``xgyro`` an ``imu-range`` fault reports: finite, but beyond
every bundled profile's gyro range (2000 deg/s = 34.9 rad/s)."""


@dataclass(frozen=True)
class Fault:
    """A fault injected at simulation time ``t_s`` (see :func:`parse_fault`)."""

    kind: str
    t_s: float
    arg: int = 0


def parse_fault(text: str) -> Fault:
    """Parse ``KIND@T`` or ``motor-fail@T:INDEX`` (T in simulated seconds).

    ``imu-stop``: no more IMU streams (HIGHRES_IMU, ATTITUDE...);
    ``imu-nan``: HIGHRES_IMU gyro fields become NaN;
    ``link-drop``: nothing is sent or read any more;
    ``motor-fail``: motor INDEX (0-based) stops;
    ``heartbeat-stop``: no more HEARTBEAT (requested or periodic); every other
    message still flows both ways (a lost-link test without a stale IMU);
    ``imu-range``: HIGHRES_IMU ``xgyro`` reads :data:`IMU_RANGE_GYRO_RAD_S`
    (finite, beyond the gyro's range); the other fields and streams are true;
    ``rc-lost``: the autopilot's receiver loses its signal: RC_CHANNELS goes on
    as such a receiver reports on PX4 (chancount 0, every channel UINT16_MAX, RSSI
    0) and on ArduPilot (the last values, RSSI unchanged: only SYS_STATUS's RC
    health and the radio failsafe say so); with a joystick pilot the joystick
    stops; the autopilot gets no sticks (its RC-loss failsafe follows, as
    ``sitl.autopilot`` and ``sitl.ardupilot`` describe);
    ``position-lost``: the position estimate is lost: no more LOCAL_POSITION_NED,
    and the autopilot's position modes fail over as the real stacks' do.
    The autopilot's own loop keeps the true IMU samples in every case.
    """
    kind, _, rest = text.partition("@")
    when, colon, arg = rest.partition(":")
    try:
        t_s = float(when)
        index = int(arg) if colon else 0  # "motor-fail@6:" has no motor: an error
    except ValueError:
        raise ValueError(f"fault {text!r}: expected KIND@SECONDS[:MOTOR]") from None
    if kind not in FAULT_KINDS or not (t_s >= 0.0 and math.isfinite(t_s)):
        raise ValueError(f"fault {text!r}: KIND is one of {', '.join(FAULT_KINDS)}, SECONDS >= 0")
    if (kind == "motor-fail") != bool(colon):
        raise ValueError(
            f"fault {text!r}: expected motor-fail@SECONDS:MOTOR (0-based), other kinds KIND@SECONDS"
        )
    return Fault(kind, t_s, index)


class OutgoingFaults:
    """Faults applied to messages as the face encodes them.

    Wraps the face's pymavlink ``send`` (every message it sends goes through it,
    HEARTBEAT included, before signing and packing); installed only when such a
    fault is injected, so a run without one sends exactly what it always did.
    """

    def __init__(self, mav: Any) -> None:
        self._send = mav.send
        self.drop_heartbeat = False
        self.gyro_x_rad_s: float | None = None
        self.dropped_heartbeats = 0
        mav.send = self.send

    def send(self, msg: Any, force_mavlink1: bool = False) -> None:
        mid = msg.get_msgId()
        if mid == ID_HEARTBEAT and self.drop_heartbeat:
            self.dropped_heartbeats += 1
            return
        if mid == ID_HIGHRES_IMU and self.gyro_x_rad_s is not None:
            msg.xgyro = self.gyro_x_rad_s
        self._send(msg, force_mavlink1=force_mavlink1)
