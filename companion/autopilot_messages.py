"""The autopilot's messages other than the IMU sample and the pilot's frames,
each to what keeps it.

HEARTBEAT goes to the flight core (the engaged edge is its decision); the
autopilot's own words (STATUSTEXT) become events; EXTENDED_SYS_STATE's landed
state gates the law's learning; LOCAL_POSITION_NED feeds the flight modes and
says whether a position is there to hand back to; TIMESYNC answers measure the
link; SYS_STATUS carries the pre-arm checks and the RC receiver's health;
ATTITUDE_TARGET the autopilot's collective before a take-over. Message numbers
and fields are MAVLink's common set.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from companion.autopilot_state import AutopilotState
from companion.control import RateController
from companion.link.timesync import LinkClock
from companion.modes import ModeLaws
from companion.pilot import PilotInput
from companion.shell import Shell

__all__ = ["AutopilotMessages"]

_MSG_HEARTBEAT = 0
_MSG_SYS_STATUS = 1
_MSG_LOCAL_POSITION_NED = 32
_MSG_ATTITUDE_TARGET = 83
_MSG_TIMESYNC = 111
_MSG_EXTENDED_SYS_STATE = 245
_MSG_STATUSTEXT = 253
_LANDED_STATE_UNDEFINED = 0  # MAV_LANDED_STATE_UNDEFINED
_LANDED_STATE_ON_GROUND = 1  # MAV_LANDED_STATE_ON_GROUND
_POSITION_TIMEOUT_S = 1.0
"""A position estimate counts as valid while LOCAL_POSITION_NED (sent by PX4 and
ArduPilot only while their estimate is valid) is younger than this."""


class AutopilotMessages:
    """Routes one run's autopilot messages (module docstring).

    Parameters
    ----------
    shell
        Where events go.
    clock
        The shell's clock, s.
    on_heartbeat
        The flight core's HEARTBEAT handler.
    ap, pilot, modes, controller, link_clock
        What keeps the autopilot's word on itself, the pilot's input, the flight
        mode's laws, the rate law and the link's clock: the core's own.
    """

    def __init__(
        self,
        shell: Shell,
        clock: Callable[[], float],
        on_heartbeat: Callable[[Any], None],
        *,
        ap: AutopilotState,
        pilot: PilotInput,
        modes: ModeLaws,
        controller: RateController,
        link_clock: LinkClock,
    ) -> None:
        self.shell = shell
        self.clock = clock
        self.on_heartbeat = on_heartbeat
        self.ap = ap
        self.pilot = pilot
        self.modes = modes
        self.controller = controller
        self.link_clock = link_clock
        self.last_position: float | None = None
        """When the last finite LOCAL_POSITION_NED came."""

    def on_message(self, msg: Any, arrival: float) -> None:
        """A message from the generic parser, ``arrival`` on the shell's clock."""
        mid = msg.get_msgId()
        if mid == _MSG_HEARTBEAT:
            self.on_heartbeat(msg)
        elif mid == _MSG_STATUSTEXT:
            text = msg.text.decode(errors="replace") if isinstance(msg.text, bytes) else msg.text
            self.shell.event("autopilot_says", text.rstrip("\x00"))
        elif mid == _MSG_EXTENDED_SYS_STATE:
            self.on_landed_state(int(msg.landed_state))
        elif mid == _MSG_LOCAL_POSITION_NED:
            # A hand-back without RC holds with a valid position: a finite one.
            if self.modes.on_local_position(msg):
                self.last_position = self.clock()
        elif mid == _MSG_TIMESYNC and msg.tc1 != 0:
            # An answer to ours (the autopilot's own requests, tc1 = 0, go unanswered).
            self.link_clock.reply(msg.tc1, msg.ts1, arrival)
        elif mid == _MSG_SYS_STATUS:
            # The pre-arm checks (--engage auto waits for them before arming), and the
            # RC receiver's health (ArduPilot streams a lost radio's last pulses).
            change = self.pilot.receiver_report(self.ap.sys_status(msg))
            if change is not None:
                self.shell.event(*change)
        elif mid == _MSG_ATTITUDE_TARGET:
            self.modes.on_attitude_target(float(msg.thrust), self.clock())

    def on_landed_state(self, state: int) -> None:
        """EXTENDED_SYS_STATE's ``landed_state``: no identification on the ground.

        An autopilot that never sends it (or sends UNDEFINED) leaves the
        collective as the only gate."""
        if state != _LANDED_STATE_UNDEFINED:
            self.modes.landed_state_seen = True
        on_ground = state == _LANDED_STATE_ON_GROUND
        if on_ground != self.controller.on_ground:
            self.controller.on_ground = on_ground
            self.modes.on_ground_changed(on_ground)
            self.shell.event(
                "landed_state", "on the ground" if on_ground else f"in the air ({state})"
            )

    def position_valid(self, now: float) -> bool:
        """A position estimate to hand back to: a recent finite LOCAL_POSITION_NED,
        and, in the modes that fly on it, one they judge fresh."""
        pos = self.last_position
        valid = pos is not None and now - pos <= _POSITION_TIMEOUT_S
        if self.modes.needs_position:
            valid = valid and self.modes.position_fresh()
        return valid
