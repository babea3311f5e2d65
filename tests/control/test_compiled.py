"""The compiled control core's stale-extension guard
(:mod:`companion.control._compiled`), on files laid out by hand: nothing is
compiled or loaded.

The real thing, the core compiled by the wheel's build, runs in
tests/install/test_wheel.py: this directory's tests against it, and a
paper-acro flight flown by it matching the pure-Python one sample for sample
(one build for both, so the suite compiles once).
"""

from __future__ import annotations

import hashlib
import json
import shutil
from importlib.machinery import EXTENSION_SUFFIXES
from pathlib import Path

import pytest

from companion.control._compiled import MANIFEST, MODULES, StaleExtensionError, check_extensions

ROOT = Path(__file__).resolve().parents[2]
SUFFIX = EXTENSION_SUFFIXES[0]


def _package(tmp_path: Path) -> Path:
    """A copy of companion/control's sources (no extension yet)."""
    pkg = tmp_path / "control"
    pkg.mkdir()
    for m in MODULES:
        shutil.copy(ROOT / "companion" / "control" / f"{m}.py", pkg / f"{m}.py")
    return pkg


def _compile(pkg: Path, modules: tuple[str, ...] = MODULES, manifest: bool = True) -> None:
    """Lay out what setup.py leaves: an extension per module and the manifest."""
    for m in modules:
        (pkg / f"{m}{SUFFIX}").write_bytes(b"")
    if manifest:
        digests = {m: hashlib.sha256((pkg / f"{m}.py").read_bytes()).hexdigest() for m in MODULES}
        (pkg / MANIFEST).write_text(json.dumps(digests), encoding="utf-8")


def test_pure_python_is_not_compiled(tmp_path: Path) -> None:
    assert check_extensions(_package(tmp_path)) is False


def test_current_extensions_are_compiled(tmp_path: Path) -> None:
    pkg = _package(tmp_path)
    _compile(pkg)
    assert check_extensions(pkg) is True


def test_an_edited_source_refuses_its_old_extension(tmp_path: Path) -> None:
    pkg = _package(tmp_path)
    _compile(pkg)
    with (pkg / "mfc.py").open("a", encoding="utf-8") as f:
        f.write("\n# an edit\n")
    with pytest.raises(StaleExtensionError, match=r"the compiled mfc differ from the source"):
        check_extensions(pkg)


def test_an_extension_without_its_manifest_is_refused(tmp_path: Path) -> None:
    pkg = _package(tmp_path)
    _compile(pkg, manifest=False)
    with pytest.raises(StaleExtensionError, match=rf"{MANIFEST} is unreadable"):
        check_extensions(pkg)


def test_an_extension_without_its_source_is_refused(tmp_path: Path) -> None:
    pkg = _package(tmp_path)
    _compile(pkg)
    (pkg / "pid.py").unlink()
    with pytest.raises(StaleExtensionError, match=r"cannot read a compiled module's source"):
        check_extensions(pkg)


def test_some_modules_compiled_and_others_not_is_refused(tmp_path: Path) -> None:
    pkg = _package(tmp_path)
    _compile(pkg, modules=("mfc", "mixer"))
    missing = ", ".join(m for m in MODULES if m not in ("mfc", "mixer"))
    with pytest.raises(StaleExtensionError, match=rf"{missing} not compiled"):
        check_extensions(pkg)
