"""Whether a build compiles the control core (``_build/mfc_compile.py``), and what
``companion.control.CORE`` says afterwards (``companion/control/_compiled.py``).

The real builds are in test_wheel.py (the default wheel) and
tests/control/test_compiled.py (``MFC_COMPILE=1``, in place)."""

from __future__ import annotations

import json
import sys
import sysconfig
from pathlib import Path
from types import ModuleType

import pytest

from companion.control._compiled import CORE_RECORD, describe_core
from tests.file_module import load_file_module

ROOT = Path(__file__).resolve().parents[2]


def _mfc_compile() -> ModuleType:
    """``_build/mfc_compile.py``: what the build decides on this machine."""
    return load_file_module(ROOT / "_build" / "mfc_compile.py")


@pytest.fixture
def mc(monkeypatch: pytest.MonkeyPatch) -> ModuleType:
    """The module, with MFC_COMPILE and the editable flag unset."""
    module = _mfc_compile()
    monkeypatch.delenv(module.ENV, raising=False)
    monkeypatch.delenv(module.EDITABLE_ENV, raising=False)
    return module


def _toolchain(monkeypatch: pytest.MonkeyPatch, mc: ModuleType, problem: str | None) -> None:
    monkeypatch.setattr(mc, "toolchain_problem", lambda: problem)


def test_a_wheel_is_compiled_where_the_toolchain_is(
    mc: ModuleType, monkeypatch: pytest.MonkeyPatch
) -> None:
    _toolchain(monkeypatch, mc, None)
    choice = mc.choose(editable=False)
    assert (choice.compile, choice.required, choice.fallback) == (True, False, False)


def test_a_wheel_without_the_toolchain_falls_back_with_a_warning(
    mc: ModuleType, monkeypatch: pytest.MonkeyPatch
) -> None:
    _toolchain(monkeypatch, mc, "no C compiler: 'gcc' is not on PATH")
    choice = mc.choose(editable=False)
    assert (choice.compile, choice.fallback) == (False, True)
    assert choice.why == "no C compiler: 'gcc' is not on PATH"


def test_an_editable_install_stays_pure_python(
    mc: ModuleType, monkeypatch: pytest.MonkeyPatch
) -> None:
    _toolchain(monkeypatch, mc, None)
    assert not mc.choose(editable=True).compile
    monkeypatch.setenv(mc.EDITABLE_ENV, "1")  # as the backend's editable hooks set it
    choice = mc.choose()
    assert (choice.compile, choice.fallback) == (False, False)
    assert "editable install" in choice.why


@pytest.mark.parametrize("editable", [False, True])
def test_mfc_compile_1_requires_the_compiled_core(
    mc: ModuleType, monkeypatch: pytest.MonkeyPatch, editable: bool
) -> None:
    _toolchain(monkeypatch, mc, "no C compiler")  # setup.py then fails, naming it
    monkeypatch.setenv(mc.ENV, "1")
    choice = mc.choose(editable=editable)
    assert (choice.compile, choice.required) == (True, True)


def test_mfc_compile_0_builds_pure_python_without_a_warning(
    mc: ModuleType, monkeypatch: pytest.MonkeyPatch
) -> None:
    _toolchain(monkeypatch, mc, None)
    monkeypatch.setenv(mc.ENV, "0")
    choice = mc.choose(editable=False)
    assert (choice.compile, choice.fallback, choice.why) == (
        False,
        False,
        "MFC_COMPILE=0 at build time",
    )


@pytest.mark.parametrize("value", ["yes", "true", "2"])
def test_another_mfc_compile_is_refused(
    mc: ModuleType, monkeypatch: pytest.MonkeyPatch, value: str
) -> None:
    monkeypatch.setenv(mc.ENV, value)
    with pytest.raises(ValueError, match=rf"MFC_COMPILE='{value}': expected 1"):
        mc.choose(editable=False)


def _include(monkeypatch: pytest.MonkeyPatch, folder: Path) -> None:
    paths = sysconfig.get_paths()
    monkeypatch.setattr(sysconfig, "get_paths", lambda: {**paths, "include": str(folder)})


def test_the_toolchain_needs_the_compiler_on_path(
    mc: ModuleType, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    (tmp_path / "Python.h").write_text("", encoding="utf-8")
    _include(monkeypatch, tmp_path)
    monkeypatch.setenv("CC", "/nonexistent/cc -pthread")
    assert mc.toolchain_problem() == (
        "no C compiler: '/nonexistent/cc' is not on PATH (Debian, Ubuntu, Raspberry Pi OS: "
        "apt install build-essential)"
    )
    monkeypatch.setenv("CC", f"{sys.executable} -pthread")  # any executable stands in
    assert mc.toolchain_problem() is None


def test_the_toolchain_needs_a_configured_compiler(
    mc: ModuleType, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("CC", raising=False)
    monkeypatch.setattr(sysconfig, "get_config_var", lambda name: None)
    problem = mc.toolchain_problem()
    assert problem is not None and problem.startswith("no C compiler configured")


def test_the_toolchain_needs_the_python_headers(
    mc: ModuleType, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("CC", sys.executable)
    _include(monkeypatch, tmp_path)
    assert mc.toolchain_problem() == (
        f"no Python headers: {tmp_path / 'Python.h'} is missing (Debian, Ubuntu, "
        "Raspberry Pi OS: apt install python3-dev)"
    )


# ------------------------------------------------------ what runs, afterwards


def _record(folder: Path, compiled: bool, why: str) -> Path:
    (folder / CORE_RECORD).write_text(json.dumps({"compiled": compiled, "why": why}))
    return folder


def test_the_compiled_core_says_so(tmp_path: Path) -> None:
    assert describe_core(True, tmp_path) == "compiled (mypyc)"


def test_a_pure_wheel_says_why(tmp_path: Path) -> None:
    why = "no Python headers: /usr/include/python3.11/Python.h is missing"
    assert describe_core(False, _record(tmp_path, False, why)) == f"pure Python ({why})"


def test_a_checkout_says_it_is_not_a_wheel(tmp_path: Path) -> None:
    assert describe_core(False, tmp_path) == (
        "pure Python (not installed from a wheel: a checkout or an editable install)"
    )
    (tmp_path / CORE_RECORD).write_text("{not json")
    assert describe_core(False, tmp_path).startswith("pure Python (not installed from a wheel")


def test_a_compiled_wheel_whose_extensions_are_gone_says_so(tmp_path: Path) -> None:
    text = describe_core(False, _record(tmp_path, True, "a C compiler and the Python headers"))
    assert text == "pure Python (its build compiled the core, but the extensions are missing here)"
