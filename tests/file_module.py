"""A script or build helper that is not in a package, imported as a module."""

from __future__ import annotations

import functools
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

__all__ = ["load_file_module"]


@functools.cache
def load_file_module(path: Path) -> ModuleType:
    """``path`` imported once as a module named after its file (``scripts/`` and
    ``_build/`` are not packages)."""
    spec = importlib.util.spec_from_file_location(path.stem, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while a class is made
    spec.loader.exec_module(module)
    return module
