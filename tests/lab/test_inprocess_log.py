"""An in-process flight writes the control log companion run writes: same topics,
read back by the format's reference reader (mcap) and by companion replay."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from companion.config import load_controller
from companion.profile import load_profile
from companion.records import EVENTS_TOPIC, columns, read_control_log, topics
from companion.replay import compare, replay
from sitl.lab.simulate import simulate_flight
from sitl.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[2]


def test_a_simulated_flight_opens_as_a_real_one_and_replays_exactly(tmp_path: Path) -> None:
    profile = load_profile(ROOT / "vehicle_profiles" / "f450.yaml")
    sc = load_scenario("paper-acro").model_copy(update={"duration_s": 2.0})
    path = tmp_path / "control.mcap"
    rec = simulate_flight(profile, load_controller(), sc, control_log=path)
    n = len(rec.columns["t_s"])
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics is not None
    counts = {
        c.topic: summary.statistics.channel_message_counts.get(c.id, 0)
        for c in summary.channels.values()
    }
    assert set(counts) == {t.name for t in topics(columns(4))} | {EVENTS_TOPIC}
    assert counts["/law/roll"] == counts["/rates"] == n
    assert counts[EVENTS_TOPIC] >= 2  # engaged, the landed state
    cols, _ = read_control_log(path)
    np.testing.assert_array_equal(cols["t_s"], rec.columns["t_s"])
    np.testing.assert_array_equal(cols["u_roll"], np.asarray(rec.columns["u"])[:, 0])
    diffs = compare(cols, replay(path, load_controller(), profile))
    assert max(diffs.values()) == 0.0, diffs
