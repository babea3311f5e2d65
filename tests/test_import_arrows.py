"""Imports go one way: the product imports nothing of the simulator or the lab, and the
scripts import the package, never the tests.

Read from the source with :mod:`ast` (an ``import`` statement, or
``importlib.import_module`` / ``__import__`` of a literal name), so a comment or a
docstring that names a module counts for nothing. What the product finds of the lab
at run time it finds through the entry points the lab registers (:mod:`companion.lab`).
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def imported(path: Path) -> Iterator[tuple[int, str]]:
    """Each module ``path`` imports, with its line: absolute names only (a relative
    import stays inside its own package)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0 and node.module is not None:
                yield node.lineno, node.module
        elif isinstance(node, ast.Call) and node.args:
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
            first = node.args[0]
            if (
                name in ("import_module", "__import__")
                and isinstance(first, ast.Constant)
                and isinstance(first.value, str)
            ):
                yield node.lineno, first.value


def offences(files: list[Path], banned: str) -> list[str]:
    return [
        f"{path.relative_to(ROOT)}:{line}: imports {name}"
        for path in files
        for line, name in imported(path)
        if name == banned or name.startswith(banned + ".")
    ]


def python_scripts() -> list[Path]:
    """Every Python file in ``scripts/``: by its suffix or its ``#!`` line."""
    found = []
    for path in sorted((ROOT / "scripts").iterdir()):
        if not path.is_file():
            continue
        if path.suffix == ".py" or path.read_bytes()[:64].split(b"\n")[0].find(b"python") > 0:
            found.append(path)
    return found


def test_the_product_imports_nothing_of_the_simulator() -> None:
    files = sorted((ROOT / "companion").rglob("*.py"))
    assert len(files) > 40
    assert offences(files, "sitl") == []


def test_the_scripts_import_nothing_of_the_tests() -> None:
    files = python_scripts()
    assert {"fuzz.py", "reproduce_paper.py"} <= {p.name for p in files}
    assert offences(files, "tests") == []


def test_the_check_sees_each_kind_of_import(tmp_path: Path) -> None:
    """What the two tests above would catch, and what they leave alone."""
    src = tmp_path / "m.py"
    src.write_text(
        '"""import sitl in a docstring."""\n'
        "# from sitl import x (a comment)\n"
        "import sitl.lab\n"
        "from sitl.runner import Runner\n"
        "import importlib\n"
        "importlib.import_module('sitl.lab.cli')\n"
        "__import__('sitl')\n"
        "from .sitl import y\n"
        "import sitlike\n",
        encoding="utf-8",
    )
    assert [line for line, name in imported(src) if name.split(".")[0] == "sitl"] == [3, 4, 6, 7]
