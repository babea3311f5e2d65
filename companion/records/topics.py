"""The control log's columns and the MCAP topics they are written to, defined once.

:func:`columns` is the per-sample layout the app fills (one float64 per
column); :func:`topics` splits any list of those columns into one topic per
concern, with the JSON schema each topic's messages follow. The writer and the
reader (:mod:`companion.records.control_log`) both derive their layout from
these two functions, so a new column is added in one place.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.control import AXES

__all__ = [
    "EVENTS_TOPIC",
    "Topic",
    "TopicFormat",
    "columns",
    "event_json",
    "event_schema",
    "stamp_ns",
    "stamps_ns",
    "topics",
]

EVENTS_TOPIC = "/events"
"""The topic the run's events go to (as ``events.jsonl`` has them)."""


def columns(n_motors: int) -> list[str]:
    """The control log's columns, in order, for a vehicle with ``n_motors``.

    ``t_s`` (IMU sample time on the autopilot's clock, s), ``wall_s``
    (the datagram's arrival on the companion's monotonic clock, s),
    ``latency_us`` (datagram arrival to command sent), ``engaged`` and
    ``held`` (0/1); per axis (roll, pitch, yaw): ``ref_<axis>_rad_s``,
    ``meas_<axis>_rad_s``, ``err_<axis>_rad_s``, ``f_hat_<axis>``,
    ``u_<axis>``, ``torque_<axis>``, ``sat_<axis>`` (0/1); then ``thrust``
    (pilot's collective, 0..1), ``thrust_out`` (realised),
    ``motor_1`` .. ``motor_<n_motors>``, ``sent_<axis>_rad_s``, the body
    rates sent with ``--output rates`` (NaN when none were sent),
    ``on_ground`` (0/1: the autopilot said ON_GROUND, so nothing was learnt),
    ``link_rtt_ms`` (the last TIMESYNC round trip) and ``sample_age_ms`` (the
    sample's age, on the autopilot's clock, when its command left); both NaN
    until the autopilot first answers TIMESYNC. Then what the outer loops
    (``--mode angle|altitude|position``) flew, NaN where the mode holds no such
    setpoint or has no estimate (all NaN with ``--mode rates``):
    ``sp_roll_rad``, ``sp_pitch_rad``, ``sp_yaw_rad`` (the attitude loop's
    setpoint; the heading NaN while the yaw stick is a rate), ``est_roll_rad``,
    ``est_pitch_rad``, ``est_yaw_rad`` (the autopilot's attitude estimate),
    ``sp_north_m``, ``sp_east_m``, ``sp_up_m`` (the position and altitude held,
    NaN while a stick moves it or on the ground), ``est_north_m``,
    ``est_east_m``, ``est_up_m`` (the autopilot's local position estimate) and
    ``outer_gain_scale`` (the outer gains' backoff while the rate loop saturates:
    1 as shipped, down to the backoff's floor). Last, ``law_ref_<axis>_rad_s``:
    the reference the law flew when it was not the pilot's rate (rates output to
    an autopilot that shapes its setpoints: the pilot's rate so shaped,
    :mod:`companion.control.shaping`), NaN otherwise. Then the model the law
    flies, per axis, as configured or identified online: ``alpha_<axis>`` (its
    input gain, rad/s^m per command unit), ``lag_<axis>_s`` (the actuator lag)
    and ``delay_<axis>_s`` (the loop's delay); NaN for a law with no model (the
    PID). Last, ``yaw_share``: the share of roll and pitch the mixer may give yaw
    while the heading is being lost (0..1; 0 when none is offered).
    """
    if not isinstance(n_motors, int) or isinstance(n_motors, bool) or n_motors < 1:
        raise ValueError(f"n_motors must be a positive integer, got {n_motors!r}")
    cols = ["t_s", "wall_s", "latency_us", "engaged", "held"]
    for a in AXES:
        cols += [
            f"ref_{a}_rad_s",
            f"meas_{a}_rad_s",
            f"err_{a}_rad_s",
            f"f_hat_{a}",
            f"u_{a}",
            f"torque_{a}",
            f"sat_{a}",
        ]
    cols += ["thrust", "thrust_out"]
    cols += [f"motor_{i}" for i in range(1, n_motors + 1)]
    cols += [f"sent_{a}_rad_s" for a in AXES]
    cols += ["on_ground", "link_rtt_ms", "sample_age_ms"]
    cols += [f"sp_{a}_rad" for a in AXES] + [f"est_{a}_rad" for a in AXES]
    cols += [f"{w}_{d}_m" for w in ("sp", "est") for d in ("north", "east", "up")]
    cols += ["outer_gain_scale"]
    cols += [f"law_ref_{a}_rad_s" for a in AXES]
    cols += [f"{q}_{a}{unit}" for q, unit in _MODEL for a in AXES]
    cols += ["yaw_share"]
    return cols


