"""The build backend: setuptools', asking for mypy (which brings mypyc) only
when the build compiles the control core (mfc_compile.py decides: by default a
wheel where a C compiler and the Python headers are present, never an editable
install unless ``MFC_COMPILE=1``). A pure-Python build needs nothing beyond
setuptools, so it works offline from a wheel cache and on platforms without a
mypy wheel.

The editable hooks tell ``setup.py`` they are editable (``mfc_compile.EDITABLE_ENV``):
pip calls each hook in a process of its own, and setuptools runs ``setup.py``
inside it."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

from mfc_compile import EDITABLE_ENV, choose
from setuptools import build_meta as _setuptools
from setuptools.build_meta import *  # noqa: F403  (the rest of the PEP 517/660 hooks)

MYPYC = ["mypy>=1.10"]

T = TypeVar("T")


def _compile(*, editable: bool) -> list[str]:
    return MYPYC if choose(editable=editable).compile else []


@contextmanager
def _editable() -> Iterator[None]:
    before = os.environ.get(EDITABLE_ENV)
    os.environ[EDITABLE_ENV] = "1"
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(EDITABLE_ENV, None)
        else:
            os.environ[EDITABLE_ENV] = before


def _as_editable(hook: Callable[..., T], *args: Any, **kwargs: Any) -> T:
    with _editable():
        return hook(*args, **kwargs)


def get_requires_for_build_wheel(config_settings: dict[str, Any] | None = None) -> list[str]:
    return [
        *_setuptools.get_requires_for_build_wheel(config_settings),
        *_compile(editable=False),
    ]


def get_requires_for_build_editable(config_settings: dict[str, Any] | None = None) -> list[str]:
    return [
        *_as_editable(_setuptools.get_requires_for_build_editable, config_settings),
        *_compile(editable=True),
    ]


def prepare_metadata_for_build_editable(
    metadata_directory: str, config_settings: dict[str, Any] | None = None
) -> str:
    return _as_editable(
        _setuptools.prepare_metadata_for_build_editable, metadata_directory, config_settings
    )


def build_editable(
    wheel_directory: str,
    config_settings: dict[str, Any] | None = None,
    metadata_directory: str | None = None,
) -> str:
    return _as_editable(
        _setuptools.build_editable, wheel_directory, config_settings, metadata_directory
    )
