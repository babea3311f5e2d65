"""What runs a flight core: the :class:`Shell` protocol.

:class:`companion.core.FlightCore` does no I/O; whatever drives it (``companion
run``'s asyncio shell over MAVLink, :class:`companion.app.Companion`; the lab's
in-process flights, :class:`sitl.lab.inprocess.LabShell`) gives it what arrives
and carries out what it asks through these calls. Each is called from inside
the core's own call and must not wait: the asyncio shell starts a task for what
takes time (engaging, handing back).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

__all__ = ["Shell"]


class Shell(Protocol):
    """What the core asks of whatever runs it."""

    @property
    def stopping(self) -> bool:
        """The run is ending: nothing engages, no second failsafe."""

    def event(self, kind: str, detail: str) -> None:
        """Record an event (never raises)."""

    def send_actuator_controls(self, time_usec: int, controls: tuple[float, ...]) -> None: ...

    def send_body_rates(self, time_boot_ms: int, rates: Sequence[float], thrust: float) -> None: ...

    def engage(self) -> None:
        """Start engaging (the pilot's switch went high)."""

    def cancel_engaging(self) -> bool:
        """Abandon an engagement under way; whether there was one."""

    def hand_back(self, reason: str, *, was_commanding: bool) -> None:
        """Hand back to a safe mode (the pilot's switch went low)."""

    def after_failsafe(self, kind: str, detail: str, *, was_commanding: bool) -> None:
        """Hand back after a failsafe, then end the run or wait, as configured;
        calls :meth:`FlightCore.failsafe_over` when done."""

    def rerequest_streams(self, why: str) -> None:
        """Ask for the streams again (the autopilot rebooted)."""

    def stop(self, *, hand_back_owed: bool) -> None:
        """End the run (its duration is over)."""
