"""The optional compiled control core (``MFC_COMPILE=1``, see ``setup.py``).

Two parts:

* the stale-extension guard (:mod:`companion.control._compiled`), on files
  laid out by hand: nothing is compiled or loaded;
* the real thing: ``setup.py build_ext --inplace`` on a copy of the project,
  then, in a fresh interpreter on that copy, this directory's tests run against
  the extensions, and a paper-acro flight flown by them matches the pure-Python
  flight sample for sample.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from importlib.machinery import EXTENSION_SUFFIXES
from pathlib import Path

import numpy as np
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


# ----------------------------------------------------------------- the real build

FLIGHT = """
import sys
import numpy as np
from pathlib import Path
import companion.control as control
from companion.config import load_controller
from companion.profile import load_profile
from sitl.lab.simulate import simulate_flight
from sitl.scenario import load_scenario

sc = load_scenario("paper-acro").model_copy(update={"duration_s": 8.0})
profile = load_profile(Path(sys.argv[1]) / "vehicle_profiles" / "f450_cut_props.yaml")
rec = simulate_flight(profile, load_controller(), sc)
np.savez(sys.argv[2], compiled=control.COMPILED, mfc=control.mfc.__file__,
         **{k: v for k, v in rec.columns.items() if v.dtype.kind in "fiub"})
"""


@pytest.fixture(scope="module")
def compiled_copy(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A copy of the project with its control core compiled in place by setup.py."""
    copy = tmp_path_factory.mktemp("compiled")
    for name in ("setup.py", "pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, copy / name)
    ignore = shutil.ignore_patterns("__pycache__", "*.so", MANIFEST)
    # (_build: setup.py imports its compile decision from there)
    for name in ("_build", "companion", "sitl", "tests", "vehicle_profiles"):
        shutil.copytree(ROOT / name, copy / name, ignore=ignore)
    env = {**os.environ, "MFC_COMPILE": "1"}
    build = subprocess.run(
        [sys.executable, "setup.py", "-q", "build_ext", "--inplace"],
        cwd=copy, env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    return copy


def _in(copy: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """Run Python in ``copy``, importing the project from there (not from ROOT)."""
    env = {**os.environ, "PYTHONPATH": str(copy)}
    return subprocess.run(
        [sys.executable, *args], cwd=copy, env=env, capture_output=True, text=True, timeout=600
    )


def test_the_control_tests_pass_on_the_compiled_core(compiled_copy: Path) -> None:
    # pytest.main in an interpreter that has just imported the compiled core (and
    # said so), so the tests run against it.
    main = (
        "import sys, pytest, companion.control as c; print('compiled', c.COMPILED); "
        "sys.exit(pytest.main(['-q', '-p', 'no:cacheprovider', 'tests/control', "
        "'--deselect', 'tests/control/test_compiled.py']))"
    )
    run = _in(compiled_copy, "-c", main)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]
    assert run.stdout.startswith("compiled True"), run.stdout[:200]
    assert " passed" in run.stdout.splitlines()[-1], run.stdout[-500:]


def test_a_compiled_flight_matches_the_pure_python_one(compiled_copy: Path, tmp_path: Path) -> None:
    script = tmp_path / "flight.py"
    script.write_text(FLIGHT, encoding="utf-8")
    runs = {}
    for name, copy in (("compiled", compiled_copy), ("pure", ROOT)):
        out = tmp_path / f"{name}.npz"
        run = _in(copy, str(script), str(ROOT), str(out))
        assert run.returncode == 0, run.stderr[-3000:]
        runs[name] = np.load(out)
    compiled, pure = runs["compiled"], runs["pure"]
    assert bool(compiled["compiled"]) and str(compiled["mfc"]).endswith(SUFFIX)
    assert not bool(pure["compiled"]) and str(pure["mfc"]).endswith(".py")
    keys = set(pure.files) - {"compiled", "mfc"}
    assert keys == set(compiled.files) - {"compiled", "mfc"}
    assert len(pure["t_s"]) > 1500  # 8 s at 250 Hz
    for k in sorted(keys):
        np.testing.assert_array_equal(compiled[k], pure[k], err_msg=k)
