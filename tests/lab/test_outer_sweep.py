"""The outer-loop sweep (sitl/lab/outer_sweep.py): crashes classified by the
true-state flights, the summary's counts, and one small run through the executor."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pandas
import pyarrow as pa
import pyarrow.parquet
import pytest

from sitl.lab.campaign_store import _digest
from sitl.lab.outer_sweep import (
    classify,
    flight_key,
    main,
    summary_markdown,
    sweep_flights,
    true_state_flights,
    vehicles,
)
from sitl.lab.table import OUTER_SWEEP_FIGURES, OUTER_SWEEP_SCHEMA, outer_sweep_table

ROOT = Path(__file__).resolve().parents[2]


def _rec(law: str, crashed: bool, *, true_state: bool = False, scenario: str = "square",
         h: float = 1.0, seed: int = 20200318) -> dict[str, Any]:  # fmt: skip
    return {
        "vehicle": "f450", "damage": "motor60", "scenario": scenario, "law": law, "seed": seed,
        "true_state": true_state, "crashed": crashed, "pos_rms_h_m": h, "pos_rms_v_m": 0.1,
        "path_rms_m": None, "att_mae_deg": 2.0, "yaw_mae_deg": 1.0,
    }  # fmt: skip


def test_a_case_is_feasible_when_either_law_survives_on_the_true_state() -> None:
    k = ("f450", "motor60", "square", 20200318)
    # Nobody crashed: feasible without a true-state flight.
    assert classify([_rec("mfc", False), _rec("px4", False)])[k]["feasible"] is True
    # MFC crashed, PX4 on the true state survived: feasible, and MFC's crash counts.
    recs = [_rec("mfc", True), _rec("px4", False),
            _rec("mfc", True, true_state=True), _rec("px4", False, true_state=True)]  # fmt: skip
    assert classify(recs)[k]["feasible"] is True
    text = summary_markdown(recs)
    assert "**MFC crashes on a feasible case: 1**: f450/motor60/square" in text
    # Both crash on the true state too: infeasible, in its own line, not counted.
    recs = [_rec("mfc", True), _rec("px4", True),
            _rec("mfc", True, true_state=True), _rec("px4", True, true_state=True)]  # fmt: skip
    assert classify(recs)[k]["feasible"] is False
    text = summary_markdown(recs)
    assert "**MFC crashes on a feasible case: 0**" in text
    assert "- Infeasible: f450/motor60/square" in text
    # A crash whose true-state flights are missing is unknown, not feasible.
    assert classify([_rec("mfc", True), _rec("px4", False)])[k]["feasible"] is None


def test_the_table_has_a_row_per_flight_with_its_cases_feasibility() -> None:
    recs = [_rec("mfc", True), _rec("px4", False),
            _rec("mfc", True, true_state=True), _rec("px4", False, true_state=True)]  # fmt: skip
    recs[1]["step_reach_s"] = [3.2, None]
    feasible = {k: c["feasible"] for k, c in classify(recs).items()}
    table = outer_sweep_table(recs, feasible)
    assert table.schema.equals(OUTER_SWEEP_SCHEMA)
    rows = table.to_pylist()
    assert [(r["law"], r["true_state"], r["crashed"]) for r in rows] == [
        ("mfc", False, True), ("px4", False, False), ("mfc", True, True), ("px4", True, False),
    ]  # fmt: skip
    assert all(r["feasible"] is True for r in rows)
    assert rows[1]["step_reach_s"] == [3.2, None] and rows[0]["step_reach_s"] is None
    # What a record lacks is null, never made up.
    assert rows[0]["path_rms_m"] is None and rows[0]["lift_off_s"] is None
    assert set(OUTER_SWEEP_FIGURES) < set(OUTER_SWEEP_SCHEMA.names)


def test_the_table_is_documented() -> None:
    text = (ROOT / "docs" / "campaigns.md").read_text(encoding="utf-8")
    section = text.split("\n## The outer sweep's table\n", 1)[1].split("\n## ", 1)[0]
    documented = re.findall(r"^\| `(\w+)` \| ([\w<>]+) \|", section, flags=re.MULTILINE)
    types = {"string": pa.string(), "float64": pa.float64(), "int64": pa.int64(),
             "bool": pa.bool_(), "list<float64>": pa.list_(pa.float64())}  # fmt: skip
    assert [(n, types[t]) for n, t in documented] == [(f.name, f.type) for f in OUTER_SWEEP_SCHEMA]


def test_the_summary_counts_where_mfc_is_better() -> None:
    recs = [_rec("mfc", False, h=0.5), _rec("px4", False, h=1.0)]
    recs += [_rec("mfc", False, scenario="hold", h=2.0), _rec("px4", False, scenario="hold")]
    text = summary_markdown(recs)
    assert "- pos_rms_h_m: 1 of 2" in text
    assert "- att_mae_deg: 0 of 2" in text  # equal is not better
    assert "- path_rms_m: 0 of 0" in text
    assert "| f450 | motor60 | square | 0.50 | 1.00 | - | 1.00 | 1.00 | - | yes |" in text


def test_each_seed_is_a_case_of_its_own() -> None:
    # MFC crashed on one seed of two, and PX4 survived that seed on the true state.
    recs = [_rec("mfc", False, h=0.5), _rec("px4", False),
            _rec("mfc", True, seed=20200319), _rec("px4", False, seed=20200319),
            _rec("mfc", True, true_state=True, seed=20200319),
            _rec("px4", False, true_state=True, seed=20200319)]  # fmt: skip
    cases = classify(recs)
    assert set(cases) == {("f450", "motor60", "square", s) for s in (20200318, 20200319)}
    text = summary_markdown(recs)
    assert text.startswith("2 cases, 6 flights; 2 feasible, 0 infeasible")
    assert "**MFC crashes on a feasible case: 1**: f450/motor60/square (seed 20200319)" in text
    assert "| vehicle | damage | scenario | seed | pos_rms_h_m |" in text
    row = "| f450 | motor60 | square | 20200318 | 0.50 | 1.00 | - | 1.00 | 1.00 | - | yes |"
    assert row in text
    assert "| f450 | motor60 | square | 20200319 | - | - | - | - | - | MFC | yes |" in text
    # The table's rows carry their own seed's feasibility.
    feasible = {k: c["feasible"] for k, c in classify(recs[:4]).items()}
    rows = outer_sweep_table(recs[:4], feasible).to_pylist()
    assert [r["feasible"] for r in rows] == [True, True, None, None]


def test_seeds_are_the_scenarios_and_the_next_and_only_a_crashed_seed_flies_again() -> None:
    fleet = vehicles(["f450"], corners=False)
    one = sweep_flights(fleet, ["square"], ["motor60"])
    assert [f.seed for f in one] == [None, None]  # the keys of a sweep flown before --seeds
    three = sweep_flights(fleet, ["square"], ["motor60"], seeds=3)
    assert [(f.seed, f.law) for f in three] == [
        (s, law) for s in (20200318, 20200319, 20200320) for law in ("mfc", "px4")
    ]
    given = sweep_flights(fleet, ["square"], ["motor60"], seed=7, seeds=2)
    assert sorted({f.seed for f in given}) == [7, 8]
    recs = [_rec("mfc", False), _rec("px4", False),
            _rec("mfc", True, seed=20200319), _rec("px4", False, seed=20200319)]  # fmt: skip
    again = true_state_flights(recs, fleet, ["square"], ["motor60"], seeds=3)
    assert [(f.seed, f.law, f.true_state) for f in again] == [
        (20200319, "mfc", True), (20200319, "px4", True),
    ]  # fmt: skip
    # One seed, named by the scenario: a crash on it is flown again as before.
    again = true_state_flights([*recs[:2], _rec("mfc", True)], fleet, ["square"], ["motor60"])
    assert [(f.seed, f.law) for f in again] == [(None, "mfc"), (None, "px4")]
    with pytest.raises(ValueError, match="seeds: expected at least 1, got 0"):
        sweep_flights(fleet, ["square"], ["motor60"], seeds=0)


def test_only_crashed_cases_are_flown_again_on_the_true_state() -> None:
    fleet = vehicles(["f450"], corners=False)
    flights = sweep_flights(fleet, ["square", "position-hold"], ["intact", "motor60"])
    assert len(flights) == 2 * 2 * 2
    damaged = {f.damage: f.profile.physics.damage.motors for f in flights}
    assert not damaged["intact"]
    assert [(m.motor, m.thrust_efficiency) for m in damaged["motor60"]] == [(0, 0.6)]
    recs = [_rec("mfc", True), _rec("px4", False)]
    again = true_state_flights(recs, fleet, ["square", "position-hold"], ["intact", "motor60"])
    assert [(f.damage, f.scenario, f.law, f.true_state) for f in again] == [
        ("motor60", "square", "mfc", True),
        ("motor60", "square", "px4", True),
    ]


def small_sweep(out: Path, *more: str) -> list[str]:
    """The arguments of a two-second sweep of the F450's hold, on one worker."""
    return ["--out", str(out), "--profiles", "f450", "--scenarios", "position-hold",
            "--damage", "intact", "--duration", "2", "--seed", "1", "--workers", "1",
            *more]  # fmt: skip