_MODEL = (("alpha", ""), ("lag", "_s"), ("delay", "_s"))
"""The model the law flies, per axis: ``alpha_<axis>``, ``lag_<axis>_s``,
``delay_<axis>_s`` (:meth:`companion.control.RateController.identified`)."""


_AX = "|".join(AXES)

# Each column's topic and field, in the order the topics are registered: a
# pattern on the column's name, the topic (``{0}``: the axis the pattern
# caught) and the field (the same).
_PLACES: tuple[tuple[str, str, str], ...] = (
    (r"(?P<f>t_s|wall_s|latency_us)", "/link", "{f}"),
    (r"link_(?P<f>rtt_ms)", "/link", "{f}"),
    (r"(?P<f>sample_age_ms)", "/link", "{f}"),
    (rf"(?P<f>(ref|meas|sent|law_ref)_({_AX})_rad_s)", "/rates", "{f}"),
    (rf"err_(?P<a>{_AX})_rad_s", "/law/{a}", "err_rad_s"),
    (rf"f_hat_(?P<a>{_AX})", "/law/{a}", "f_hat"),
    (rf"u_(?P<a>{_AX})", "/law/{a}", "u"),
    (rf"torque_(?P<a>{_AX})", "/law/{a}", "torque"),
    (rf"sat_(?P<a>{_AX})", "/law/{a}", "saturated"),
    (rf"alpha_(?P<a>{_AX})", "/law/{a}", "alpha"),
    (rf"lag_(?P<a>{_AX})_s", "/law/{a}", "lag_s"),
    (rf"delay_(?P<a>{_AX})_s", "/law/{a}", "delay_s"),
    (
        r"(?P<f>thrust|thrust_out|motor_[1-9][0-9]*|engaged|held|on_ground|yaw_share)",
        "/mixer",
        "{f}",
    ),
    (rf"(?P<f>(sp|est)_({_AX})_rad|(sp|est)_(north|east|up)_m|outer_gain_scale)", "/outer", "{f}"),
)
_COMPILED = tuple((re.compile(p), t, f) for p, t, f in _PLACES)

_TOPIC_ORDER = ("/rates", *(f"/law/{a}" for a in AXES), "/mixer", "/link", "/outer")

_DESCRIPTIONS = {
    "/rates": "Body rates per axis (rad/s): the pilot's reference, the gyro as the law saw "
    "it, the rates sent with rates output, and the law's shaped reference (NaN: none).",
    "/law": "The model-free law on one axis: tracking error (rad/s), the estimate of F, the "
    "law's output u before mixing, the torque the mixer realised ([-1, 1]), whether "
    "the mixer saturated the axis (0/1), and the model it flies: alpha (its input gain, "
    "rad/s^m per command unit), the actuator lag and the loop's delay (s); NaN for the PID.",
    "/mixer": "The mixer and the gates: the pilot's collective and the realised one (0..1), "
    "the motor commands ([idle, 1]), engaged, held (a non-finite input repeated the last "
    "output) and on_ground (the autopilot said ON_GROUND: nothing learnt), all 0/1, and "
    "yaw_share (the share of roll and pitch yaw may take while the heading is being "
    "lost, 0..1).",
    "/link": "The sample on both clocks: t_s (the IMU stamp, autopilot clock, s), wall_s "
    "(its arrival, companion monotonic clock, s), latency_us (arrival to command sent), "
    "rtt_ms (last TIMESYNC round trip) and sample_age_ms (the sample's age when its "
    "command left); NaN before the first TIMESYNC answer.",
    "/outer": "The outer loops (--mode angle|altitude|position): attitude setpoint and "
    "estimate (rad), position setpoint and estimate (m, north/east/up), the outer gains' "
    "scale. Written only for samples where the mode holds one of them.",
}


@dataclass(frozen=True)
class Topic:
    """One topic of the control log: its fields and the columns they come from."""

    name: str
    """``/rates``, ``/law/roll``, ...."""
    fields: tuple[str, ...]
    """The JSON fields, in order."""
    columns: tuple[int, ...]
    """For each field, its column's index in the log's column list."""
    sparse: bool
    """Written only for samples where a field is finite (``/outer``)."""

    @property
    def schema_name(self) -> str:
        """``mfc.rates``, ``mfc.law``, ...: one schema per kind of topic."""
        return "mfc." + self.name.strip("/").split("/")[0]

    def schema(self) -> bytes:
        """The JSON schema of this topic's messages (non-finite values are ``null``)."""
        kind = self.name.strip("/").split("/")[0]
        props = {f: {"type": ["number", "null"]} for f in self.fields}
        doc = {
            "title": self.schema_name,
            "description": _DESCRIPTIONS["/" + kind],
            "type": "object",
            "properties": props,
        }
        return json.dumps(doc).encode()


def _place(column: str) -> tuple[str, str]:
    for pattern, topic, field in _COMPILED:
        m = pattern.fullmatch(column)
        if m is not None:
            g = m.groupdict()
            return topic.format(**g), field.format(**g)
    raise ValueError(f"column {column!r} has no topic in the control log")


