"""The companion link as part of the plant: delay, jitter, loss, duplication, reordering.

A companion computer is not on the flight controller: every IMU sample crosses
a link to reach it (the *uplink*), every command crosses it back (the
*downlink*). :class:`LinkSpec` says what such a link does to a message, per
direction; :class:`LinkModel` decides, for each message, when (and whether, and
how many times) it arrives. The in-process simulation (``sitl.lab.simulate``)
and the SITL's MAVLink face (``sitl.mavlink_link``) use the same model, so a
flight through a link is the same in process and over UDP.

What a message goes through, per direction
-------------------------------------------
- a delay ``delay_s + jitter_s * (2 u - 1)`` (``u`` uniform in [0, 1)), never
  below zero: uniform over ``delay_s +/- jitter_s``;
- on a FIFO link (``fifo``: serial links, which cannot reorder), never before
  the message sent before it on the same stream; otherwise two messages whose
  delays differ by more than their spacing arrive in the other order;
- lost with probability ``loss``; sent twice with probability ``duplicate``
  (the copy has its own delay).

Time is simulation time: a message is delivered at the first simulation step at
or after its arrival (the physics step, 1 ms by default).

Determinism
-----------
Each stream (a direction and a MAVLink message id) draws from its own generator,
spawned from the scenario's seed (:func:`link_seed_sequence`), and each message
draws the same four numbers whatever the link does with them. So the delays of
the IMU stream do not depend on how many heartbeats (whose timing follows the
wall clock) went before, and the same seed gives the same flight.

Named profiles
--------------
:data:`LINK_PROFILES` holds a few links from their documented figures; any
field may also be given (``--link delay_ms=10,jitter_ms=5``), see
:func:`parse_link`.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import Field

from companion.schema import StrictModel

__all__ = [
    "DOWN",
    "ID_EXTENDED_SYS_STATE",
    "ID_HIGHRES_IMU",
    "ID_RC_CHANNELS",
    "ID_SET_ACTUATOR_CONTROL_TARGET",
    "ID_SET_ATTITUDE_TARGET",
    "LINK_PROFILES",
    "UP",
    "LinkModel",
    "LinkSpec",
    "link_seed_sequence",
    "parse_link",
]

UP: Literal[0] = 0
"""The uplink: autopilot to companion (IMU samples, RC, states)."""
DOWN: Literal[1] = 1
"""The downlink: companion to autopilot (setpoints, commands)."""

# The streams the in-process simulation models, by their MAVLink message ids (the
# SITL's face keys every stream by its id).
ID_RC_CHANNELS = 65
ID_SET_ACTUATOR_CONTROL_TARGET = 139
ID_SET_ATTITUDE_TARGET = 82
ID_HIGHRES_IMU = 105
ID_EXTENDED_SYS_STATE = 245

_SEED_CHILD = 4
"""The link's child of the scenario's seed sequence: the plant, the IMU, the wind
and the pilot have children 0-3 (``sitl.world.flight_streams``)."""


class LinkSpec(StrictModel):
    """What the link does to a message, per direction (``up_*``: to the companion,
    ``down_*``: back to the autopilot)."""

    name: str = "custom"
    up_delay_s: float = Field(0.0, ge=0.0, le=1.0)
    up_jitter_s: float = Field(0.0, ge=0.0, le=1.0)
    down_delay_s: float = Field(0.0, ge=0.0, le=1.0)
    down_jitter_s: float = Field(0.0, ge=0.0, le=1.0)
    loss: float = Field(0.0, ge=0.0, le=0.5, description="probability a message is lost")
    duplicate: float = Field(0.0, ge=0.0, le=0.5, description="probability it arrives twice")
    fifo: bool = Field(True, description="a stream's messages arrive in the order sent")

    @property
    def ideal(self) -> bool:
        """Every message arrives at once, once, in order: no model needed."""
        return (
            self.up_delay_s == 0.0
            and self.up_jitter_s == 0.0
            and self.down_delay_s == 0.0
            and self.down_jitter_s == 0.0
            and self.loss == 0.0
            and self.duplicate == 0.0
        )

    def describe(self) -> str:
        """One line for logs and reports: ``uart (2.0+-0.5 ms up, 2.0+-0.5 ms down)``."""
        up = f"{self.up_delay_s * 1e3:g}+-{self.up_jitter_s * 1e3:g} ms up"
        down = f"{self.down_delay_s * 1e3:g}+-{self.down_jitter_s * 1e3:g} ms down"
        extra = "".join(
            (
                f", {self.loss:.1%} lost" if self.loss else "",
                f", {self.duplicate:.1%} duplicated" if self.duplicate else "",
                "" if self.fifo else ", reordering",
            )
        )
        return f"{self.name} ({up}, {down}{extra})"


def _symmetric(name: str, delay_ms: float, jitter_ms: float, **kw: float | bool) -> LinkSpec:
    d, j = delay_ms * 1e-3, jitter_ms * 1e-3
    return LinkSpec(name=name, up_delay_s=d, up_jitter_s=j, down_delay_s=d, down_jitter_s=j, **kw)


LINK_PROFILES: dict[str, LinkSpec] = {
    # Every message at once: the lockstep link every flight used before links were modelled.
    "ideal": LinkSpec(name="ideal"),
    # UDP between processes on one board or over Ethernet: the kernel's network
    # stack, well under a millisecond.
    "ethernet": _symmetric("ethernet", 0.3, 0.1),
    # A UART at 921600 baud (10 bits a byte: 92 kB/s): a 76-byte HIGHRES_IMU frame
    # takes 0.8 ms on the wire, and the autopilot's MAVLink sender, which runs
    # its loop about every millisecond, adds up to one more.
    "uart": _symmetric("uart", 2.0, 0.5),
    # A USB-serial adapter: USB full-speed polls every 1 ms frame, and the
    # adapter holds a short packet until its latency timer (FTDI's default is
    # 16 ms, 1 ms once set low) or a full buffer: a few milliseconds, varying.
    "usb-serial": _symmetric("usb-serial", 5.0, 2.0),
    # Wi-Fi between the companion and a separate autopilot board: tens of ms with
    # retransmissions; datagrams are lost and overtake each other.
    "wifi": _symmetric("wifi", 10.0, 5.0, loss=0.01, fifo=False),
}
"""The named links (``--link NAME``)."""

_FIELDS_MS = {
    "delay_ms": ("up_delay_s", "down_delay_s"),
    "jitter_ms": ("up_jitter_s", "down_jitter_s"),
    "up_delay_ms": ("up_delay_s",),
    "up_jitter_ms": ("up_jitter_s",),
    "down_delay_ms": ("down_delay_s",),
    "down_jitter_ms": ("down_jitter_s",),
}


def parse_link(text: str) -> LinkSpec:
    """A named profile (``uart``), or fields (``delay_ms=10,jitter_ms=5,loss=0.01``),
    or a profile with fields changed (``wifi,loss=0``).

    Fields: ``delay_ms``, ``jitter_ms`` (both directions), ``up_delay_ms``,
    ``up_jitter_ms``, ``down_delay_ms``, ``down_jitter_ms``, ``loss``,
    ``duplicate`` (probabilities), ``fifo`` (``true`` / ``false``).

    Raises
    ------
    ValueError
        Naming the part that is wrong and what was expected.
    """
    parts = [p.strip() for p in text.split(",") if p.strip()]
    if not parts:
        raise ValueError(
            f"link {text!r}: expected a profile ({', '.join(LINK_PROFILES)}) or fields"
        )
    base = LINK_PROFILES["ideal"]
    name = "custom"
    if "=" not in parts[0]:
        if parts[0] not in LINK_PROFILES:
            raise ValueError(
                f"link {text!r}: unknown profile {parts[0]!r}; expected one of "
                f"{', '.join(LINK_PROFILES)} or fields such as delay_ms=5,jitter_ms=2"
            )
        base = LINK_PROFILES[parts[0]]
        name = parts[0] if len(parts) == 1 else f"{parts[0]}*"
        parts = parts[1:]
    fields = base.model_dump()
    known = ", ".join([*_FIELDS_MS, "loss", "duplicate", "fifo"])
    for part in parts:
        key, eq, value = part.partition("=")
        key, value = key.strip(), value.strip()
        if not eq:
            raise ValueError(f"link {text!r}: {part!r} is not KEY=VALUE")
        if key in _FIELDS_MS:
            ms = _number(value)
            if ms is None or not 0.0 <= ms <= 1000.0:
                raise ValueError(
                    f"link {text!r}: {key}={value!r}: expected milliseconds in 0..1000"
                )
            for f in _FIELDS_MS[key]:
                fields[f] = ms * 1e-3
        elif key in ("loss", "duplicate"):
            prob = _number(value)
            if prob is None or not 0.0 <= prob <= 0.5:
                raise ValueError(
                    f"link {text!r}: {key}={value!r}: expected a probability in 0..0.5"
                )
            fields[key] = prob
        elif key == "fifo":
            if value.lower() not in ("true", "false"):
                raise ValueError(f"link {text!r}: fifo={value!r}: expected true or false")
            fields["fifo"] = value.lower() == "true"
        else:
            raise ValueError(f"link {text!r}: unknown field {key!r}; expected one of {known}")
    fields["name"] = name
    return LinkSpec(**fields)


def _number(text: str) -> float | None:
    """``text`` as a finite float, or None."""
    try:
        x = float(text)
    except ValueError:
        return None
    return x if math.isfinite(x) else None


def link_seed_sequence(seed: int) -> np.random.SeedSequence:
    """The link's seed sequence for a scenario seed (independent of the plant's,
    the IMU's, the wind's and the pilot's)."""
    return np.random.SeedSequence(seed, spawn_key=(_SEED_CHILD,))


