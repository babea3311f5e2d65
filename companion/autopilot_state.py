"""What the autopilot says of itself: its mode, armed state, failsafe state,
pre-arm checks and RC receiver, from its HEARTBEAT and SYS_STATUS.

PX4 and ArduPilot say they are failing safe in HEARTBEAT's ``system_status``
(MAV_STATE_CRITICAL, MAV_STATE_EMERGENCY), whatever mode they show. They
report their pre-arm checks as a sensor in SYS_STATUS
(MAV_SYS_STATUS_PREARM_CHECK, healthy while they pass), and their RC receiver
as another (MAV_SYS_STATUS_SENSOR_RC_RECEIVER): ArduPilot keeps streaming a
lost radio's last pulses in RC_CHANNELS, and clears the receiver's health when
its own radio failsafe triggers; PX4 drops the sensor from the present mask.
MAVLink's common message set defines both (``MAV_STATE``,
``MAV_SYS_STATUS_SENSOR``).
"""

from __future__ import annotations

from typing import Any

__all__ = ["FAILSAFE_STATES", "AutopilotState"]

_SENSOR_RC_RECEIVER = 1 << 16  # MAV_SYS_STATUS_SENSOR_RC_RECEIVER
_SENSOR_PREARM_CHECK = 1 << 28  # MAV_SYS_STATUS_PREARM_CHECK
_STATE_NAMES = {5: "CRITICAL", 6: "EMERGENCY"}
FAILSAFE_STATES = frozenset(_STATE_NAMES)
"""HEARTBEAT ``system_status`` values with which PX4 and ArduPilot say they are
failing safe (MAV_STATE_CRITICAL, MAV_STATE_EMERGENCY), whatever mode they show."""
_BASE_MODE_ARMED = 128


class AutopilotState:
    """The autopilot's last word on itself."""

    def __init__(self) -> None:
        self.mode: int | None = None
        """The last HEARTBEAT's ``custom_mode``."""
        self.armed = False
        self.status: int | None = None
        """The last HEARTBEAT's ``system_status`` (MAV_STATE)."""
        self.heartbeats = 0
        """HEARTBEATs counted once the stack is known."""
        self.prearm_ready: bool | None = None
        """The pre-arm checks pass, as SYS_STATUS says; None: it says nothing about
        them (not reported, or no SYS_STATUS yet)."""
        self.n_sys_status = 0
        self._rc_receiver_seen = False

    def heartbeat(self, msg: Any) -> tuple[str, str] | None:
        """A HEARTBEAT's mode, armed state and status; the event its failsafe state's
        change calls for, or None."""
        self.mode = int(msg.custom_mode)
        self.armed = bool(msg.base_mode & _BASE_MODE_ARMED)
        status, before = int(msg.system_status), self.status
        self.status = status
        if status == before or before is None:
            return None
        if status in FAILSAFE_STATES:
            return "autopilot_failsafe", f"system status {_STATE_NAMES[status]}"
        if before in FAILSAFE_STATES:
            return "autopilot_failsafe_cleared", f"system status {status}"
        return None

    def sys_status(self, msg: Any) -> bool | None:
        """A SYS_STATUS: the pre-arm checks, and whether the RC receiver is healthy
        (None: no receiver reported at all, nothing to judge by)."""
        self.n_sys_status += 1
        present = int(msg.onboard_control_sensors_present)
        health = int(msg.onboard_control_sensors_health)
        enabled = int(msg.onboard_control_sensors_enabled)
        if present & _SENSOR_PREARM_CHECK:
            self.prearm_ready = bool(health & _SENSOR_PREARM_CHECK) or not (
                enabled & _SENSOR_PREARM_CHECK
            )
        else:
            self.prearm_ready = None
        bit = _SENSOR_RC_RECEIVER
        if present & bit:
            self._rc_receiver_seen = True
            return bool(health & bit) or not (enabled & bit)
        if self._rc_receiver_seen:
            return False  # it was there and is gone (PX4 on a radio or joystick loss)
        return None
