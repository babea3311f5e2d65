"""The per-vehicle retuning of PX4's cascade: its search space (the flights are the lab's)."""

from __future__ import annotations

import dataclasses

import pytest

from sitl.lab import cascade_tune
from sitl.lab.cascade_pid import PX4_DEFAULT_CASCADE
from sitl.lab.cascade_tune import SPAN, TUNED_FIELDS, candidates, compare, main


def test_the_default_comes_first_and_the_draws_stay_within_the_span() -> None:
    cands = candidates(20, seed=3)
    assert len(cands) == 20 and cands[0] == PX4_DEFAULT_CASCADE
    for g in cands[1:]:
        for f in TUNED_FIELDS:
            ratio = getattr(g, f) / getattr(PX4_DEFAULT_CASCADE, f)
            assert 1.0 / SPAN <= ratio <= SPAN, (f, ratio)
        untouched = {
            f.name for f in dataclasses.fields(PX4_DEFAULT_CASCADE) if f.name not in TUNED_FIELDS
        }
        for f in untouched:
            assert getattr(g, f) == getattr(PX4_DEFAULT_CASCADE, f)
    assert len({g.xy_p_1_s for g in cands}) == 20  # every draw its own


def test_the_same_seed_draws_the_same_candidates() -> None:
    assert candidates(8, seed=5) == candidates(8, seed=5)
    assert candidates(8, seed=5) != candidates(8, seed=6)


@pytest.mark.long
def test_compare_flies_each_case_on_each_seed_with_its_ratios(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The hold on two seeds on two workers, the MFC on PX4's gyro, PX4's default
    standing in for the tuned gains."""
    monkeypatch.setattr(cascade_tune, "TEST_SCENARIOS", ("position-hold",))
    default = {f: getattr(PX4_DEFAULT_CASCADE, f) for f in TUNED_FIELDS}
    rows = compare({"vehicles": {"f450": {"gains": default}}}, seeds=2, workers=2, mfc_gyro_hz=250)
    assert [(r["scenario"], r["seed"]) for r in rows] == [
        ("position-hold", 20200318),
        ("position-hold", 20200319),
    ]
    for r in rows:
        a, b, ratio = r["pos_rms_h_m"]
        assert ratio == pytest.approx(a / b)
        assert r["crashed"] == (False, False)
    assert rows[0]["pos_rms_h_m"] != rows[1]["pos_rms_h_m"]


@pytest.mark.parametrize(
    ("flag", "value", "expected"),
    [("--seeds", "0", "--seeds: expected at least 1"), ("--mfc-gyro-hz", "5000", "1-1000 Hz")],
)
def test_a_bad_compare_option_is_refused(
    capsys: pytest.CaptureFixture[str], flag: str, value: str, expected: str
) -> None:
    with pytest.raises(SystemExit) as err:
        main(["--compare", "runs/none.json", flag, value])
    assert err.value.code == 2
    assert expected in capsys.readouterr().err
