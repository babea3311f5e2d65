"""Whether the control modules are compiled, and whether they are current.

``setup.py`` compiles the modules in :data:`MODULES` with mypyc (a wheel, by
default, where a C compiler and the Python headers are present;
``MFC_COMPILE=1`` requires it) and writes ``_compiled.json`` beside them: the
SHA-256 of each source it compiled. Python imports an extension module in
preference to its ``.py``, so an extension left over from before an edit would
silently run the old law; :func:`check_extensions` refuses that.

Every wheel also carries ``_core.json``, what its build did and why;
:data:`CORE` says which core runs, and why when it is the pure one.
"""

from __future__ import annotations

import hashlib
import json
from importlib.machinery import EXTENSION_SUFFIXES
from pathlib import Path

MODULES = ("estimator", "identifier", "intelligent", "mfc", "mixer", "pid", "prefilter", "sticks")
MANIFEST = "_compiled.json"
CORE_RECORD = "_core.json"
"""What a wheel's build did with the core: ``{"compiled": bool, "why": str}``."""


class StaleExtensionError(ImportError):
    """A compiled control module does not match its source."""


def check_extensions(package_dir: Path | None = None) -> bool:
    """True if every control module has a current compiled extension, False if
    none has one; raises :class:`StaleExtensionError` naming the files otherwise
    (an extension built from another source, or only some modules compiled)."""
    here = package_dir or Path(__file__).resolve().parent
    compiled = [m for m in MODULES if any((here / f"{m}{s}").exists() for s in EXTENSION_SUFFIXES)]
    if not compiled:
        return False
    rebuild = "rebuild (MFC_COMPILE=1 pip install ...) or delete the extensions"
    manifest = here / MANIFEST
    try:
        digests = json.loads(manifest.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise StaleExtensionError(
            f"{here}: compiled control modules ({', '.join(compiled)}) but {manifest} "
            f"is unreadable ({exc}); {rebuild}"
        ) from None
    try:
        stale = [
            m
            for m in compiled
            if digests.get(m) != hashlib.sha256((here / f"{m}.py").read_bytes()).hexdigest()
        ]
    except OSError as exc:
        raise StaleExtensionError(
            f"{here}: cannot read a compiled module's source to check it ({exc}); {rebuild}"
        ) from None
    if stale:
        raise StaleExtensionError(
            f"{here}: the compiled {', '.join(stale)} differ from the source "
            f"(changed since {MANIFEST} was written); {rebuild}"
        )
    if len(compiled) != len(MODULES):
        missing = [m for m in MODULES if m not in compiled]
        raise StaleExtensionError(f"{here}: {', '.join(missing)} not compiled; {rebuild}")
    return True


def describe_core(compiled: bool, package_dir: Path | None = None) -> str:
    """One line for a person: which core runs, and why when it is the pure one.

    ``"compiled (mypyc)"``, or ``"pure Python (<why>)"`` with the reason the
    wheel's build recorded (no C compiler, no Python headers, a failed compile,
    ``MFC_COMPILE=0``), or that no wheel built it (a checkout or an editable
    install)."""
    if compiled:
        return "compiled (mypyc)"
    here = package_dir or Path(__file__).resolve().parent
    try:
        record = json.loads((here / CORE_RECORD).read_text(encoding="utf-8"))
        built_compiled, why = bool(record["compiled"]), str(record["why"])
    except (OSError, ValueError, KeyError, TypeError):
        return "pure Python (not installed from a wheel: a checkout or an editable install)"
    if built_compiled:
        return "pure Python (its build compiled the core, but the extensions are missing here)"
    return f"pure Python ({why})"


COMPILED = check_extensions()
"""True when the control modules are mypyc-compiled extensions (all of them)."""

CORE = describe_core(COMPILED)
"""Which control core runs, for a person: ``"compiled (mypyc)"`` or
``"pure Python (<why>)"`` (:func:`describe_core`)."""