@pytest.mark.long
def test_a_small_sweep_writes_its_flights_and_summary_and_resumes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = small_sweep(tmp_path)
    assert main(argv) == 0
    records = json.loads((tmp_path / "flights.json").read_text())
    assert sorted(r["law"] for r in records) == ["mfc", "px4"]
    assert not any(r["crashed"] or r["true_state"] for r in records)
    summary = (tmp_path / "summary.md").read_text()
    assert summary.startswith("1 cases, 2 flights; 1 feasible, 0 infeasible")
    # The same flights as a table, readable by pandas in one line.
    df = pandas.read_parquet(tmp_path / "flights.parquet")
    assert pyarrow.parquet.read_schema(tmp_path / "flights.parquet").equals(
        OUTER_SWEEP_SCHEMA, check_metadata=False
    )
    assert list(df["law"]) == [r["law"] for r in records]
    assert list(df["pos_rms_h_m"]) == [r["pos_rms_h_m"] for r in records]
    assert df["feasible"].tolist() == [True, True]
    # As if killed before its last flight landed: the same command flies only that one.
    stored = sorted((tmp_path / "flights").glob("*.json"))
    assert len(stored) == 2
    stored[1].unlink()
    (tmp_path / "summary.md").unlink()
    kept = stored[0].stat().st_mtime_ns
    assert main(argv) == 0
    assert "resuming: 1 of 2 flights done" in capsys.readouterr().err
    assert stored[0].stat().st_mtime_ns == kept and stored[1].exists()
    resumed = json.loads((tmp_path / "flights.json").read_text())
    assert [{**r, "wall_s": 0} for r in resumed] == [{**r, "wall_s": 0} for r in records]
    # A finished sweep is moved aside, whole, and flown afresh.
    assert main(argv) == 0
    assert "resuming" not in capsys.readouterr().err
    (earlier,) = tmp_path.glob("earlier-*")
    assert (earlier / "summary.md").read_text() == summary


