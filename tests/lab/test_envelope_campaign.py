"""The envelope campaign (sitl/lab/envelope.py) at the corners of the envelope.

The campaign's targets, checked where they are hardest to meet: at three of the named
corner vehicles (:func:`sitl.envelope.corners`, :data:`CORNERS_FLOWN`), intact, on
the real test flight
(``envelope-test``, 30 s). To stay quick the PID is tuned on the first
:data:`TRAIN_SLICE_S` seconds of ``train-acro`` with :data:`BUDGET` flights (two
rounds of the search) instead of the campaign's 35 s and 40 flights. No crash
and the ratio targets are asserted as the envelope states them; the median ratio is
also held near what was measured, so that a regression fails.
"""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path
from typing import Any

import pyarrow.parquet
import pytest
from click.testing import CliRunner

from companion.cli import cli
from companion.config import DEFAULT_CONTROLLER
from companion.control import AXES
from sitl.envelope import corners
from sitl.lab.envelope import envelope_meta, run_envelope, write_envelope_outputs
from sitl.lab.envelope_setup import (
    CASES,
    CONTROLLERS,
    RATIO_TARGET,
    EnvelopeCase,
    EnvelopeSetup,
    envelope_cases,
    load_setup,
)
from sitl.lab.envelope_verdicts import verdicts
from sitl.lab.table import ENVELOPE_SCHEMA

ROOT = Path(__file__).resolve().parents[2]

TRAIN_SLICE_S = 15.0
BUDGET = 25
Records = list[dict[str, Any]]


def _short(setup: EnvelopeSetup, train_s: float, test_s: float | None = None) -> EnvelopeSetup:
    train = setup.train.model_copy(update={"duration_s": train_s})
    test = setup.test if test_s is None else setup.test.model_copy(update={"duration_s": test_s})
    return EnvelopeSetup(
        setup.mfc, setup.pid_default, setup.controller_profile, train, test,
        setup.tune_budget, setup.seed, setup.oracle,
    )  # fmt: skip


@pytest.fixture(scope="module")
def corner_setup() -> EnvelopeSetup:
    # The oracle's 30 s flights (about 13 s each here) are left to the shorter tests
    # below: the corners' figures are about MFC and the PIDs.
    setup = _short(load_setup(tune_budget=BUDGET, seed=1), TRAIN_SLICE_S)
    return dataclasses.replace(setup, oracle=False)


CORNERS_FLOWN = ("tiny-fast", "heavy-weak")
"""Two of the five corners, for the suite's time: the one whose ratios sit nearest
the target and the heavy, weak one, nearest a crash (each case flies the same
whichever others fly with it; the full campaign flies all five, and the last one,
59 cases, is in docs/research/envelope.md: no crash on a feasible case). Left out
for the suite's time, tiny-slow-motor measured 0.86 / 0.97 / 0.35 and 0.94 of the
default PID."""


@pytest.fixture(scope="module")
def corner_cases() -> list[EnvelopeCase]:
    cases = envelope_cases(corners_only=True, damage=False)
    return [c for c in cases if c.vehicle in CORNERS_FLOWN]


@pytest.fixture(scope="module")
def corner_records(corner_setup: EnvelopeSetup, corner_cases: list[EnvelopeCase]) -> Records:
    return run_envelope(corner_cases, corner_setup, workers=2, progress=False)


def _table(records: Records) -> str:
    return "; ".join(
        f"{r['vehicle']}: "
        + ", ".join(
            f"{a} {r['flights']['mfc']['mae_deg_s'][a]}/{r['flights']['pid_tuned']['mae_deg_s'][a]}"
            f"/{r['flights']['pid_default']['mae_deg_s'][a]}"
            for a in AXES
        )
        for r in records
    )


