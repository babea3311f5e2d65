"""Output folders that keep what was there before.

Every command that writes output first moves an earlier run's outputs,
untouched, into ``earlier-<UTC time of their last write>/`` beside them
(:func:`move_earlier`). ``companion run --log-dir`` also locks its folder for
the run's life (:func:`lock_log_dir`), before it moves anything: a second run
on a folder in use refuses to start instead of moving a live flight's records
away.
"""

from __future__ import annotations

import fcntl
import os
from collections.abc import Iterable
from datetime import datetime, timezone
from pathlib import Path

from companion.errors import LogDirInUseError

__all__ = ["LOCK_FILE", "RECORD_FILES", "lock_log_dir", "move_earlier", "prepare_log_dir"]

RECORD_FILES = ("flight.tlog", "control.mcap", "events.jsonl")
"""What ``companion run --log-dir DIR`` writes into DIR."""

LOCK_FILE = "companion.lock"
"""The lock of a ``--log-dir`` in use; it holds the pid of the run that last took it."""


def move_earlier(folder: str | Path, names: Iterable[str], *, what: str) -> Path | None:
    """Move the earlier outputs ``names`` in ``folder`` aside, untouched, before a new run writes.

    ``names`` are file or folder names, or glob patterns (``worst-*.png``);
    those present go into a new subfolder ``earlier-<UTC time of their last
    write>`` (``-1``, ``-2``, ... when that exists). Returns the subfolder, or
    None when there was nothing to move.

    Raises
    ------
    ValueError
        If they cannot be moved; the message starts with ``what`` (e.g. ``--out runs/x``).
    """
    d = Path(folder)
    held = sorted({p for n in names for p in d.glob(n) if not p.name.startswith("earlier-")})
    if not held:
        return None
    try:
        when = datetime.fromtimestamp(max(p.lstat().st_mtime for p in held), tz=timezone.utc)
        base = d / f"earlier-{when:%Y%m%dT%H%M%SZ}"
        dest, n = base, 0
        while True:
            try:
                dest.mkdir()
                break
            except FileExistsError:
                n += 1
                dest = base.with_name(f"{base.name}-{n}")
        for p in held:
            p.rename(dest / p.name)
    except OSError as exc:
        raise ValueError(f"{what}: cannot move the earlier outputs aside: {exc}") from None
    return dest


def prepare_log_dir(path: str | Path) -> Path | None:
    """Make ``path`` ready for one run's records; never overwrite an earlier run's.

    Creates the folder if needed. Records already in it (an earlier run's, or a
    start-up killed before it could tidy up) are moved aside (:func:`move_earlier`).
    Returns the subfolder they went to, or None when there was nothing to move.
    Take the folder's lock (:func:`lock_log_dir`) first.

    Raises
    ------
    ValueError
        If the folder cannot be created or written, naming it.
    """
    d = Path(path)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"--log-dir {d}: cannot create the folder: {exc.strerror}") from None
    if not os.access(d, os.W_OK | os.X_OK):
        raise ValueError(f"--log-dir {d}: the folder is not writable")
    return move_earlier(d, RECORD_FILES, what=f"--log-dir {d}")


def lock_log_dir(folder: str | Path) -> int:
    """Lock ``folder`` (an existing one) for this run: an exclusive ``flock`` on its
    :data:`LOCK_FILE`, which then holds this process's pid.

    Returns the lock file's descriptor: closing it releases the lock, and so
    does the OS when the process ends, however it ends (a stale pid left in the
    file locks nothing).

    Raises
    ------
    LogDirInUseError
        If another run holds the lock (in this process or another), naming the
        folder and that run's pid.
    OSError
        If the lock file cannot be created or written.
    """
    path = Path(folder) / LOCK_FILE
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "unknown"
        os.close(fd)
        raise LogDirInUseError(
            f"--log-dir {folder} is in use by another companion run (pid {holder}, which "
            f"holds {path}): give another folder, or stop that run first"
        ) from None
    except BaseException:
        os.close(fd)
        raise
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
    except BaseException:
        os.close(fd)
        raise
    return fd
