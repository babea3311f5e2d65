"""Crashes no controller avoids are told apart: a campaign flies the oracle
that knows the plant and may also set the collective (sitl/lab/oracle.py) on each
case where a controller crashed; if it crashes too, the case is infeasible, and
its flights are reported apart, not counted as crashes."""

from __future__ import annotations

from pathlib import Path

import pytest

from companion.config import load_controller
from companion.profile import load_profile
from sitl.lab import campaign
from sitl.lab.campaign import FlightSpec, run_campaign, summary_markdown
from sitl.lab.envelope_setup import envelope_cases
from sitl.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[2]


def _heavy_weak_motor60() -> FlightSpec:
    """The envelope's hard case: 5 kg, T/W 1.8, one motor at 60 %, out of the double
    flip at about 7 m sinking at 8 m/s; MFC reaches the ground at 9.4 s."""
    (case,) = [
        c
        for c in envelope_cases(corners_only=True, damage=True, damage_on=5)
        if (c.vehicle, c.case) == ("heavy-weak", "motor60")
    ]
    sc = load_scenario("envelope-test").model_copy(update={"duration_s": 11.0})
    return FlightSpec("heavy-weak", case.profile, 0.6, 0.0, sc.seed, "mfc", load_controller(), sc)


def _x500() -> FlightSpec:
    sc = load_scenario("paper-acro").model_copy(update={"duration_s": 3.0})
    profile = load_profile(ROOT / "vehicle_profiles" / "x500.yaml")
    return FlightSpec("x500", profile, 1.0, 0.0, sc.seed, "mfc", load_controller(), sc)


def test_a_crash_the_collective_oracle_also_suffers_is_infeasible() -> None:
    specs = [_heavy_weak_motor60(), _x500()]
    records = run_campaign(specs, workers=1, progress=False)
    hw, x5 = records
    assert hw["crashed"] and hw["feasible"] is False
    assert not x5["crashed"] and x5["feasible"] is True
    summary = summary_markdown(records, _meta())
    # one controller, two flights: no crash on a feasible case, one infeasible flight
    assert "| mfc | mfc | 2 | 0 | 1 |" in summary, summary


def test_a_crash_the_oracle_flies_through_is_a_crash(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """The same crashed flight, with an oracle that flies the case (the verdict
    replaced): the flight counts as a crash on a feasible case."""
    asked = tmp_path / "asked"  # the oracle runs on a worker process: it tells by file

    def flies(spec: FlightSpec) -> bool:
        with asked.open("a", encoding="utf-8") as f:
            f.write(spec.profile_name + "\n")
        return False

    monkeypatch.setattr(campaign, "oracle_crashes", flies)
    records = run_campaign([_heavy_weak_motor60(), _x500()], workers=1, progress=False)
    # only cases where a controller crashed are judged
    assert asked.read_text(encoding="utf-8").split() == ["heavy-weak"]
    assert [r["feasible"] for r in records] == [True, True]
    assert "| mfc | mfc | 2 | 1 | 0 |" in summary_markdown(records, _meta())


def _meta() -> dict[str, object]:
    return {"scenario": "mixed", "duration_s": 11.0, "profiles": ["heavy-weak", "x500"],
            "damages": [0.6, 1.0], "gusts_m_s": [0.0], "seeds": [1], "workers": 1,
            "wall_time_s": 0.0}  # fmt: skip


def _envelope_record(vehicle: str, case: str, crashed: dict[str, bool], feasible: bool) -> dict:
    ratio = {a: (0.9 if not crashed["mfc"] else None) for a in ("roll", "pitch", "yaw")}
    return {
        "vehicle": vehicle,
        "case": case,
        "feasible": feasible,
        "flights": {c: {"crashed": crashed[c], "crashed_at_s": 9.4 if crashed[c] else None,
                        "mae_deg_s": {a: 10.0 for a in ("roll", "pitch", "yaw")}}
                    for c in ("mfc", "pid_tuned", "pid_default")},
        "ratio_mfc_tuned": ratio,
        "ratio_mfc_default": {a: 0.8 if not crashed["mfc"] else None for a in ratio},
    }  # fmt: skip


def test_the_envelope_targets_leave_infeasible_cases_out_and_count_them() -> None:
    from sitl.lab.envelope_verdicts import verdicts

    fine = {"mfc": False, "pid_tuned": False, "pid_default": False}
    every = {"mfc": True, "pid_tuned": True, "pid_default": True}
    records = [
        _envelope_record("a", "intact", fine, True),
        _envelope_record("a", "motor60", every, False),
    ]
    v = verdicts(records)
    assert v["all"]["no_mfc_crash"] and v["all"]["ratio_within_target"]
    assert (v["all"]["cases"], v["all"]["infeasible"], v["all"]["mfc_crashes"]) == (2, 1, 0)
    assert v["crashes"]["mfc"] == 1  # every crash is still counted as such
    # The same crash on a feasible case fails the target.
    records[1]["feasible"] = True
    v = verdicts(records)
    assert not v["all"]["no_mfc_crash"] and v["all"]["mfc_crashes"] == 1
    assert v["all"]["infeasible"] == 0
