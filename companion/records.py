"""Flight records: a MAVLink telemetry log (``.tlog``) and a columnar CSV log.

Both writers sit on the control path (they are called once per MAVLink
message and once per control sample), so both are cheap appends to an
in-memory buffer; the buffer goes to the operating system in one ``write``
when ``flush_interval_s`` has passed since the last flush. Nothing calls
``fsync`` (it can block for tens of milliseconds on an SD card): a killed
process loses at most the rows of the last ``flush_interval_s``; a power cut
may lose what the kernel had not written back.

A write error (disk full, removed medium) never reaches the control loop: it
is logged once, the writer stops recording (``failed`` holds the error) and
later rows are counted in ``dropped``.

Formats are described in ``docs/logs.md``.
"""

from __future__ import annotations

import contextlib
import logging
import math
import struct
import time
from collections.abc import Collection, Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

__all__ = [
    "AXES",
    "EXACT_FORMAT",
    "OUTPUT_FORMAT",
    "ColumnarLog",
    "TlogWriter",
    "columns",
    "exact_columns",
    "read_columnar",
]

log = logging.getLogger(__name__)

AXES = ("roll", "pitch", "yaw")

EXACT_FORMAT = "%.17g"
"""Round-trips any float64 exactly: used for what replay feeds the controller."""
OUTPUT_FORMAT = "%.14g"
"""14 significant digits (relative error <= 5e-14): derived values, at ~60 % of the cost."""

_pack_usec = struct.Struct(">Q").pack


