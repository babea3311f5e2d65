"""The bundled SITL's autopilots are not the product's code.

The plant's personalities fly their own rate loops and mixers
(``sitl.px4_control``, ``sitl.ardupilot_control``): nothing in ``sitl`` outside
the lab imports ``companion.control``, so a bug or a tuning choice in the product
cannot hide on both sides of a test (docs/architecture.md, "Who may import whom").
"""

from __future__ import annotations

import ast
from pathlib import Path

SITL = Path(__file__).resolve().parents[2] / "sitl"


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found.update(f"{node.module}.{a.name}" for a in node.names)
    return found


def test_the_plant_imports_nothing_from_the_product_laws() -> None:
    files = [p for p in SITL.rglob("*.py") if "lab" not in p.relative_to(SITL).parts]
    assert len(files) > 30
    offenders = {
        str(p.relative_to(SITL.parent)): sorted(
            m for m in _imports(p) if m == "companion.control" or m.startswith("companion.control.")
        )
        for p in files
    }
    assert {k: v for k, v in offenders.items() if v} == {}


def test_the_check_sees_an_import() -> None:
    probe = SITL.parent / "tests" / "sitl" / "_probe_import.py"
    try:
        probe.write_text("from companion.control.mixer import Mixer\n")
        assert "companion.control.mixer" in _imports(probe)
    finally:
        probe.unlink()
