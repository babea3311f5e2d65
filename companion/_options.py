"""Command-line value types shared by ``companion`` and ``sitl``.

click's ``FloatRange`` lets ``nan`` through every bound (it compares false with
anything) and ``inf`` past an open end; a watchdog given ``--stale-imu-s nan``
would never fire. :class:`Finite` closes that. :func:`usable_out_dir` checks an
output folder before any work starts (making it and a file in it, then undoing
that), so a bad ``--out`` fails at once rather than after a long run.
"""

from __future__ import annotations

import contextlib
import math
import os
import tempfile
from pathlib import Path
from typing import Any

import click

__all__ = ["SEED", "Finite", "out_dir_problem", "usable_out_dir", "usable_out_file"]

SEED = click.IntRange(min=0)
"""A seed: numpy's generators take a non-negative integer."""


class Finite(click.FloatRange):
    """A ``click.FloatRange`` whose value must also be a finite number."""

    name = "finite float range"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        rv = super().convert(value, param, ctx)
        if not math.isfinite(rv):
            self.fail(f"{value!r} is not a finite number.", param, ctx)
        return rv


def out_dir_problem(value: str | Path) -> str | None:
    """Why ``value`` cannot be an output folder, or None if it can: the folder
    exists or can be made, and a file can be written in it. Checked by doing it
    (making the missing folders and a temporary file), then undone, so nothing
    is left behind if the command stops before it starts its work."""
    if isinstance(value, str) and not value.strip():
        return "expected a folder path, got an empty one"
    path = Path(value)
    made: list[Path] = []
    try:
        missing = []
        p = Path(os.path.abspath(path))  # with any ".." resolved, as mkdir -p would
        while not p.exists():
            if p.is_symlink():
                return f"cannot create the folder {path}: {p} is a broken symlink"
            missing.append(p)
            p = p.parent
        if not p.is_dir():
            return f"cannot create the folder {path}: {p} is not a folder"
        for d in reversed(missing):
            d.mkdir()
            made.append(d)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as exc:  # PermissionError from exists() in a folder we cannot enter
        return f"cannot create the folder or write in {path}: {exc.strerror or exc}"
    finally:
        for d in reversed(made):
            with contextlib.suppress(OSError):
                d.rmdir()
    return None


def usable_out_dir(
    ctx: click.Context, param: click.Parameter, value: str | Path | None
) -> Path | None:
    """A click callback for a ``click.Path(file_okay=False)`` option: see
    :func:`out_dir_problem`."""
    if value is None:
        return None
    problem = out_dir_problem(value)
    if problem is not None:
        raise click.BadParameter(problem, ctx, param)
    return Path(value)


def usable_out_file(
    ctx: click.Context, param: click.Parameter, value: str | Path | None
) -> Path | None:
    """A click callback for an output file option: not empty, not a folder, and
    its folder passes :func:`usable_out_dir`."""
    if value is None:
        return None
    if isinstance(value, str) and not value.strip():
        raise click.BadParameter("expected a file path, got an empty one", ctx, param)
    path = Path(value)
    if path.is_dir() or str(value).endswith(("/", ".")):
        raise click.BadParameter(f"{value} is a folder; expected a file path", ctx, param)
    usable_out_dir(ctx, param, path.parent)
    return path