def test_a_sweep_on_two_seeds_flies_and_reports_each(tmp_path: Path) -> None:
    argv = small_sweep(tmp_path, "--seeds", "2")
    assert main(argv) == 0
    records = json.loads((tmp_path / "flights.json").read_text())
    assert sorted((r["seed"], r["law"]) for r in records) == [
        (1, "mfc"), (1, "px4"), (2, "mfc"), (2, "px4"),
    ]  # fmt: skip
    # Two seeds fly two flights, not one twice.
    by_seed = {r["seed"]: r["pos_rms_h_m"] for r in records if r["law"] == "mfc"}
    assert by_seed[1] != by_seed[2]
    summary = (tmp_path / "summary.md").read_text()
    assert summary.startswith("2 cases, 4 flights; 2 feasible, 0 infeasible")
    assert "| f450 | intact | position-hold | 1 |" in summary
    assert "| f450 | intact | position-hold | 2 |" in summary
    df = pandas.read_parquet(tmp_path / "flights.parquet")
    assert sorted(df["seed"]) == [1, 1, 2, 2] and df["feasible"].all()


@pytest.mark.parametrize(
    ("flag", "value", "expected"),
    [
        ("--scenarios", "loop", "--scenarios: 'loop' is not one of"),
        ("--damage", "motor10", "--damage: 'motor10' is not one of"),
        ("--seeds", "0", "--seeds: expected at least 1, got 0"),
        ("--mfc-gyro-hz", "0", "--mfc-gyro-hz: expected a rate in 1-1000 Hz, got 0"),
    ],
)
def test_a_bad_choice_is_refused_before_any_flight(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], flag: str, value: str, expected: str
) -> None:
    with pytest.raises(SystemExit) as err:
        main(["--out", str(tmp_path / "out"), flag, value])
    assert err.value.code == 2
    assert expected in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_mfc_gyro_hz_makes_the_mfcs_flights_others_and_keeps_every_other_key() -> None:
    fleet = vehicles(["f450"], False)
    plain = sweep_flights(fleet, ["square"], ["intact"])
    px4_gyro = sweep_flights(fleet, ["square"], ["intact"], mfc_gyro_hz=250.0)
    mfc, px4 = (next(f for f in px4_gyro if f.law == law) for law in ("mfc", "px4"))
    # A flight without the option keeps the key it had before the option was added
    # (the stored flights of a sweep resume); with it, the MFC's flight is another,
    # PX4's the same.
    assert [flight_key(f) for f in plain] == [
        _digest({
            "vehicle": f.vehicle, "damage": f.damage, "scenario": f.scenario, "law": f.law,
            "true_state": f.true_state, "profile": f.profile.model_dump(mode="json"),
            "duration_s": f.duration_s, "seed": f.seed,
        })[:20]
        for f in plain
    ]  # fmt: skip
    assert flight_key(mfc) != flight_key(plain[0])
    assert flight_key(px4) == flight_key(plain[1])


def test_a_sweep_on_px4s_gyro_says_so_in_its_records_and_summary(tmp_path: Path) -> None:
    argv = small_sweep(tmp_path, "--mfc-gyro-hz", "250")
    assert main(argv) == 0
    records = json.loads((tmp_path / "flights.json").read_text())
    assert {r["law"]: r.get("gyro_hz") for r in records} == {"mfc": 250.0, "px4": None}
    summary = (tmp_path / "summary.md").read_text()
    assert "The MFC flew the gyro as PX4 sends it to a companion, at 250 Hz" in summary
