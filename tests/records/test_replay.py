"""Replay a control log recorded from an in-process flight."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

import sitl.lab.simulate as simulate_mod
from companion.config import (
    DEFAULT_CONTROLLER,
    PID_DEFAULT_CONTROLLER,
    MfcConfig,
    build_controller,
    load_controller,
)
from companion.control.mfc import ControlOutput
from companion.profile import VehicleProfile, load_profile
from companion.records import ControlLog, columns, read_control_log
from companion.replay import compare, output_columns, replay
from sitl.scenario import load_scenario

PROFILES = Path(__file__).resolve().parents[2] / "vehicle_profiles"


class _Recording:
    """Wraps the flight's controller to keep every ControlOutput (err, thrust_out)."""

    def __init__(self, inner: Any, outputs: list[ControlOutput]) -> None:
        self._inner = inner
        self._outputs = outputs

    def update(self, *args: Any) -> ControlOutput:
        out: ControlOutput = self._inner.update(*args)
        self._outputs.append(out)
        return out

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


def fly(
    monkeypatch: pytest.MonkeyPatch, cfg: Any, profile: VehicleProfile, duration_s: float
) -> tuple[dict[str, np.ndarray], list[ControlOutput]]:
    outputs: list[ControlOutput] = []
    law = _Recording(build_controller(cfg, profile), outputs)
    sc = load_scenario("step-response").model_copy(update={"duration_s": duration_s})
    rec = simulate_mod.simulate_flight(profile, cfg, sc, law=law)
    assert not rec.meta["crashed"]
    assert len(outputs) == len(rec.columns["t_s"])
    return rec.columns, outputs


def write_log(
    path: Path,
    cols: dict[str, np.ndarray],
    outputs: list[ControlOutput],
    n_motors: int,
    engaged: np.ndarray | None = None,
) -> None:
    """Rows in the columns() layout from a FlightRecord and the outputs it flew with."""
    n = len(cols["t_s"])
    eng = np.ones(n) if engaged is None else engaged
    with ControlLog(path, columns(n_motors), meta={"profile": "f450"}) as log:
        for i in range(n):
            o = outputs[i]
            # The record and the captured outputs are the same flight.
            assert tuple(cols["u"][i]) == o.u and tuple(cols["motors"][i]) == o.motors
            row: list[float] = [cols["t_s"][i], 0.001 * i, 90.0, eng[i], o.held]
            for a in range(3):
                row += [
                    cols["ref_rad_s"][i][a],
                    cols["meas_rad_s"][i][a],
                    o.error[a],
                    o.f_hat[a],
                    o.u[a],
                    o.torque[a],
                    o.saturated_axes[a],
                ]
            row += [cols["thrust"][i], o.thrust, *o.motors, np.nan, np.nan, np.nan, 0.0]
            row += [np.nan, np.nan]  # link_rtt_ms, sample_age_ms: no TIMESYNC answer
            row += [np.nan] * 13  # the outer loops': --mode rates
            row += [np.nan] * 3  # law_ref: the pilot's rates flown unshaped
            row += [np.nan] * 9  # the law's model: not compared by replay
            row += [0.0]  # yaw_share: none offered in --mode rates
            log.append(row)


@pytest.fixture(scope="module")
def f450() -> VehicleProfile:
    return load_profile(PROFILES / "f450.yaml")


