"""The control log as MCAP, read back with the ``mcap`` package (the reference reader).

Its topics and schemas, exact values, the two clocks, the events, a killed
writer (a real process, SIGKILLed), and :func:`read_control_log` against what
the reference reader sees.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.exceptions import EndOfFile
from mcap.reader import NonSeekingReader, make_reader

from companion.records import (
    ControlLog,
    RecordWriter,
    columns,
    last_sample_time,
    read_control_log,
    topics,
)

ROOT = Path(__file__).resolve().parents[2]
TOPICS = ["/rates", "/law/roll", "/law/pitch", "/law/yaw", "/mixer", "/link", "/outer", "/events"]


def test_columns_layout() -> None:
    cols = columns(4)
    assert cols[:5] == ["t_s", "wall_s", "latency_us", "engaged", "held"]
    assert cols[5:12] == [
        "ref_roll_rad_s", "meas_roll_rad_s", "err_roll_rad_s", "f_hat_roll", "u_roll",
        "torque_roll", "sat_roll",
    ]  # fmt: skip
    assert cols[12] == "ref_pitch_rad_s" and cols[19] == "ref_yaw_rad_s"
    assert cols[-39:-26] == [
        "sat_yaw", "thrust", "thrust_out", "motor_1", "motor_2", "motor_3", "motor_4",
        "sent_roll_rad_s", "sent_pitch_rad_s", "sent_yaw_rad_s", "on_ground",
        "link_rtt_ms", "sample_age_ms",
    ]  # fmt: skip
    assert cols[-26:-13] == [
        "sp_roll_rad", "sp_pitch_rad", "sp_yaw_rad", "est_roll_rad", "est_pitch_rad",
        "est_yaw_rad", "sp_north_m", "sp_east_m", "sp_up_m", "est_north_m", "est_east_m",
        "est_up_m", "outer_gain_scale",
    ]  # fmt: skip
    assert cols[-13:-10] == ["law_ref_roll_rad_s", "law_ref_pitch_rad_s", "law_ref_yaw_rad_s"]
    assert cols[-10:-1] == [
        "alpha_roll", "alpha_pitch", "alpha_yaw", "lag_roll_s", "lag_pitch_s", "lag_yaw_s",
        "delay_roll_s", "delay_pitch_s", "delay_yaw_s",
    ]  # fmt: skip
    assert cols[-1] == "yaw_share"
    assert len(cols) == 5 + 21 + 2 + 4 + 3 + 1 + 2 + 13 + 3 + 9 + 1
    assert len(columns(6)) == len(cols) + 2
    with pytest.raises(ValueError):
        columns(0)


def test_every_column_has_one_topic_and_field() -> None:
    cols = columns(6)
    tps = topics(cols)
    assert [t.name for t in tps] == TOPICS[:-1]
    placed = sorted(j for t in tps for j in t.columns)
    assert placed == list(range(len(cols)))
    law = {t.name: t.fields for t in tps}
    assert law["/law/pitch"] == (
        "err_rad_s", "f_hat", "u", "torque", "saturated", "alpha", "lag_s", "delay_s",
    )  # fmt: skip
    assert cols[tps[2].columns[1]] == "f_hat_pitch"
    assert law["/link"] == ("t_s", "wall_s", "latency_us", "rtt_ms", "sample_age_ms")
    assert "motor_6" in law["/mixer"] and "engaged" in law["/mixer"]
    with pytest.raises(ValueError, match="no topic"):
        topics(["t_s", "x"])
    with pytest.raises(ValueError, match="duplicate"):
        topics(["t_s", "t_s"])


def flight_rows(n: int, cols: list[str], seed: int = 3) -> np.ndarray:
    """Rows in the columns() layout: stamps on an autopilot's clock, awkward values."""
    rng = np.random.default_rng(seed)
    scale = 10.0 ** rng.integers(-12, 8, size=(n, len(cols)))
    data = rng.standard_normal((n, len(cols))) * scale
    data[:, cols.index("t_s")] = 1234.5 + np.arange(n) * 0.004  # 250 Hz, since boot
    data[:, cols.index("wall_s")] = 98765.25 + np.arange(n) * 0.004
    data[:, cols.index("engaged")] = 1.0
    outer = [j for j, c in enumerate(cols) if c.startswith(("sp_", "est_", "outer_"))]
    data[:, outer] = np.nan  # rates mode: nothing on /outer ...
    data[7, outer[0]] = 0.25  # ... but for one sample
    data[8, cols.index("meas_roll_rad_s")] = np.nan  # a held (non-finite) measurement
    data[9, cols.index("u_yaw")] = -0.0
    return data


