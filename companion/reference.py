"""Scripted rate references: fly a reference file instead of the pilot's sticks.

A CSV file with a header line and one row per breakpoint::

    t_s,roll_deg_s,pitch_deg_s,yaw_deg_s[,thrust]
    0.0,0,0,0
    2.0,0,0,0
    2.1,180,0,0
    3.0,180,0,0
    3.1,0,0,0

``t_s`` counts from engagement (s, at most
:data:`~companion.profile.FLIGHT_MAX_S`) and must increase; rates (deg/s,
within +/-2000) are linearly interpolated between rows and held after the last
one. Without a ``thrust`` column the collective still comes from the pilot's
throttle stick (so a person or the SITL's pilot keeps the altitude); with one,
the file sets it (0..1).
"""

from __future__ import annotations

import bisect
import csv
import math
from dataclasses import dataclass
from pathlib import Path

from companion.errors import ConfigError
from companion.profile import FLIGHT_MAX_S, RATE_LIMIT_MAX_DEG_S
from companion.schema import read_text

__all__ = ["ReferenceScript", "load_reference"]

_DEG = math.pi / 180.0
_COLUMNS = ("t_s", "roll_deg_s", "pitch_deg_s", "yaw_deg_s")


@dataclass(frozen=True)
class ReferenceScript:
    """Breakpoints of a scripted reference (rates in rad/s)."""

    t_s: tuple[float, ...]
    rates_rad_s: tuple[tuple[float, float, float], ...]
    thrust: tuple[float, ...] | None

    def at(self, t_s: float) -> tuple[tuple[float, float, float], float | None]:
        """Rates (rad/s) and thrust (None: take the pilot's) at ``t_s`` from engagement."""
        ts = self.t_s
        if t_s <= ts[0]:
            i = 0
            frac = 0.0
            j = 0
        elif t_s >= ts[-1]:
            i = j = len(ts) - 1
            frac = 0.0
        else:
            j = bisect.bisect_right(ts, t_s)
            i = j - 1
            frac = (t_s - ts[i]) / (ts[j] - ts[i])
        a, b = self.rates_rad_s[i], self.rates_rad_s[j]
        rates = (
            a[0] + frac * (b[0] - a[0]),
            a[1] + frac * (b[1] - a[1]),
            a[2] + frac * (b[2] - a[2]),
        )
        thrust = None
        if self.thrust is not None:
            thrust = self.thrust[i] + frac * (self.thrust[j] - self.thrust[i])
        return rates, thrust


def load_reference(path: str | Path) -> ReferenceScript:
    """Read and validate a reference file.

    Raises
    ------
    ConfigError
        Naming the file, the line and what was expected.
    """
    p = Path(path)
    text = read_text(p)
    rows = list(csv.reader(line for line in text.splitlines() if line.strip()))
    if not rows:
        raise ConfigError(str(p), ["(file): expected a header line and at least one row"])
    header = [h.strip() for h in rows[0]]
    if (
        tuple(header[:4]) != _COLUMNS
        or len(header) > 5
        or (len(header) == 5 and header[4] != "thrust")
    ):
        raise ConfigError(
            str(p),
            [f"line 1: expected the header {','.join(_COLUMNS)}[,thrust], got {','.join(header)}"],
        )
    has_thrust = len(header) == 5
    problems: list[str] = []
    ts: list[float] = []
    rates: list[tuple[float, float, float]] = []
    thrust: list[float] = []
    for n, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            problems.append(f"line {n}: expected {len(header)} values, got {len(row)}")
            continue
        try:
            vals = [float(v) for v in row]
        except ValueError:
            problems.append(f"line {n}: expected numbers, got {','.join(row)}")
            continue
        if not all(math.isfinite(v) for v in vals):
            problems.append(f"line {n}: expected finite numbers")
            continue
        if ts and vals[0] <= ts[-1]:
            problems.append(f"line {n}: t_s must increase (got {vals[0]} after {ts[-1]})")
            continue
        if not 0.0 <= vals[0] <= FLIGHT_MAX_S:
            problems.append(f"line {n}: t_s must be in [0, {FLIGHT_MAX_S:g}] s, got {vals[0]:g}")
            continue
        if any(abs(v) > RATE_LIMIT_MAX_DEG_S for v in vals[1:4]):
            problems.append(f"line {n}: rates beyond +/-{RATE_LIMIT_MAX_DEG_S:g} deg/s")
            continue
        if has_thrust and not 0.0 <= vals[4] <= 1.0:
            problems.append(f"line {n}: thrust must be in [0, 1], got {vals[4]}")
            continue
        ts.append(vals[0])
        rates.append((vals[1] * _DEG, vals[2] * _DEG, vals[3] * _DEG))
        if has_thrust:
            thrust.append(vals[4])
    if not ts and not problems:
        problems.append("(file): expected at least one row after the header")
    if problems:
        raise ConfigError(str(p), problems)
    return ReferenceScript(tuple(ts), tuple(rates), tuple(thrust) if has_thrust else None)
