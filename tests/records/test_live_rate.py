"""The live view sends at most RATE_HZ samples a second, by the samples' own stamps."""

from __future__ import annotations

import math

from companion.live import RATE_HZ, LiveView
from companion.records import columns


def _rows_taken(view: LiveView, stamps: list[float]) -> int:
    cols = columns(4)
    t = cols.index("t_s")
    before = len(view._buf)
    for s in stamps:
        row = [0.0] * len(cols)
        row[t] = s
        view.append(row)
    return (len(view._buf) - before) // len(cols)


def test_a_250_hz_stream_is_sent_at_200_a_second_and_a_reboot_restarts_it() -> None:
    view = LiveView(columns(4), port=0, flush_interval_s=1.0)
    view.start()
    try:
        assert RATE_HZ == 200.0
        one_second = [100.0 + k * 0.004 for k in range(250)]
        # Four in five (give or take the one a stamp's last bit decides).
        assert abs(_rows_taken(view, one_second) - 200) <= 1
        # The autopilot rebooted: its stamps start again from zero, and are sent.
        assert abs(_rows_taken(view, [0.5 + k * 0.004 for k in range(250)]) - 200) <= 1
        # A stamp that is not a number is sent (the control log says what it was).
        assert _rows_taken(view, [math.nan]) == 1
    finally:
        view.close()