def columns(n_motors: int) -> list[str]:
    """The columnar flight log's columns, in order, for a vehicle with ``n_motors``.

    ``t_s`` (IMU sample time, s), ``wall_s`` (monotonic clock, s),
    ``latency_us`` (datagram arrival to command sent), ``engaged`` and
    ``held`` (0/1); per axis (roll, pitch, yaw): ``ref_<axis>_rad_s``,
    ``meas_<axis>_rad_s``, ``err_<axis>_rad_s``, ``f_hat_<axis>``,
    ``u_<axis>``, ``torque_<axis>``, ``sat_<axis>`` (0/1); then ``thrust``
    (pilot's collective, 0..1), ``thrust_out`` (realised) and
    ``motor_1`` .. ``motor_<n_motors>``.
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
    return cols


def exact_columns(cols: Sequence[str]) -> set[str]:
    """The columns written with full float64 precision by default.

    Time stamps and everything replay feeds a controller (``t_s``, ``wall_s``,
    ``thrust``, ``ref_*``, ``meas_*``), so a replay starts from bit-identical
    inputs.
    """
    return {c for c in cols if c in ("t_s", "wall_s", "thrust") or c.startswith(("ref_", "meas_"))}


class TlogWriter:
    """Append MAVLink frames to a ``.tlog`` file.

    The format is the one pymavlink's ``mavutil.mavlogfile`` reads (and QGC,
    MAVProxy and Mission Planner write): for each message, an 8-byte
    big-endian unsigned integer of unix time in microseconds, then the raw
    MAVLink frame, nothing else. ``mavutil.mavlink_connection(path)`` and
    ``mavlogdump.py path`` read it; ``msg._timestamp`` is the time given here.

    Parameters
    ----------
    path
        The file to create (parent directories are created; an existing file
        is replaced).
    flush_interval_s
        The buffer goes to the OS on the first :meth:`write` at least this long
        after the last flush (monotonic clock).
    """

    def __init__(self, path: str | Path, *, flush_interval_s: float = 0.2) -> None:
        if not (math.isfinite(flush_interval_s) and flush_interval_s >= 0.0):
            raise ValueError(f"flush_interval_s must be >= 0, got {flush_interval_s!r}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f: BinaryIO | None = open(self.path, "wb")  # noqa: SIM115 (closed in close())
        self._buf = bytearray()
        self._interval = flush_interval_s
        self._next_flush = time.monotonic() + flush_interval_s
        self.written_in = 0
        """Frames received from the link (``outgoing=False``)."""
        self.written_out = 0
        """Frames sent by the companion (``outgoing=True``)."""
        self.dropped = 0
        """Frames not recorded because of an earlier write error."""
        self.failed: OSError | None = None

    def write(self, unix_time_s: float, raw: bytes, outgoing: bool) -> None:
        """Record one MAVLink frame (``raw``, as on the wire) seen at ``unix_time_s``.

        ``outgoing`` only counts (``written_out``/``written_in``): a tlog has no
        direction field; the sender is in each frame's system and component ids.
        """
        if self._f is None:
            if self.failed is not None:
                self.dropped += 1
                return
            raise ValueError(f"{self.path}: TlogWriter is closed")
        buf = self._buf
        buf += _pack_usec(int(unix_time_s * 1e6 + 0.5) if unix_time_s > 0.0 else 0)
        buf += raw
        if outgoing:
            self.written_out += 1
        else:
            self.written_in += 1
        if time.monotonic() >= self._next_flush:
            self.flush()

    def flush(self) -> None:
        """Hand the buffer to the OS now (no fsync)."""
        f = self._f
        self._next_flush = time.monotonic() + self._interval
        if f is None or not self._buf:
            return
        try:
            f.write(self._buf)
            f.flush()
        except OSError as exc:
            self._fail(exc)
        self._buf.clear()

    def _fail(self, exc: OSError) -> None:
        log.error("%s: cannot write the MAVLink log, recording stops: %s", self.path, exc)
        self.failed = exc
        f, self._f = self._f, None
        if f is not None:
            with contextlib.suppress(OSError):
                f.close()

    def close(self) -> None:
        """Flush and close; closing twice is harmless."""
        if self._f is None:
            return
        self.flush()
        if self._f is not None:
            try:
                self._f.close()
            except OSError as exc:
                self._fail(exc)
            self._f = None

    def __enter__(self) -> TlogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ColumnarLog:
    """A CSV flight log: ``# key: value`` metadata lines, a header line, one row per sample.

    Parameters
    ----------
    path
        The file to create (parent directories are created; an existing file
        is replaced).
    columns
        Column names, in order (usually :func:`columns`).
    meta
        Metadata written as ``# key: value`` lines before the header (profile,
        controller, ...). ``format``, ``version``, ``start_unix_s`` and
        ``start_utc`` are added unless given. Newlines in values become spaces.
    flush_interval_s
        Formatted rows go to the OS on the first :meth:`append` at least this
        long after the last flush.
    exact
        Columns written with ``%.17g`` (exact float64 round trip); the others
        use ``%.14g``. Default: :func:`exact_columns`.

    Notes
    -----
    Each row is formatted when appended (steady cost, a few microseconds) and
    kept in a list; a flush is one ``write`` of the joined lines. Formatting
    in the flush instead would turn 200 rows into a millisecond-long burst
    that delays the next IMU sample at 1 kHz.
    """

    def __init__(
        self,
        path: str | Path,
        columns: list[str],
        *,
        meta: dict[str, Any] | None = None,
        flush_interval_s: float = 0.2,
        exact: Collection[str] | None = None,
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
        exact_set = exact_columns(cols) if exact is None else set(exact)
        self._fmt = ",".join(EXACT_FORMAT if c in exact_set else OUTPUT_FORMAT for c in cols) + "\n"
        self._lines: list[str] = []
        self._interval = flush_interval_s
        self.rows = 0
        """Rows appended."""
        self.dropped = 0
        """Rows not recorded because of an earlier write error."""
        self.failed: OSError | None = None

        from companion import __version__

        now = time.time()
        full_meta: dict[str, Any] = {
            "format": "companion-columnar 1",
            "version": __version__,
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
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f: BinaryIO | None = open(self.path, "wb")  # noqa: SIM115 (closed in close())
        # The header goes out at once: a killed process leaves a readable file.
        self._f.write("".join(head).encode())
        self._f.flush()
        self._next_flush = time.monotonic() + flush_interval_s

    def append(self, row: Sequence[float]) -> None:
        """Record one row (numbers in column order; bools and ints are fine).

        Raises
        ------
        ValueError
            If ``len(row)`` is not the number of columns.
        """
        try:
            line = self._fmt % tuple(row)
        except TypeError:
            if len(row) != self.n_columns:
                raise ValueError(
                    f"{self.path}: row has {len(row)} values, expected {self.n_columns}"
                ) from None
            raise
        if self._f is None:
            if self.failed is not None:
                self.dropped += 1
                return
            raise ValueError(f"{self.path}: ColumnarLog is closed")
        self.rows += 1
        self._lines.append(line)
        if time.monotonic() >= self._next_flush:
            self.flush()

    def flush(self) -> None:
        """Hand the formatted rows to the OS now (no fsync)."""
        f = self._f
        self._next_flush = time.monotonic() + self._interval
        if f is None or not self._lines:
            return
        data = "".join(self._lines).encode()
        self._lines.clear()
        try:
            f.write(data)
            f.flush()
        except OSError as exc:
            log.error("%s: cannot write the flight log, recording stops: %s", self.path, exc)
            self.failed = exc
            self._f = None
            with contextlib.suppress(OSError):
                f.close()

    def close(self) -> None:
        """Flush and close; closing twice is harmless."""
        if self._f is None:
            return
        self.flush()
        f, self._f = self._f, None
        if f is not None:
            try:
                f.close()
            except OSError as exc:
                log.error("%s: closing the flight log failed: %s", self.path, exc)
                self.failed = exc

    def __enter__(self) -> ColumnarLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_columnar(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Read a :class:`ColumnarLog` file: ``({column: float64 array}, {key: value})``.

    A last line cut short (no final newline, as a killed writer can leave) is
    ignored; any other malformed line raises.

    Raises
    ------
    ValueError
        Naming the file (and the line) when the file has no header or a
        malformed row before the last line.
    """
    p = Path(path)
    text = p.read_bytes().decode("utf-8", errors="replace")
    lines = text.split("\n")
    # ``split`` leaves "" after a final newline, or the unterminated tail.
    if lines and lines[-1] != "":
        log.info("%s: ignoring a truncated last line", p)
    lines.pop()
    meta: dict[str, str] = {}
    i = 0
    while i < len(lines) and lines[i].startswith("#"):
        key, sep, val = lines[i][1:].partition(":")
        if sep:
            meta[key.strip()] = val.strip()
        i += 1
    if i >= len(lines):
        raise ValueError(f"{p}: no header line (not a columnar log, or cut before its header)")
    names = lines[i].strip().split(",")
    body = lines[i + 1 :]
    n = len(names)
    if body:
        try:
            data = np.loadtxt(body, delimiter=",", dtype=np.float64, ndmin=2)
        except ValueError as exc:
            raise ValueError(f"{p}: malformed row: {exc}") from exc
        if data.shape[1] != n:
            raise ValueError(f"{p}: rows have {data.shape[1]} values, header names {n}")
    else:
        data = np.empty((0, n), dtype=np.float64)
    cols = {name: np.ascontiguousarray(data[:, j]) for j, name in enumerate(names)}
    return cols, meta
