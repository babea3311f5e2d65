"""No command overwrites an earlier run's output: it is moved, untouched, into
``earlier-<UTC time>/`` beside it first (companion.records.move_earlier), and a
``--log-dir`` in use is refused (companion.records.lock_log_dir).

Each command writes twice into one place, or once where an earlier run's
outputs (stand-ins with known bytes) already are; the earlier ones must come
out intact and only the command's own outputs move (a stranger's file stays).
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from companion.cli import cli as companion_cli
from companion.config import DEFAULT_CONTROLLER
from companion.records import LOCK_FILE, RECORD_FILES, ControlLog, columns, read_control_log
from sitl.cli import cli as sitl_cli
from sitl.flight_log import read_log
from sitl.lab.envelope_setup import load_setup
from sitl.lab.fly import free_udp_port
from sitl.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
F450 = ROOT / "vehicle_profiles" / "f450.yaml"


def companion(*args: str) -> Result:
    return CliRunner().invoke(companion_cli, list(args), catch_exceptions=False)


def plant(folder: Path, names: list[str]) -> dict[str, bytes]:
    """An earlier run's outputs (and a stranger's file): each with its own bytes."""
    folder.mkdir(parents=True, exist_ok=True)
    written = {}
    for name in [*names, "notes.txt"]:
        p = folder / name
        p.parent.mkdir(parents=True, exist_ok=True)
        written[name] = f"earlier {name}\n".encode()
        p.write_bytes(written[name])
    return written


def kept(folder: Path, written: dict[str, bytes]) -> Path:
    """The one earlier-* folder holds every planted output, intact; the stranger's
    file has not moved. Returns that folder."""
    (earlier,) = folder.glob("earlier-*")
    for name, data in written.items():
        where = folder if name == "notes.txt" else earlier
        assert (where / name).read_bytes() == data, name
    return earlier


def short_scenario(folder: Path, name: str, duration_s: float) -> Path:
    sc = load_scenario(name).model_copy(update={"name": f"short-{name}", "duration_s": duration_s})
    path = folder / f"short-{name}.yaml"
    path.write_text(sc.model_dump_json(), encoding="utf-8")
    return path


def test_simulate_moves_the_earlier_report_aside(tmp_path: Path) -> None:
    scenario = short_scenario(tmp_path, "step-response", 1.0)
    out = tmp_path / "out"
    args = ["simulate", "--scenario", str(scenario), "--out", str(out), "--no-progress"]
    first = companion(*args)
    assert first.exit_code == 0, first.output
    written = {n: (out / n).read_bytes() for n in ("metrics.json", "report.md", "rates.png")}
    (out / "notes.txt").write_bytes(b"mine")
    written["notes.txt"] = b"mine"
    second = companion(*args)
    assert second.exit_code == 0, second.output
    earlier = kept(out, written)
    assert f"moved to {earlier}" in second.output
    assert json.loads((out / "metrics.json").read_text())["samples"] > 0  # the second's own


@pytest.mark.integration
def test_fly_moves_the_earlier_flight_aside_whole(tmp_path: Path) -> None:
    # What an earlier `fly --compare-passthrough` left: its report, both processes'
    # logs, the companion's records and the pass-through flight.
    out = tmp_path / "out"
    written = plant(out, ["metrics.json", "report.md", "sitl.npz", "companion.stderr",
                          "companion/control.mcap", "companion/events.jsonl",
                          "passthrough/companion/control.mcap"])  # fmt: skip
    res = companion("fly", "--duration", "1", "--out", str(out), "--no-progress")
    assert res.exit_code == 0, res.output + (out / "companion.stderr").read_text()
    kept(out, written)
    assert not (out / "passthrough").exists()
    assert read_control_log(out / "companion" / "control.mcap")[0]["t_s"].size > 0
    assert not list((out / "companion").glob("earlier-*"))  # moved whole, by fly


def replay_log(path: Path) -> None:
    """A small control.mcap (columns() layout) naming its profile, for replay to re-run."""
    names = columns(4)
    with ControlLog(path, names, meta={"profile_path": str(F450)}) as log:
        for i in range(20):
            row = dict.fromkeys(names, 0.0) | {"t_s": 0.004 * i, "engaged": 1.0, "thrust": 0.5}
            log.append([row[n] for n in names])


def test_replay_out_moves_an_earlier_file_aside(tmp_path: Path) -> None:
    log = tmp_path / "control.mcap"
    replay_log(log)
    out = tmp_path / "replayed.mcap"
    written = plant(tmp_path, ["replayed.mcap"])
    res = companion("replay", str(log), "--out", str(out), "--controller", str(DEFAULT_CONTROLLER))
    assert res.exit_code == 0, res.output
    kept(tmp_path, written)
    assert read_control_log(out)[0]["u_roll"].size == 20
    assert (tmp_path / "control.mcap").exists()  # the input is not an output


def test_sitl_run_log_moves_the_earlier_log_and_its_events_aside(tmp_path: Path) -> None:
    written = plant(tmp_path, ["flight.npz", "flight.events.jsonl"])
    res = subprocess.run(
        [sys.executable, "-m", "sitl", "run", "--profile", str(F450), "--duration", "0.2",
         "--mavlink", f"udpout:127.0.0.1:{free_udp_port()}", "--log", "flight.npz"],
        cwd=tmp_path, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    earlier = kept(tmp_path, written)
    assert f"moved to {earlier.name}" in res.stderr
    assert read_log(tmp_path / "flight.npz")["t_s"].size > 0


def test_campaign_moves_the_earlier_results_aside(tmp_path: Path) -> None:
    out = tmp_path / "out"
    written = plant(out, ["campaign.json", "summary.md", "mae.png"])
    res = companion(
        "campaign", "--out", str(out), "--profiles", str(F450),
        "--controllers", str(DEFAULT_CONTROLLER), "--damage", "1.0", "--gusts", "0",
        "--seeds", "1", "--duration", "1", "--workers", "1", "--no-progress",
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    kept(out, written)
    assert json.loads((out / "campaign.json").read_text())["meta"]["flights"] == 1


def test_envelope_moves_the_earlier_results_aside(tmp_path: Path) -> None:
    setup = load_setup()
    train, test = (
        short_scenario(tmp_path, sc.name, 0.5) for sc in (setup.train, setup.test)
    )  # fmt: skip
    out = tmp_path / "out"
    written = plant(
        out, ["envelope.json", "envelope.parquet", "summary.md", "ratio.png", "worst-a-intact.png"]
    )
    res = companion(
        "envelope", "--out", str(out), "--corners-only", "--no-damage", "--tune-budget", "1",
        "--worst", "0", "--workers", "1", "--train-scenario", str(train),
        "--test-scenario", str(test), "--no-progress",
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    kept(out, written)
    assert json.loads((out / "envelope.json").read_text())["records"]


def test_sitl_envelope_moves_the_earlier_profiles_aside(tmp_path: Path) -> None:
    written = plant(tmp_path, ["envelope.json", "env-old.yaml"])
    res = CliRunner().invoke(sitl_cli, ["envelope", "--n", "2", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    kept(tmp_path, written)
    assert len(json.loads((tmp_path / "envelope.json").read_text())) == 2


# ------------------------------------------------- two companions, one --log-dir


def start_run(log_dir: Path, heartbeat_timeout_s: float) -> subprocess.Popen[str]:
    """``companion run`` waiting for an autopilot that never comes (nothing listens)."""
    return subprocess.Popen(
        [sys.executable, "-m", "companion", "run", "--connect",
         f"udpin:127.0.0.1:{free_udp_port()}", "--profile", str(F450), "--engage", "none",
         "--log-dir", str(log_dir), "--heartbeat-timeout-s", str(heartbeat_timeout_s)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip


def wait_locked(log_dir: Path, proc: subprocess.Popen[str], timeout_s: float = 30.0) -> None:
    """Until ``proc`` has written its pid into the lock (it holds the folder) and
    opened its records (after the lock: a loaded machine can show the lock alone)."""
    deadline = time.monotonic() + timeout_s
    lock = log_dir / LOCK_FILE

    def ready() -> bool:
        if not (lock.exists() and lock.read_text().strip() == str(proc.pid)):
            return False
        files = [log_dir / name for name in RECORD_FILES]
        return all(f.exists() for f in files) and (log_dir / "control.mcap").stat().st_size > 0

    while not ready():
        assert proc.poll() is None, proc.communicate()[1]
        assert time.monotonic() < deadline, "the first run never took the lock"
        time.sleep(0.05)


@pytest.mark.integration
def test_a_second_companion_on_a_log_dir_in_use_refuses_and_moves_nothing(
    tmp_path: Path,
) -> None:
    logs = tmp_path / "logs"
    first = start_run(logs, heartbeat_timeout_s=60.0)
    try:
        wait_locked(logs, first)
        header = (logs / "control.mcap").read_bytes()  # no autopilot: no rows to come
        second = start_run(logs, heartbeat_timeout_s=0.5)
        _, err = second.communicate(timeout=60)
        assert second.returncode == 1, err
        assert f"{logs} is in use by another companion run (pid {first.pid}" in err
        # Untouched: nothing moved away, nothing added (its tlog grows with our heartbeats).
        assert sorted(p.name for p in logs.iterdir()) == sorted([*RECORD_FILES, LOCK_FILE])
        assert (logs / "control.mcap").read_bytes() == header
        assert first.poll() is None
    finally:
        first.send_signal(signal.SIGKILL)  # no tidying up: the OS releases the lock
        first.communicate(timeout=30)
    # The folder is free again: the next run takes it, moving the killed run's
    # records aside intact, and its own failed start leaves only its events.
    third = start_run(logs, heartbeat_timeout_s=0.3)
    _, err = third.communicate(timeout=60)
    assert third.returncode == 1, err
    (earlier,) = logs.glob("earlier-*")
    assert (earlier / "control.mcap").read_bytes() == header
    assert "no HEARTBEAT" in (logs / "events.jsonl").read_text()
    names = sorted(p.name for p in logs.iterdir())
    assert names == sorted([earlier.name, "events.jsonl", LOCK_FILE])  # no empty control.mcap