def messages(path: Path) -> list[tuple[str, Any, Any]]:
    """``(topic, message, decoded JSON)`` in file order, by the reference reader."""
    with path.open("rb") as f:
        return [
            (ch.topic, m, json.loads(m.data))
            for _, ch, m in make_reader(f).iter_messages(log_time_order=False)
        ]


def test_the_reference_reader_sees_the_topics_schemas_and_values(tmp_path: Path) -> None:
    cols = columns(4)
    data = flight_rows(600, cols)
    path = tmp_path / "control.mcap"
    with ControlLog(path, cols, meta={"profile": "f450", "output": "rates"}) as log:
        for i, row in enumerate(data.tolist()):
            log.append(row)
            if i == 100:
                log.event({"t_s": row[0], "wall": 1.7e9, "kind": "engaged", "detail": "ü"})
    assert log.rows == 600

    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        by_topic = {c.topic: c for c in summary.channels.values()}
        assert sorted(by_topic) == sorted(TOPICS)
        counts = summary.statistics.channel_message_counts  # type: ignore[union-attr]
        assert {t: counts[c.id] for t, c in by_topic.items()} == {
            **{t: 600 for t in TOPICS[:-2]},
            "/outer": 1,
            "/events": 1,
        }
        for c in by_topic.values():
            assert c.message_encoding == "json"
            schema = summary.schemas[c.schema_id]
            assert schema.encoding == "jsonschema"
            assert json.loads(schema.data)["type"] == "object"
        (meta,) = [m for m in reader.iter_metadata() if m.name == "companion"]
        assert meta.metadata["profile"] == "f450"
        assert meta.metadata["columns"] == ",".join(cols)

    got = messages(path)
    assert got[0][0] == "/rates" and got[0][2]["meas_roll_rad_s"] == data[0, 6]
    rows: dict[str, list[tuple[int, dict[str, Any]]]] = {}
    for topic, m, obj in got:
        rows.setdefault(topic, []).append((m.sequence, obj))
    link = rows["/link"]
    assert [s for s, _ in link] == list(range(600))
    for (seq, obj), (_, law) in zip(link, rows["/law/yaw"]):
        r = data[seq]
        # Exact values: JSON numbers round-trip float64; NaN is null.
        assert obj["t_s"] == r[0] and obj["wall_s"] == r[1]
        assert law["u"] == r[cols.index("u_yaw")]
        assert law["saturated"] == r[cols.index("sat_yaw")]
    assert rows["/rates"][8][1]["meas_roll_rad_s"] is None
    assert str(rows["/law/yaw"][9][1]["u"]) == "-0.0"
    (seq, outer), = rows["/outer"]  # fmt: skip
    assert seq == 7 and outer["sp_roll_rad"] == 0.25 and outer["est_up_m"] is None
    (_, event), = rows["/events"]  # fmt: skip
    assert event == {"t_s": data[100, 0], "wall": 1.7e9, "kind": "engaged", "detail": "ü"}

    # Log time: the IMU stamp on the autopilot's clock; publish time: the companion's.
    for _, m, obj in got:
        if "t_s" in obj and "wall_s" in obj:
            assert m.log_time == round(obj["t_s"] * 1e9)
            assert m.publish_time == round(obj["wall_s"] * 1e9)
    assert {m.log_time for t, m, _ in got if t != "/events" and m.sequence == 42} == {
        round(data[42, 0] * 1e9)
    }


