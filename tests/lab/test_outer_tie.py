"""The outer sweep's verdict: better, tied or worse, the tie band the larger of 5 %
and the estimate's own error on the vertical and the attitude."""

from __future__ import annotations

from sitl.lab.outer_sweep import summary_markdown, verdict


def _flight(**figures: float | None) -> dict[str, object]:
    return {"crashed": False, **figures}


def test_within_five_percent_is_a_tie_and_beyond_it_a_verdict() -> None:
    px4 = _flight(pos_rms_h_m=1.0)
    assert verdict("pos_rms_h_m", _flight(pos_rms_h_m=1.04), px4) == "tie"
    assert verdict("pos_rms_h_m", _flight(pos_rms_h_m=0.96), px4) == "tie"
    assert verdict("pos_rms_h_m", _flight(pos_rms_h_m=1.06), px4) == "worse"
    assert verdict("pos_rms_h_m", _flight(pos_rms_h_m=0.94), px4) == "better"


def test_on_the_vertical_the_estimates_own_error_widens_the_band() -> None:
    """0.30 m against 0.20 m is 50 % worse, but both flew an estimate 0.15 m off."""
    mfc = _flight(pos_rms_v_m=0.30, est_floor_v_m=0.16)
    px4 = _flight(pos_rms_v_m=0.20, est_floor_v_m=0.14)
    assert verdict("pos_rms_v_m", mfc, px4) == "tie"
    assert verdict("pos_rms_v_m", _flight(pos_rms_v_m=0.36, est_floor_v_m=0.16), px4) == "worse"
    # The horizontal has no floor: 5 % only.
    assert verdict("pos_rms_h_m", _flight(pos_rms_h_m=0.30, est_floor_h_m=0.5),
                   _flight(pos_rms_h_m=0.20, est_floor_h_m=0.5)) == "worse"  # fmt: skip


def test_a_crash_or_a_missing_figure_has_no_verdict() -> None:
    assert (
        verdict("pos_rms_h_m", {"crashed": True, "pos_rms_h_m": 0.1}, _flight(pos_rms_h_m=1.0))
        is None
    )
    assert verdict("pos_rms_h_m", _flight(pos_rms_h_m=None), _flight(pos_rms_h_m=1.0)) is None


def test_the_summary_counts_each_verdict() -> None:
    def rec(law: str, v: float, floor: float) -> dict[str, object]:
        case = {"vehicle": "f450", "damage": "intact", "scenario": "position-hold"}
        flight = {"law": law, "true_state": False, "crashed": False}
        return {**case, **flight, "pos_rms_v_m": v, "est_floor_v_m": floor}

    text = summary_markdown([rec("mfc", 0.30, 0.15), rec("px4", 0.20, 0.15)])
    assert "- pos_rms_v_m: 0 better, 1 tied, 0 worse" in text
