"""The SITL's log keeps the run's rows only when it has a file to write them to."""

from __future__ import annotations

from pathlib import Path

from sitl.flight_log import LogWriter, read_log

N_MOTORS = 4
ROW = [0.0] * (1 + 3 + 4 + 3 + 3 + 2 * N_MOTORS + 2)


def test_a_run_without_a_log_keeps_no_rows_however_long() -> None:
    log = LogWriter(N_MOTORS, None)
    for _ in range(3 * 16384):  # 49 s at 1 kHz: past three blocks
        log.append(ROW)
    assert log.rows_kept == 0  # they were kept: 192 kB a second at 1 kHz, 17 GB a day
    log.close({})


def test_a_run_with_a_log_writes_every_row(tmp_path: Path) -> None:
    log = LogWriter(N_MOTORS, tmp_path / "run.npz")
    for k in range(16384 + 10):
        log.append([k * 0.001, *ROW[1:]])
    assert log.rows_kept == 16394
    log.close({"status": "completed"})
    assert read_log(tmp_path / "run.npz")["t_s"][-1] == 16393 * 0.001
