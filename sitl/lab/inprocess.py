"""The product's flight core, flown in process: the lab's shell around it.

``companion run`` drives :class:`companion.core.FlightCore` from MAVLink; the
lab's flights drive the same core from the simulated plant, so a lab figure is
the product's figure: the same timestamp checks, pilot input, engagement, law,
command gate and per-sample failsafes. :func:`engaged_core` builds a core that
is engaged as the product engages on PX4 (the stack recognised, the setpoints
streaming and flown, then the heartbeat that shows OFFBOARD and armed), and
:class:`LabShell` keeps what the core asks: the last command, the events, the
failsafes. A failsafe stops the commands, as it does in the product; the lab's
autopilot then holds the last one it had (the plant has no failsafe of its own).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from companion.control import RateController
from companion.core import FlightCore
from companion.run_options import RunOptions
from companion.stacks import PX4

__all__ = ["LabShell", "engaged_core", "rc_frame"]

_ARMED = 128  # MAV_MODE_FLAG_SAFETY_ARMED
_STANDBY = 4  # MAV_STATE_ACTIVE


@dataclass(frozen=True)
class _Heartbeat:
    custom_mode: int
    base_mode: int
    system_status: int


class LabShell:
    """What the core asks of an in-process flight: kept, not carried out over a link."""

    stopping = False

    def __init__(self) -> None:
        self.controls: tuple[float, ...] | None = None
        """The last actuator controls sent (roll, pitch, yaw, collective, ...)."""
        self.rates: tuple[Sequence[float], float] | None = None
        """The last body rates and collective sent."""
        self.events: list[tuple[str, str]] = []
        self.failsafes: list[tuple[str, str]] = []
        self.on_event: Callable[[str, str], None] | None = None
        """Also called with each event (a control log's ``/events``)."""

    def event(self, kind: str, detail: str) -> None:
        self.events.append((kind, detail))
        if self.on_event is not None:
            self.on_event(kind, detail)

    def send_actuator_controls(self, time_usec: int, controls: tuple[float, ...]) -> None:
        self.controls = controls

    def send_body_rates(self, time_boot_ms: int, rates: Sequence[float], thrust: float) -> None:
        self.rates = (rates, thrust)

    def engage(self) -> None:
        """The lab's flights are engaged from the start (:func:`engaged_core`)."""

    def cancel_engaging(self) -> bool:
        return False

    def hand_back(self, reason: str, *, was_commanding: bool) -> None:
        self.events.append(("hand_back", reason))

    def after_failsafe(self, kind: str, detail: str, *, was_commanding: bool) -> None:
        self.failsafes.append((kind, detail))

    def rerequest_streams(self, why: str) -> None:
        """Nothing to ask again: the plant streams what it streams."""

    def stop(self, *, hand_back_owed: bool) -> None:
        self.stopping = True


def engaged_core(
    opts: RunOptions,
    shell: LabShell,
    clock: Callable[[], float],
    *,
    controller: RateController | None = None,
) -> FlightCore:
    """A flight core for ``opts``, engaged as ``companion run`` engages a PX4."""
    core = FlightCore(opts, shell, clock, controller=controller)
    core.stack = PX4
    core.started_up = True
    core.begin_commanding()
    core.setpoints_now_flown()
    offboard = PX4.modes.custom_mode(*PX4.engage_mode)
    core.on_heartbeat(_Heartbeat(offboard, _ARMED, _STANDBY))
    assert core.engaged
    return core


def rc_frame(channels: Sequence[int]) -> tuple[Any, ...]:
    """RC_CHANNELS' fields ``(chan1_raw, ..., chan18_raw, chancount)`` for ``channels``."""
    n = len(channels)
    return (*channels, *(0,) * (18 - n), n)
