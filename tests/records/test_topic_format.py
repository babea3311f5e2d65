"""The topics' JSON messages, as the control log and the live view both write them."""

from __future__ import annotations

import json
import math

import numpy as np

from companion.records.topics import TopicFormat, columns, event_json, stamps_ns, topics

COLS = columns(4)


def _topic(name: str) -> TopicFormat:
    return TopicFormat(next(tp for tp in topics(COLS) if tp.name == name))


def test_a_row_reads_back_exactly_with_null_for_non_finite_and_the_sign_of_zero() -> None:
    fm = _topic("/rates")
    data = np.full((3, len(COLS)), 0.1)
    data[0, fm.topic.columns] = np.linspace(-1.0, 1.0, len(fm.topic.columns)) / 3.0
    data[1, fm.topic.columns[0]] = math.nan
    data[1, fm.topic.columns[1]] = -0.0
    data[2, fm.topic.columns[2]] = math.inf
    msgs = fm.messages(data)
    for r, msg in enumerate(msgs):
        assert msg is not None
        got = json.loads(msg)
        assert list(got) == list(fm.topic.fields)
        for field, col in zip(fm.topic.fields, fm.topic.columns, strict=True):
            want = data[r, col]
            if math.isfinite(want):
                assert got[field] == want and math.copysign(1.0, got[field]) == math.copysign(
                    1.0, want
                ), (r, field)
            else:
                assert got[field] is None, (r, field)
    assert isinstance(json.loads(msgs[1] or "")[fm.topic.fields[1]], float)  # -0.0, not -0


def test_a_sparse_topic_says_nothing_for_a_row_with_nothing_finite() -> None:
    fm = _topic("/outer")
    assert fm.topic.sparse
    data = np.zeros((2, len(COLS)))
    data[:, fm.topic.columns] = math.nan
    data[1, fm.topic.columns[0]] = 1.5
    msgs = fm.messages(data)
    assert msgs[0] is None and msgs[1] is not None


def test_stamps_and_events() -> None:
    assert stamps_ns(np.array([1.5, math.nan, -2.0, 0.000_000_001])) == [1_500_000_000, 0, 0, 1]
    assert json.loads(event_json({"t_s": 1.0, "x": math.nan, "p": object})) == {
        "t_s": 1.0,
        "x": None,
        "p": str(object),
    }
