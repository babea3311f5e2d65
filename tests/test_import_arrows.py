"""Imports go one way: the product imports nothing of the simulator or the lab, the
scripts import the package, never the tests, and no module of ``companion/``,
``sitl/`` or ``scripts/`` comes back to itself through its imports.

Read from the source with :mod:`ast` (an ``import`` statement, or
``importlib.import_module`` / ``__import__`` of a literal name), so a comment or a
docstring that names a module counts for nothing, while an import under
``TYPE_CHECKING`` or inside a function counts as any other. What the product finds
of the lab at run time it finds through the entry points the lab registers
(:mod:`companion.lab`). And every product module stays under 500 lines.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def imported(path: Path) -> Iterator[tuple[int, str]]:
    """Each module ``path`` imports, with its line: absolute names only (a relative
    import stays inside its own package)."""
    for line, candidates in import_candidates(path, None):
        yield line, candidates[-1]


def import_candidates(path: Path, package: str | None) -> Iterator[tuple[int, tuple[str, ...]]]:
    """What each import in ``path`` may name, with its line, the likeliest module first:
    ``from m import a`` may import the module ``m.a`` or a name of ``m``. Relative
    imports are resolved against ``package`` (the dotted package ``path`` is in), or
    left out when it is None."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, (alias.name,)
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0 and node.module is not None:
                base = node.module
            elif node.level > 0 and package is not None:
                parts = package.split(".")
                parts = parts[: len(parts) - (node.level - 1)]
                base = ".".join([*parts, *([node.module] if node.module else [])])
            else:
                continue
            if package is None:
                yield node.lineno, (base,)
                continue
            for alias in node.names:
                yield node.lineno, (f"{base}.{alias.name}", base)
        elif isinstance(node, ast.Call) and node.args:
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
            first = node.args[0]
            if (
                name in ("import_module", "__import__")
                and isinstance(first, ast.Constant)
                and isinstance(first.value, str)
            ):
                yield node.lineno, (first.value,)


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


