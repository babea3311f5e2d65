"""``companion campaign --grid FILE``: a campaign file, and the lazy grid behind it."""

from __future__ import annotations

import itertools
import json
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from companion.cli import cli
from companion.config import load_controller
from companion.profile import load_profile
from sitl.lab.campaign import Grid, build_grid
from sitl.lab.campaign_file import (
    MAX_FLIGHTS,
    load_campaign_file,
    resolve_controller,
    resolve_profile,
)
from sitl.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "companion" / "data"


def _records(out: Path) -> list[dict]:  # type: ignore[type-arg]
    doc = json.loads((out / "campaign.json").read_text(encoding="utf-8"))
    return [{k: v for k, v in r.items() if k != "wall_time_s"} for r in doc["records"]]


@pytest.mark.long
def test_a_campaign_file_flies_the_grid_its_options_would(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    camp = tmp_path / "study"
    (camp / "vehicles").mkdir(parents=True)
    shutil.copy(ROOT / "vehicle_profiles" / "x500.yaml", camp / "vehicles" / "x500.yaml")
    shutil.copy(DATA / "mfc_default.yaml", camp / "mfc_default.yaml")
    (camp / "grid.yaml").write_text(
        "# files beside this one\n"
        "profiles: [f450, vehicles/x500.yaml]\n"
        "controllers: [mfc_default.yaml, pid_tarot_tuned]\n"
        "damage: [0.8]\ngust_sigma_m_s: [1.0]\nseeds: {first: 1000, count: 1}\n"
        "duration_s: 2\noracle: false\n",
        encoding="utf-8",
    )
    monkeypatch.chdir(tmp_path)  # the file's own names are read beside it, not here
    run = CliRunner().invoke(
        cli,
        ["campaign", "--grid", "study/grid.yaml", "--out", "by-file", "--workers", "1",
         "--no-progress"],
        catch_exceptions=False,
    )  # fmt: skip
    assert run.exit_code == 0, run.output
    by_options = CliRunner().invoke(
        cli,
        ["campaign", "--out", "by-options", "--workers", "1", "--no-progress",
         "--profiles", "f450", "--profiles", str(ROOT / "vehicle_profiles" / "x500.yaml"),
         "--controllers", f"{DATA / 'mfc_default.yaml'},{DATA / 'pid_tarot_tuned.yaml'}",
         "--damage", "0.8", "--gusts", "1.0", "--seeds", "1", "--duration", "2",
         "--no-oracle"],
        catch_exceptions=False,
    )  # fmt: skip
    assert by_options.exit_code == 0, by_options.output
    a, b = _records(tmp_path / "by-file"), _records(tmp_path / "by-options")
    assert len(a) == 4 and all(r["error"] is None for r in a)
    assert a == b  # the same flights, ids and figures
    meta = json.loads((tmp_path / "by-file" / "campaign.json").read_text(encoding="utf-8"))
    assert meta["meta"]["grid_file"] == "study/grid.yaml"


def test_a_bad_campaign_file_names_its_fields_and_starts_nothing(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("damage: [1.2]\nseeds: {first: 1, count: 0}\nseedz: 3\n", encoding="utf-8")
    out = tmp_path / "out"
    run = CliRunner().invoke(cli, ["campaign", "--grid", str(bad), "--out", str(out)])
    assert run.exit_code == 2
    text = run.output
    assert str(bad) in text
    assert "damage: expected efficiencies in (0, 1]" in text
    assert "seeds.range.count" in text and "seedz: unknown key" in text
    assert not out.exists()


def test_the_grid_is_in_the_file_or_in_the_options_not_both(tmp_path: Path) -> None:
    f = tmp_path / "grid.yaml"
    f.write_text("seeds: [1, 2]\n", encoding="utf-8")
    run = CliRunner().invoke(
        cli, ["campaign", "--grid", str(f), "--seeds", "3", "--link", "uart", "--out",
              str(tmp_path / "out")]
    )  # fmt: skip
    assert run.exit_code == 2
    assert "--grid" in run.output and "drop --seeds, --link" in run.output
    assert not (tmp_path / "out").exists()


def test_a_grid_beyond_the_limit_is_refused_before_any_flight(tmp_path: Path) -> None:
    f = tmp_path / "huge.yaml"
    f.write_text(f"seeds: {{first: 0, count: {MAX_FLIGHTS}}}\n", encoding="utf-8")
    assert load_campaign_file(f).seed_values() == range(MAX_FLIGHTS)
    run = CliRunner().invoke(cli, ["campaign", "--grid", str(f), "--out", str(tmp_path / "o")])
    assert run.exit_code == 2 and "over 10,000,000" in run.output


def test_the_lazy_grid_is_the_built_grid_and_holds_only_its_axes() -> None:
    profiles = {
        n: load_profile(ROOT / "vehicle_profiles" / f"{n}.yaml", simulated=True)
        for n in ("f450", "x500")
    }
    ctrl = {"mfc": load_controller(), "pid": load_controller(DATA / "pid_tarot_tuned.yaml")}
    sc = load_scenario("train-acro")
    axes = {"damages": (1.0, 0.7), "gusts_m_s": (0.0, 2.0), "seeds": range(5, 8),
            "duration_s": 3.0}  # fmt: skip
    built, lazy = build_grid(profiles, ctrl, sc, **axes), Grid(profiles, ctrl, sc, **axes)
    assert len(lazy) == len(built) == 2 * 2 * 2 * 3 * 2

    def key(s: object) -> tuple:  # type: ignore[type-arg]
        return tuple(getattr(s, f) for f in ("profile_name", "damage", "gust_sigma_m_s",
                                             "seed", "controller_name"))  # fmt: skip

    assert [key(s) for s in lazy] == [key(s) for s in built]
    assert [key(s) for s in lazy] == [key(s) for s in lazy]  # each pass, the same order
    huge = Grid(profiles, ctrl, sc, seeds=range(10**9))
    assert len(huge) == 2 * 3 * 2 * 10**9 * 2
    first = list(itertools.islice(huge, 3))  # built one at a time, never all
    assert [s.seed for s in first] == [0, 0, 1]


@pytest.mark.parametrize("path", sorted((ROOT / "campaigns").glob("*.yaml")), ids=lambda p: p.name)
def test_the_shipped_campaign_files_load(path: Path) -> None:
    cf = load_campaign_file(path)
    assert len(cf.seed_values()) >= 1 and cf.profiles and cf.controllers
    for name in cf.profiles:
        assert resolve_profile(name, path.parent).is_file(), name
    for name in cf.controllers:
        assert Path(resolve_controller(name, path.parent)).is_file(), name
