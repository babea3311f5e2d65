"""The build backend: setuptools', asking for mypy (which brings mypyc) only
when ``MFC_COMPILE=1`` asks for the compiled control core (setup.py). A plain
``pip install .`` needs nothing beyond setuptools, so it works offline from a
wheel cache and on platforms without a mypy wheel."""

from __future__ import annotations

import os
from typing import Any

from setuptools import build_meta as _setuptools
from setuptools.build_meta import *  # noqa: F403  (the rest of the PEP 517/660 hooks)

MYPYC = ["mypy>=1.10"]


def _compile() -> list[str]:
    return MYPYC if os.environ.get("MFC_COMPILE") == "1" else []


def get_requires_for_build_wheel(config_settings: dict[str, Any] | None = None) -> list[str]:
    return [*_setuptools.get_requires_for_build_wheel(config_settings), *_compile()]


def get_requires_for_build_editable(config_settings: dict[str, Any] | None = None) -> list[str]:
    return [*_setuptools.get_requires_for_build_editable(config_settings), *_compile()]
