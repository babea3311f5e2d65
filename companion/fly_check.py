"""Which controller files have passed ``companion check-config --fly`` on this computer.

The schema takes each value of a controller file within its range, yet a
combination of values can still crash a vehicle (of 100 schema-valid mutations
of the shipped file, 8 crash or blow up in the simulator; ``check-config --fly``
catches them). So ``companion run`` flies a controller file only when it is
one of the shipped ones (``companion/data/*.yaml``, compared by content, not by
path) or when the same bytes passed the fly check here: a pass is remembered by
the SHA-256 of the file's bytes, so a file changed since is not checked.

The record is one JSON file, :data:`RECORD_NAME`, in a user-level state folder:
``$MFC_STATE_DIR`` when set, else ``$XDG_STATE_HOME/mfc-companion``, else
``~/.local/state/mfc-companion`` (the XDG Base Directory specification's state
home). Each entry holds the hash, the file's path when it was checked, the UTC
date and the verdict (``passed`` or ``failed``, with the first problems). It is
written whole or not at all (a temporary file beside it, flushed to disk, then
renamed over it) under a lock, so two checks at once lose neither; it keeps the
newest :data:`MAX_RECORDS`. A record that cannot be read (corrupt, not JSON,
unreadable, too large) counts as no check at all, with a note that says why:
never a crash, never a pass.

Pure of the simulator: the check itself is ``sitl.lab.config_check``, flown by
the command line; this module only remembers its verdicts.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import uuid
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from datetime import datetime, timezone
from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, ValidationError

from companion.config import DEFAULT_CONTROLLER
from companion.errors import ConfigError
from companion.schema import read_text

__all__ = [
    "MAX_RECORDS",
    "RECORD_NAME",
    "STATE_DIR_ENV",
    "FlyCheck",
    "file_sha256",
    "fly_check_of",
    "record_fly_check",
    "record_path",
    "state_dir",
]

STATE_DIR_ENV = "MFC_STATE_DIR"
"""The environment variable that names the state folder itself (tests, the service)."""

RECORD_NAME = "fly-checks.json"
_LOCK_NAME = "fly-checks.lock"
_FORMAT = "mfc-companion fly checks"

MAX_RECORDS = 100
"""Entries kept, newest first: a companion computer flies a handful of files; the
record stays far below the 1 MiB any file read here may be."""

_PROBLEMS_KEPT = 3
"""A failed check's first problems kept in its entry (the command printed them all)."""

_SHIPPED_DIR = DEFAULT_CONTROLLER.parent

Status = Literal["shipped", "passed", "failed", "unchecked"]


class _Entry(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    path: str
    date: str
    verdict: Literal["passed", "failed"]
    problems: list[str] = []


class _Record(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    format: Literal["mfc-companion fly checks"]
    version: Literal[1]
    checks: dict[str, _Entry]


@dataclass(frozen=True)
class FlyCheck:
    """What this computer knows of one controller file: its fly check's status."""

    path: Path
    """The file, as given."""
    sha256: str
    status: Status
    date: str = ""
    """When it was checked (UTC, ISO 8601), for ``passed`` and ``failed``."""
    checked_path: str = ""
    """The path the file had when it was checked."""
    problems: tuple[str, ...] = ()
    """A failed check's first problems."""
    note: str = ""
    """Why the record could not be read (the file then counts as not checked)."""

    @property
    def may_fly(self) -> bool:
        """``companion run`` flies it without ``--skip-fly-check``."""
        return self.status in ("shipped", "passed")

    @property
    def when(self) -> str:
        """The check's date as a pilot reads it: ``2025-06-01 14:02 UTC``."""
        return self.date[:16].replace("T", " ") + " UTC" if self.date else ""

    def describe(self) -> str:
        """One line: which it is."""
        if self.status == "shipped":
            return f"{self.path}: a shipped controller"
        if self.status == "passed":
            return f"{self.path}: passed the fly check on {self.when}"
        if self.status == "failed":
            first = f": {self.problems[0]}" if self.problems else ""
            return f"{self.path}: failed the fly check on {self.when}{first}"
        text = f"{self.path}: not checked in the simulator on this computer"
        return f"{text} ({self.note})" if self.note else text

    @property
    def fix(self) -> str:
        """The command that checks it."""
        return f"companion check-config --controller {self.path} --fly"

    @property
    def advice(self) -> str:
        """What to do about a file that may not fly: check it, or mend it first."""
        if self.status == "failed":
            return f"do not fly it as it is: change it, then check it again with `{self.fix}`"
        return f"fly it in the simulator first: `{self.fix}`"


def state_dir(environ: Mapping[str, str] | None = None) -> Path:
    """The folder of the record: ``$MFC_STATE_DIR``, else ``$XDG_STATE_HOME/mfc-companion``
    (an absolute path only, as the XDG specification says), else
    ``~/.local/state/mfc-companion``."""
    env = os.environ if environ is None else environ
    if env.get(STATE_DIR_ENV):
        return Path(env[STATE_DIR_ENV])
    xdg = env.get("XDG_STATE_HOME", "")
    base = Path(xdg) if os.path.isabs(xdg) else Path.home() / ".local" / "state"
    return base / "mfc-companion"


def record_path(environ: Mapping[str, str] | None = None) -> Path:
    """The record file: :data:`RECORD_NAME` in :func:`state_dir`."""
    return state_dir(environ) / RECORD_NAME


def file_sha256(path: str | Path) -> str:
    """The SHA-256 of a file's bytes, hex.

    Raises
    ------
    companion.errors.ConfigError
        Naming the file when it cannot be read.
    """
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 16), b""):
                digest.update(block)
    except OSError as exc:
        raise ConfigError(str(path), [f"cannot read file: {exc.strerror or exc}"]) from exc
    return digest.hexdigest()


