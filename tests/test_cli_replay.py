"""``companion replay LOG`` through the command line, on a log a real flight wrote.

The contract (companion/cli/_replay.py ``replay_cmd``, companion/replay.py): re-run a
controller on the ``control.mcap`` of a flight; with the recorded controller the
outputs match the log to rounding, with another one they show what it would
have commanded; it prints the engaged sample count, the largest differences
per column and the largest one overall, and with ``--out`` writes the replayed
outputs as a control log. A file that is not a control log, or in another
format, is exit 2; a log the recorded controller no longer reproduces is exit 1.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from companion.records import FORMAT, read_control_log
from companion.replay import output_columns
from sitl.lab.fly import fly_mavlink

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[1]
F450 = ROOT / "vehicle_profiles" / "f450.yaml"
DATA = ROOT / "companion" / "data"


def companion(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "companion", *args],
        cwd=cwd, capture_output=True, text=True, timeout=120,
    )  # fmt: skip


def rewrite(src: Path, dst: Path, **meta: str) -> None:
    """``src`` copied with the mcap package's reader and writer, its ``companion``
    metadata updated with ``meta``."""
    with src.open("rb") as f, dst.open("wb") as out:
        reader = make_reader(f)
        w = Writer(out)
        w.start()
        for m in reader.iter_metadata():
            w.add_metadata(m.name, {**m.metadata, **meta} if m.name == "companion" else m.metadata)
        summary = reader.get_summary()
        assert summary is not None
        for s in summary.schemas.values():
            assert w.register_schema(s.name, s.encoding, s.data) == s.id
        for c in summary.channels.values():
            assert w.register_channel(c.topic, c.message_encoding, c.schema_id) == c.id
        for _, c, m in reader.iter_messages(log_time_order=False):
            w.add_message(c.id, m.log_time, m.data, m.publish_time, m.sequence)
        w.finish()


def largest(stdout: str) -> float:
    m = re.search(r"^largest difference: (\S+)$", stdout, re.MULTILINE)
    assert m, stdout
    return float(m.group(1))


def test_replay_of_a_recorded_flight_reproduces_it_and_writes_the_outputs(tmp_path: Path) -> None:
    # A short lockstep flight (5 s engaged, paper-acro's first maneuvers) records
    # control.mcap; the paths in its header are absolute, so replay finds the
    # recorded controller and profile from any working directory.
    flight = fly_mavlink(F450, "paper-acro", tmp_path / "flight", duration_s=5.0, timeout_s=60.0)
    assert flight.companion_rc == 0, flight.why()
    log = flight.control_log
    cols, meta = read_control_log(log)
    n_engaged = int((cols["engaged"] > 0.5).sum())
    assert n_engaged >= 5.0 * 250 - 5  # 5 s of samples at 250 Hz
    out = tmp_path / "replayed.mcap"

    res = companion("replay", str(log), "--out", str(out), cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert lines[0] == (
        f"replayed {n_engaged} engaged samples of {log} with {meta['controller_path']} "
        f"on {meta['profile_path']}"
    )
    per_column = [ln for ln in lines if "max |recorded - replayed| =" in ln]
    assert 1 <= len(per_column) <= 8
    # The recorded controller reproduces the flight: to rounding (outputs are of
    # order 1 to 500, in us for u; the laws are deterministic).
    assert largest(res.stdout) < 1e-6
    assert lines[-1] == f"wrote {out}"

    rep, rep_meta = read_control_log(out)
    assert list(rep) == ["t_s", "engaged", *output_columns(4)]
    assert rep_meta["replay_of"] == str(log)
    assert rep_meta["controller"] == meta["controller_path"]
    np.testing.assert_array_equal(rep["t_s"], cols["t_s"])
    eng = cols["engaged"] > 0.5
    for name in ("u_roll", "torque_pitch", "f_hat_yaw", "motor_1", "thrust_out"):
        np.testing.assert_allclose(rep[name][eng], cols[name][eng], rtol=0, atol=1e-6)
        assert np.all(np.isnan(rep[name][~eng]))  # not flying then: no output

    # Another controller on the same samples commands something else (open loop).
    other = DATA / "mfc_table1.yaml"
    res2 = companion("replay", str(log), "--controller", str(other), cwd=tmp_path)
    assert res2.returncode == 0, res2.stderr
    assert res2.stdout.startswith(f"replayed {n_engaged} engaged samples of {log} with {other} ")
    assert largest(res2.stdout) > 1.0
    assert "wrote" not in res2.stdout

    # The log says it was flown with another controller than the one that flew it
    # (as when a controller file changes after its flight): the recorded controller
    # no longer reproduces it, and replay says so and fails.
    forged = tmp_path / "forged.mcap"
    rewrite(log, forged, controller_path=str(other))
    res3 = companion("replay", str(forged), cwd=tmp_path)
    assert res3.returncode == 1, (res3.stdout, res3.stderr)
    assert largest(res3.stdout) > 1.0
    assert f"error: the recorded controller {other} on " in res3.stderr
    assert f"does not reproduce {forged}" in res3.stderr

    # A log cut in the middle of a chunk (its writer was killed): the whole chunks
    # replay, and the cut is reported.
    cut = tmp_path / "cut.mcap"
    with log.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    last = max(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    cut.write_bytes(log.read_bytes()[: last.chunk_start_offset + last.chunk_length // 2])
    res4 = companion("replay", str(cut), cwd=tmp_path)
    assert res4.returncode == 0, res4.stderr
    assert "was not closed by its writer" in res4.stderr
    assert largest(res4.stdout) < 1e-6
    assert 0 < int(res4.stdout.split()[1]) <= n_engaged


def test_replay_of_a_file_that_is_not_a_control_log_exits_2(tmp_path: Path) -> None:
    bogus = tmp_path / "not_a_log.mcap"
    bogus.write_bytes(b"\x00\x01 definitely not a control log\n" * 10)
    res = companion("replay", str(bogus), cwd=tmp_path)
    assert res.returncode == 2, (res.stdout, res.stderr)
    assert res.stderr.startswith("error: ")
    assert str(bogus) in res.stderr
    assert "replayed" not in res.stdout


def test_replay_of_a_log_in_another_format_exits_2(tmp_path: Path) -> None:
    future = tmp_path / "future.mcap"
    with future.open("wb") as f:
        w = Writer(f)
        w.start()
        w.add_metadata("companion", {"format": "mfc-companion control log 9", "columns": "t_s"})
        w.finish()
    res = companion("replay", str(future), cwd=tmp_path)
    assert res.returncode == 2, (res.stdout, res.stderr)
    assert f"error: {future}: format 'mfc-companion control log 9" in res.stderr
    assert f"this version reads '{FORMAT}'" in res.stderr
