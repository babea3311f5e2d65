"""The compiled control core: built by default where it can be.

A wheel (``pip install .``, ``pip wheel .``) compiles the control laws
(``companion/control``: estimator, identifier, the intelligent controllers, the
MFC assembly, mixer, PID, prefilter, sticks) to C extensions with mypyc, from
the same typed source, where a C compiler and the Python headers are present;
where they are not, or the compile fails, it is built pure Python with a
warning. An editable install (``pip install -e .``) stays pure Python.
``MFC_COMPILE=1`` requires the compiled core (the build fails without it),
``MFC_COMPILE=0`` builds pure Python. ``_build/mfc_compile.py`` decides.

Beside the extensions goes ``_compiled.json``, the SHA-256 of each source
compiled, so that ``companion.control`` refuses to import an extension whose
source has changed since. Every wheel also carries ``_core.json``: what its
build chose and why, which ``companion.control.CORE`` reports afterwards
(pip shows a build's output only with ``-v``). Everything else about the
package is in ``pyproject.toml``.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
from dataclasses import dataclass
from importlib.machinery import EXTENSION_SUFFIXES
from pathlib import Path
from typing import Any

from setuptools import setup
from setuptools.command.build_ext import build_ext
from setuptools.command.build_py import build_py
from setuptools.errors import BaseError, CCompilerError

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "_build"))
from mfc_compile import Choice, choose  # noqa: E402

# = companion.control._compiled.MODULES
CONTROL = ("estimator", "identifier", "intelligent", "mfc", "mixer", "pid", "prefilter", "sticks")
# (not imported: that package checks its extensions on import; a module missing
# here makes the check refuse the build, and tests/control/test_compiled.py fail)
MANIFEST = "_compiled.json"  # = companion.control._compiled.MANIFEST
CORE_RECORD = "_core.json"  # = companion.control._compiled.CORE_RECORD

BUILDS = frozenset({"build", "build_ext", "bdist_wheel", "editable_wheel", "install", "develop"})
"""The commands that build extensions; the others (egg_info, dist_info, sdist:
the backend asking for metadata or requirements) need no compile."""


def _say(text: str) -> None:
    sys.stderr.write(f"mfc-companion: {text}\n")
    sys.stderr.flush()


@dataclass
class Outcome:
    """What the build does with the core, as it goes (a compile may fail)."""

    compiled: bool
    why: str


def _pure(why: str, *, warn: bool) -> None:
    if not warn:  # asked for (MFC_COMPILE=0, an editable install): a note, no warning
        _say(f"the control core is built pure Python: {why}")
        return
    _say(
        "WARNING: the control core is built pure Python, about 3x slower per update than "
        f"compiled: {why}. To compile it, install a C compiler and the Python headers "
        "(apt install build-essential python3-dev) and reinstall; MFC_COMPILE=1 makes a "
        "build that cannot compile it fail instead."
    )


def _control_dir(base: Path) -> Path:
    dest = base / "companion" / "control"
    dest.mkdir(parents=True, exist_ok=True)
    return dest


def _record(build_lib: str, compiled: bool, why: str) -> None:
    """Write what this build did into the wheel (``companion.control.CORE`` reads it)."""
    path = _control_dir(Path(build_lib)) / CORE_RECORD
    path.write_text(json.dumps({"compiled": compiled, "why": why}) + "\n", encoding="utf-8")


def _remove_compiled(build_lib: str) -> None:
    """Remove a compiled core an earlier build left in ``build_lib`` (``build/`` is
    reused): a pure-Python wheel must not carry it."""
    base = Path(build_lib)
    control = base / "companion" / "control"
    stale = [control / f"{m}{s}" for m in CONTROL for s in EXTENSION_SUFFIXES]
    for path in [*stale, control / MANIFEST, *base.glob("companion_control__mypyc.*")]:
        path.unlink(missing_ok=True)


def _commands(choice: Choice, outcome: Outcome) -> dict[str, Any]:
    class BuildPy(build_py):
        """Also writes the build's outcome into a wheel (not an editable install)."""

        def run(self) -> None:
            super().run()
            if not getattr(self, "editable_mode", False):
                if not outcome.compiled:
                    _remove_compiled(self.build_lib)
                _record(self.build_lib, outcome.compiled, outcome.why)

    class BuildExt(build_ext):
        """Compiles the core and writes its manifest; falls back to pure Python
        when the compile fails, unless the compiled core is required."""

        def run(self) -> None:
            if not self.extensions:
                return  # pure Python
            try:
                super().run()
            except (CCompilerError, BaseError, OSError) as exc:
                if choice.required:
                    raise
                for out in self.get_outputs():
                    Path(out).unlink(missing_ok=True)
                detail = str(exc) if len(str(exc)) <= 200 else f"{str(exc)[:197]}..."
                outcome.compiled, outcome.why = False, f"the C compile failed ({detail})"
                _pure(outcome.why, warn=True)
                if not self.inplace:
                    _remove_compiled(self.build_lib)
                    _record(self.build_lib, False, outcome.why)
                return
            src = HERE / "companion" / "control"
            digests = {
                m: hashlib.sha256((src / f"{m}.py").read_bytes()).hexdigest() for m in CONTROL
            }
            dest = _control_dir(HERE if self.inplace else Path(self.build_lib))
            (dest / MANIFEST).write_text(json.dumps(digests, indent=1) + "\n")
            if not self.inplace:
                _record(self.build_lib, True, outcome.why)

    return {"build_py": BuildPy, "build_ext": BuildExt}


