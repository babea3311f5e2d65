"""The oracle of sitl/lab/oracle.py, flown in the lab's simulation, and its hook.

Flights are slices of ``paper-acro`` to keep this file near 20 s on one worker:
the first ``SLICE_S`` s (take-off, an all-axis wiggle, a punch, the roll flip, a
roll reversal, a punch and the back flip), not the full 60 s the paper's figures
come from. Every figure is the flights' own: the MAE against the filtered gyro.
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.config import build_controller, load_controller
from companion.control import AXES
from companion.profile import VehicleProfile, load_profile
from sitl.lab.oracle import (
    COLLECTIVE_MARGIN_M,
    OracleController,
    collective_command,
    fly_oracle,
    oracle_flight,
)
from sitl.lab.paper.analysis import motion_limits
from sitl.lab.report import compute_metrics
from sitl.lab.simulate import FlightRecord, simulate_flight
from sitl.scenario import Scenario, load_scenario

ROOT = Path(__file__).resolve().parents[2]
SLICE_S = 17.0
PAPER_VEHICLES = ("f450", "f450_cut_props", "tarot650")
IDEAL_TOLERANCE = 0.12
"""Relative, either way: the oracle's roll and pitch MAE against the offline ideal
tracker's on the same reference through the same filter. The ideal tracker has no
noise, no coupling between the axes, no spread shared by roll and pitch and one lag;
on this slice the oracle is 1 % (roll) and 10 % (pitch) above it, on the full flight
6 % and 5 %."""


def _profile(name: str) -> VehicleProfile:
    return load_profile(ROOT / "vehicle_profiles" / f"{name}.yaml")


def _slice(duration_s: float = SLICE_S) -> Scenario:
    return load_scenario("paper-acro").model_copy(update={"duration_s": duration_s})


@functools.cache
def _oracle(profile: str, duration_s: float = SLICE_S) -> FlightRecord:
    rec: FlightRecord = fly_oracle(_profile(profile), _slice(duration_s))
    return rec


@functools.cache
def _mfc_mae(profile: str) -> dict[str, float]:
    m = compute_metrics(simulate_flight(_profile(profile), load_controller(), _slice()))
    assert not m["crashed"]
    mae: dict[str, float] = m["mae_deg_s"]
    return mae


def test_the_oracle_reaches_the_offline_ideal_tracker_on_roll_and_pitch() -> None:
    """Same reference (the oracle flight's own, airborne), same gyro filter, no noise
    for the ideal tracker: within ``IDEAL_TOLERANCE`` either way on the F450 (its two
    motor time constants are equal, so the ideal tracker's lag is the plant's; on the
    Tarot and the x500 it takes the faster of two and the oracle sits 10-15 % above)."""
    profile = _profile("f450")
    rec = _oracle("f450")
    m = compute_metrics(rec)
    assert not m["crashed"]
    weight = _slice().imu_model(profile).first_stage_filter_weight
    ideal = motion_limits(rec, profile, weight)["ideal_tracker_measured_deg_s"]
    for axis in AXES[:2]:
        ratio = m["mae_deg_s"][axis] / ideal[axis]
        assert abs(ratio - 1.0) <= IDEAL_TOLERANCE, (axis, m["mae_deg_s"], ideal)


@pytest.mark.parametrize("axis", AXES[:2])
@pytest.mark.parametrize(
    "profile",
    # The default run flies the F450; the others are long checks (scripts/test --long).
    [p if p == "f450" else pytest.param(p, marks=pytest.mark.long) for p in PAPER_VEHICLES],
)
def test_the_oracle_is_no_worse_than_mfc_on_roll_and_pitch(profile: str, axis: str) -> None:
    """The shipped MFC (mfc_default.yaml given the vehicle's own profile, as the paper
    flights) against the oracle on the same slice, axis by axis, as measured.

    Not on yaw: there the oracle trails MFC today on every paper vehicle (17 s slice:
    F450 1.26 vs 0.85, cut props 5.04 vs 3.76, Tarot 1.67 vs 1.01 deg/s; full flight
    7.7 vs 7.2, 26.4 vs 24.9, 13.0 vs 11.7): it tracks the true rate behind the
    mixer's roll-and-pitch-first priority while MFC closes its loop on the filtered
    gyro. What the oracle should aim at on yaw is an open question, not a test.

    Within 6 %: the oracle tracks the true rate and the figures are read from the
    filtered gyro, and it plans through the product's mixer while the plant's
    autopilot allocates as PX4 does (``sitl.px4_control``), so MFC can edge it on a
    slice. It does on the cut props' pitch, where the allocator saturates and the
    oracle's switching law turns the allocator's last bits into a different flight:
    with the pseudo-inverse from LAPACK, its pitch on this slice was 7.356, 7.548
    and 7.585 under three of OpenBLAS's CPU kernels; computed in a fixed order
    (``sitl.linalg``, the same on every machine) it is 7.564 against MFC's 7.186,
    5.3 %. On the other five it leads MFC by 5-9 % (``python -c`` over
    ``_oracle`` and ``_mfc_mae``, 2026-11-30)."""
    m = compute_metrics(_oracle(profile))
    mfc = _mfc_mae(profile)
    assert not m["crashed"]
    assert m["mae_deg_s"][axis] <= 1.06 * mfc[axis], (axis, m["mae_deg_s"], mfc)


class _Riding:
    """An MFC controller flown as usual, with an oracle riding along through the hook.

    Every attribute is the MFC's; ``see_plant`` hands the plant to the oracle, which
    answers the same sample (its command is kept, never sent)."""

    def __init__(self, inner: Any, oracle: OracleController) -> None:
        object.__setattr__(self, "_inner", inner)
        object.__setattr__(self, "_oracle", oracle)
        object.__setattr__(self, "shadow", [])
        object.__setattr__(self, "seen_rates", [])

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)

    def __setattr__(self, name: str, value: Any) -> None:
        setattr(self._inner, name, value)

    def see_plant(self, quad: Any) -> None:
        self._oracle.see_plant(quad)
        self.seen_rates.append(quad.state.rate_frd_rad_s)

    def update(self, dt: float, gyro: Any, ref: Any, thrust: float) -> Any:
        self.shadow.append(self._oracle.update(dt, gyro, ref, thrust).u)
        return self._inner.update(dt, gyro, ref, thrust)


def test_the_hook_leaves_a_normal_flight_unchanged() -> None:
    """The same MFC flight, bit for bit, with an oracle reading the plant through the
    hook at every sample; the hook gives it the true state the flight records, and the
    oracle asks for torque the same way MFC does (it is not idle)."""
    profile = _profile("f450")
    sc = _slice(8.0)
    cfg = load_controller()
    plain = simulate_flight(profile, cfg, sc)
    oracle = OracleController(profile, period_s=1.0 / sc.imu_model(profile).rate_hz)
    riding = _Riding(build_controller(cfg, profile), oracle)
    watched = simulate_flight(profile, cfg, sc, law=riding)
    assert plain.columns.keys() == watched.columns.keys()
    for key, col in plain.columns.items():
        np.testing.assert_array_equal(col, watched.columns[key], err_msg=key)
    drop = {"wall_time_s"}
    assert {k: v for k, v in plain.meta.items() if k not in drop} == {
        k: v for k, v in watched.meta.items() if k not in drop
    }
    np.testing.assert_array_equal(np.array(riding.seen_rates), plain.columns["true_rad_s"])
    shadow = np.array(riding.shadow)
    air = plain.columns["airborne"].astype(bool)
    for i, axis in enumerate(AXES):
        # Measured 0.42 / 0.46 / 0.72: the oracle answers the same errors, harder.
        corr = np.corrcoef(shadow[air, i], plain.columns["torque"][air, i])[0, 1]
        assert corr > 0.3, (axis, corr)


def test_the_oracle_flight_is_deterministic() -> None:
    """Same seed, same figures (the wall time aside); and they are a flight's figures."""
    profile = _profile("x500")
    sc = _slice(7.0)
    a = oracle_flight(profile, sc, seed=5)
    b = oracle_flight(profile, sc, seed=5)
    a.pop("wall_time_s")
    b.pop("wall_time_s")
    assert a == b
    assert a["controller"] == "oracle" and not a["crashed"]
    assert a["airborne_time_s"] > 2.0
    mae = a["mae_deg_s"]
    assert all(0.0 < mae[axis] < 5.0 for axis in AXES), mae


def test_the_collective_oracle_sets_the_collective_and_tracks_as_well() -> None:
    """With the collective its own, the oracle flies the slice (through the roll and
    the back flip, where it cuts the thrust while it points down) as it tracks without."""
    profile = _profile("f450")
    rec = fly_oracle(profile, _slice(), collective=True)
    m = compute_metrics(rec)
    base = compute_metrics(_oracle("f450"))
    assert not m["crashed"] and m["controller"] == "oracle+collective"
    assert not np.array_equal(rec.columns["motors"], _oracle("f450").columns["motors"])
    for axis in AXES[:2]:
        assert m["mae_deg_s"][axis] <= 1.05 * base["mae_deg_s"][axis], (m, base)
    assert m["mae_deg_s"]["roll"] < 10.0, m["mae_deg_s"]  # a flight's figure (8.2 measured)


@pytest.mark.parametrize(
    ("pilot", "altitude_m", "climb_m_s", "cos_tilt", "want"),
    [
        (0.6, 8.0, -2.0, -0.5, 0.05),  # thrust points down: none
        (0.3, 2.0, -4.0, 0.9, 1.0),  # sinking within the braking distance: all of it
        (0.3, 20.0, -4.0, 0.9, 0.3),  # high enough: the pilot's
        (0.3, 0.5, 1.0, 0.9, 0.3),  # climbing near the ground: the pilot's
        (0.01, 30.0, 0.0, 1.0, 0.05),  # never below idle
    ],
)
def test_the_collective_law(
    pilot: float, altitude_m: float, climb_m_s: float, cos_tilt: float, want: float
) -> None:
    got = collective_command(
        pilot,
        altitude_m=altitude_m,
        climb_rate_m_s=climb_m_s,
        cos_tilt=cos_tilt,
        brake_m_s2=4.0,
        idle=0.05,
    )
    assert got == pytest.approx(want)
    # The braking distance: 4 m/s at 4 m/s^2 takes 2 m, plus the margin.
    assert math.isclose(COLLECTIVE_MARGIN_M + 4.0**2 / (2 * 4.0), 3.0)


def test_simulate_oracle_adds_the_oracles_figures_to_metrics_json(tmp_path: Path) -> None:
    """``companion simulate --oracle``: metrics.json gains the oracle's MAE on the same
    flight, the flight's ratio to it, and the feasibility verdict (a flight that flew
    is feasible); the figures are the oracle flight's own."""
    from click.testing import CliRunner

    from companion.cli import cli

    text = (ROOT / "sitl" / "scenarios" / "paper-acro.yaml").read_text(encoding="utf-8")
    scenario = tmp_path / "short.yaml"
    scenario.write_text(text.replace("name: paper-acro", "name: short") + "duration_s: 6.0\n")
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["simulate", "--profile", "vehicle_profiles/x500.yaml",
                                   "--scenario", str(scenario), "--out", str(out),
                                   "--no-progress", "--oracle"])  # fmt: skip
    assert res.exit_code == 0, res.output
    metrics = json.loads((out / "metrics.json").read_text(encoding="utf-8"))
    oracle = metrics["oracle"]
    want = oracle_flight(_profile("x500"), load_scenario(str(scenario)))
    assert oracle["mae_deg_s"] == want["mae_deg_s"] and oracle["crashed"] is False
    for axis in AXES:
        ratio = metrics["mae_deg_s"][axis] / want["mae_deg_s"][axis]
        assert oracle["ratio"][axis] == pytest.approx(ratio, abs=1e-3)
    assert oracle["feasible"] is True
    assert "oracle: MAE roll" in res.output
