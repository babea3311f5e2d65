"""The PX4 tree the real-stack harness launches: a copy that lost its command
links is run from a shadow with the links back, as often as it is launched."""

from __future__ import annotations

import os
from pathlib import Path

from sitl.lab.realstack.launch import px4_tree


def lost_links_tree(root: Path) -> Path:
    """A PX4 install whose ``px4-*`` command links were copied as text files
    holding ``px4`` (what an archive without symlinks leaves)."""
    root.mkdir()
    launcher = root / "px4-sitl"
    launcher.write_text("#!/bin/sh\n", encoding="utf-8")
    launcher.chmod(0o755)
    tree = root / "px4-1.16.0"
    (tree / "etc").mkdir(parents=True)
    (tree / "bin").mkdir()
    (tree / "bin" / "px4").write_text("binary", encoding="utf-8")
    (tree / "bin" / "px4").chmod(0o755)
    for name in ("px4-param", "px4-commander"):
        (tree / "bin" / name).write_text("px4", encoding="utf-8")
    return launcher


def test_a_tree_with_lost_links_runs_from_a_shadow_with_them_back(tmp_path: Path) -> None:
    launcher = lost_links_tree(tmp_path / "stacks")
    into = tmp_path / "work"
    into.mkdir()
    got = px4_tree(launcher, into)
    assert got == into / "px4-shadow" / "px4-sitl" and os.access(got, os.X_OK)
    bin_dir = into / "px4-shadow" / "px4-1.16.0" / "bin"
    assert os.readlink(bin_dir / "px4-param") == "px4"
    assert (bin_dir / "px4").resolve() == (launcher.parent / "px4-1.16.0" / "bin" / "px4")


def test_a_second_launch_into_the_same_directory_builds_the_shadow_again(
    tmp_path: Path,
) -> None:
    """A second session on one work directory found the first one's shadow and
    stopped on ``FileExistsError``."""
    launcher = lost_links_tree(tmp_path / "stacks")
    into = tmp_path / "work"
    into.mkdir()
    px4_tree(launcher, into)
    (launcher.parent / "px4-1.16.0" / "bin" / "px4-mavlink").write_text("px4", encoding="utf-8")
    got = px4_tree(launcher, into)
    assert os.readlink(got.parent / "px4-1.16.0" / "bin" / "px4-mavlink") == "px4"


def test_a_tree_with_its_links_runs_as_it_is(tmp_path: Path) -> None:
    launcher = lost_links_tree(tmp_path / "stacks")
    probe = launcher.parent / "px4-1.16.0" / "bin" / "px4-param"
    probe.unlink()
    probe.symlink_to("px4")
    assert px4_tree(launcher, tmp_path) == launcher
    assert not (tmp_path / "px4-shadow").exists()
