"""The ground station's clock at an autopilot boot time (sitl/lab/realstack/modes.py),
on ATTITUDE rows the ground station's reader thread keeps appending: no stack needed."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import pytest

from sitl.lab.realstack.gcs import Sample
from sitl.lab.realstack.modes import gcs_time_of_boot


class GrowingRows(list[Sample]):
    """ATTITUDE rows that gain one each time they are read, as the reader thread
    appends while the tier reads (the tier's mission test failed on it once:
    ``fp and xp are not of the same length``)."""

    def __iter__(self) -> Any:
        rows = list(super().__iter__())
        last = rows[-1]
        self.append(Sample(last.t_s + 0.02, {"time_boot_ms": last.fields["time_boot_ms"] + 20}))
        return iter(rows)


def test_rows_that_grow_while_read_give_the_time_between_the_two_around_it() -> None:
    # The autopilot's clock 100 s behind the ground station's, rows every 20 ms.
    rows = GrowingRows(Sample(100.0 + 0.02 * k, {"time_boot_ms": 20 * k}) for k in range(50))
    session: Any = SimpleNamespace(gcs=SimpleNamespace(records={"ATTITUDE": rows}))
    assert gcs_time_of_boot(session, 0.5) == pytest.approx(100.5)
    assert gcs_time_of_boot(session, 0.51) == pytest.approx(100.51)
