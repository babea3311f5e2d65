"""ColumnarLog / read_columnar: round trip, metadata, truncation, a killed writer, cost."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from companion.records import ColumnarLog, columns, read_columnar


def test_columns_layout() -> None:
    cols = columns(4)
    assert cols[:5] == ["t_s", "wall_s", "latency_us", "engaged", "held"]
    assert cols[5:12] == [
        "ref_roll_rad_s", "meas_roll_rad_s", "err_roll_rad_s", "f_hat_roll", "u_roll",
        "torque_roll", "sat_roll",
    ]  # fmt: skip
    assert cols[12] == "ref_pitch_rad_s" and cols[19] == "ref_yaw_rad_s"
    assert cols[-29:-16] == [
        "sat_yaw", "thrust", "thrust_out", "motor_1", "motor_2", "motor_3", "motor_4",
        "sent_roll_rad_s", "sent_pitch_rad_s", "sent_yaw_rad_s", "on_ground",
        "link_rtt_ms", "sample_age_ms",
    ]  # fmt: skip
    assert cols[-16:-3] == [
        "sp_roll_rad", "sp_pitch_rad", "sp_yaw_rad", "est_roll_rad", "est_pitch_rad",
        "est_yaw_rad", "sp_north_m", "sp_east_m", "sp_up_m", "est_north_m", "est_east_m",
        "est_up_m", "outer_gain_scale",
    ]  # fmt: skip
    assert cols[-3:] == ["law_ref_roll_rad_s", "law_ref_pitch_rad_s", "law_ref_yaw_rad_s"]
    assert len(cols) == 5 + 21 + 2 + 4 + 3 + 1 + 2 + 13 + 3
    assert len(columns(6)) == len(cols) + 2
    with pytest.raises(ValueError):
        columns(0)


def random_rows(n: int, ncol: int, seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    # awkward magnitudes: tiny, huge, negative, exact binary fractions
    scale = 10.0 ** rng.integers(-12, 8, size=(n, ncol))
    return rng.standard_normal((n, ncol)) * scale


def test_round_trip_with_metadata(tmp_path: Path) -> None:
    cols = columns(4)
    data = random_rows(500, len(cols))
    data[:, 3] = 1.0  # engaged
    data[7, 4] = True  # held as a bool
    data[8, 6] = np.nan  # a held (non-finite) measurement
    meta = {"profile": "f450", "controller": "mfc", "note": "two\nlines: ok"}
    path = tmp_path / "a" / "flight.bin"
    with ColumnarLog(path, cols, meta=meta) as log:
        for row in data:
            log.append(row.tolist())
        log.append((True, *data[0, 1:].tolist()))  # bools and tuples are fine
    assert log.rows == 501

    assert path.read_bytes().startswith(b"# ")
    got, gmeta = read_columnar(path)
    assert list(got) == cols
    assert gmeta["profile"] == "f450" and gmeta["controller"] == "mfc"
    assert gmeta["note"] == "two lines: ok"
    assert {"version", "byteorder", "start_unix_s", "start_utc", "format"} <= set(gmeta)
    assert abs(float(gmeta["start_unix_s"]) - time.time()) < 60
    for j, c in enumerate(cols):
        # Binary float64: every column bit for bit (NaN where NaN).
        np.testing.assert_array_equal(got[c][:500], data[:, j])
    assert got["held"][7] == 1.0 and got["t_s"][500] == 1.0


def test_wrong_row_length_raises(tmp_path: Path) -> None:
    cols = columns(4)
    with ColumnarLog(tmp_path / "x.bin", cols) as log:
        n = len(cols)
        with pytest.raises(ValueError, match=f"{n - 1} values, expected {n}"):
            log.append([0.0] * (n - 1))
        with pytest.raises(ValueError, match=f"{n + 1} values, expected {n}"):
            log.append([0.0] * (n + 1))
        log.append([0.0] * n)
    got, _ = read_columnar(tmp_path / "x.bin")
    assert len(got["t_s"]) == 1


def test_bad_columns_rejected(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="duplicate"):
        ColumnarLog(tmp_path / "x.bin", ["a", "a"])
    with pytest.raises(ValueError, match="invalid column"):
        ColumnarLog(tmp_path / "y.bin", ["a,b"])


def test_truncated_last_row_is_ignored(tmp_path: Path) -> None:
    path = tmp_path / "t.bin"
    cols = ["t_s", "x", "y"]
    with ColumnarLog(path, cols, meta={"k": "v"}) as log:
        for i in range(10):
            log.append((i * 0.001, i, -i))
    full = path.read_bytes()
    for cut in (len(full) - 3, len(full) - 8, len(full) - 23):  # inside the last row
        path.write_bytes(full[:cut])
        got, meta = read_columnar(path)
        assert meta["k"] == "v"
        np.testing.assert_array_equal(got["x"], np.arange(9.0))
    # header only, and a header cut short
    header_end = full.index(b"rows follow\n") + len(b"rows follow\n")
    path.write_bytes(full[:header_end])
    got, _ = read_columnar(path)
    assert got["t_s"].shape == (0,)
    path.write_bytes(full[: header_end - 3])
    with pytest.raises(ValueError, match=r"t\.bin"):
        read_columnar(path)


def test_a_value_that_is_not_a_number_raises_and_keeps_rows_whole(tmp_path: Path) -> None:
    path = tmp_path / "n.bin"
    with ColumnarLog(path, ["a", "b"]) as log:
        log.append((1.0, 2.0))
        with pytest.raises(ValueError, match="not a number"):
            log.append((3.0, "x"))  # type: ignore[arg-type]
        log.append((5.0, 6.0))
    got, _ = read_columnar(path)
    np.testing.assert_array_equal(got["a"], [1.0, 5.0])


_KILLED_WRITER = textwrap.dedent(
    """
    import os, signal, sys, time
    from companion.records import ColumnarLog, columns

    cols = columns(4)
    log = ColumnarLog(sys.argv[1], cols, meta={"profile": "f450"}, flush_interval_s=0.2)
    start = time.monotonic()
    k = 0
    while True:
        t = time.monotonic() - start
        if t >= 1.0:
            break
        log.append([k * 0.001, t] + [0.5] * (len(cols) - 2))
        k += 1
        time.sleep(0.001)
    sys.stdout.write(f"{k} {t!r}\\n")
    sys.stdout.flush()
    os.kill(os.getpid(), signal.SIGKILL)
    """
)


def test_killed_writer_loses_at_most_the_last_flush_interval(tmp_path: Path) -> None:
    path = tmp_path / "killed.bin"
    proc = subprocess.run(
        [sys.executable, "-c", _KILLED_WRITER, str(path)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    n_str, last_str = proc.stdout.split()
    n_rows, last_wall = int(n_str), float(last_str)
    got, meta = read_columnar(path)
    assert meta["profile"] == "f450"
    k = got["t_s"] / 0.001
    np.testing.assert_allclose(k, np.arange(len(k)), atol=1e-6)  # intact and in order
    assert 100 < len(k) <= n_rows
    # the rows lost are those of the last flush interval at most (plus slack)
    assert last_wall - got["wall_s"][-1] < 0.2 + 0.05
