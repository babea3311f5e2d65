"""TlogWriter output read back by pymavlink's own readers (mavutil, mavlogdump)."""

from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"  # before pymavlink is imported: encode and parse MAVLink 2

import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink2

from companion.records import TlogWriter

T0 = 1_767_225_600.0  # 2026-01-01T00:00:00Z


def encoder() -> mavlink2.MAVLink:
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    mav.robust_parsing = True
    return mav


def frames() -> list[tuple[float, bytes, bool, str]]:
    """(time, raw frame, outgoing, type) for a few messages of both directions."""
    ap = encoder()
    comp = mavlink2.MAVLink(None, srcSystem=1, srcComponent=191)
    out = []
    hb = ap.heartbeat_encode(2, 12, 129, 6 << 16, 4).pack(ap)
    out.append((T0 + 0.000123, hb, False, "HEARTBEAT"))
    for k in range(5):
        imu = ap.highres_imu_encode(
            1_000_000 + 1000 * k, 0.1, 0.2, -9.81, 0.01 * k, -0.02 * k, 0.5, 0, 0, 0, 0, 0, 0, 0, 0
        ).pack(ap)
        out.append((T0 + 0.001 * (k + 1), imu, False, "HIGHRES_IMU"))
        cmd = comp.set_actuator_control_target_encode(
            1_000_000 + 1000 * k, 0, 1, 1, [0.1 * k, -0.1, 0.05, 0.6, 0, 0, 0, 0]
        ).pack(comp)
        out.append((T0 + 0.001 * (k + 1) + 0.0002, cmd, True, "SET_ACTUATOR_CONTROL_TARGET"))
    return out


def test_messages_and_timestamps_read_back_with_mavutil(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "dir" / "flight.tlog"  # parents are created
    data = frames()
    w = TlogWriter(path)
    for t, raw, outgoing, _ in data:
        w.write(t, raw, outgoing)
    w.close()
    w.close()  # harmless
    assert (w.written_in, w.written_out) == (6, 5)
    assert path.stat().st_size == sum(8 + len(raw) for _, raw, _, _ in data)

    m = mavutil.mavlink_connection(str(path))
    got = []
    while True:
        msg = m.recv_match()
        if msg is None:
            break
        got.append(msg)
    m.close()
    assert [g.get_type() for g in got] == [typ for _, _, _, typ in data]
    for g, (t, raw, _, _) in zip(got, data):
        assert g._timestamp == pytest.approx(t, abs=1e-6)
        assert bytes(g.get_msgbuf()) == raw
    imus = [g for g in got if g.get_type() == "HIGHRES_IMU"]
    assert [i.time_usec for i in imus] == [1_000_000 + 1000 * k for k in range(5)]
    assert imus[3].xgyro == pytest.approx(0.03)
    cmds = [g for g in got if g.get_type() == "SET_ACTUATOR_CONTROL_TARGET"]
    assert cmds[2].controls[0] == pytest.approx(0.2)
    assert cmds[0].get_srcComponent() == 191

    # recv_match with a type filter (the mmap index path)
    m = mavutil.mavlink_connection(str(path))
    hb = m.recv_match(type="HEARTBEAT")
    assert hb is not None and hb.custom_mode == 6 << 16
    assert hb._timestamp == pytest.approx(T0 + 0.000123, abs=1e-6)
    m.close()


def test_mavlogdump_prints_the_messages(tmp_path: Path) -> None:
    path = tmp_path / "flight.tlog"
    with TlogWriter(path) as w:
        for t, raw, outgoing, _ in frames():
            w.write(t, raw, outgoing)
    proc = subprocess.run(
        [sys.executable, "-m", "pymavlink.tools.mavlogdump", "--format", "json", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    import json

    lines = [json.loads(s) for s in proc.stdout.splitlines() if s.startswith("{")]
    assert [d["meta"]["type"] for d in lines] == [typ for _, _, _, typ in frames()]
    assert lines[0]["meta"]["timestamp"] == pytest.approx(T0 + 0.000123, abs=1e-6)
    assert lines[1]["data"]["time_usec"] == 1_000_000
    # and the default (human) format
    proc = subprocess.run(
        [sys.executable, "-m", "pymavlink.tools.mavlogdump", "--types", "HIGHRES_IMU", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    shown = [s for s in proc.stdout.splitlines() if "HIGHRES_IMU" in s]
    assert len(shown) == 5
    assert "time_usec : 1004000" in shown[-1]


def test_write_after_close_raises(tmp_path: Path) -> None:
    w = TlogWriter(tmp_path / "x.tlog")
    w.close()
    with pytest.raises(ValueError, match="closed"):
        w.write(T0, b"\xfd", False)


_KILLED_WRITER = textwrap.dedent(
    """
    import os, signal, sys, time
    os.environ["MAVLINK20"] = "1"
    from pymavlink.dialects.v20 import common as mavlink2
    from companion.records import TlogWriter

    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    w = TlogWriter(sys.argv[1], flush_interval_s=0.2)
    start = time.monotonic()
    k = 0
    while time.monotonic() - start < 1.0:
        raw = mav.highres_imu_encode(k, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0).pack(mav)
        w.write(time.time(), raw, False)
        k += 1
        time.sleep(0.001)
    last = time.time()
    sys.stdout.write(f"{k} {last!r}\\n")
    sys.stdout.flush()
    os.kill(os.getpid(), signal.SIGKILL)  # no close(), no atexit, no buffers flushed
    """
)


def test_killed_writer_loses_at_most_the_last_flush_interval(tmp_path: Path) -> None:
    path = tmp_path / "killed.tlog"
    proc = subprocess.run(
        [sys.executable, "-c", _KILLED_WRITER, str(path)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    n_written, last_written = proc.stdout.split()
    n_written_i, last_t = int(n_written), float(last_written)

    m = mavutil.mavlink_connection(str(path))
    got = []
    while (msg := m.recv_match()) is not None:
        got.append(msg)
    m.close()
    assert all(g.get_type() == "HIGHRES_IMU" for g in got)
    # Everything that reached the file is intact and in order ...
    assert [g.time_usec for g in got] == list(range(len(got)))
    assert len(got) > 100
    # ... and only the last flush interval (0.2 s, plus scheduling slack) is missing.
    assert last_t - got[-1]._timestamp < 0.2 + 0.05
    assert len(got) <= n_written_i
