"""The link's cost beyond the round trip's own (sitl/lab/link_limit.py)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sitl.lab.link_limit import cost_table, fly_through, main


def _flight(link: str, mfc: tuple[float, float, float], tracker: tuple[float, float]) -> dict:
    return {
        "vehicle": "f450",
        "link": link,
        "crashed": False,
        "mfc_deg_s": dict(zip(("roll", "pitch", "yaw"), mfc, strict=True)),
        "tracker_deg_s": dict(zip(("roll", "pitch"), tracker, strict=True)),
    }


def test_the_cost_is_mfcs_ratio_to_the_tracker_over_the_same_on_the_ideal_link() -> None:
    flights = [
        _flight("ideal", (6.0, 5.0, 4.0), (5.0, 5.0)),  # MFC 1.2x / 1.0x the tracker
        _flight("uart", (9.0, 6.0, 5.0), (6.0, 6.0)),  # 1.5x / 1.0x
    ]
    (row,) = cost_table(flights)
    assert row["cost"] == {"roll": pytest.approx(1.25), "pitch": pytest.approx(1.0)}
    assert row["yaw_ratio"] == pytest.approx(1.25)
    assert row["target"] == 1.1
    assert not row["met"]


def test_a_crash_is_never_within_target() -> None:
    flights = [
        _flight("ideal", (6.0, 5.0, 4.0), (5.0, 5.0)),
        _flight("delay_ms=10", (6.0, 5.0, 4.0), (5.0, 5.0)),
    ]
    flights[1]["crashed"] = True
    (row,) = cost_table(flights)
    assert row["cost"] == {"roll": 1.0, "pitch": 1.0}
    assert not row["met"]


@pytest.mark.slow
def test_a_flight_through_a_link_pays_for_its_round_trip() -> None:
    ideal = fly_through(("f450", "ideal", 6.0, None))
    late = fly_through(("f450", "delay_ms=10", 6.0, None))
    assert not ideal["crashed"] and not late["crashed"]
    # The perfect tracker answers 10 ms each way late, and MFC with it: both lose.
    for axis in ("roll", "pitch"):
        assert late["tracker_deg_s"][axis] > ideal["tracker_deg_s"][axis]
        assert late["mfc_deg_s"][axis] > ideal["mfc_deg_s"][axis]


@pytest.mark.long
@pytest.mark.slow
@pytest.mark.integration
def test_a_rates_flight_over_mavlink_pays_for_its_round_trip_too() -> None:
    """``--output rates``: the companion and the SITL as two processes, the SITL's
    PX4 rate loop in the plant and the link modelled by the SITL."""
    ideal = fly_through(("f450", "ideal", 6.0, None), "rates")
    late = fly_through(("f450", "delay_ms=10", 6.0, None), "rates")
    assert not ideal["crashed"] and not late["crashed"]
    for axis in ("roll", "pitch"):
        assert late["tracker_deg_s"][axis] > ideal["tracker_deg_s"][axis]
        assert late["mfc_deg_s"][axis] > ideal["mfc_deg_s"][axis]


def test_a_flight_a_failsafe_ended_is_never_within_target() -> None:
    flights = [
        _flight("ideal", (6.0, 5.0, 4.0), (5.0, 5.0)),
        _flight("delay_ms=10", (6.0, 5.0, 4.0), (5.0, 5.0)),
    ]
    flights[1]["failsafes"] = ["failsafe_envelope: tracking error ..."]
    (row,) = cost_table(flights)
    assert row["cost"] == {"roll": 1.0, "pitch": 1.0}
    assert row["failsafes"] and not row["met"]


def test_passthrough_needs_the_rates_output(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["--passthrough"])
    assert exit_.value.code == 2
    assert "--passthrough: needs --output rates (got --output actuator)" in capsys.readouterr().err
    with pytest.raises(ValueError, match="needs output 'rates'"):
        fly_through(("f450", "ideal", 1.0, None), "actuator", passthrough=True)


@pytest.mark.long
@pytest.mark.slow
@pytest.mark.integration
def test_a_passthrough_flight_is_the_autopilots_own_rate_loop_on_the_same_flight() -> None:
    """``--passthrough``: the same seed and link, the pilot's rates sent as they
    are; lockstep makes each flight repeatable, so a different MAE is a
    different controller."""
    mfc = fly_through(("f450", "ideal", 6.0, None), "rates")
    passed = fly_through(("f450", "ideal", 6.0, None), "rates", passthrough=True)
    assert (mfc["controller"], passed["controller"]) == ("mfc", "passthrough")
    assert not passed["crashed"]
    assert passed["mfc_deg_s"] != mfc["mfc_deg_s"]


@pytest.mark.long
@pytest.mark.slow
@pytest.mark.integration
def test_a_sitl_param_reaches_the_autopilots_rate_loop() -> None:
    """``--sitl-param MC_ROLLRATE_K=3``: the SITL's PX4 boots with a stiffer roll
    rate loop; the same lockstep flight then tracks roll differently."""
    default = fly_through(("f450", "ideal", 6.0, None), "rates", passthrough=True)
    stiff = fly_through(
        ("f450", "ideal", 6.0, None), "rates", passthrough=True, sitl_params=("MC_ROLLRATE_K=3",)
    )
    assert stiff["sitl_params"] == ["MC_ROLLRATE_K=3"]
    assert stiff["mfc_deg_s"]["roll"] < default["mfc_deg_s"]["roll"]
    with pytest.raises(ValueError, match="sitl_params: needs output 'rates'"):
        fly_through(("f450", "ideal", 1.0, None), "actuator", sitl_params=("MC_ROLLRATE_K=3",))


@pytest.mark.long
@pytest.mark.slow
@pytest.mark.integration
def test_law_axes_reach_the_companion() -> None:
    """``--law-axes yaw``: the companion corrects yaw only (``--rates-law-axes``);
    the same lockstep flight then flies roll differently from the full law's. By
    default (auto) the companion reads the SITL's rate gains: at the defaults it
    corrects every axis, on a loop tripled it flies the yaw-only flight exactly."""
    full = fly_through(("f450", "ideal", 6.0, None), "rates")
    yaw = fly_through(("f450", "ideal", 6.0, None), "rates", law_axes="yaw")
    assert (full["law_axes"], yaw["law_axes"]) == ("roll,pitch,yaw", "yaw")  # as flown
    assert not yaw["crashed"]
    assert yaw["mfc_deg_s"]["roll"] != full["mfc_deg_s"]["roll"]
    stiff = ("MC_ROLLRATE_K=3", "MC_PITCHRATE_P=0.45")
    chosen = fly_through(("f450", "ideal", 6.0, None), "rates", sitl_params=stiff)
    asked = fly_through(("f450", "ideal", 6.0, None), "rates", sitl_params=stiff, law_axes="yaw")
    assert chosen["mfc_deg_s"] == asked["mfc_deg_s"]
    assert chosen["law_axes"] == "yaw"
    with pytest.raises(ValueError, match="law_axes: needs output 'rates'"):
        fly_through(("f450", "ideal", 1.0, None), "actuator", law_axes="yaw")


def test_a_link_with_no_target_gets_its_cost_and_no_verdict() -> None:
    flights = [
        _flight("ideal", (6.0, 5.0, 4.0), (5.0, 5.0)),
        _flight("delay_ms=5", (9.0, 6.0, 5.0), (6.0, 6.0)),
    ]
    (row,) = cost_table(flights)
    assert row["cost"] == {"roll": pytest.approx(1.25), "pitch": pytest.approx(1.0)}
    assert row["target"] is None and row["met"] is None


def test_a_bad_link_is_refused_naming_it(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["--link", "uart", "--link", "delay_ms=abc"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "--link: link 'delay_ms=abc': delay_ms='abc': expected milliseconds" in err


@pytest.mark.slow
def test_links_given_are_flown_with_the_ideal_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--link uart --link delay_ms=5``: those two and the ideal link, nothing else;
    UART judged against its target, the 5 ms link given its cost alone."""
    code = main(
        ["--vehicle", "f450", "--duration", "6", "--workers", "1", "--out", str(tmp_path),
         "--link", "uart", "--link", "delay_ms=5", "--link", "ideal"]
    )  # fmt: skip
    assert code == 0
    out = capsys.readouterr().out
    saved = json.loads((tmp_path / "link_limit.json").read_text(encoding="utf-8"))
    assert [f["link"] for f in saved["flights"]] == ["ideal", "uart", "delay_ms=5"]
    rows = {r["link"]: r for r in saved["costs"]}
    assert rows["uart"]["target"] == 1.1 and rows["uart"]["met"] is not None
    assert rows["delay_ms=5"]["target"] is None and rows["delay_ms=5"]["met"] is None
    assert "| f450 | delay_ms=5 |" in out and "vehicle-link pairs within target" in out
    assert out.rstrip().endswith(("1 of 1 vehicle-link pairs within target",
                                  "0 of 1 vehicle-link pairs within target"))  # fmt: skip
