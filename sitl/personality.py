"""What the SITL's autopilot personalities share: arming, modes, events, RC presence.

The PX4-like :class:`sitl.autopilot.Autopilot` and the ArduCopter-like
:class:`sitl.ardupilot.ArduCopter` derive from :class:`Personality`. Neither has
sockets or a clock: the simulation loop (``sitl.runner``) drives one with
simulation time, and its MAVLink face (``sitl.px4_face``, ``sitl.ardupilot_face``)
turns messages into calls on it, so every rule is testable without a network.

This module holds the rules both stacks have; each stack's own (mode numbers,
failsafe parameters, what a refusal answers, its flight laws) stay in its module.

Shared rules
------------
* Arming an armed vehicle is ACCEPTED; then the stack's own checks (a crashed
  vehicle is refused by both). Arming resets the failsafe, the rate loop and the
  climb-rate integrator.
* Disarming a disarmed vehicle is ACCEPTED; in the air it is refused unless
  forced (``param2`` = 21196 on both stacks) or crashed.
* A crash disarms (forced) and holds the motor outputs from then on.
* RC is present while frames keep arriving within the stack's timeout
  (:attr:`Personality.rc_timeout_s`); the last frame's sticks are kept.
* A mode change resets the climb-rate integrator. Mode changes, arming,
  disarming, refusals and failsafes are recorded as :class:`Event` s.
* The rate loop and the mixer are each stack's own (PX4's ``RateControl`` and
  control allocation in ``sitl.px4_control``, ArduCopter's attitude controller,
  ``AC_PID`` and ``AP_MotorsMatrix`` in ``sitl.ardupilot_control``), written from
  the stacks' sources and independent of the companion's laws.

Also shared: the firmware version a stack reports (:class:`FirmwareVersion`,
``AUTOPILOT_VERSION.flight_sw_version``) and the parameter table
(:class:`ParamStore`, :class:`ParamSpec`). Each stack's store decides how a
value is kept (``sitl.ardupilot_params``: rounded and saturated as ArduPilot
does; ``sitl.px4_params``: int32 or float32 as PX4 does) and its face how a
value rides in ``PARAM_VALUE.param_value`` (C-cast or bytewise).
"""

from __future__ import annotations

import logging
import math
import re
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any, ClassVar, Generic, Protocol, TypeVar

from companion.profile import VehicleProfile

__all__ = [
    "FORCE_DISARM_MAGIC",
    "MAV_SEVERITY_CRITICAL",
    "MAV_SEVERITY_INFO",
    "MAV_SEVERITY_WARNING",
    "PILOT_ACRO_RATE_MAX_RAD_S",
    "Event",
    "FirmwareVersion",
    "MavResult",
    "Mode",
    "ParamSpec",
    "ParamStore",
    "Personality",
    "clip",
    "stick_unit",
    "throttle_unit",
]

logger = logging.getLogger(__name__)

MAV_SEVERITY_CRITICAL = 2
MAV_SEVERITY_WARNING = 4
MAV_SEVERITY_INFO = 6

FORCE_DISARM_MAGIC = 21196
"""``MAV_CMD_COMPONENT_ARM_DISARM`` param2 that forces a disarm in the air (PX4, ArduPilot)."""

PILOT_ACRO_RATE_MAX_RAD_S = (math.radians(720.0), math.radians(720.0), math.radians(360.0))
"""Full-stick ACRO body rates (roll, pitch, yaw) of both personalities: the bundled
pilot's stick map (``sitl.pilot``: 720, 720, 360 deg/s), so scripted maneuvers fly
as written."""


class MavResult(IntEnum):
    """``MAV_RESULT`` values used in ``COMMAND_ACK``."""

    ACCEPTED = 0
    TEMPORARILY_REJECTED = 1
    DENIED = 2
    UNSUPPORTED = 3
    FAILED = 4


@dataclass(frozen=True)
class Event:
    """Something that happened, for the log (mode change, arm, failsafe...)."""

    t_s: float
    kind: str
    detail: dict[str, Any] = field(default_factory=dict)