def test_read_control_log_gives_the_columns_exactly(tmp_path: Path) -> None:
    cols = columns(4)
    data = flight_rows(500, cols)
    path = tmp_path / "control.mcap"
    with ControlLog(path, cols, meta={"note": "two\nlines"}, flush_interval_s=0.0) as log:
        for row in data.tolist():
            log.append(row)
        log.append((True, *data[0, 1:].tolist()))  # bools and tuples are fine
    got, meta = read_control_log(path)
    assert list(got) == cols
    assert meta["note"] == "two\nlines" and "cut_short" not in meta
    assert {"version", "start_unix_s", "start_utc", "format"} <= set(meta)
    assert abs(float(meta["start_unix_s"]) - time.time()) < 60
    for j, c in enumerate(cols):
        np.testing.assert_array_equal(got[c][:500], data[:, j])  # NaN where NaN
    assert got["t_s"][500] == 1.0
    assert np.signbit(got["u_yaw"][9])
    assert last_sample_time(path) == 1.0  # the last sample's, whatever came before


def test_wrong_rows_and_columns_raise(tmp_path: Path) -> None:
    cols = columns(4)
    with ControlLog(tmp_path / "x.mcap", cols) as log:
        n = len(cols)
        with pytest.raises(ValueError, match=f"{n - 1} values, expected {n}"):
            log.append([0.0] * (n - 1))
        with pytest.raises(ValueError, match="not a number"):
            log.append([0.0] * (n - 1) + ["x"])  # type: ignore[list-item]
        log.append([0.0] * n)
    got, _ = read_control_log(tmp_path / "x.mcap")
    assert len(got["t_s"]) == 1
    with pytest.raises(ValueError, match="duplicate"):
        ControlLog(tmp_path / "y.mcap", ["t_s", "t_s"])
    with pytest.raises(ValueError, match="no topic"):
        ControlLog(tmp_path / "z.mcap", ["t_s", "a,b"])


def test_other_files_are_refused_naming_them(tmp_path: Path) -> None:
    bogus = tmp_path / "bogus.mcap"
    bogus.write_bytes(b"\x00\x01 definitely not a control log\n" * 10)
    with pytest.raises(ValueError, match="bogus"):
        read_control_log(bogus)


_KILLED_WRITER = textwrap.dedent(
    """
    import sys, time
    from companion.records import ControlLog, RecordWriter, columns

    cols = columns(4)
    writer = RecordWriter()
    log = ControlLog(sys.argv[1], cols, meta={"profile": "f450"}, writer=writer)
    start = time.monotonic()
    k = 0
    while True:
        t = time.monotonic() - start
        if t >= 1.0:
            break
        log.append([100.0 + k * 0.001, t] + [0.5] * (len(cols) - 2))
        if k % 250 == 0:
            log.event({"t_s": 100.0 + k * 0.001, "wall": time.time(), "kind": "tick"})
        k += 1
        time.sleep(0.001)
    while writer.pending_chunks:  # the thread has written what it was handed ...
        time.sleep(0.01)
    sys.stdout.write(f"{k} {t!r}\\n")
    sys.stdout.flush()
    time.sleep(60)  # ... and is killed here, the last flush interval's rows in memory
    """
)


