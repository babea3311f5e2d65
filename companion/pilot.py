"""The pilot's input: a radio's RC_CHANNELS, or a joystick's MANUAL_CONTROL.

Each valid frame gives the sticks' rates, collective and deflections
(:class:`companion.control.sticks.StickMap`) and the channels the engage switch
is read from. A glitch (a channel missing or out of range) changes nothing: the
last valid sticks hold, as PX4 and ArduPilot hold theirs, until the RC-lost
failsafe (which watches :attr:`PilotInput.last_valid`) says otherwise.

ArduPilot keeps sending RC_CHANNELS with the last pulses it had after its radio
is lost; what says it is lost is the RC receiver's health in its SYS_STATUS.
While the autopilot calls its receiver unhealthy, its RC_CHANNELS are not the
pilot's (:attr:`PilotInput.receiver_healthy`).

A joystick (PX4 without a radio: a ground station's joystick, which PX4 streams
back as MANUAL_CONTROL) is used only while no valid radio frame came within the
RC timeout: a radio, where there is one, is the pilot's input.

No I/O and no clock: each frame comes with its arrival time.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from companion.control.sticks import StickMap, joystick_channels
from companion.shell import Shell

__all__ = ["EngageSwitch", "PilotInput"]


class PilotInput:
    """The pilot's last valid input and when it came.

    Parameters
    ----------
    sticks
        The stick map (the controller file's rate curves and channels).
    timeout_s
        The RC timeout: how long a frame counts as fresh.
    """

    def __init__(self, sticks: StickMap, timeout_s: float) -> None:
        self.sticks = sticks
        self.timeout_s = timeout_s
        self.channels: tuple[int, ...] = ()
        self.rate_rad_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self.thrust = 0.0
        self.deflection: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self.last_valid: float | None = None
        """When the last valid frame came, from either input."""
        self.last_radio: float | None = None
        """When the last valid RC_CHANNELS frame came (a radio, not a joystick)."""
        self.last_joystick: float | None = None
        """When the last MANUAL_CONTROL frame came, valid or not."""
        self.receiver_healthy = True
        """The autopilot's SYS_STATUS says its RC receiver is healthy (or says nothing)."""
        self.n_invalid = 0
        self.n_unhealthy = 0

    def from_radio(self, v: Sequence[Any], now: float) -> tuple[int, ...] | None:
        """RC_CHANNELS ``(chan1_raw, ..., chan18_raw, chancount)``: the channels if
        the frame is the pilot's and valid, else None."""
        if not self.receiver_healthy:
            self.n_unhealthy += 1
            return None
        count = v[18]
        chans = tuple(v[: min(count, 18)] if count else v[:18])
        if not self._take(chans, now):
            return None
        self.last_radio = now
        return chans

    def from_joystick(self, v: Sequence[Any], now: float) -> tuple[int, ...] | None:
        """MANUAL_CONTROL ``(x, y, z, r, enabled_extensions, aux1, ..., aux6)``: the
        joystick's axes and buttons as channels if they are the pilot's input now
        and valid, else None."""
        last, self.last_joystick = self.last_joystick, now
        if last is None or now - last > self.timeout_s:
            # PX4 answers the stream's request with one frame at once, a ground
            # station's joystick or not: a joystick is a stream, from its second frame.
            return None
        radio = self.last_radio
        if radio is not None and now - radio <= self.timeout_s:
            return None
        chans = joystick_channels(v, self.sticks.channels)
        return chans if self._take(chans, now) else None

    def _take(self, chans: tuple[int, ...], now: float) -> bool:
        cmd = self.sticks.map(chans)
        if not cmd.valid:
            self.n_invalid += 1
            return False
        self.channels = chans
        self.rate_rad_s, self.thrust, self.deflection = cmd.rate_rad_s, cmd.thrust, cmd.deflection
        self.last_valid = now
        return True

    def fresh(self, now: float) -> bool:
        """A valid frame came within the RC timeout."""
        last = self.last_valid
        return last is not None and now - last <= self.timeout_s

    def valid_rc(self, now: float) -> bool:
        """Valid frames are coming and the autopilot's receiver is healthy: RC a
        safe mode may be flown on."""
        return self.fresh(now) and self.receiver_healthy

    def receiver_report(self, healthy: bool | None) -> tuple[str, str] | None:
        """The autopilot's word on its RC receiver (SYS_STATUS; None: it says
        nothing): while it calls it unhealthy, its RC_CHANNELS are not the
        pilot's. Returns the event a change calls for, or None."""
        if healthy is None or healthy == self.receiver_healthy:
            return None
        self.receiver_healthy = healthy
        if healthy:
            return "rc_receiver", "the autopilot reports its RC receiver healthy again"
        return (
            "rc_receiver_lost",
            "the autopilot reports its RC receiver unhealthy (SYS_STATUS): its RC_CHANNELS "
            "are the last pulses it had, not the pilot's",
        )


class EngageSwitch:
    """The engage switch on one channel (``--engage rc-switch``): high 1700-2200 us
    engages, below 1300 (or beyond 2200: not a switch position) hands back.

    A switch already high when the companion starts (or restarts, in flight)
    engages nothing until it has been low: the pilot puts it low, then high.
    """

    def __init__(self, channel: int) -> None:
        self.channel = channel
        self.high = False
        self._seen_low = False
        self._said_high = False
        self.value = 0
        """The channel's last value, us."""

    def edge(self, chans: Sequence[int]) -> str | None:
        """``"high"`` (engage), ``"low"`` (hand back), ``"high_at_start"`` (said once:
        nothing engages until it has been low) or None, on one valid frame."""
        ch = self.channel
        value = self.value = chans[ch - 1] if ch <= len(chans) else 0
        high = 1700 <= value <= 2200
        if not self._seen_low:
            if not high:
                self._seen_low = True
            elif not self._said_high:
                self._said_high = True
                return "high_at_start"
            return None
        if not self.high and high:
            self.high = True
            return "high"
        if self.high and (value < 1300 or value > 2200):
            self.high = False
            return "low"
        return None

    def on_frame(
        self,
        chans: Sequence[int],
        shell: Shell,
        *,
        engaged: bool,
        commanding: bool,
        release: Callable[[], bool],
    ) -> None:
        """Act on one valid frame's edge: tell the pilot a switch high at start does
        nothing, engage on high, abandon or hand back on low (``release`` stops
        the commands in this call and says whether there were any)."""
        edge = self.edge(chans)
        if edge is None:
            return
        ch, value = self.channel, self.value
        if edge == "high_at_start":
            shell.event(
                "rc_switch_high_at_start",
                f"ch{ch} high ({value} us) at start: nothing engages until the "
                "switch has been low; put it low, then high to engage",
            )
        elif edge == "high":
            shell.event("rc_switch", f"ch{ch} high ({value} us): engaging")
            shell.engage()
        else:
            # Still waiting for the flight mode's estimates: nothing was sent yet.
            if not commanding and shell.cancel_engaging():
                shell.event("rc_switch", f"ch{ch} low ({value} us): engagement abandoned")
            if engaged or commanding:
                was = release()
                shell.event("rc_switch", f"ch{ch} low ({value} us): handing back")
                shell.hand_back("pilot switched back", was_commanding=was)