_FIRMWARE_TYPES = {"dev": 0, "alpha": 64, "beta": 128, "rc": 192}
"""``FIRMWARE_VERSION_TYPE`` of a version's suffix; none is OFFICIAL (255)."""
_FIRMWARE_RE = re.compile(r"v?(\d+)\.(\d+)\.(\d+)(?:-(dev|alpha|beta|rc)\d*)?")


@dataclass(frozen=True)
class FirmwareVersion:
    """A flight stack's version, as ``AUTOPILOT_VERSION.flight_sw_version`` carries it.

    Both stacks pack it as ``major << 24 | minor << 16 | patch << 8 | type``
    (PX4 ``px4_firmware_version()``; ArduPilot ``GCS_MAVLINK::send_autopilot_version``
    from ``AP_FWVersion``), ``type`` a ``FIRMWARE_VERSION_TYPE``: 0 dev, 64
    alpha, 128 beta, 192 rc, 255 official release.
    """

    major: int
    minor: int
    patch: int
    fw_type: int = 255

    @classmethod
    def parse(cls, text: str) -> FirmwareVersion:
        """``MAJOR.MINOR.PATCH`` with an optional ``-dev``/``-alpha``/``-beta``/``-rcN``.

        Raises
        ------
        ValueError
            For anything else, or a part above 255.
        """
        m = _FIRMWARE_RE.fullmatch(text.strip())
        parts = [int(m.group(i)) for i in (1, 2, 3)] if m else []
        if m is None or any(p > 255 for p in parts):
            raise ValueError(
                f"{text!r}: expected MAJOR.MINOR.PATCH, each 0..255, optionally with "
                "-dev, -alpha, -beta or -rcN (e.g. 1.13.3, 1.14.0-rc1, 4.7.0-dev)"
            )
        suffix = m.group(4)
        return cls(parts[0], parts[1], parts[2], _FIRMWARE_TYPES[suffix] if suffix else 255)

    @property
    def flight_sw_version(self) -> int:
        """``AUTOPILOT_VERSION.flight_sw_version``."""
        return self.major << 24 | self.minor << 16 | self.patch << 8 | self.fw_type

    def at_least(self, major: int, minor: int) -> bool:
        """This is ``major.minor`` or later (a pre-release of it counts as it)."""
        return (self.major, self.minor) >= (major, minor)

    def __str__(self) -> str:
        names = {v: k for k, v in _FIRMWARE_TYPES.items()}
        suffix = f"-{names[self.fw_type]}" if self.fw_type in names else ""
        return f"{self.major}.{self.minor}.{self.patch}{suffix}"


@dataclass(frozen=True)
class ParamSpec:
    """One autopilot parameter: name, default, MAVLink type, documented range.

    ``param_type`` is the ``MAV_PARAM_TYPE`` the stack reports; ``min_value`` /
    ``max_value`` are the parameter reference's range, shown, not enforced
    (neither stack enforces it on ``PARAM_SET``).
    """

    name: str
    default: float
    param_type: int
    min_value: float = -math.inf
    max_value: float = math.inf
    doc: str = ""