class LinkModel:
    """When each message of a flight arrives, from a :class:`LinkSpec` and a seed.

    :meth:`arrivals` is asked once per message sent, in the order sent within
    its stream, and answers the times (zero, one or two) it arrives.
    """

    def __init__(self, spec: LinkSpec, seed: int) -> None:
        self.spec = spec
        self._seed_seq = link_seed_sequence(seed)
        self._rngs: dict[tuple[int, int], np.random.Generator] = {}
        self._last: dict[tuple[int, int], float] = {}
        self._delay = ((spec.up_delay_s, spec.up_jitter_s), (spec.down_delay_s, spec.down_jitter_s))
        self.sent = [0, 0]
        self.lost = [0, 0]
        self.duplicated = [0, 0]

    def _rng(self, key: tuple[int, int]) -> np.random.Generator:
        rng = self._rngs.get(key)
        if rng is None:
            ss = np.random.SeedSequence(
                self._seed_seq.entropy, spawn_key=(*self._seed_seq.spawn_key, *key)
            )
            rng = self._rngs[key] = np.random.default_rng(ss)
        return rng

    def arrivals(self, direction: int, stream: int, t_sent_s: float) -> tuple[float, ...]:
        """When a message of ``stream`` (its MAVLink message id) sent at
        ``t_sent_s`` in ``direction`` (:data:`UP` or :data:`DOWN`) arrives: ``()``
        lost, one time, or two (duplicated), in order."""
        spec = self.spec
        key = (direction, stream)
        u_delay, u_loss, u_dup, u_dup_delay = self._rng(key).random(4)
        self.sent[direction] += 1
        if u_loss < spec.loss:
            self.lost[direction] += 1
            return ()
        delay, jitter = self._delay[direction]
        t = t_sent_s + max(0.0, delay + jitter * (2.0 * u_delay - 1.0))
        if spec.fifo:
            t = max(t, self._last.get(key, -math.inf))
            self._last[key] = t
        if u_dup >= spec.duplicate:
            return (t,)
        self.duplicated[direction] += 1
        t2 = t_sent_s + max(0.0, delay + jitter * (2.0 * u_dup_delay - 1.0))
        if spec.fifo:
            t2 = max(t2, t)
            self._last[key] = t2
        return (t, t2) if t2 >= t else (t2, t)

    def counts(self) -> dict[str, int]:
        """Messages sent, lost and duplicated per direction, for summaries."""
        return {
            "up_sent": self.sent[UP],
            "up_lost": self.lost[UP],
            "up_duplicated": self.duplicated[UP],
            "down_sent": self.sent[DOWN],
            "down_lost": self.lost[DOWN],
            "down_duplicated": self.duplicated[DOWN],
        }
