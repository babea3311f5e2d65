"""The documentation site: it builds with ``mkdocs build --strict``, every page is
in the nav, and the generated reference pages match the code."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
import yaml

from tests.file_module import load_file_module

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"
GENERATOR = ROOT / "scripts" / "docs_reference.py"


def _generator() -> ModuleType:
    """``scripts/docs_reference.py`` as a module (scripts/ is not a package)."""
    return load_file_module(GENERATOR)


def _nav_pages(nav: Any) -> list[str]:
    """Every page a ``mkdocs.yml`` nav names, in order."""
    if isinstance(nav, str):
        return [nav]
    if isinstance(nav, list):
        return [p for item in nav for p in _nav_pages(item)]
    if isinstance(nav, dict):
        return [p for value in nav.values() for p in _nav_pages(value)]
    return []


def test_mkdocs_build_strict(tmp_path: Path) -> None:
    """The whole site builds with every warning an error: broken links and
    anchors, links out of docs/, pages left out of the nav (mkdocs.yml's
    ``validation`` makes those warnings)."""
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file",
         str(ROOT / "mkdocs.yml"), "--site-dir", str(tmp_path / "site")],
        cwd=ROOT, capture_output=True, text=True, timeout=120, check=False, env=env,
    )  # fmt: skip
    warnings = [line for line in proc.stderr.splitlines() if "WARNING" in line]
    assert proc.returncode == 0, "\n".join(warnings) or proc.stderr[-3000:]
    assert (tmp_path / "site" / "index.html").is_file()
    assert (tmp_path / "site" / "reference" / "cli" / "index.html").is_file()


def test_every_page_is_in_the_nav() -> None:
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text(encoding="utf-8"))
    in_nav = _nav_pages(config["nav"])
    pages = sorted(p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md"))
    missing = [p for p in pages if p not in in_nav]
    assert not missing, f"pages in docs/ but not in the nav of mkdocs.yml: {missing}"
    absent = [p for p in in_nav if not (DOCS / p).is_file()]
    assert not absent, f"the nav of mkdocs.yml names pages docs/ does not have: {absent}"
    twice = sorted({p for p in in_nav if in_nav.count(p) > 1})
    assert not twice, f"pages in the nav more than once: {twice}"


def test_reference_pages_match_the_code() -> None:
    gen = _generator()
    for rel, text in gen.render().items():
        path = ROOT / rel
        assert path.is_file(), f"{rel} is missing: run `python scripts/docs_reference.py`"
        assert path.read_text(encoding="utf-8") == text, (
            f"{rel} is out of date with the code: run `python scripts/docs_reference.py` "
            "and commit the result"
        )


def test_reference_generation_is_deterministic() -> None:
    gen = _generator()
    assert gen.render() == gen.render()


def test_reference_notes_name_real_fields() -> None:
    """A note for a field that was renamed or removed would silently vanish."""
    assert _generator().unknown_notes() == []


@pytest.mark.parametrize(
    "expected",
    [
        "### `companion run` {#companion-run}",
        "### `companion fly` {#companion-fly}",  # a lab command, imported lazily
        "### `sitl run` {#sitl-run}",
        "| `--engage` | one of `auto`, `rc-switch`, `none` | `rc-switch` |",
        "| `--engage-channel` | integer, 5 <= x <= 18 | `5` |",
    ],
)
def test_cli_reference_covers_the_commands(expected: str) -> None:
    assert expected in _generator().cli_reference()


@pytest.mark.parametrize(
    "expected",
    [
        "### MfcAxisConfig {#controller-mfcaxisconfig}",
        "At `axes.roll.alpha_adapt`, `axes.pitch.alpha_adapt`, `axes.yaw.alpha_adapt`.",
        "| `window_s` | number | required | > 0, <= 0.5 |",
        "### VehicleProfile {#profile-vehicleprofile}",
        "| `motor_idle` | number | `0.05` | >= 0, <= 0.3 |",
        "### Scenario {#scenario-scenario}",
    ],
)
def test_config_reference_covers_the_models(expected: str) -> None:
    assert expected in _generator().config_reference()


def test_the_generator_checks_as_a_script() -> None:
    proc = subprocess.run(
        [sys.executable, str(GENERATOR), "--check"],
        cwd=ROOT, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr


def test_the_generator_names_itself_when_a_page_is_stale(tmp_path: Path) -> None:
    gen = _generator()
    for rel, text in gen.render().items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text + "stale\n", encoding="utf-8")
    assert sorted(gen.stale(tmp_path)) == sorted(gen.render())