@pytest.mark.long
@pytest.mark.slow  # ~35 s on 2 cores: 2 corners x (25 tuning flights + 3 test flights)
def test_no_crash_at_the_corners(corner_records: Records) -> None:
    assert [r["vehicle"] for r in corner_records] == list(CORNERS_FLOWN)
    crashed = [
        (r["vehicle"], c, r["flights"][c]["crashed_at_s"])
        for r in corner_records
        for c in ("mfc", "pid_tuned")
        if r["flights"][c]["crashed"]
    ]
    assert crashed == [], crashed


# The targets at the corners: ratio <= RATIO_TARGET (1.25) on every corner and axis,
# and MFC better than PX4's default PID everywhere. Both met since the margin falls on
# slow lags with much authority (docs/research/gains.md#strong-vehicle-margin). Measured with the
# shipped controller (this test's short tuning, 25 flights on 15 s of train-acro),
# ratio MFC / tuned PID roll/pitch/yaw: tiny-fast 0.84/0.98/0.98, tiny-slow-motor
# 0.86/0.97/0.35, heavy-weak 0.86/0.76/0.76; MFC over the default PID at most 0.94
# (tiny-slow-motor). docs/research/envelope.md has the full campaign.


@pytest.mark.long
@pytest.mark.slow
def test_ratio_to_the_tuned_pid_holds_at_the_corners(corner_records: Records) -> None:
    ratios = [r["ratio_mfc_tuned"][a] for r in corner_records for a in AXES]
    assert None not in ratios
    assert max(ratios) <= RATIO_TARGET, "MAE M/T/D: " + _table(corner_records)


# A regression check (today's output): the median (the upper middle of 6) of the
# corner ratios above, as measured by this module's corner_records fixture
# (CORNERS_FLOWN, no damage, the PID tuned with 25 flights on 15 s of train-acro,
# seed 1): 0.86 (0.855 over the three corners flown before)
#   pytest tests/lab/test_envelope_campaign.py -k median
MEASURED_MEDIAN_RATIO = 0.86


