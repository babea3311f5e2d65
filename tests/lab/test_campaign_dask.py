"""``companion campaign`` on Dask: a real scheduler and workers on loopback.

The campaign runs as a separate client process (``python -m companion``), once on
a ``LocalCluster`` and against ``dask scheduler`` and ``dask worker`` processes:
the records are the same; a worker or the client SIGKILLed mid-campaign loses no
flight and flies none twice; the Parquet table has the documented schema; a flight
that raises is a row with its error, not a hang.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from companion.config import DEFAULT_CONTROLLER, load_controller
from companion.profile import load_profile
from sitl.lab import campaign, children
from sitl.lab.campaign import FlightSpec, run_campaign, write_outputs
from sitl.lab.campaign_store import CampaignStore
from sitl.lab.executor import Executor
from sitl.lab.table import FLIGHTS_SCHEMA, read_table
from sitl.scenario import load_scenario
from tests.lab import executor_tasks

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
DASK = Path(sys.executable).parent / "dask"
PID = ROOT / "companion" / "data" / "pid_tarot_tuned.yaml"
TINY = ("--profiles", "f450,tarot650", "--damage", "0.8", "--gusts", "1", "--seeds", "1",
        "--duration", "3", "--no-progress")  # fmt: skip
# 8 flights, long enough to be killed among: 2 profiles x 2 seeds x 2 controllers.
LONGER = ("--profiles", "f450,tarot650", "--damage", "0.8", "--gusts", "1", "--seeds", "2",
          "--duration", "6", "--no-progress")  # fmt: skip


def _campaign_cmd(out: Path, *args: str) -> list[str]:
    return [sys.executable, "-m", "companion", "campaign", "--out", str(out), *args]


def _stop(proc: subprocess.Popen[bytes]) -> None:
    """End ``proc`` and whatever it started (its own session), SIGKILL if it lingers."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        if proc.poll() is not None:
            break
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=10)


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Where the processes' stderr goes (``<name>.stderr``)."""
    return tmp_path_factory.mktemp("logs")


@pytest.fixture(scope="module")
def spawn(logs: Path) -> Iterator[Callable[..., subprocess.Popen[bytes]]]:
    """Start a process in its own session, stderr to a file; all ended at teardown."""
    procs: list[subprocess.Popen[bytes]] = []

    def start(args: list[str], name: str) -> subprocess.Popen[bytes]:
        with (logs / f"{name}.stderr").open("wb") as err:
            proc = children.start(args, cwd=ROOT, stdout=err, stderr=err,
                                   start_new_session=True)  # fmt: skip
        procs.append(proc)
        return proc

    try:
        yield start
    finally:
        for p in procs:
            _stop(p)


