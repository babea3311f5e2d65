"""Whether a build compiles the control core with mypyc: decided here, once, for
both the build backend (which then asks for mypy) and ``setup.py`` (which
compiles).

``MFC_COMPILE=1``
    compile; the build fails, saying why, where that is impossible.
``MFC_COMPILE=0``
    pure Python.
unset (or empty)
    a wheel (``pip install .``, ``pip wheel .``) is compiled where a C
    compiler and the Python headers are present, else built pure Python with a
    warning; an editable install (``pip install -e .``) stays pure Python, so
    that a developer's edits run as written.

Standard library only: the backend imports this before any build requirement
is installed.
"""

from __future__ import annotations

import os
import shlex
import shutil
import sysconfig
from dataclasses import dataclass
from pathlib import Path

__all__ = ["EDITABLE_ENV", "ENV", "Choice", "choose", "toolchain_problem"]

ENV = "MFC_COMPILE"
EDITABLE_ENV = "_MFC_EDITABLE_BUILD"
"""Set to ``1`` by the backend around its editable hooks (backend.py)."""


@dataclass(frozen=True)
class Choice:
    """What the build does with the control core."""

    compile: bool
    required: bool
    """``MFC_COMPILE=1``: a compile that cannot happen fails the build."""
    why: str
    """One line for a person: why this choice."""
    fallback: bool = False
    """Pure Python because the compile cannot happen here (not because it was
    asked for): the build warns."""


def toolchain_problem() -> str | None:
    """What is missing to compile a C extension for this Python, or None.

    The compiler is ``$CC``, else the one Python was built with
    (``sysconfig``'s ``CC``, as setuptools uses it); the headers are
    ``Python.h`` in ``sysconfig.get_paths()["include"]``.
    """
    cc = os.environ.get("CC") or sysconfig.get_config_var("CC") or ""
    try:
        words = shlex.split(cc)
    except ValueError:
        words = []
    if not words:
        return "no C compiler configured for this Python (sysconfig CC is empty; set CC)"
    if shutil.which(words[0]) is None:
        return (
            f"no C compiler: {words[0]!r} is not on PATH (Debian, Ubuntu, Raspberry Pi OS: "
            "apt install build-essential)"
        )
    header = Path(sysconfig.get_paths()["include"]) / "Python.h"
    if not header.is_file():
        return (
            f"no Python headers: {header} is missing (Debian, Ubuntu, Raspberry Pi OS: "
            "apt install python3-dev)"
        )
    return None


def choose(*, editable: bool | None = None) -> Choice:
    """The choice for this build, from ``MFC_COMPILE``, the kind of build and the toolchain.

    ``editable`` None reads :data:`EDITABLE_ENV`. Raises ``ValueError`` for an
    ``MFC_COMPILE`` other than 0, 1 or empty.
    """
    flag = os.environ.get(ENV, "").strip()
    if editable is None:
        editable = os.environ.get(EDITABLE_ENV) == "1"
    if flag == "1":
        return Choice(compile=True, required=True, why=f"{ENV}=1")
    if flag == "0":
        return Choice(compile=False, required=False, why=f"{ENV}=0 at build time")
    if flag:
        raise ValueError(f"{ENV}={flag!r}: expected 1 (compile), 0 (pure Python) or unset")
    if editable:
        return Choice(
            compile=False,
            required=False,
            why=f"an editable install ({ENV}=1 pip install -e . compiles it)",
        )
    problem = toolchain_problem()
    if problem is not None:
        return Choice(compile=False, required=False, why=problem, fallback=True)
    return Choice(
        compile=True, required=False, why="a C compiler and the Python headers were found"
    )