@pytest.mark.long
@pytest.mark.slow
@pytest.mark.regression
def test_median_ratio_to_the_tuned_pid_at_the_corners(corner_records: Records) -> None:
    ratios = sorted(r["ratio_mfc_tuned"][a] for r in corner_records for a in AXES)
    detail = "MAE M/T/D: " + _table(corner_records)
    assert ratios[len(ratios) // 2] <= max(1.15 * MEASURED_MEDIAN_RATIO, 1.0), detail


@pytest.mark.long
@pytest.mark.slow
def test_mfc_beats_px4_default_pid_at_the_corners(corner_records: Records) -> None:
    worse = [
        (r["vehicle"], a, r["ratio_mfc_default"][a])
        for r in corner_records
        for a in AXES
        if r["ratio_mfc_default"][a] is None or r["ratio_mfc_default"][a] >= 1.0
    ]
    assert worse == [], worse


@pytest.mark.long
@pytest.mark.slow
def test_records_and_output_files(
    corner_records: Records,
    corner_setup: EnvelopeSetup,
    corner_cases: list[EnvelopeCase],
    tmp_path: Path,
) -> None:
    for r in corner_records:
        assert r["case"] == "intact"
        assert set(r["flights"]) == set(CONTROLLERS)
        assert r["tune"]["flights"] <= BUDGET
        assert r["tune"]["train_objective_deg_s"] <= r["tune"]["start_objective_deg_s"]
        assert set(r["tuned_gains"]) == {"rp_kp", "rp_ki", "rp_kd", "yaw_kp", "yaw_ki"}
        for a in AXES:
            m, t = r["flights"]["mfc"]["mae_deg_s"][a], r["flights"]["pid_tuned"]["mae_deg_s"][a]
            assert r["ratio_mfc_tuned"][a] == pytest.approx(m / t, rel=1e-3)
        assert r["oracle"] is None and r["ratio_mfc_oracle"] is None  # not asked for
    meta = envelope_meta(
        corner_cases, corner_setup, wall_time_s=0.0, workers=2,
        mfc_controller=str(Path(DEFAULT_CONTROLLER).resolve()),
    )  # fmt: skip
    paths = write_envelope_outputs(
        corner_records, tmp_path, meta, setup=corner_setup, cases=corner_cases, worst_k=1
    )
    for key in ("json", "summary", "plot"):
        assert paths[key].stat().st_size > 0
    worst = [p for k, p in paths.items() if k.startswith("worst-")]
    assert len(worst) == 1
    for png in (paths["plot"], worst[0]):
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    doc = json.loads(paths["json"].read_text(encoding="utf-8"))
    assert doc["records"] == json.loads(json.dumps(corner_records))
    assert doc["verdicts"] == json.loads(json.dumps(verdicts(corner_records)))
    assert doc["meta"]["test_scenario"]["name"] == "envelope-test"
    summary = paths["summary"].read_text(encoding="utf-8")
    assert "ratio.png" in summary and worst[0].name in summary
    # The summary is kept in docs/: the shipped file is named from the checkout's root.
    assert "MFC is `companion/data/mfc_default.yaml`" in summary
    assert summary.count("met**") == 10  # five targets, two scopes
    assert "## Ratio MFC / oracle per axis" not in summary  # not flown
    for r in corner_records:
        assert f"| {r['vehicle']} | intact |" in summary
    _check_table(paths["table"], corner_records)


def _documented_envelope_schema() -> list[tuple[str, str]]:
    """(column, type) rows of the envelope table's schema in docs/campaigns.md."""
    text = (ROOT / "docs" / "campaigns.md").read_text(encoding="utf-8")
    section = text.split("\n## The envelope's table\n", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"^\| `(\w+)` \| (\w+) \|", section, flags=re.MULTILINE)


def _check_table(path: Path, records: Records) -> None:
    """``envelope.parquet`` has the documented schema and the records' figures, a row
    per test flight (the oracle's only where it flew)."""
    import pandas as pd
    import pyarrow as pa
    import pyarrow.parquet as pq

    types = {"string": pa.string(), "float64": pa.float64(), "int64": pa.int64(),
             "bool": pa.bool_()}  # fmt: skip
    documented = [(name, types[t]) for name, t in _documented_envelope_schema()]
    assert documented == [(f.name, f.type) for f in ENVELOPE_SCHEMA]
    assert pq.read_schema(path).equals(ENVELOPE_SCHEMA, check_metadata=False)
    df = pd.read_parquet(path)
    expected = []
    for r in records:
        flights = {**r["flights"], **({"oracle": r["oracle"]} if r["oracle"] else {})}
        for c, f in flights.items():
            expected.append((r["vehicle"], r["case"], c, f["mae_deg_s"]["yaw"], f["crashed"],
                             r["feasible"], r["vehicle_info"]["mass_kg"]))  # fmt: skip
    got = df[["vehicle", "case", "controller", "mae_yaw_deg_s", "crashed", "feasible",
              "mass_kg"]].itertuples(index=False, name=None)  # fmt: skip
    assert list(got) == expected


def test_damage_cases_follow_the_corners() -> None:
    cases = envelope_cases(n=3, seed=5, damage=True, damage_on=2)
    names = [v.name for v in corners()]
    vehicles = list(dict.fromkeys(c.vehicle for c in cases))
    assert vehicles[: len(names)] == names and len(vehicles) == len(names) + 3
    damaged = [c.vehicle for c in cases if c.case != "intact"]
    assert damaged == [names[0]] * 3 + [names[1]] * 3
    assert [c.case for c in cases[:4]] == list(CASES)
    assert len({c.profile.name for c in cases}) == len(cases)


def test_refuses_to_tune_on_a_test_flight() -> None:
    for name in ("envelope-test", "paper-acro"):
        with pytest.raises(ValueError, match="test flight"):
            load_setup(train_scenario=name)


@pytest.mark.long
def test_same_records_whatever_the_workers() -> None:
    setup = _short(load_setup(tune_budget=3, seed=2), 2.0, 3.0)
    cases = envelope_cases(corners_only=True, damage=True, damage_on=1)[:3]
    one = run_envelope(cases, setup, workers=1, progress=False)
    two = run_envelope(cases, setup, workers=2, progress=False)
    assert one == two
    for r in one:  # the limit, flown on the same test flight
        for a in AXES:
            m, o = r["flights"]["mfc"]["mae_deg_s"][a], r["oracle"]["mae_deg_s"][a]
            assert r["ratio_mfc_oracle"][a] == pytest.approx(m / o, rel=1e-3)
    assert [(r["vehicle"], r["case"]) for r in one] == [(c.vehicle, c.case) for c in cases]


@pytest.mark.long
def test_cli_corners_only(tmp_path: Path) -> None:
    setup = load_setup()
    for name, sc, s in (("train", setup.train, 2.0), ("test", setup.test, 3.0)):
        short = sc.model_copy(update={"name": f"short-{name}", "duration_s": s})
        (tmp_path / f"{name}.yaml").write_text(short.model_dump_json(), encoding="utf-8")
    out = tmp_path / "out"
    args = [
        "envelope", "--out", str(out), "--corners-only", "--damage-on", "1",
        "--tune-budget", "2", "--train-scenario", str(tmp_path / "train.yaml"),
        "--test-scenario", str(tmp_path / "test.yaml"), "--worst", "1", "--workers", "2",
        "--no-progress",
    ]  # fmt: skip
    result = CliRunner().invoke(cli, args, catch_exceptions=False)
    assert result.exit_code == 0, result.output
    assert "summary:" in result.output
    doc = json.loads((out / "envelope.json").read_text(encoding="utf-8"))
    n_corners = len(corners())
    assert doc["meta"]["vehicles"] == n_corners
    assert len(doc["records"]) == n_corners + 3
    assert doc["meta"]["damaged_vehicles"] == [corners()[0].name]
    assert doc["meta"]["damage_retuned"] is True
    assert (out / "ratio.png").exists() and len(list(out.glob("worst-*.png"))) == 1
    assert "## Ratio MFC / oracle per axis" in (out / "summary.md").read_text(encoding="utf-8")
    _check_table(out / "envelope.parquet", doc["records"])
    rows = pyarrow.parquet.read_metadata(out / "envelope.parquet").num_rows
    assert rows == len(doc["records"]) * 4  # the oracle flew every case
    bad = CliRunner().invoke(cli, [*args[:3], "--train-scenario", "envelope-test"])
    assert bad.exit_code != 0 and "test flight" in bad.output


@pytest.mark.long
def test_a_killed_envelope_resumes_without_reflying_finished_cases(tmp_path: Path) -> None:
    from sitl.lab.campaign_store import CampaignStore, grid_digest
    from sitl.lab.envelope import CASES_DIR, RUN_MANIFEST, case_ids

    setup = _short(load_setup(tune_budget=2, seed=2), 2.0, 3.0)
    cases = envelope_cases(corners_only=True, damage=False)[:3]
    store = CampaignStore(tmp_path, manifest=RUN_MANIFEST, finished="envelope.json")
    store.start(grid_digest(case_ids(cases, setup)), len(cases))
    first = run_envelope(cases, setup, workers=2, progress=False, store=store)
    files = sorted((tmp_path / CASES_DIR).glob("*.json"))
    assert len(files) == 3
    # As if killed before the last case landed: its record is missing.
    lost = tmp_path / CASES_DIR / f"{case_ids(cases, setup)[2]}.json"
    lost.unlink()
    kept = {p: p.stat().st_mtime_ns for p in files if p != lost}
    assert store.can_resume(grid_digest(case_ids(cases, setup)))
    again = run_envelope(cases, setup, workers=2, progress=False, store=store)
    assert again == first and lost.exists()
    assert {p: p.stat().st_mtime_ns for p in kept} == kept  # not flown again