def _extensions(choice: Choice, outcome: Outcome) -> list[Any]:
    """The mypyc extensions, or [] (having said why) when the core is built pure Python."""
    if not choice.compile:
        _pure(choice.why, warn=choice.fallback)
        return []
    if choice.required:
        from mfc_compile import toolchain_problem

        problem = toolchain_problem()
        if problem is not None:
            sys.exit(f"MFC_COMPILE=1: cannot compile the control core: {problem}")
    try:
        from mypyc.build import mypycify
    except ImportError:
        if choice.required:
            sys.exit(
                "MFC_COMPILE=1: the compiled control core needs mypy (mypyc): pip install mypy"
            )
        outcome.why = "mypy (mypyc) is not in the build environment"
        _pure(outcome.why, warn=True)
        return []
    _say(f"compiling the control core with mypyc ({choice.why}; MFC_COMPILE=0 skips it)")
    try:
        # One shared library for the control modules, named after the package.
        # No config file: the project's (pyproject.toml) loads the pydantic plugin,
        # which the build environment lacks; the control modules need neither.
        extensions = mypycify(
            ["--config-file", os.devnull, *(f"companion/control/{m}.py" for m in CONTROL)],
            opt_level="3",
            group_name="companion_control",
        )
    except (Exception, SystemExit) as exc:  # mypyc reports type errors by exiting
        if choice.required:
            raise
        outcome.why = f"mypyc could not translate the control core ({exc!r})"
        _pure(outcome.why, warn=True)
        return []
    for ext in extensions:
        # No fused multiply-add (gcc contracts a*b+c where the CPU has FMA, as on
        # the Raspberry Pi's aarch64): every operation rounds as Python's does, so
        # the compiled law computes the same floats as the pure one.
        ext.extra_compile_args = [*ext.extra_compile_args, "-ffp-contract=off"]
    outcome.compiled = True
    return list(extensions)


def main() -> None:
    try:
        choice = choose()
    except ValueError as exc:
        sys.exit(str(exc))
    outcome = Outcome(compiled=False, why=choice.why)
    kwargs: dict[str, Any] = {"cmdclass": _commands(choice, outcome)}
    if BUILDS.intersection(sys.argv[1:]):
        extensions = _extensions(choice, outcome)
        if extensions:
            kwargs["ext_modules"] = extensions
    setup(**kwargs)


main()
