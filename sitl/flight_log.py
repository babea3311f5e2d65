"""The SITL's flight log: true state per physics step (``.npz``) and events (JSON lines).

Written by the simulation loop (``sitl.runner``), read back by :func:`read_log`.

Format
------
``--log FILE`` (e.g. ``flight.npz``) writes, at the end of the run, a NumPy
``.npz`` with one row per physics step:

==================== ============ ===============================================
key                  shape        meaning
==================== ============ ===============================================
``t_s``              (N,)         simulation time, s
``rate_frd_rad_s``   (N, 3)       true body rates
``q_wxyz``           (N, 4)       true attitude (body FRD -> world NED)
``pos_ned_m``        (N, 3)       position, m
``vel_ned_m_s``      (N, 3)       velocity, m/s
``motor_w_rad_s``    (N, n)       rotor speeds
``motor_cmd``        (N, n)       normalised motor commands applied over the step
``custom_mode``      (N,)         PX4 custom_mode (main << 16 | sub << 24)
``armed``            (N,)         bool
``imu_t_s``          (M,)         each IMU sample's time stamp (what HIGHRES_IMU and
                                  ATTITUDE carry), s: the autopilot's clock
``imu_gyro_rad_s``   (M, 3)       its gyro reading (FRD, filtered and noisy, as sent)
``summary``          ()           JSON string: status, seed, clock, counters, timing
==================== ============ ===============================================

The IMU samples are what an autopilot's own log keeps of its sensors (PX4's
``sensor_combined``): a companion's control log, stamped with the samples' times,
lines up with them on one time axis.

and, while running, ``FILE`` with the suffix replaced by ``.events.jsonl``: one
JSON object per line (``{"t_s": ..., "kind": "mode", ...}``), flushed as each
event happens; an injected fault is ``{"t_s": ..., "kind": "fault", "fault":
"imu-stop", "arg": 0}`` (``arg``: the motor of ``motor-fail``, else 0); the last
line is ``{"kind": "summary", ...}``. Read both back with :func:`read_log`.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sitl.personality import Event

__all__ = ["FlightLog", "LogWriter", "events_path", "read_log"]

logger = logging.getLogger(__name__)


def events_path(log_path: Path) -> Path:
    """The events file next to a log: ``flight.npz`` -> ``flight.events.jsonl``."""
    return log_path.with_suffix(".events.jsonl")


class LogWriter:
    """Per-step true-state rows in growing numpy blocks; events to JSON lines."""

    _BLOCK = 16384

    def __init__(self, n_motors: int, path: Path | None) -> None:
        self.n = n_motors
        # t, rate3, q4, pos3, vel3, w n, cmd n, custom_mode, armed
        self.width = 1 + 3 + 4 + 3 + 3 + 2 * n_motors + 2
        self._blocks: list[np.ndarray] = []
        self._buf = np.empty((self._BLOCK, self.width))
        self._i = 0
        self._imu: list[tuple[float, float, float, float]] = []
        self.path = path
        self._events = None
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._events = events_path(path).open("w", encoding="utf-8")

    @property
    def rows_kept(self) -> int:
        """Rows held for the ``.npz`` (none without a path: a run without ``--log``
        keeps nothing, however long it runs)."""
        return len(self._blocks) * self._BLOCK + self._i

    def append(self, row: list[float]) -> None:
        if self.path is None:
            return
        if self._i == self._BLOCK:
            self._blocks.append(self._buf)
            self._buf = np.empty((self._BLOCK, self.width))
            self._i = 0
        self._buf[self._i] = row
        self._i += 1

    def imu(self, t_s: float, gyro_rad_s: tuple[float, float, float]) -> None:
        """An IMU sample the autopilot took (stamped ``t_s``)."""
        if self.path is not None:
            self._imu.append((t_s, *gyro_rad_s))

    def event(self, ev: Event) -> None:
        if self._events is not None:
            # The event's own time and kind win over any same-named detail key.
            record = {"t_s": ev.t_s, "kind": ev.kind, **ev.detail}
            record["t_s"], record["kind"] = ev.t_s, ev.kind
            self._events.write(json.dumps(record) + "\n")
            self._events.flush()

    def close(self, summary: dict[str, Any]) -> None:
        """Write the summary (a run's ``RunSummary`` as a dict) and the ``.npz``."""
        if self.path is None:
            return
        if self._events is not None:
            self._events.write(json.dumps({"kind": "summary", **summary}) + "\n")
            self._events.close()
            self._events = None
        data = np.concatenate([*self._blocks, self._buf[: self._i]], axis=0)
        n = self.n
        c = 14
        imu = np.array(self._imu, dtype=float).reshape(-1, 4)
        # Write beside the target and rename: a reader never sees half a log, and
        # a signal during the write leaves the previous state, not a corrupt file.
        tmp = self.path.with_name(self.path.name + ".part.npz")
        np.savez_compressed(
            tmp,
            t_s=data[:, 0],
            rate_frd_rad_s=data[:, 1:4],
            q_wxyz=data[:, 4:8],
            pos_ned_m=data[:, 8:11],
            vel_ned_m_s=data[:, 11:14],
            motor_w_rad_s=data[:, c : c + n],
            motor_cmd=data[:, c + n : c + 2 * n],
            custom_mode=data[:, c + 2 * n].astype(np.uint32),
            armed=data[:, c + 2 * n + 1].astype(bool),
            imu_t_s=imu[:, 0],
            imu_gyro_rad_s=imu[:, 1:4],
            summary=np.array(json.dumps(summary)),
        )
        os.replace(tmp, self.path)
        logger.info("log written to %s (%d rows)", self.path, data.shape[0])


@dataclass
class FlightLog:
    """A log read back by :func:`read_log`: arrays by key, events, summary."""

    arrays: dict[str, np.ndarray]
    events: list[dict[str, Any]]
    summary: dict[str, Any]

    def __getitem__(self, key: str) -> np.ndarray:
        return self.arrays[key]


def read_log(path: str | Path) -> FlightLog:
    """Read a SITL log (``.npz``) and its ``.events.jsonl`` back.

    Raises
    ------
    FileNotFoundError
        If the ``.npz`` file does not exist.
    """
    p = Path(path)
    with np.load(p) as z:
        arrays = {k: z[k] for k in z.files if k != "summary"}
        summary = json.loads(str(z["summary"])) if "summary" in z.files else {}
    events: list[dict[str, Any]] = []
    ep = events_path(p)
    if ep.exists():
        for line in ep.read_text(encoding="utf-8").splitlines():
            if line.strip():
                events.append(json.loads(line))
    return FlightLog(arrays, [e for e in events if e.get("kind") != "summary"], summary)
