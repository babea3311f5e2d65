"""The columnar control log (``control.bin``): one float64 row per control sample."""

from __future__ import annotations

import logging
import math
import struct
import sys
import time
from array import array
from collections.abc import Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from companion.control import AXES
from companion.records.writer import BufferedLog, Chunk, RecordWriter, Sink

__all__ = ["FORMAT", "ColumnarLog", "columns", "last_row", "read_columnar"]

log = logging.getLogger("companion.records")

FORMAT = "companion-columnar 2 (binary float64 rows)"
_MARKER = b"# float64 rows follow\n"


def columns(n_motors: int) -> list[str]:
    """The columnar flight log's columns, in order, for a vehicle with ``n_motors``.

    ``t_s`` (IMU sample time, s), ``wall_s`` (monotonic clock, s),
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
    :mod:`companion.control.shaping`), NaN otherwise.
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
    return cols


class ColumnarLog(BufferedLog):
    """A binary columnar flight log: a text header, then one float64 row per sample.

    Layout: ``# key: value`` metadata lines, a line of comma-separated column
    names, the marker line ``# float64 rows follow``, then the rows as raw
    float64 in the writer's byte order (recorded in the ``byteorder``
    metadata). Every value round-trips exactly; :func:`read_columnar` reads it
    back into numpy arrays (``companion log-csv`` style conversion is one
    ``numpy.savetxt`` away).

    Parameters
    ----------
    path
        The file to create (parent directories are created; an existing file
        is replaced).
    columns
        Column names, in order (usually :func:`columns`).
    meta
        Metadata written as ``# key: value`` lines (profile, controller, ...).
        ``format``, ``version``, ``byteorder``, ``start_unix_s`` and
        ``start_utc`` are added unless given. Newlines in values become spaces.
    flush_interval_s
        Buffered rows are handed on at the first :meth:`append` at least this
        long after the last flush.
    writer
        Hand the rows to this :class:`RecordWriter` (file key: the file's name)
        instead of writing them from the caller; the header is still written
        at once, by :meth:`RecordWriter.open`. None: write synchronously.

    Notes
    -----
    :meth:`append` copies the row into an ``array('d')`` (well under a
    microsecond for 32 columns) and a flush swaps that array for an empty one
    and hands over a byte view of it (no copy): nothing is formatted on the
    control path, so there is no per-sample formatting cost and no flush
    burst to delay the next IMU sample.
    """

    _sink: Sink  # always a file here

    def __init__(
        self,
        path: str | Path,
        columns: list[str],
        *,
        meta: dict[str, Any] | None = None,
        flush_interval_s: float = 0.2,
        writer: RecordWriter | None = None,
    ) -> None:
        cols = list(columns)
        if not cols:
            raise ValueError("columns must not be empty")
        if len(set(cols)) != len(cols):
            raise ValueError(f"duplicate column names in {cols}")
        for c in cols:
            if not c or any(ch in c for ch in ",#\n\r ") or c != c.strip():
                raise ValueError(f"invalid column name {c!r}")
        if not (math.isfinite(flush_interval_s) and flush_interval_s >= 0.0):
            raise ValueError(f"flush_interval_s must be >= 0, got {flush_interval_s!r}")
        self.path = Path(path)
        self.columns = cols
        self.n_columns = len(cols)
        self._buf = array("d")
        self._interval = flush_interval_s
        self.rows = 0
        """Rows appended."""
        self.dropped = 0
        """Rows not recorded because of an earlier write error."""

        from companion import __version__

        now = time.time()
        full_meta: dict[str, Any] = {
            "format": FORMAT,
            "version": __version__,
            "byteorder": sys.byteorder,
            "start_unix_s": f"{now:.6f}",
            "start_utc": datetime.fromtimestamp(now, timezone.utc).isoformat(),
        }
        full_meta.update(meta or {})
        head = []
        for k, v in full_meta.items():
            key = " ".join(str(k).replace(":", "_").split())
            val = " ".join(str(v).splitlines())
            head.append(f"# {key}: {val}\n")
        head.append(",".join(cols) + "\n")
        head.append(_MARKER.decode())
        # The header goes out at once: a killed process leaves a readable file.
        self._sink = Sink(self.path, "flight log", writer, header="".join(head).encode())
        self._open = True  # False once closed, or stopped by a write error
        self._next_flush = time.monotonic() + flush_interval_s

    def append(self, row: Sequence[float]) -> None:
        """Record one row (numbers in column order; bools and ints are fine).

        Raises
        ------
        ValueError
            If ``len(row)`` is not the number of columns, or a value is not a number.
        """
        if len(row) != self.n_columns:
            raise ValueError(f"{self.path}: row has {len(row)} values, expected {self.n_columns}")
        if not self._open:
            if self._sink.failed is not None:
                self.dropped += 1
                return
            raise ValueError(f"{self.path}: ColumnarLog is closed")
        n = len(self._buf)
        try:
            self._buf.extend(row)
        except TypeError as exc:
            del self._buf[n:]  # keep rows whole
            raise ValueError(f"{self.path}: row has a value that is not a number: {exc}") from None
        self.rows += 1
        if time.monotonic() >= self._next_flush:
            self.flush()

    def _take(self) -> Chunk:
        buf, self._buf = self._buf, array("d")
        return memoryview(buf).cast("B")


def last_row(path: str | Path) -> tuple[float, ...] | None:
    """The last complete row of a :class:`ColumnarLog` being written, or None.

    Reads only the header and the file's tail: cheap enough to poll a live log.
    """
    p = Path(path)
    try:
        with p.open("rb") as f:
            head = f.read(65536)
            i = head.find(_MARKER)
            if i < 0:
                return None
            names_line = head[:i].rstrip(b"\n").rsplit(b"\n", 1)[-1]
            n = names_line.count(b",") + 1
            start = i + len(_MARKER)
            size = p.stat().st_size
            n_rows = (size - start) // (8 * n)
            if n_rows <= 0:
                return None
            f.seek(start + (n_rows - 1) * 8 * n)
            data = f.read(8 * n)
    except OSError:
        return None
    order = "<" if sys.byteorder == "little" else ">"
    return struct.unpack(f"{order}{n}d", data)


def read_columnar(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Read a :class:`ColumnarLog` file: ``({column: float64 array}, {key: value})``.

    A last row cut short (a killed writer can leave one) is ignored; the
    returned metadata then has ``partial_last_row_bytes``.

    Raises
    ------
    ValueError
        Naming the file when it has no header, no row marker, or another format.
    """
    p = Path(path)
    raw = p.read_bytes()
    head, sep, body = raw.partition(_MARKER)
    if not sep:
        raise ValueError(f"{p}: not a columnar log (no '{_MARKER.decode().strip()}' line)")
    lines = head.decode("utf-8", errors="replace").split("\n")
    meta: dict[str, str] = {}
    names: list[str] = []
    for line in lines:
        if line.startswith("#"):
            key, colon, val = line[1:].partition(":")
            if colon:
                meta[key.strip()] = val.strip()
        elif line.strip():
            names = line.strip().split(",")
    if not names:
        raise ValueError(f"{p}: no column-name line before the rows")
    fmt = meta.get("format", "")
    if fmt.split(" (")[0] != FORMAT.split(" (")[0]:
        raise ValueError(f"{p}: format {fmt!r}; this version reads {FORMAT!r}")
    n = len(names)
    width = 8 * n
    n_rows = len(body) // width
    if len(body) % width:
        log.info("%s: ignoring a truncated last row", p)
        meta["partial_last_row_bytes"] = str(len(body) % width)
    dtype = np.dtype("<f8" if meta.get("byteorder", "little") == "little" else ">f8")
    data = np.frombuffer(body[: n_rows * width], dtype=dtype).reshape(n_rows, n)
    cols = {
        name: np.ascontiguousarray(data[:, j], dtype=np.float64) for j, name in enumerate(names)
    }
    return cols, meta
