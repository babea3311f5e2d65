"""The shipped Foxglove layout plots fields the control log's topics have."""

from __future__ import annotations

import json
from pathlib import Path

from companion.records import EVENTS_TOPIC, columns, topics

LAYOUT = Path(__file__).resolve().parents[2] / "docs" / "foxglove-layout.json"


def _panel_ids(node: object) -> list[str]:
    if isinstance(node, str):
        return [node]
    assert isinstance(node, dict)
    return _panel_ids(node["first"]) + _panel_ids(node["second"])


def test_every_plotted_path_is_a_field_of_a_topic() -> None:
    doc = json.loads(LAYOUT.read_text(encoding="utf-8"))
    fields = {f"{tp.name}.{f}" for tp in topics(columns(4)) for f in tp.fields}
    plotted = [
        p["value"]
        for key, cfg in doc["configById"].items()
        if key.startswith("Plot!")
        for p in cfg["paths"]
    ]
    assert len(plotted) > 20
    assert sorted(set(plotted) - fields) == []
    # Each axis: its rate against its reference; F per axis; saturation; motors; the link.
    for a in ("roll", "pitch", "yaw"):
        assert {f"/rates.ref_{a}_rad_s", f"/rates.meas_{a}_rad_s", f"/law/{a}.f_hat",
                f"/law/{a}.saturated"} <= set(plotted)  # fmt: skip
    assert {"/mixer.motor_1", "/link.sample_age_ms"} <= set(plotted)
    assert doc["configById"]["RawMessages!events"]["topicPath"] == EVENTS_TOPIC
    # The arrangement shows every panel configured, once.
    assert sorted(_panel_ids(doc["layout"])) == sorted(doc["configById"])
