"""Optional compiled control core.

``pip install .`` installs pure Python. With ``MFC_COMPILE=1`` in the
environment, the control laws (``companion/control``: estimator, identifier,
the intelligent controllers, the MFC assembly, mixer, PID, prefilter, sticks)
are also compiled to C extensions with mypyc, from the same typed
source; nothing else changes. Beside them goes ``_compiled.json``, the SHA-256
of each source compiled, so that ``companion.control`` refuses to import an
extension whose source has changed since (README, "A compiled control core").
Everything else about the package is in ``pyproject.toml``.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
from pathlib import Path

from setuptools import setup
from setuptools.command.build_ext import build_ext

# = companion.control._compiled.MODULES
CONTROL = ("estimator", "identifier", "intelligent", "mfc", "mixer", "pid", "prefilter", "sticks")
# (not imported: that package checks its extensions on import; a module missing
# here makes the check refuse the build, and tests/control/test_compiled.py fail)
HERE = Path(__file__).resolve().parent


class BuildExtWithManifest(build_ext):
    def run(self) -> None:
        super().run()
        src = HERE / "companion" / "control"
        digests = {m: hashlib.sha256((src / f"{m}.py").read_bytes()).hexdigest() for m in CONTROL}
        dest = (HERE if self.inplace else Path(self.build_lib)) / "companion" / "control"
        dest.mkdir(parents=True, exist_ok=True)
        (dest / "_compiled.json").write_text(json.dumps(digests, indent=1) + "\n")


kwargs = {}
try:
    from mypyc.build import mypycify
except ImportError:
    mypycify = None
if os.environ.get("MFC_COMPILE") == "1" and mypycify is None and "egg_info" not in sys.argv:
    # (egg_info: the backend asking what the build needs, before mypy is there)
    sys.exit("MFC_COMPILE=1: the compiled control core needs mypy (mypyc): pip install mypy")
if os.environ.get("MFC_COMPILE") == "1" and mypycify is not None:
    # One shared library for the control modules, named after the package.
    # No config file: the project's (pyproject.toml) loads the pydantic plugin,
    # which the build environment lacks; the control modules need neither.
    extensions = mypycify(
        ["--config-file", os.devnull, *(f"companion/control/{m}.py" for m in CONTROL)],
        opt_level="3",
        group_name="companion_control",
    )
    for ext in extensions:
        # No fused multiply-add (gcc contracts a*b+c where the CPU has FMA, as on
        # the Raspberry Pi's aarch64): every operation rounds as Python's does, so
        # the compiled law computes the same floats as the pure one.
        ext.extra_compile_args = [*ext.extra_compile_args, "-ffp-contract=off"]
    kwargs = {"ext_modules": extensions, "cmdclass": {"build_ext": BuildExtWithManifest}}

setup(**kwargs)