def test_a_killed_writer_leaves_what_the_reference_reader_opens(tmp_path: Path) -> None:
    """SIGKILL a real process writing the log through the writer thread, as the app does."""
    path = tmp_path / "control.mcap"
    proc = subprocess.Popen(
        [sys.executable, "-c", _KILLED_WRITER, str(path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line, proc.communicate(timeout=30)[1]
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    n_rows, last_wall = int(line.split()[0]), float(line.split()[1])

    # No footer: the reference reader reads on until the file ends.
    got: list[tuple[str, Any]] = []
    with path.open("rb") as f, pytest.raises(EndOfFile):
        for _, ch, m in NonSeekingReader(f).iter_messages(log_time_order=False):
            got.append((ch.topic, m))
    link = [json.loads(m.data) for topic, m in got if topic == "/link"]
    seqs = [m.sequence for topic, m in got if topic == "/link"]
    assert seqs == list(range(len(seqs)))  # whole and in order
    assert 100 < len(seqs) <= n_rows
    for topic in ("/rates", "/law/roll", "/law/pitch", "/law/yaw", "/mixer"):
        assert sum(t == topic for t, _ in got) == len(seqs)  # whole samples only
    # What is lost is the last flush interval at most (0.2 s, plus a loaded
    # machine's slack between two rows).
    assert last_wall - link[-1]["wall_s"] < 0.2 + 0.1
    assert [m.log_time for t, m in got if t == "/link"][-1] == round(link[-1]["t_s"] * 1e9)
    # Every event logged before the last whole sample is there, in order; how
    # many that is depends on the machine's speed (one per 250 rows).
    events = [json.loads(m.data)["t_s"] for t, m in got if t == "/events"]
    logged = [100.0 + k * 0.001 for k in range(0, n_rows, 250)]
    assert events == logged[: len(events)]
    assert len(events) >= sum(t < link[-1]["t_s"] for t in logged) >= 1

    cols, meta = read_control_log(path)  # ours agrees, and says so
    assert meta["cut_short"] == "true" and meta["profile"] == "f450"
    assert cols["t_s"].size == len(seqs) and cols["wall_s"][-1] == link[-1]["wall_s"]
    assert last_sample_time(path) == pytest.approx(link[-1]["t_s"], abs=1e-6)


def test_a_writer_thread_log_matches_a_synchronous_one(tmp_path: Path) -> None:
    cols = columns(4)
    data = flight_rows(300, cols)
    w = RecordWriter()
    try:
        a = ControlLog(tmp_path / "a.mcap", cols, flush_interval_s=0.0, writer=w)
        with ControlLog(tmp_path / "b.mcap", cols, flush_interval_s=0.0) as b:
            for row in data.tolist():
                a.append(row)
                b.append(row)
        a.close()
    finally:
        assert w.close() is True
    ga, gb = read_control_log(tmp_path / "a.mcap")[0], read_control_log(tmp_path / "b.mcap")[0]
    for c in cols:
        np.testing.assert_array_equal(ga[c], gb[c])
    assert w.stats("a.mcap").written_chunks == 300


@pytest.mark.parametrize("threaded", [False, True])
def test_what_the_run_learnt_later_overrides_its_first_metadata(
    tmp_path: Path, threaded: bool
) -> None:
    """``ControlLog.learnt``: a later metadata record (``companion.learnt``, which the
    reference reader sees too), read back over the first; the layout stays the first's."""
    cols = columns(4)
    data = flight_rows(20, cols)
    path = tmp_path / "control.mcap"
    w = RecordWriter() if threaded else None
    log = ControlLog(path, cols, meta={"rates_law_axes": "auto", "profile": "f450"}, writer=w)
    log.append(data[0].tolist())
    log.flush()  # what was learnt goes out alone
    log.learnt({"rates_law_axes": "yaw", "columns": "t_s"})
    log.flush()
    for row in data[1:].tolist():
        log.append(row)
    log.close()
    if w is not None:
        assert w.close() is True
    got, meta = read_control_log(path)
    assert meta["rates_law_axes"] == "yaw" and meta["profile"] == "f450"
    assert list(got) == cols and len(got["t_s"]) == 20
    with path.open("rb") as f:
        records = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert records["companion"]["rates_law_axes"] == "auto"
    assert records["companion.learnt"]["rates_law_axes"] == "yaw"
