"""The product imports nothing from the simulator or the lab, nor their libraries.

Each check runs in a fresh interpreter in which ``sitl`` and the lab's libraries
(matplotlib, tqdm, Dask, pyarrow, pandas) cannot be imported, as on a companion
computer's install.
"""

from __future__ import annotations

import pkgutil
import subprocess
import sys
import textwrap
from pathlib import Path

import companion

ROOT = Path(__file__).resolve().parents[1]
LAB_ONLY = ("sitl", "matplotlib", "tqdm", "distributed", "dask", "pyarrow", "pandas")

_BLOCK = textwrap.dedent(
    f"""
    import importlib.abc, sys
    class _Absent(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in {LAB_ONLY!r}:
                raise ModuleNotFoundError(f"No module named {{name!r}} (blocked)", name=name)
            return None
    sys.meta_path.insert(0, _Absent())
    """
)


def _product_modules() -> list[str]:
    names = ["companion"]
    for info in pkgutil.walk_packages(companion.__path__, "companion."):
        if info.name != "companion.__main__":  # it runs the command line
            names.append(info.name)
    return sorted(names)


def _run(code: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", _BLOCK + textwrap.dedent(code)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )


def test_every_product_module_imports_without_the_lab() -> None:
    modules = _product_modules()
    assert {"companion.app", "companion.cli", "companion.control.mfc"} <= set(modules)
    proc = _run(
        f"""
        import importlib, sys
        for name in {modules!r}:
            importlib.import_module(name)
        loaded = sorted(m for m in sys.modules if m.split(".")[0] in {LAB_ONLY!r})
        assert not loaded, loaded
        print(len({modules!r}))
        """
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == str(len(modules))


def test_the_blocker_blocks() -> None:
    """The check above could not pass by accident: the lab really is unimportable."""
    proc = _run("import sitl.lab.simulate")
    assert proc.returncode != 0
    assert "blocked" in proc.stderr


def test_product_commands_work_and_lab_commands_explain_without_the_lab() -> None:
    proc = _run(
        """
        from companion.cli import cli
        try:
            cli(["--help"], prog_name="companion")
        except SystemExit as exc:
            assert exc.code == 0, exc.code
        """
    )
    assert proc.returncode == 0, proc.stderr
    for name in ("run", "check-config", "replay", "fly", "simulate"):
        assert name in proc.stdout
    proc = _run(
        """
        from companion.cli import cli
        cli(["fly", "--duration", "1"], prog_name="companion")
        """
    )
    assert proc.returncode == 1
    assert "lab command" in proc.stderr and "mfc-companion[lab]" in proc.stderr


def test_check_config_fly_without_the_lab_exits_2_saying_what_brings_it() -> None:
    """``--fly`` flies the lab's simulator (the entry point it registers): without the
    lab, nothing is printed but the reason, and the exit is bad input's."""
    proc = _run(
        """
        from companion.cli import cli
        cli(["check-config", "--fly"], prog_name="companion")
        """
    )
    assert proc.returncode == 2, proc.stderr
    assert "check-config --fly flies the bundled simulator" in proc.stderr
    assert "mfc-companion[lab]" in proc.stderr and "Traceback" not in proc.stderr
    assert proc.stdout == ""