@lru_cache(maxsize=1)
def _shipped() -> frozenset[str]:
    """The hashes of the shipped controller files."""
    return frozenset(file_sha256(p) for p in sorted(_SHIPPED_DIR.glob("*.yaml")))


def _read_record(path: Path) -> tuple[dict[str, _Entry], str]:
    """The entries by hash, and why the record could not be read ("" when it could,
    or when there is none yet)."""
    try:
        os.stat(path)
    except FileNotFoundError:
        return {}, ""  # never checked anything here: nothing to say
    except OSError as exc:
        return {}, f"the record {path} cannot be read: {exc.strerror or exc}"
    try:
        text = read_text(path)  # bounded, a regular file only, UTF-8
        record = _Record.model_validate(json.loads(text))
    except ConfigError as exc:
        why = "; ".join(p.removeprefix("cannot read file: ") for p in exc.problems)
        return {}, f"the record {path} cannot be read: {why}"
    except json.JSONDecodeError as exc:
        return {}, f"the record {path} is not JSON ({exc.msg}, line {exc.lineno})"
    except ValidationError as exc:
        return {}, f"the record {path} is not a fly-check record ({exc.error_count()} problems)"
    return dict(record.checks), ""


def fly_check_of(path: str | Path, environ: Mapping[str, str] | None = None) -> FlyCheck:
    """What the record says of the controller file ``path``.

    Raises
    ------
    companion.errors.ConfigError
        When ``path`` cannot be read. An unreadable record is a note, not an error.
    """
    p = Path(path)
    digest = file_sha256(p)
    if digest in _shipped():
        return FlyCheck(p, digest, "shipped")
    try:
        record = record_path(environ)
    except RuntimeError as exc:  # no home folder, and no state folder named
        return FlyCheck(p, digest, "unchecked", note=f"{exc}; set {STATE_DIR_ENV}")
    entries, note = _read_record(record)
    entry = entries.get(digest)
    if entry is None:
        return FlyCheck(p, digest, "unchecked", note=note)
    return FlyCheck(
        p, digest, entry.verdict, date=entry.date, checked_path=entry.path,
        problems=tuple(entry.problems),
    )  # fmt: skip


@contextlib.contextmanager
def _locked(folder: Path) -> Iterator[None]:
    """An exclusive lock on the folder's lock file while the record is rewritten."""
    fd = os.open(folder / _LOCK_NAME, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


def _write_whole(path: Path, text: str) -> None:
    """``text`` at ``path``, whole or not at all: a temporary file beside it, on disk,
    renamed over it."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp")
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
    with contextlib.suppress(OSError):  # the rename itself on disk (best effort)
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)


def record_fly_check(
    check: FlyCheck,
    passed: bool,
    problems: tuple[str, ...] | list[str] = (),
    *,
    now: datetime | None = None,
    environ: Mapping[str, str] | None = None,
) -> tuple[Path, str]:
    """Remember a fly check's verdict for the file ``check`` describes (its hash, as
    read before the flights). Returns the record's path and a note when an unreadable
    record was replaced ("" otherwise).

    Raises
    ------
    OSError
        When the state folder or the record cannot be written.
    """
    folder = state_dir(environ)
    folder.mkdir(parents=True, exist_ok=True, mode=0o700)
    path = folder / RECORD_NAME
    when = (now or datetime.now(timezone.utc)).astimezone(timezone.utc)
    entry = _Entry(
        path=str(check.path.resolve()),
        date=when.isoformat(timespec="seconds").replace("+00:00", "Z"),
        verdict="passed" if passed else "failed",
        problems=[p[:300] for p in problems[:_PROBLEMS_KEPT]],
    )
    with _locked(folder):
        entries, note = _read_record(path)
        entries.pop(check.sha256, None)
        entries[check.sha256] = entry  # newest last
        kept = dict(list(entries.items())[-MAX_RECORDS:])
        record = _Record(format=_FORMAT, version=1, checks=kept)
        _write_whole(path, json.dumps(record.model_dump(mode="json"), indent=1) + "\n")
    return path, note
