"""A controller file flies only after it passed ``check-config --fly`` on this computer.

Found by an outside campaign: of 100 schema-valid mutations of the shipped
controller, 8 crash or blow up in the simulator (``adapt_min_thrust: 0.88`` alone
is one), plain ``check-config`` said nothing and ``companion run`` flew them.
Here: the record (companion.fly_check) and its corners, ``companion run``'s
refusal (exit 2, nothing opened, nothing sent), ``--skip-fly-check`` and shadow
mode (each flies and says so in an event), and preflight's line. The pass
recorded by a real ``check-config --fly``: tests/lab/test_config_check.py.
"""

from __future__ import annotations

import json
import logging
import os
import socket
from datetime import datetime, timezone
from pathlib import Path

import pytest
from click.testing import CliRunner, Result

from companion.cli import cli
from companion.config import DEFAULT_CONTROLLER, load_controller
from companion.fly_check import (
    MAX_RECORDS,
    RECORD_NAME,
    STATE_DIR_ENV,
    fly_check_of,
    record_fly_check,
    record_path,
    state_dir,
)

ROOT = Path(__file__).resolve().parents[1]
F450 = ROOT / "vehicle_profiles" / "f450.yaml"
EXIT_BAD_INPUT = 2


@pytest.fixture
def state(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """An empty state folder of this test's own."""
    folder = tmp_path / "state"
    monkeypatch.setenv(STATE_DIR_ENV, str(folder))
    return folder


def mutant(folder: Path) -> Path:
    """The shipped controller with ``adapt_min_thrust: 0.88`` alone: schema-valid, and
    in the simulator it crashes the heavy-weak corner and tracks the F450 and the
    Tarot more than 20 deg/s worse than the shipped one (check-config --fly fails it)."""
    text = DEFAULT_CONTROLLER.read_text(encoding="utf-8")
    assert "\nadapt_min_thrust: 0.15 " in text
    path = folder / "mutant.yaml"
    path.write_text(text.replace("\nadapt_min_thrust: 0.15 ", "\nadapt_min_thrust: 0.88 "))
    assert load_controller(path).adapt_min_thrust == 0.88  # type: ignore[union-attr]
    return path


def events(log_dir: Path) -> list[dict[str, object]]:
    lines = (log_dir / "events.jsonl").read_text(encoding="utf-8").splitlines()
    return [json.loads(line) for line in lines]


def companion(*args: str) -> Result:
    return CliRunner().invoke(cli, list(args))


# ----------------------------------------------------------------------------- the record


def test_the_state_folder_follows_the_environment(tmp_path: Path) -> None:
    home = Path.home()
    assert state_dir({}) == home / ".local" / "state" / "mfc-companion"
    assert state_dir({"XDG_STATE_HOME": "/x/state"}) == Path("/x/state/mfc-companion")
    assert state_dir({"XDG_STATE_HOME": "relative"}) == home / ".local/state/mfc-companion"
    env = {"XDG_STATE_HOME": "/x/state", STATE_DIR_ENV: str(tmp_path)}
    assert state_dir(env) == tmp_path  # the folder itself
    assert record_path(env) == tmp_path / RECORD_NAME


def test_a_shipped_file_is_known_by_its_content(state: Path, tmp_path: Path) -> None:
    copy = tmp_path / "elsewhere.yaml"
    copy.write_bytes(DEFAULT_CONTROLLER.read_bytes())
    assert fly_check_of(DEFAULT_CONTROLLER).status == "shipped"
    assert fly_check_of(copy).status == "shipped"
    assert fly_check_of(copy).may_fly
    copy.write_bytes(DEFAULT_CONTROLLER.read_bytes() + b"# mine\n")  # one byte is enough
    assert fly_check_of(copy).status == "unchecked"
    assert not state.exists()  # reading makes nothing


def test_a_verdict_is_remembered_by_hash_and_a_changed_file_is_not_checked(
    state: Path, tmp_path: Path
) -> None:
    path = mutant(tmp_path)
    check = fly_check_of(path)
    assert (check.status, check.note) == ("unchecked", "")
    when = datetime(2025, 6, 1, 14, 2, 7, tzinfo=timezone.utc)
    record, note = record_fly_check(check, passed=True, now=when)
    assert (record, note) == (state / RECORD_NAME, "")
    passed = fly_check_of(path)
    assert (passed.status, passed.date, passed.checked_path) == (
        "passed", "2025-06-01T14:02:07Z", str(path.resolve()),
    )  # fmt: skip
    assert passed.describe() == f"{path}: passed the fly check on 2025-06-01 14:02 UTC"
    # The same bytes elsewhere are the same file; changed bytes are another one.
    moved = tmp_path / "moved.yaml"
    moved.write_bytes(path.read_bytes())
    assert fly_check_of(moved).status == "passed"
    path.write_text(path.read_text(encoding="utf-8") + "# tuned\n", encoding="utf-8")
    assert fly_check_of(path).status == "unchecked"
    record_fly_check(fly_check_of(path), passed=False, problems=["heavy-weak: crashed"] * 9)
    failed = fly_check_of(path)
    assert failed.status == "failed" and failed.problems == ("heavy-weak: crashed",) * 3
    assert "failed the fly check on" in failed.describe() and not failed.may_fly
    assert sorted(os.listdir(state)) == ["fly-checks.json", "fly-checks.lock"]  # no temp file


def test_the_record_keeps_the_newest(state: Path, tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    for i in range(MAX_RECORDS + 5):
        path.write_text(f"# {i}\n", encoding="utf-8")
        record_fly_check(fly_check_of(path), passed=True)
    doc = json.loads((state / RECORD_NAME).read_text(encoding="utf-8"))
    assert len(doc["checks"]) == MAX_RECORDS
    assert fly_check_of(path).status == "passed"  # the last one is kept
    path.write_text("# 0\n", encoding="utf-8")
    assert fly_check_of(path).status == "unchecked"  # the first one is not


@pytest.mark.parametrize(
    ("content", "said"),
    [
        (b"{not json", "is not JSON"),
        (b"\xff\xfe", "cannot be read: not UTF-8"),
        (b'{"format": "x", "version": 1, "checks": {}}', "is not a fly-check record"),
        (b'{"format": "mfc-companion fly checks", "version": 1, "checks": []}', "is not a"),
        (b"[]", "is not a fly-check record"),
        (None, "cannot be read"),  # a folder where the record should be
    ],
)
def test_a_corrupt_record_counts_as_not_checked_and_says_why(
    state: Path, tmp_path: Path, content: bytes | None, said: str
) -> None:
    path = mutant(tmp_path)
    state.mkdir()
    if content is None:
        (state / RECORD_NAME).mkdir()
    else:
        (state / RECORD_NAME).write_bytes(content)
    check = fly_check_of(path)
    assert check.status == "unchecked" and said in check.note, check.note
    assert str(state / RECORD_NAME) in check.describe()
    # The command says so and refuses, with the same note: never a crash, never a pass.
    res = companion("run", "--connect", "udpout:127.0.0.1:9", "--controller", str(path))
    assert res.exit_code == EXIT_BAD_INPUT and said in res.output, res.output
    if content is not None:  # a new verdict replaces it, and says so
        _, note = record_fly_check(check, passed=True)
        assert said in note
        assert fly_check_of(path).status == "passed"


# ------------------------------------------------------------------------- companion run


def test_run_refuses_an_unchecked_mutant_before_opening_anything(
    state: Path, tmp_path: Path
) -> None:
    path = mutant(tmp_path)
    logs = tmp_path / "logs"
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as peer:
        peer.bind(("127.0.0.1", 0))
        peer.settimeout(0.3)
        port = peer.getsockname()[1]
        res = companion(
            "run", "--connect", f"udpout:127.0.0.1:{port}", "--profile", str(F450),
            "--controller", str(path), "--engage", "rc-switch", "--log-dir", str(logs),
        )  # fmt: skip
        with pytest.raises(TimeoutError):
            peer.recv(65535)  # not a byte of MAVLink
    assert res.exit_code == EXIT_BAD_INPUT, res.output
    assert f"error: {path}: not checked in the simulator on this computer" in res.output
    assert f"`companion check-config --controller {path} --fly`" in res.output
    assert "--skip-fly-check" in res.output and "Traceback" not in res.output
    assert not logs.exists()


def test_run_refuses_a_file_that_failed_the_check_naming_its_problem(
    state: Path, tmp_path: Path
) -> None:
    path = mutant(tmp_path)
    record_fly_check(fly_check_of(path), passed=False, problems=["heavy-weak: crashed"])
    res = companion("run", "--connect", "udpout:127.0.0.1:9", "--controller", str(path))
    assert res.exit_code == EXIT_BAD_INPUT, res.output
    assert f"{path}: failed the fly check on" in res.output
    assert "heavy-weak: crashed" in res.output and "do not fly it as it is" in res.output


@pytest.mark.parametrize(
    ("option", "said"),
    [
        (("--skip-fly-check",), "flown anyway (--skip-fly-check)"),
        (("--engage", "none"), "flown in shadow mode (--engage none), which sends nothing"),
    ],
)
def test_skipping_the_check_flies_and_records_it(
    state: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture,
    option: tuple[str, ...], said: str,
) -> None:  # fmt: skip
    """The run goes on (here it finds no autopilot: exit 1) and its events say it was
    not checked; with --skip-fly-check the log warns."""
    path = mutant(tmp_path)
    logs = tmp_path / "logs"
    with caplog.at_level(logging.INFO, logger="companion"):
        res = companion(
            "run", "--connect", "udpout:127.0.0.1:9", "--profile", str(F450),
            "--controller", str(path), "--heartbeat-timeout-s", "0.2", "--log-dir", str(logs),
            *option,
        )  # fmt: skip
    assert res.exit_code == 1, res.output  # started: no autopilot answered
    skipped = [e for e in events(logs) if e["kind"] == "fly_check_skipped"]
    assert len(skipped) == 1, events(logs)
    detail = str(skipped[0]["detail"])
    assert detail.startswith(f"{path}: not checked in the simulator") and said in detail
    warned = [r for r in caplog.records if "fly_check_skipped" in r.getMessage()]
    assert [r.levelno for r in warned] == [logging.WARNING]


def test_a_shipped_controller_needs_nothing_and_says_nothing(state: Path, tmp_path: Path) -> None:
    logs = tmp_path / "logs"
    res = companion(
        "run", "--connect", "udpout:127.0.0.1:9", "--profile", str(F450),
        "--heartbeat-timeout-s", "0.2", "--log-dir", str(logs),
    )  # fmt: skip
    assert res.exit_code == 1, res.output
    assert not [e for e in events(logs) if str(e["kind"]).startswith("fly_check")]


def test_plain_check_config_says_run_will_refuse_the_file(state: Path, tmp_path: Path) -> None:
    path = mutant(tmp_path)
    res = companion("check-config", "--controller", str(path))
    assert res.exit_code == 0, res.output
    assert f"note: {path}: not checked in the simulator on this computer" in res.stderr
    assert f"`companion check-config --controller {path} --fly`" in res.stderr
    assert "note:" not in companion("check-config").stderr  # the shipped one


# ----------------------------------------------------------------------------- preflight


@pytest.mark.parametrize(
    ("args", "status", "said"),
    [
        ((), "PASS", f"{DEFAULT_CONTROLLER}: a shipped controller"),
        (("--controller", "MUTANT"), "FAIL", "not checked in the simulator on this computer; "
         "companion run refuses it"),
        (("--controller", "MUTANT", "--skip-fly-check"), "WARN", "flown anyway"),
        (("--controller", "MUTANT", "--engage", "none"), "WARN", "shadow mode"),
        (("--controller", "PASSED"), "PASS", "passed the fly check on 2025-06-01 14:02 UTC"),
    ],
)  # fmt: skip
def test_preflight_says_which_controller_it_is(
    state: Path, tmp_path: Path, args: tuple[str, ...], status: str, said: str
) -> None:
    """Learnt as run learns it (--controller, else the --output's shipped file); no
    autopilot answers here, and the line is there all the same."""
    path = mutant(tmp_path)
    passed = tmp_path / "passed.yaml"
    passed.write_bytes(path.read_bytes() + b"# passed\n")
    when = datetime(2025, 6, 1, 14, 2, tzinfo=timezone.utc)
    record_fly_check(fly_check_of(passed), passed=True, now=when)
    args = tuple({"MUTANT": str(path), "PASSED": str(passed)}.get(a, a) for a in args)
    res = companion(
        "preflight", "--connect", "udpout:127.0.0.1:9", "--heartbeat-timeout-s", "0.1",
        "--watch-s", "1", *args,
    )  # fmt: skip
    assert res.exit_code == 1, res.output  # the link fails: no autopilot
    (line,) = [ln for ln in res.output.splitlines() if ln.split()[1:2] == ["controller"]]
    assert line.startswith(status) and said in line, line
    if status != "PASS":
        assert "companion check-config --controller" in res.output