def topics(cols: Sequence[str]) -> list[Topic]:
    """The topics that hold ``cols`` (any of :func:`columns`' names, in any order).

    Raises
    ------
    ValueError
        If a column is not one of the control log's, or appears twice.
    """
    if len(set(cols)) != len(cols):
        raise ValueError(f"duplicate column names in {list(cols)}")
    grouped: dict[str, list[tuple[str, int]]] = {}
    for j, c in enumerate(cols):
        topic, field = _place(c)
        grouped.setdefault(topic, []).append((field, j))
    return [
        Topic(
            name=name,
            fields=tuple(f for f, _ in grouped[name]),
            columns=tuple(j for _, j in grouped[name]),
            sparse=name == "/outer",
        )
        for name in _TOPIC_ORDER
        if name in grouped
    ]


def event_schema() -> bytes:
    """The JSON schema of ``/events`` (the objects ``events.jsonl`` has)."""
    doc = {
        "title": "mfc.event",
        "description": "What happened (engaged, handed back, failsafes, counters): the "
        "objects of events.jsonl. t_s is the last IMU sample's time (autopilot clock, s), "
        "wall the unix time.",
        "type": "object",
        "properties": {
            "t_s": {"type": "number"},
            "wall": {"type": "number"},
            "kind": {"type": "string"},
            "detail": {"type": "string"},
        },
    }
    return json.dumps(doc).encode()


def stamps_ns(seconds: np.ndarray) -> list[int]:
    """Seconds as whole nanoseconds (the messages' log time, in MCAP and in the
    live view); 0 for NaN or negative."""
    v = np.where(np.isfinite(seconds) & (seconds >= 0.0), seconds, 0.0)
    return np.rint(np.minimum(v, 1.8e10) * 1e9).astype(np.int64).tolist()  # type: ignore[no-any-return]


def stamp_ns(t: Any, default: int) -> int:
    """An event's stamp (its ``t_s`` or ``wall``) as :func:`stamps_ns` gives it;
    ``default`` when it is not a number."""
    return stamps_ns(np.array([float(t)]))[0] if isinstance(t, int | float) else default


class TopicFormat:
    """One topic's JSON messages from its columns, as the log and the live view
    both write them.

    A row's *code* says which of its fields are special (:meth:`codes`): bit i,
    field i is not finite (written ``null``); bit k + i, for k fields, it is
    -0.0 (which ``%.17g`` would write as ``-0``, an integer zero). Each code
    gets a %-template once (:meth:`template`); a row is then one %-format.
    """

    __slots__ = ("templates", "topic")

    def __init__(self, tp: Topic) -> None:
        self.topic = tp
        self.templates: dict[int, tuple[str, list[int]] | None] = {}
        """The templates made so far, by code."""

    def codes(self, data: np.ndarray) -> tuple[list[int], list[list[float]]]:
        """Each row's code and values, for this topic's columns of ``data``."""
        vals = data[:, self.topic.columns]
        k = len(self.topic.fields)
        weights = 1 << np.arange(k, dtype=np.int64)
        special = ~np.isfinite(vals) * weights
        special += ((vals == 0.0) & np.signbit(vals)) * (weights << k)
        return special.sum(axis=1).tolist(), vals.tolist()

    def template(self, code: int) -> tuple[str, list[int]] | None:
        """The message for rows with ``code``: a %-format and the fields it
        takes; None for a sparse topic's row with nothing finite."""
        if code in self.templates:
            return self.templates[code]
        tp = self.topic
        k = len(tp.fields)
        made: tuple[str, list[int]] | None = None
        if not (tp.sparse and code == (1 << k) - 1):
            parts, keep = [], []
            for i, name in enumerate(tp.fields):
                if code >> i & 1:
                    parts.append(f'"{name}":null')
                elif code >> (k + i) & 1:
                    parts.append(f'"{name}":-0.0')
                else:
                    parts.append(f'"{name}":%.17g')
                    keep.append(i)
            made = ("{" + ",".join(parts) + "}", keep)
        self.templates[code] = made
        return made

    def messages(self, data: np.ndarray) -> list[str | None]:
        """Every row's message (None: a sparse topic with nothing to say)."""
        codes, rows = self.codes(data)
        out: list[str | None] = []
        for code, row in zip(codes, rows, strict=True):
            tmpl = self.template(code)
            if tmpl is None:
                out.append(None)
            else:
                fmt, keep = tmpl
                out.append(fmt % (tuple(row) if not code else tuple(row[i] for i in keep)))
        return out


def event_json(ev: dict[str, Any]) -> str:
    """An event as a JSON object: non-finite numbers ``null``, anything else
    JSON cannot hold as its ``str``."""
    if all(not isinstance(v, float) or math.isfinite(v) for v in ev.values()):
        return json.dumps(ev, default=str, allow_nan=False)
    safe = {k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in ev.items()}
    return json.dumps(safe, default=str)
