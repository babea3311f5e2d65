"""``--live``: a real Foxglove WebSocket client watches a real flight.

The viewer (:mod:`sitl.lab.live_viewer`) speaks the protocol to the
companion's server as the Foxglove app does, while ``companion fly`` (the SITL
and ``companion run`` as two processes, lockstep) flies paper-acro.
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.control import AXES
from companion.live import RATE_HZ
from companion.records import EVENTS_TOPIC, columns, topics
from sitl.lab.fly import fly_mavlink, free_tcp_port, merge_logs
from sitl.lab.live_viewer import Seen, watch
from sitl.lab.report import compute_metrics

pytestmark = [pytest.mark.integration, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
F450 = ROOT / "vehicle_profiles" / "f450.yaml"


class _Viewer:
    """A viewer watching in a thread of its own while the flight runs."""

    def __init__(self, port: int, **kwargs: Any) -> None:
        self.seen: Seen | None = None
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(port, kwargs), daemon=True)
        self._thread.start()

    def _run(self, port: int, kwargs: dict[str, Any]) -> None:
        try:
            self.seen = asyncio.run(watch(f"ws://127.0.0.1:{port}", **kwargs))
        except BaseException as exc:
            self.error = exc

    def result(self) -> Seen:
        self._thread.join(120)
        assert self.error is None, repr(self.error)
        assert self.seen is not None
        return self.seen


def _last_counters(events: list[dict[str, Any]]) -> dict[str, int]:
    detail = [e["detail"] for e in events if e["kind"] == "counters"][-1]
    return {
        k: int(v) for k, v in (p.split("=", 1) for p in detail.split()) if "." in k and v.isdigit()
    }


def test_a_viewer_sees_every_topic_of_a_flight_as_it_flies(tmp_path: Path) -> None:
    """``companion fly --live``: every topic advertised with its schema, the messages
    decoded, and what they say is the flight's: the roll rate follows its
    reference about as well as the flight's own metrics say it did."""
    port = free_tcp_port()
    viewer = _Viewer(port, seconds=90.0, until_closed=True, connect_timeout_s=60.0)
    out = tmp_path / "fly"
    proc = subprocess.run(
        [sys.executable, "-m", "companion", "fly", "--out", str(out), "--no-progress",
         "--duration", "10", "--live", f"127.0.0.1:{port}"],
        cwd=ROOT, capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    seen = viewer.result()
    assert seen.server_info["name"] == "mfc-companion"
    expected = {tp.name for tp in topics(columns(4))} | {EVENTS_TOPIC}
    assert expected <= set(seen.channels), sorted(seen.channels)
    for name in expected:
        ch = seen.channels[name]
        assert ch["encoding"] == "json"
    metrics = json.loads((out / "metrics.json").read_text(encoding="utf-8"))
    # Every sample of the engaged flight reached the viewer (it read as fast as
    # they came): one /rates message per sample, matched with /mixer by log time.
    engaged_at = {t: m["engaged"] for t, m in seen.messages["/mixer"] if m["engaged"] is not None}
    rates = [(t, m) for t, m in seen.messages["/rates"] if engaged_at.get(t) == 1.0]
    # The F450's IMU at 250 Hz, sent at most RATE_HZ a second (four in five).
    assert len(rates) >= 10.0 * min(250.0, RATE_HZ) - 2, len(rates)
    for a in AXES:
        ref = np.array([m[f"ref_{a}_rad_s"] for _, m in rates], dtype=float)
        meas = np.array([m[f"meas_{a}_rad_s"] for _, m in rates], dtype=float)
        mae = float(np.degrees(np.mean(np.abs(meas - ref))))
        # The flight's MAE is against the SITL's true rates; the gyro the law saw is
        # the same flight's, within its noise.
        assert mae == pytest.approx(metrics["mae_deg_s"][a], rel=0.5, abs=1.0), (a, mae)
    ref_roll = np.array([m["ref_roll_rad_s"] for _, m in rates])
    assert np.ptp(ref_roll) > 1.0  # the pilot really rolled
    law = [m for t, m in seen.messages["/law/roll"] if engaged_at.get(t) == 1.0]
    f_hat = np.array([m["f_hat"] for m in law], dtype=float)
    assert len(law) == len(rates) and np.isfinite(f_hat).all() and np.ptp(f_hat) > 0.0
    kinds = [m["kind"] for _, m in seen.messages[EVENTS_TOPIC]]
    assert "engaged" in kinds and "counters" in kinds, kinds
    # Log times are the IMU stamps, as in control.mcap: increasing while engaged (the
    # SITL's clock may jump before, at its start).
    times = [t for t, _ in rates]
    assert (np.diff(times) > 0).all() and times[0] > 0


@pytest.mark.long
def test_a_viewer_that_stops_reading_costs_the_flight_nothing(tmp_path: Path) -> None:
    """A viewer subscribed to everything that stops reading half a second after its
    first message:
    the flight is the same flight, sample for sample, as one with nobody watching
    (lockstep flights of one seed are identical), and the messages the SDK dropped
    for the viewer are counted in the run's counters.

    25 s of flight: the kernel takes up to 4 MB (tcp_wmem's largest send buffer)
    of what the viewer does not read before the SDK's own backlog (4096 messages)
    fills, and a 10 s flight (about 17 000 messages) did not always pass that
    (seen in the suite with both cores busy)."""
    duration_s = 25.0
    kwargs: dict[str, Any] = {"duration_s": duration_s}
    alone = fly_mavlink(F450, "paper-acro", tmp_path / "alone", **kwargs)
    port = free_tcp_port()
    # On a slow link: a small receive buffer, so its socket fills up within the flight.
    viewer = _Viewer(port, seconds=40.0, stop_reading_after_s=0.5, keep=False,
                     rcvbuf_bytes=4096, connect_timeout_s=60.0)  # fmt: skip
    watched = fly_mavlink(
        F450,
        "paper-acro",
        tmp_path / "watched",
        companion_args=("--live", f"127.0.0.1:{port}"),
        **kwargs,
    )
    for f in (alone, watched):
        assert f.companion_rc == 0, f.why()
    seen = viewer.result()
    assert seen.counts.get("/rates", 0) > 0  # it was subscribed and got some first
    metrics = [compute_metrics(merge_logs(f)) for f in (alone, watched)]
    for m in metrics:
        m.pop("wall_time_s", None)
    assert metrics[0] == metrics[1]
    counters = _last_counters(watched.companion_events)
    assert counters.get("live.viewer_overflows", 0) >= 1, counters
    # Seven topics of every sample sent (at most RATE_HZ a second) while engaged.
    assert counters.get("live.published", 0) > 0.9 * duration_s * RATE_HZ * 7, counters