def _wait_for(what: str, ok: Callable[[], bool], timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not ok():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


def _scheduler_address(path: Path) -> str | None:
    """The address in a dask scheduler file, or None while it is missing or half-written."""
    try:
        address = json.loads(path.read_text(encoding="utf-8"))["address"]
    except (OSError, ValueError, KeyError):
        return None
    return str(address)


@pytest.fixture(scope="module")
def cluster(logs: Path, spawn: Callable[..., subprocess.Popen[bytes]]) -> Any:
    """A ``dask scheduler`` and two single-thread ``dask worker`` processes on 127.0.0.1:
    the scheduler's address and the worker processes. The module's tests share it;
    the one that kills a worker comes last."""
    sched_file = logs / "scheduler.json"
    spawn([str(DASK), "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
           "--scheduler-file", str(sched_file)], "scheduler")  # fmt: skip

    # The scheduler creates the file before it writes it: wait for its contents.
    def written() -> bool:
        return _scheduler_address(sched_file) is not None

    _wait_for("the scheduler", written)
    address = _scheduler_address(sched_file)
    assert address is not None
    worker = [str(DASK), "worker", address, "--nthreads", "1", "--no-nanny", "--no-dashboard",
              "--host", "127.0.0.1"]  # fmt: skip
    workers = [spawn([*worker, "--name", f"w{i}"], f"worker{i}") for i in range(2)]
    for i in range(2):
        log = logs / f"worker{i}.stderr"
        _wait_for(f"worker {i}", lambda log=log: "Registered to" in log.read_text())
    return address, workers


def _records(out: Path, drop: tuple[str, ...] = ("wall_time_s",)) -> list[dict[str, Any]]:
    doc = json.loads((out / "campaign.json").read_text(encoding="utf-8"))
    return [{k: v for k, v in r.items() if k not in drop} for r in doc["records"]]


def _flight_files(out: Path) -> dict[str, tuple[int, int]]:
    """Each stored flight's id and (inode, mtime in ns)."""
    return {p.stem: (p.stat().st_ino, p.stat().st_mtime_ns)
            for p in (out / "flights").glob("*.json")}  # fmt: skip


@pytest.fixture(scope="module")
def local_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny campaign on a LocalCluster of two worker processes."""
    out = tmp_path_factory.mktemp("local") / "out"
    res = subprocess.run(_campaign_cmd(out, *TINY, "--workers", "2"), cwd=ROOT,
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert res.returncode == 0, res.stderr
    return out


def test_a_cluster_flies_the_records_of_a_local_run(local_run: Path, tmp_path: Path,
                                                    cluster: Any) -> None:  # fmt: skip
    address, _ = cluster
    out = tmp_path / "out"
    res = subprocess.run(_campaign_cmd(out, *TINY, "--scheduler", address), cwd=ROOT,
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert f"--scheduler {address}: dashboard http" in res.stderr
    local, remote = _records(local_run), _records(out)
    assert len(local) == 4 and all(r["error"] is None for r in local)
    assert json.dumps(remote) == json.dumps(local)  # byte for byte, in grid order
    meta = json.loads((out / "campaign.json").read_text(encoding="utf-8"))["meta"]
    assert (meta["scheduler"], meta["workers"], meta["flown_this_run"]) == (address, 2, 4)


@pytest.mark.long
def test_a_killed_client_resumes_and_flies_only_the_rest(tmp_path: Path, cluster: Any,
                                                         spawn: Any) -> None:  # fmt: skip
    address, _ = cluster
    out = tmp_path / "out"
    cmd = _campaign_cmd(out, *LONGER, "--scheduler", address)
    client = spawn(cmd, "client-b")
    _wait_for("a first flight", lambda: bool(_flight_files(out)) or client.poll() is not None)
    client.send_signal(signal.SIGKILL)
    client.wait(timeout=10)
    before = _flight_files(out)
    assert 0 < len(before) < 8 and not (out / "campaign.json").exists()
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=80)
    assert res.returncode == 0, res.stderr
    assert f"resuming: {len(before)} of 8 flights done" in res.stderr
    assert "moved to" not in res.stderr
    after = _flight_files(out)
    assert {k: after[k] for k in before} == before  # not flown, not rewritten
    meta = json.loads((out / "campaign.json").read_text(encoding="utf-8"))["meta"]
    assert (meta["flown_this_run"], meta["resumed_flights"]) == (8 - len(before), len(before))
    ids = [r["flight_id"] for r in _records(out)]
    assert len(ids) == 8 and set(ids) == set(after)


def _documented_schema() -> list[tuple[str, str]]:
    """(column, type) rows of the schema table in docs/campaigns.md."""
    text = (ROOT / "docs" / "campaigns.md").read_text(encoding="utf-8")
    section = text.split("\n## The table\n", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"^\| `(\w+)` \| (\w+) \|", section, flags=re.MULTILINE)


def test_the_table_has_the_documented_schema(local_run: Path) -> None:
    import pandas as pd

    types = {"string": pa.string(), "float64": pa.float64(), "int64": pa.int64(),
             "bool": pa.bool_()}  # fmt: skip
    documented = [(name, types[t]) for name, t in _documented_schema()]
    assert documented == [(f.name, f.type) for f in FLIGHTS_SCHEMA]
    path = local_run / "flights.parquet"
    assert pq.read_schema(path).equals(FLIGHTS_SCHEMA, check_metadata=False)
    df = pd.read_parquet(path)
    assert list(df.columns) == FLIGHTS_SCHEMA.names and len(df) == 4
    assert df["seed"].dtype == "int64" and df["mae_roll_deg_s"].dtype == "float64"
    arrow = pd.read_parquet(path, dtype_backend="pyarrow")
    assert [arrow[f.name].dtype for f in FLIGHTS_SCHEMA] == [
        pd.ArrowDtype(f.type) for f in FLIGHTS_SCHEMA
    ]
    # campaign.json's records are the table's rows
    recs = _records(local_run, drop=())
    assert [r["flight_id"] for r in recs] == df["flight_id"].tolist()
    assert [r["mae_deg_s"]["yaw"] for r in recs] == df["mae_yaw_deg_s"].tolist()
    assert [r["rms_deg_s"]["roll"] for r in recs] == df["rms_roll_deg_s"].tolist()


def test_a_flight_that_raises_is_an_error_row_not_a_hang(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sc = load_scenario("paper-acro").model_copy(update={"duration_s": 1.0})
    f450 = load_profile(ROOT / "vehicle_profiles" / "f450.yaml")
    good = FlightSpec("f450", f450, 1.0, 0.0, 7, "mfc", load_controller(), sc)
    bad = FlightSpec("f450", f450, 1.0, 0.0, -1, "mfc", load_controller(), sc)  # no such seed
    pulled = [0]

    def numbers() -> Iterator[int]:
        for x in [1, 0, 4, *range(5, 22)]:
            pulled[0] += 1
            yield x

    first: list[int] = []
    with Executor(workers=1) as ex:
        outcomes = ex.run(executor_tasks.reciprocal, numbers(), total=20, desc="reciprocals",
                          on_result=lambda o: first.append(pulled[0]))  # fmt: skip
        records = run_campaign([good, bad], executor=ex, store=CampaignStore(tmp_path),
                               progress=False)  # fmt: skip
    assert [o.index for o in outcomes] == list(range(20))
    assert outcomes[0].value == 1.0 and outcomes[2].value == 0.25
    assert outcomes[1].error is not None and outcomes[1].error.startswith("ZeroDivisionError")
    assert first[0] <= 2  # items are pulled as workers free up, not all at once
    bar = capsys.readouterr().err
    assert "reciprocals: 100%" in bar and "errors=1" in bar  # the bar shows the failure
    assert records[0]["error"] is None and records[0]["crashed"] is False
    assert records[1]["crashed"] is None and "ValueError" in records[1]["error"]
    write_outputs(records, tmp_path, {"scenario": sc.name, "duration_s": 1.0,
                  "profiles": ["f450"], "damages": [1.0], "gusts_m_s": [0.0],
                  "seeds": [7, -1], "workers": 1, "wall_time_s": 0.0})  # fmt: skip
    row = read_table(tmp_path / "flights.parquet").to_pylist()[1]
    assert row["seed"] == -1 and "ValueError" in row["error"]
    assert row["crashed"] is None and row["mae_roll_deg_s"] is None
    assert "1 flights raised" in (tmp_path / "summary.md").read_text(encoding="utf-8")


def test_flights_and_oracle_verdicts_are_stored_and_not_redone(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """Every flight crashes (the flight replaced); the oracle is asked once per case,
    and a second run on the same folder asks neither again."""
    calls = tmp_path / "calls"  # the replacements run on a worker: they tell by file

    def crashes(spec: FlightSpec) -> dict[str, Any]:
        with calls.open("a", encoding="utf-8") as f:
            f.write("fly\n")
        return {**campaign._failed_record(spec, ""), "error": None, "crashed": True}

    def oracle_crashes_too(spec: FlightSpec) -> bool:
        with calls.open("a", encoding="utf-8") as f:
            f.write(f"oracle {spec.seed}\n")
        return True

    monkeypatch.setattr(campaign, "fly_one", crashes)
    monkeypatch.setattr(campaign, "oracle_crashes", oracle_crashes_too)
    sc = load_scenario("paper-acro").model_copy(update={"duration_s": 1.0})
    f450 = load_profile(ROOT / "vehicle_profiles" / "f450.yaml")
    ctrl = {"mfc": load_controller(DEFAULT_CONTROLLER), "pid": load_controller(PID)}
    specs = [FlightSpec("f450", f450, 1.0, 0.0, seed, name, cfg, sc)
             for seed in (1, 2) for name, cfg in ctrl.items()]  # fmt: skip
    store = CampaignStore(tmp_path / "out")
    with Executor(workers=1) as ex:
        first = run_campaign(specs, executor=ex, store=store, progress=False)
        second = run_campaign(specs, executor=ex, store=store, progress=False)
    assert sorted(calls.read_text(encoding="utf-8").splitlines()) == [
        "fly", "fly", "fly", "fly", "oracle 1", "oracle 2"
    ]  # fmt: skip
    assert first == second and [r["feasible"] for r in first] == [False] * 4
    assert len(list((tmp_path / "out" / "oracle").glob("*.json"))) == 2


def test_a_bad_scheduler_is_refused_naming_the_option(tmp_path: Path) -> None:
    res = subprocess.run(_campaign_cmd(tmp_path / "out", "--scheduler", "tcp://nowhere"),
                         cwd=ROOT, capture_output=True, text=True, timeout=60)  # fmt: skip
    assert res.returncode == 2 and "--scheduler" in res.stderr and "tcp://HOST:PORT" in res.stderr
    assert not (tmp_path / "out").exists()
    with pytest.raises(ValueError, match=r"no Dask scheduler answered at tcp://127\.0\.0\.1:9 "):
        Executor("tcp://127.0.0.1:9", connect_timeout_s=0.5).__enter__()


def test_a_worker_killed_mid_campaign_loses_no_flight(tmp_path: Path, cluster: Any,
                                                      spawn: Any, logs: Path) -> None:  # fmt: skip
    """Last in the module: it leaves the cluster one worker short."""
    address, workers = cluster
    out = tmp_path / "out"
    client = spawn(_campaign_cmd(out, *LONGER, "--scheduler", address), "client-a")
    _wait_for("a first flight", lambda: bool(_flight_files(out)) or client.poll() is not None)
    workers[0].send_signal(signal.SIGKILL)
    assert client.wait(timeout=80) == 0, (logs / "client-a.stderr").read_text()
    records = _records(out)
    ids = [r["flight_id"] for r in records]
    assert len(records) == 8 and len(set(ids)) == 8
    assert set(_flight_files(out)) == set(ids)
    assert all(r["error"] is None for r in records)