@pytest.mark.parametrize("controller", [DEFAULT_CONTROLLER, PID_DEFAULT_CONTROLLER])
def test_replay_reproduces_the_flight(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, f450: VehicleProfile, controller: Path
) -> None:
    cfg = load_controller(controller)
    cols, outputs = fly(monkeypatch, cfg, f450, 3.0)
    path = tmp_path / "flight.csv"
    write_log(path, cols, outputs, f450.n_motors)
    recorded, _ = read_control_log(path)

    replayed = replay(path, cfg, f450)
    assert set(output_columns(f450.n_motors)) <= set(replayed)
    diffs = compare(recorded, replayed)
    expected = {
        *(f"{p}_{a}" for p in ("f_hat", "u", "torque", "sat") for a in ("roll", "pitch", "yaw")),
        *(f"err_{a}_rad_s" for a in ("roll", "pitch", "yaw")),
        *(f"motor_{i}" for i in range(1, 5)),
        "thrust_out",
        "held",
    }
    assert expected <= set(diffs)
    worst = max(diffs.values())
    assert worst < 1e-9, {k: v for k, v in diffs.items() if v >= 1e-9}
    # the flight did something worth reproducing
    assert np.ptp(recorded["torque_roll"]) > 5e-3 and np.ptp(recorded["motor_1"]) > 0.5
    # paths and the columns dict are accepted as well
    again = replay(recorded, str(controller), PROFILES / "f450.yaml")
    assert max(compare(recorded, again).values()) < 1e-9


def test_another_config_gives_other_outputs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, f450: VehicleProfile
) -> None:
    cfg = load_controller(DEFAULT_CONTROLLER)
    assert isinstance(cfg, MfcConfig)
    cols, outputs = fly(monkeypatch, cfg, f450, 2.0)
    path = tmp_path / "flight.csv"
    write_log(path, cols, outputs, f450.n_motors)
    recorded, _ = read_control_log(path)

    data = cfg.model_dump()
    data["axes"]["roll"]["kp"] = 2.0 * data["axes"]["roll"]["kp"]
    data["axes"]["roll"]["kd"] = 0.5 * data["axes"]["roll"]["kd"]
    other = MfcConfig.model_validate(data)
    diffs = compare(recorded, replay(path, other, f450))
    assert diffs["u_roll"] > 1.0
    assert diffs["motor_1"] > 1e-3
    # pitch and yaw laws are untouched and the inputs are the same, but roll
    # changes the mix and so the estimators' "applied" feedback: no exact claim.
    pid = replay(path, load_controller(PID_DEFAULT_CONTROLLER), f450)
    assert compare(recorded, pid)["u_roll"] > 1.0


def test_disengaged_rows_reset_the_controller(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, f450: VehicleProfile
) -> None:
    cfg = load_controller(DEFAULT_CONTROLLER)
    cols, outputs = fly(monkeypatch, cfg, f450, 2.0)
    n = len(cols["t_s"])
    k = n // 2
    engaged = np.ones(n)
    engaged[k - 50 : k] = 0.0
    path = tmp_path / "flight.csv"
    write_log(path, cols, outputs, f450.n_motors, engaged)
    recorded, _ = read_control_log(path)
    replayed = replay(path, cfg, f450)

    # before the gap: the flight itself
    head = {c: v[: k - 50] for c, v in recorded.items()}
    assert max(compare(head, {c: v[: k - 50] for c, v in replayed.items()}).values()) < 1e-9
    # in the gap: nothing (the controller was not flying)
    assert np.isnan(replayed["u_roll"][k - 50 : k]).all()
    # after it: a fresh controller started there, dt = 0 on its first row
    tail = {c: v[k:] for c, v in recorded.items()}
    fresh = replay(tail, cfg, f450)
    for c in output_columns(f450.n_motors):
        np.testing.assert_array_equal(replayed[c][k:], fresh[c], err_msg=c)
    # which is not what was flown (the recorded flight never reset)
    assert compare(tail, fresh)["f_hat_roll"] > 0.0


def test_missing_columns_are_named(tmp_path: Path, f450: VehicleProfile) -> None:
    path = tmp_path / "x.csv"
    with ControlLog(path, ["t_s", "thrust"]) as log:
        log.append((0.0, 0.5))
    with pytest.raises(ValueError, match="meas_roll_rad_s"):
        replay(path, load_controller(DEFAULT_CONTROLLER), f450)
    with pytest.raises(ValueError, match="true_roll_rad_s"):
        replay(path, load_controller(DEFAULT_CONTROLLER), f450, rate_source="true")