def module_name(path: Path, root: Path) -> str:
    """The dotted name of ``path`` under ``root`` (a package's ``__init__.py`` is the
    package; a script without a ``.py`` suffix is named by its file)."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    if path.suffix != ".py":
        parts[-1] = path.name
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def import_graph(files: list[Path], root: Path) -> dict[str, dict[str, int]]:
    """Module -> the modules among ``files`` it imports -> the first line that does.

    ``import a.b`` and ``from a.b import c`` are arrows to ``a.b`` (or to ``a.b.c``
    when that is a module), not to the packages ``a`` and ``a.b`` Python also runs
    on the way: those would tie every package to its own submodules."""
    names = {module_name(p, root): p for p in files}
    graph: dict[str, dict[str, int]] = {}
    for name, path in names.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        arrows = graph.setdefault(name, {})
        for line, candidates in import_candidates(path, package):
            target = next((c for c in candidates if c in names), None)
            if target is not None and target != name:
                arrows.setdefault(target, line)
    return graph


def circles(graph: dict[str, dict[str, int]]) -> list[set[str]]:
    """The import circles of ``graph``: each set of two or more modules every one of
    which reaches every other (its strongly connected components, Tarjan's)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[set[str]] = []
    for start in sorted(graph):
        if start in index:
            continue
        # Iterative depth-first search: (node, its unvisited successors).
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, successors = work[-1]
            for nxt in successors:
                if nxt not in index:
                    index[nxt] = low[nxt] = len(index)
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(sorted(graph[nxt]))))
                    break
                if nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component: set[str] = set()
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.add(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        found.append(component)
    return found


def describe(circle: set[str], graph: dict[str, dict[str, int]], files: dict[str, str]) -> str:
    """A circle's arrows, one a line: ``file:line -> file``."""
    return "\n".join(
        f"  {files[a]}:{graph[a][b]} -> {files[b]}"
        for a in sorted(circle)
        for b in sorted(graph[a])
        if b in circle
    )


def circle_problems(files: list[Path], root: Path, known: set[frozenset[str]]) -> list[str]:
    """What is wrong with the imports among ``files``: each circle not in ``known``
    (named by its arrows), and each entry of ``known`` that is no longer a circle
    (its files, relative to ``root``)."""
    graph = import_graph(files, root)
    where = {module_name(p, root): p.relative_to(root).as_posix() for p in files}
    found = {frozenset(where[m] for m in c): c for c in circles(graph)}
    return [
        "import circle (each arrow: file:line -> file):\n" + describe(c, graph, where)
        for k, c in sorted(found.items(), key=lambda kc: sorted(kc[0]))
        if k not in known
    ] + [
        f"no longer a circle, remove it from _KNOWN_CIRCLES: {sorted(k)}"
        for k in sorted(known, key=sorted)
        if k not in found
    ]


_KNOWN_CIRCLES: set[frozenset[str]] = set()
"""Import circles tolerated while someone takes them apart, each as the set of its
files relative to the repository (``frozenset({"companion/a.py", "companion/b.py"})``),
with a comment saying who removes it. Empty: there is none. An entry that no longer
names a circle fails the test, so the list cannot go stale."""


def test_no_module_comes_back_to_itself() -> None:
    files = [
        *sorted((ROOT / "companion").rglob("*.py")),
        *sorted((ROOT / "sitl").rglob("*.py")),
        *python_scripts(),
    ]
    assert len(files) > 100
    problems = circle_problems(files, ROOT, _KNOWN_CIRCLES)
    assert not problems, "\n\n".join(problems)


def test_the_circle_check_sees_each_kind_of_import(tmp_path: Path) -> None:
    """A circle closed by a ``TYPE_CHECKING`` import, one closed in a function and one
    closed by a relative import are found; one-way arrows and a package's own
    ``__init__`` importing its submodule are not circles. A known circle passes; a
    known one that is gone does not."""
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    sources = {
        "__init__.py": "from pkg.a import A\n",
        "a.py": "from pkg.b import B\nA = 1\n",
        "b.py": "import typing\nif typing.TYPE_CHECKING:\n    from pkg.a import A\n",
        "c.py": "import pkg.sub.d\n",
        "sub/__init__.py": "",
        "sub/d.py": "def f():\n    from pkg import c\n",
        "e.py": "from .sub import f\nimport numpy\n",
        "sub/f.py": "from .. import e\n",
        "g.py": "import pkg.a\nimportlib.import_module('pkg.sub.d')\n",
    }
    for name, text in sources.items():
        (pkg / name).write_text(text, encoding="utf-8")
    files = sorted(pkg.rglob("*.py"))
    graph = import_graph(files, tmp_path)
    assert graph["pkg.g"] == {"pkg.a": 1, "pkg.sub.d": 2}
    assert sorted(sorted(c) for c in circles(graph)) == [
        ["pkg.a", "pkg.b"],
        ["pkg.c", "pkg.sub.d"],
        ["pkg.e", "pkg.sub.f"],
    ]
    known = {
        frozenset({"pkg/a.py", "pkg/b.py"}),
        frozenset({"pkg/c.py", "pkg/sub/d.py"}),
        frozenset({"pkg/e.py", "pkg/g.py"}),
    }
    assert circle_problems(files, tmp_path, known) == [
        "import circle (each arrow: file:line -> file):\n"
        "  pkg/e.py:1 -> pkg/sub/f.py\n"
        "  pkg/sub/f.py:1 -> pkg/e.py",
        "no longer a circle, remove it from _KNOWN_CIRCLES: ['pkg/e.py', 'pkg/g.py']",
    ]


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


def test_every_product_module_is_under_500_lines() -> None:
    """A module a reader holds whole: the house's own rule for ``companion/``."""
    long = {
        str(p.relative_to(ROOT)): n
        for p in sorted((ROOT / "companion").rglob("*.py"))
        if (n := len(p.read_text(encoding="utf-8").splitlines())) >= 500
    }
    assert not long, long