class ParamStore(ABC):
    """A stack's parameter table (``PARAM_REQUEST_*`` / ``PARAM_SET``), ordered by name.

    The index a ``PARAM_VALUE`` carries is the position in name order (both
    stacks list their parameters sorted). A subclass says how a value is kept
    (:meth:`_coerce`); the autopilot may refuse values it cannot fly
    (:meth:`add_check`) and follow changes (:meth:`on_change`).
    """

    def __init__(self, specs: Sequence[ParamSpec]) -> None:
        self.specs = tuple(sorted(specs, key=lambda s: s.name))
        self._by_name = {s.name: s for s in self.specs}
        self._values = {s.name: float(s.default) for s in self.specs}
        self._listeners: list[Callable[[str, float], None]] = []
        self._checks: list[Callable[[str, float], None]] = []

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.specs)

    def __contains__(self, name: str) -> bool:
        return name in self._by_name

    def __len__(self) -> int:
        return len(self.specs)

    def __getitem__(self, name: str) -> float:
        return self._values[name]

    def index(self, name: str) -> int:
        return self.specs.index(self._by_name[name])

    def by_index(self, index: int) -> ParamSpec | None:
        return self.specs[index] if 0 <= index < len(self.specs) else None

    def spec(self, name: str) -> ParamSpec | None:
        return self._by_name.get(name)

    def on_change(self, fn: Callable[[str, float], None]) -> None:
        """Call ``fn(name, value)`` after every successful :meth:`set`."""
        self._listeners.append(fn)

    def add_check(self, fn: Callable[[str, float], None]) -> None:
        """Call ``fn(name, value)`` before a value is stored; a ValueError refuses it."""
        self._checks.append(fn)

    def set(self, name: str, value: float) -> float:
        """Store ``value`` as the stack keeps it; return what was stored.

        Raises
        ------
        KeyError
            For an unknown name.
        ValueError
            For a value the stack cannot keep (non-finite) or the autopilot refuses.
        """
        spec = self._by_name[name]
        value = self._coerce(spec, value)
        for check in self._checks:
            check(name, value)
        self._values[name] = value
        for fn in self._listeners:
            fn(name, value)
        return value

    @abstractmethod
    def _coerce(self, spec: ParamSpec, value: float) -> float:
        """The value as the stack stores it; ValueError if it cannot."""


