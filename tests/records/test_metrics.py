"""metrics.json from a companion control log and a SITL log: held and non-finite samples."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.control import AXES
from companion.records import ControlLog, columns
from sitl.lab.fly import FlightProcesses, merge_logs
from sitl.lab.report import compute_metrics, write_report

N = 100
MEAS_RAD_S = (0.1, 0.2, -0.3)
"""Measured rate per axis on every valid sample; the pilot commands 0."""
TRUE_RAD_S = 0.05
NAN_ROWS = range(40, 45)
"""Samples whose gyro was NaN: held, error NaN (as an ``imu-nan`` fault leaves them)."""
HELD_FINITE_ROW = 60
"""A held sample whose gyro was finite (another input was not)."""


def write_flight(out: Path, *, held_rows: Any = ()) -> FlightProcesses:
    """A 100-sample engaged, airborne flight: ``out/companion/control.mcap``, ``out/sitl.npz``."""
    t = 10.0 + 0.004 * np.arange(N)
    names = columns(4)
    with ControlLog(out / "companion" / "control.mcap", names, meta={"profile": "f450"}) as log:
        for i, t_s in enumerate(t):
            row = dict.fromkeys(names, 0.0)
            row.update(t_s=t_s, wall_s=t_s, engaged=1.0)
            held = i in NAN_ROWS or i == HELD_FINITE_ROW or i in held_rows
            row["held"] = float(held)
            for a, meas in zip(AXES, MEAS_RAD_S, strict=True):
                if i in NAN_ROWS:
                    meas = math.nan
                elif held:
                    meas = 5.0  # finite, but not what the controller acted on
                row[f"meas_{a}_rad_s"] = meas
                row[f"err_{a}_rad_s"] = math.nan if i in NAN_ROWS else meas
            log.append([row[c] for c in names])
    sitl_t = np.arange(0.0, 11.0, 0.001)
    n = len(sitl_t)
    np.savez(
        out / "sitl.npz",
        t_s=sitl_t,
        rate_frd_rad_s=np.full((n, 3), TRUE_RAD_S),
        q_wxyz=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)),
        pos_ned_m=np.tile([0.0, 0.0, -1.0], (n, 1)),  # 1 m up: airborne throughout
        summary=np.array(json.dumps({"status": "completed"})),
    )
    return FlightProcesses(out, 0, 0, 1.0, sitl_summary={"status": "completed"})


def _no_nan(name: str) -> Any:
    raise AssertionError(f"metrics.json holds {name}")


def test_held_and_nonfinite_samples_are_left_out_of_the_error_metrics(tmp_path: Path) -> None:
    flight = write_flight(tmp_path)
    record = merge_logs(flight)
    assert record.columns["held"].sum() == len(NAN_ROWS) + 1
    write_report(record, tmp_path, controller_path="none.yaml", profile_path="none.yaml")
    text = (tmp_path / "metrics.json").read_text(encoding="utf-8")
    m = json.loads(text, parse_constant=_no_nan)  # strict JSON: no NaN, no Infinity
    expected = {a: round(math.degrees(abs(v)), 3) for a, v in zip(AXES, MEAS_RAD_S, strict=True)}
    assert m["mae_deg_s"] == expected
    assert m["rms_deg_s"] == expected
    assert m["max_abs_deg_s"] == expected
    assert m["mae_true_deg_s"] == dict.fromkeys(AXES, round(math.degrees(TRUE_RAD_S), 3))
    assert m["mae_skipped_samples"] == len(NAN_ROWS) + 1
    assert m["samples"] == N
    assert m["nonfinite_events"] == len(NAN_ROWS) + 1


def test_a_flight_without_skipped_samples_counts_zero(tmp_path: Path) -> None:
    record = merge_logs(write_flight(tmp_path))
    record.columns["held"][:] = False
    record.columns["meas_rad_s"][np.isnan(record.columns["meas_rad_s"])] = 0.1
    m = compute_metrics(record)
    assert m["mae_skipped_samples"] == 0
    assert all(math.isfinite(v) for v in m["mae_deg_s"].values())


def test_nothing_valid_while_airborne_gives_no_error_metrics(tmp_path: Path) -> None:
    m = compute_metrics(merge_logs(write_flight(tmp_path, held_rows=range(N))))
    assert m["mae_skipped_samples"] == N
    for key in ("mae_deg_s", "rms_deg_s", "max_abs_deg_s", "mae_true_deg_s"):
        assert m[key] == dict.fromkeys(AXES), key
    # Saturation is about what the mixer did, held or not: still measured.
    assert m["time_in_saturation_s"]["any"] == pytest.approx(0.0)
    json.dumps(m, allow_nan=False)
