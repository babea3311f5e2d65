"""``companion campaign``: a tiny grid through the CLI in process, and its outputs."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from companion.cli import cli
from companion.control import AXES
from companion.profile import load_profile
from sitl.lab.campaign import damaged_profile

ROOT = Path(__file__).resolve().parents[2]


def _run(out: Path) -> dict:  # type: ignore[type-arg]
    args = [
        "campaign", "--out", str(out),
        "--profiles", str(ROOT / "vehicle_profiles" / "f450.yaml"),
        "--profiles", str(ROOT / "vehicle_profiles" / "tarot650.yaml"),
        "--damage", "0.8", "--gusts", "1.0", "--seeds", "1",
        "--duration", "5", "--workers", "2", "--no-progress",
    ]  # fmt: skip
    result = CliRunner().invoke(cli, args, catch_exceptions=False)
    assert result.exit_code == 0, result.output
    doc: dict = json.loads((out / "campaign.json").read_text(encoding="utf-8"))  # type: ignore[type-arg]
    return doc


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict, dict]:  # type: ignore[type-arg]
    a = tmp_path_factory.mktemp("campaign_a")
    b = tmp_path_factory.mktemp("campaign_b")
    return a, _run(a), _run(b)


def test_outputs_exist_and_records_are_consistent(two_runs: tuple) -> None:  # type: ignore[type-arg]
    out, doc, _ = two_runs
    for name in ("campaign.json", "summary.md", "mae.png"):
        assert (out / name).stat().st_size > 0
    assert (out / "mae.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    recs = doc["records"]
    assert len(recs) == 2 * 1 * 1 * 1 * 2 == doc["meta"]["flights"]
    combos = {(r["profile"], r["controller"]) for r in recs}
    assert combos == {
        (p, c) for p in ("f450", "tarot650") for c in ("mfc_default", "pid_tarot_tuned")
    }
    for r in recs:
        assert (r["damage"], r["gust_sigma_m_s"], r["seed"]) == (0.8, 1.0, 1000)
        assert r["controller_kind"] == ("mfc" if r["controller"] == "mfc_default" else "pid")
        assert isinstance(r["crashed"], bool)
        assert all(r["mae_deg_s"][a] is not None and r["mae_deg_s"][a] >= 0 for a in AXES)
        assert r["sim_time_s"] == pytest.approx(5.0, abs=0.01) or r["crashed"]
    summary = (out / "summary.md").read_text(encoding="utf-8")
    for c in ("mfc_default", "pid_tarot_tuned"):
        assert f"| {c} |" in summary
    assert "mae.png" in summary


def test_every_flight_is_read_against_the_oracle_in_its_case(two_runs: tuple) -> None:  # type: ignore[type-arg]
    from sitl.lab.oracle import oracle_flight
    from sitl.scenario import load_scenario

    out, doc, _ = two_runs
    recs = doc["records"]
    by_profile = {r["profile"]: r["oracle_mae_deg_s"] for r in recs}
    for r in recs:  # one oracle flight per case, shared by the case's controllers
        assert r["oracle_mae_deg_s"] == by_profile[r["profile"]]
        assert all(v is not None and v > 0 for v in r["oracle_mae_deg_s"].values())
    # The stored limit is the oracle's own flight of that case.
    tarot = damaged_profile(load_profile(ROOT / "vehicle_profiles" / "tarot650.yaml"), 0.8)
    sc = load_scenario("train-acro")
    wind = type(sc.wind).model_validate({**sc.wind.model_dump(), "gust_sigma_m_s": 1.0})
    sc = sc.model_copy(update={"duration_s": 5.0, "wind": wind})
    assert oracle_flight(tarot, sc, seed=1000)["mae_deg_s"] == by_profile["tarot650"]
    summary = (out / "summary.md").read_text(encoding="utf-8")
    assert "## Against the limit" in summary
    assert "| mfc_default / pid_tarot_tuned |" in summary
    assert summary.count("| tarot650 | ") >= 3  # a row per axis


def test_same_seed_same_mae(two_runs: tuple) -> None:  # type: ignore[type-arg]
    _, doc_a, doc_b = two_runs
    assert [r["mae_deg_s"] for r in doc_a["records"]] == [r["mae_deg_s"] for r in doc_b["records"]]


def test_damage_scales_one_motor_on_top_of_existing_damage() -> None:
    cut = load_profile(ROOT / "vehicle_profiles" / "f450_cut_props.yaml")
    assert damaged_profile(cut, 1.0) is cut
    d = damaged_profile(cut, 0.5)
    m0 = next(m for m in d.physics.damage.motors if m.motor == 0)
    base = next(m for m in cut.physics.damage.motors if m.motor == 0)
    assert m0.thrust_efficiency == pytest.approx(0.5 * base.thrust_efficiency)
    assert m0.imbalance_n == base.imbalance_n
    f450 = load_profile(ROOT / "vehicle_profiles" / "f450.yaml")
    d = damaged_profile(f450, 0.6)
    assert [(m.motor, m.thrust_efficiency) for m in d.physics.damage.motors] == [(0, 0.6)]
    with pytest.raises(ValueError):
        damaged_profile(f450, 0.0)


def test_bad_input_is_refused() -> None:
    result = CliRunner().invoke(cli, ["campaign", "--damage", "x", "--no-progress"])
    assert result.exit_code == 2