def clip(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else hi if x > hi else x


def stick_unit(us: float) -> float:
    """Centred stick in µs (1000..2000) -> [-1, 1]."""
    return clip((us - 1500.0) / 500.0, -1.0, 1.0)


def throttle_unit(us: float) -> float:
    """Throttle stick in µs (1000..2000) -> [0, 1]."""
    return clip((us - 1000.0) / 1000.0, 0.0, 1.0)


class Mode(Protocol):
    """A stack's flight mode: a name and the HEARTBEAT ``custom_mode``."""

    @property
    def name(self) -> str: ...

    @property
    def custom_mode(self) -> int: ...


class _RateLoop(Protocol):
    def reset(self) -> None: ...


ModeT = TypeVar("ModeT", bound=Mode)


class Personality(ABC, Generic[ModeT]):
    """Base of the simulated autopilots: the state and rules both stacks share.

    Parameters
    ----------
    profile
        The vehicle: ``limits`` gives the rate limits; each stack builds its own
        mixer from the frame (``sitl.px4_control``, ``sitl.ardupilot_control``).
    initial_mode
        Mode at boot.

    Subclasses set :attr:`refusal`, :attr:`land_mode`, :attr:`log`,
    ``rate_pid`` (the stack's rate loop) and :attr:`params`, implement
    :attr:`base_mode`, :attr:`system_status`, :attr:`external_control`,
    :attr:`rc_timeout_s`, :meth:`_arming_checks` and :meth:`_step`, and reset their
    own state in the ``_on_*`` hooks.
    """

    refusal: ClassVar[MavResult]
    """What a refused arm or disarm answers (PX4: DENIED, ArduPilot: FAILED)."""
    land_mode: ClassVar[object]
    """The mode that lands (``MAV_LANDED_STATE_LANDING`` while armed in it)."""
    log: ClassVar[logging.Logger] = logger
    """Where events are logged (each stack logs under its own module's name)."""
    rate_pid: _RateLoop
    params: ParamStore
    """The stack's parameters, which its face serves over MAVLink."""

    def __init__(self, profile: VehicleProfile, *, initial_mode: ModeT) -> None:
        self.profile = profile
        self.n_motors = profile.n_motors
        self.rate_max_rad_s = tuple(math.radians(x) for x in profile.limits.rate_max_deg_s)
        self.mode: ModeT = initial_mode
        self.armed = False
        self.crashed = False
        self.landed = True
        self.failsafe: str | None = None
        self.position_valid = True
        """A position estimate (the runner clears it for ``--no-position`` and faults)."""
        self.rejected_setpoints = 0
        self.accepted_setpoints = 0
        self.events: list[Event] = []
        self.motors: tuple[float, ...] = (0.0,) * self.n_motors
        self.last_torque_thrust: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
        self._rc_t_s: float | None = None
        self._last_sticks: tuple[int, ...] | None = None
        self._climb_integral = 0.0
        self.statustexts: list[tuple[int, str]] = []
        """STATUSTEXTs queued for the face, ``(MAV_SEVERITY, text)``."""

    # ------------------------------------------------------------------ status

    @property
    def custom_mode(self) -> int:
        return self.mode.custom_mode

    @property
    def landed_state(self) -> int:
        """``MAV_LANDED_STATE``: ON_GROUND (1), IN_AIR (2), LANDING (4)."""
        if self.landed:
            return 1
        if self.armed and self.mode == self.land_mode:
            return 4
        return 2

    @property
    @abstractmethod
    def base_mode(self) -> int:
        """HEARTBEAT ``base_mode`` (``MAV_MODE_FLAG`` bits), as the stack sets them."""

    @property
    @abstractmethod
    def system_status(self) -> int:
        """HEARTBEAT ``system_status`` (``MAV_STATE``), as the stack reports it."""

    @property
    @abstractmethod
    def external_control(self) -> bool:
        """A companion's setpoints drive the vehicle (the lockstep clock waits for them)."""

    @property
    @abstractmethod
    def rc_timeout_s(self) -> float:
        """RC silence after which RC counts as lost, s (the stack's parameter)."""

    def rc_lost(self, t_s: float) -> bool:
        """No RC frame for :attr:`rc_timeout_s` (or none ever)."""
        return self._rc_t_s is None or t_s - self._rc_t_s > self.rc_timeout_s

    def prearm_ok(self, t_s: float) -> bool:
        """The stack's pre-arm checks pass now (``SYS_STATUS`` bit
        ``MAV_SYS_STATUS_PREARM_CHECK`` healthy); each stack says what they are."""
        return not self.crashed

    def rc_receiver(self, t_s: float) -> tuple[bool, bool, bool]:
        """``SYS_STATUS``'s RC receiver bit: (present, enabled, healthy).

        The radio's: present and enabled once a frame arrived, healthy while frames
        keep arriving within :attr:`rc_timeout_s`. A stack may say otherwise.
        """
        if self._rc_t_s is None:
            return (False, False, False)
        return (True, True, not self.rc_lost(t_s))

    def drain_statustexts(self) -> list[tuple[int, str]]:
        """Return the STATUSTEXTs since the last call and forget them."""
        out, self.statustexts = self.statustexts, []
        return out

    def _text(self, severity: int, text: str) -> None:
        self.statustexts.append((severity, text[:50]))

    def drain_events(self) -> list[Event]:
        """Return the events since the last call and forget them."""
        out, self.events = self.events, []
        return out

    def _event(self, t_s: float, kind: str, **detail: Any) -> None:
        self.events.append(Event(t_s, kind, detail))
        self.log.info("t=%.3f s %s %s", t_s, kind, detail or "")

    # ---------------------------------------------------------------- commands

    def arm(self, t_s: float, *, force: bool = False) -> MavResult:
        """Arm (``MAV_CMD_COMPONENT_ARM_DISARM`` param1 = 1) unless a check refuses."""
        if self.armed:
            return MavResult.ACCEPTED
        refused = self._arming_checks(t_s, force=force)
        if refused is not None:
            return refused
        self.armed = True
        self.failsafe = None
        self.rate_pid.reset()
        self._climb_integral = 0.0
        self._on_armed(t_s)
        self._event(t_s, "armed", mode=self.mode.name)
        return MavResult.ACCEPTED

    @abstractmethod
    def _arming_checks(self, t_s: float, *, force: bool) -> MavResult | None:
        """The stack's arming checks: the refusal (see :meth:`_arm_denied`), or None."""

    def _arm_denied(self, t_s: float, reason: str) -> MavResult:
        self._event(t_s, "arm_denied", reason=reason)
        return self.refusal

    def _on_armed(self, t_s: float) -> None:
        """The stack's own state to reset at arming."""

    def disarm(self, t_s: float, *, force: bool = False, reason: str = "command") -> MavResult:
        """Disarm (param1 = 0); in the air only when forced (param2 = 21196) or crashed."""
        if not self.armed:
            return MavResult.ACCEPTED
        if not self.landed and not force and not self.crashed:
            self._event(t_s, "disarm_denied", reason="in air")
            return self.refusal
        self.armed = False
        self.motors = (0.0,) * self.n_motors
        self._event(t_s, "disarmed", reason=reason)
        return MavResult.ACCEPTED

    def _change_mode(self, t_s: float, new: ModeT, *, reason: str) -> None:
        old = self.mode
        self.mode = new
        self._climb_integral = 0.0
        self._on_mode_change(new)
        self._event(t_s, "mode", old=old.name, new=new.name, reason=reason)

    def _on_mode_change(self, new: ModeT) -> None:
        """The stack's own state to reset on entering ``new``."""

    def _enter_failsafe(self, t_s: float, cause: str, new: ModeT, *, reason: str) -> None:
        """A failsafe: switch to ``new`` (unless already in it) and record ``cause``."""
        if new != self.mode:
            self._change_mode(t_s, new, reason=reason)
        self.failsafe = cause
        self._event(t_s, "failsafe", cause=cause, action=new.name)

    # --------------------------------------------------------------- setpoints

    def reject_setpoint(self) -> None:
        """Count a setpoint the face could not use (e.g. attitude not ignored)."""
        self.rejected_setpoints += 1

    # -------------------------------------------------------------------- loop

    def update(
        self,
        t_s: float,
        gyro_frd_rad_s: Sequence[float],
        euler_rad: Sequence[float],
        *,
        climb_rate_m_s: float = 0.0,
        landed: bool = False,
        crashed: bool = False,
        sticks_us: Sequence[int] | None = None,
    ) -> tuple[float, ...]:
        """Run the autopilot on an IMU sample.

        Parameters
        ----------
        t_s
            Sample time (simulation), s.
        gyro_frd_rad_s
            Measured body rates (FRD), rad/s.
        euler_rad
            Attitude (roll, pitch, yaw), rad, from the estimator (here: truth).
        climb_rate_m_s
            Vertical speed, positive up, m/s.
        landed, crashed
            Land detector / crash flag.
        sticks_us
            RC channels AETR in µs, or None without RC.

        Returns
        -------
        tuple of float
            Normalised motor commands in [0, 1] (all zero when disarmed).
        """
        self.landed = landed
        if sticks_us is not None:
            self._rc_t_s = t_s
            self._last_sticks = tuple(sticks_us)
            self._on_rc_frame()
        if crashed and not self.crashed:
            self.crashed = True
            self._event(t_s, "crashed")
        if self.crashed:
            if self.armed:
                self.disarm(t_s, force=True, reason="crash")
            return self.motors
        return self._step(t_s, gyro_frd_rad_s, euler_rad, climb_rate_m_s)

    def _on_rc_frame(self) -> None:
        """The stack's own state to reset when an RC frame arrives."""

    @abstractmethod
    def _step(
        self,
        t_s: float,
        gyro_frd_rad_s: Sequence[float],
        euler_rad: Sequence[float],
        climb_rate_m_s: float,
    ) -> tuple[float, ...]:
        """The stack's checks and loops on a sample (not crashed)."""

    def _disarmed(self) -> tuple[float, ...]:
        """Disarmed: the rate loop forgets, the motors stop."""
        self.rate_pid.reset()
        self.motors = (0.0,) * self.n_motors
        return self.motors
