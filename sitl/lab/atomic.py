"""Files the lab writes whole or not at all: a temporary file beside the target,
then ``os.replace``, so a reader (or a run that resumes) never finds one half
written. Used by the campaign's store (:mod:`sitl.lab.campaign_store`), its
outputs (:mod:`sitl.lab.campaign_report`) and the flight tables
(:mod:`sitl.lab.table`).
"""

from __future__ import annotations

import contextlib
import json
import os
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

__all__ = ["replacing", "write_json_atomic"]


@contextlib.contextmanager
def replacing(path: Path) -> Iterator[Path]:
    """A temporary path beside ``path`` to write; it replaces ``path`` (``os.replace``)
    when the block ends without error, and is removed otherwise: ``path`` is whole
    or absent, never half written."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def write_json_atomic(path: Path, obj: Any) -> None:
    """``obj`` as indented JSON at ``path``, whole or not at all (:func:`replacing`)."""
    with replacing(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=1) + "\n", encoding="utf-8")
