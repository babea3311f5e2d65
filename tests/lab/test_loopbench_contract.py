"""``run_loop_bench``'s result keys (what ``scripts/bench.py loop --json`` prints).

The loop benchmark's contract: at least ``latency_us_p50``, ``latency_us_p99``,
``floor_us_p50``, ``floor_us_p99``, their ratio and ``missed_at_<rate>``; the
harness also reports late answers and the sample count. A short run at 250 Hz
against the real companion and the floor server; no timing target is asserted
(the machine is shared and noisy), only that every figure is there and sane.
"""

from __future__ import annotations

import math

import pytest

from sitl.lab.loopbench import run_loop_bench

pytestmark = pytest.mark.integration


@pytest.mark.long
def test_run_loop_bench_returns_every_contract_key() -> None:
    seconds, rate_hz = 2.0, 250.0
    out = run_loop_bench(seconds=seconds, rate_hz=rate_hz)
    assert isinstance(out, dict)
    latency = ("latency_us_p50", "latency_us_p99", "floor_us_p50", "floor_us_p99")
    counts = ("missed_at_250hz", "late", "floor_late", "samples")
    for key in (*latency, "ratio_p50", "ratio_p99", *counts):
        assert key in out, (key, sorted(out))
    # The missed-sample key is named after the rate (1 kHz is missed_at_1khz).
    assert "missed_at_1khz" not in out
    for key in (*latency, "ratio_p50", "ratio_p99"):
        assert isinstance(out[key], float) and math.isfinite(out[key]) and out[key] > 0.0, (
            key,
            out[key],
        )
    for key in counts:
        assert isinstance(out[key], int) and not isinstance(out[key], bool), (key, out[key])
        assert out[key] >= 0, (key, out[key])
    assert out["latency_us_p50"] <= out["latency_us_p99"]
    assert out["floor_us_p50"] <= out["floor_us_p99"]
    # The ratios are of the figures reported (each rounded to 0.1 us, ratio to 0.001).
    assert out["ratio_p50"] == pytest.approx(out["latency_us_p50"] / out["floor_us_p50"], abs=1e-3)
    assert out["ratio_p99"] == pytest.approx(out["latency_us_p99"] / out["floor_us_p99"], abs=1e-3)
    # Every slot of the run was either offered (a sample) or skipped by a late
    # harness, and a sample can only be missed or late if it was sent.
    slots = seconds * rate_hz
    assert 0.9 * slots <= out["samples"] + out["skipped"] <= 1.02 * slots, out
    assert out["samples"] > 0
    assert out["missed_at_250hz"] <= out["samples"]
    assert out["late"] <= out["samples"]
    # The companion served the whole run (no failsafe ended it early).
    assert out["ended_early"] is False and out["floor_ended_early"] is False
    assert out["rate_hz"] == rate_hz and out["seconds"] == seconds
    assert isinstance(out["targets_met"], bool)
