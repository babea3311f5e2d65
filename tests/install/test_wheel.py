"""The wheel a vehicle installs (docs/install.md), as a user gets it.

Built from a copy of this checkout by ``pip wheel`` with the default build
(the control core compiled where a C compiler and the Python headers are
present), installed with its dependencies (``[vehicle]``) into a fresh virtual
environment outside the checkout, and run from an empty folder: the commands,
a bundled profile found through the installed package, the core that runs, and
``companion preflight`` against a ``sitl run`` started from that environment.

One module-scoped build and install; how long each step took goes to stderr
(``pytest -s``) at the module's end.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from importlib.machinery import EXTENSION_SUFFIXES
from pathlib import Path
from types import ModuleType

import pytest

from tests.file_module import load_file_module

pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.long]

ROOT = Path(__file__).resolve().parents[2]
FILES = ("setup.py", "pyproject.toml", "README.md")
TREES = ("_build", "companion", "sitl", "vehicle_profiles")
"""What ``pip wheel`` reads from a checkout (pyproject.toml's packages, the build backend)."""

STICKS = """\
# A pilot on the ground: sticks centred, the engage switch (ch5) low.
duration_s: 120
rate_full_scale_deg_s: [720, 720, 360]
altitude_m: 10
aux_us: [1000]
segments:
  - {t_s: 0.0, level: true}
"""


def _mfc_compile() -> ModuleType:
    """``_build/mfc_compile.py``: what the build decides on this machine."""
    return load_file_module(ROOT / "_build" / "mfc_compile.py")


def _clean_env(**extra: str) -> dict[str, str]:
    """This process's environment without what would point a command at the checkout
    or change the build's choice."""
    drop = {"PYTHONPATH", "VIRTUAL_ENV", "MFC_COMPILE", "PYTHONHOME"}
    env = {k: v for k, v in os.environ.items() if k not in drop}
    return {**env, "PIP_NO_INPUT": "1", **extra}


def _run(
    cmd: list[str], cwd: Path, env: dict[str, str], timeout_s: float
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout_s, check=False
    )


@dataclass
class Installed:
    """A fresh virtual environment with the wheel installed, and an empty folder to run in."""

    wheel: Path
    build_output: str
    venv: Path
    empty: Path
    times_s: dict[str, float] = field(default_factory=dict)

    @property
    def env(self) -> dict[str, str]:
        return _clean_env(PATH=f"{self.venv / 'bin'}{os.pathsep}{os.environ.get('PATH', '')}")

    def run(self, *args: str, timeout_s: float = 120.0) -> subprocess.CompletedProcess[str]:
        """Run an installed command (``companion``, ``sitl``, ``python``) from the empty folder."""
        return _run([str(self.venv / "bin" / args[0]), *args[1:]], self.empty, self.env, timeout_s)

    def purelib(self) -> Path:
        out = self.run("python", "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])")
        assert out.returncode == 0, out.stderr
        return Path(out.stdout.strip())


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Installed]:
    base = tmp_path_factory.mktemp("wheel")
    times: dict[str, float] = {}

    # A copy, so that the build's build/ and *.egg-info never land in the checkout
    # and no earlier build's leftovers reach the wheel.
    t0 = time.perf_counter()
    src = base / "src"
    src.mkdir()
    for name in FILES:
        shutil.copy2(ROOT / name, src / name)
    ignore = shutil.ignore_patterns("__pycache__", "*.so", "*.pyd", "_compiled.json", "*.egg-info")
    for name in TREES:
        shutil.copytree(ROOT / name, src / name, ignore=ignore)
    dist = base / "dist"
    build = _run(
        [sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "-w", str(dist), "-v"],
        base, _clean_env(), 900.0,
    )  # fmt: skip
    times["build"] = time.perf_counter() - t0
    output = build.stdout + build.stderr
    assert build.returncode == 0, output[-4000:]
    (wheel,) = dist.glob("mfc_companion-*.whl")

    t0 = time.perf_counter()
    venv = base / "venv"
    # Installed by this pip (--python) into a venv made without one, and not
    # byte-compiled (pymavlink's dialects are large): 5x faster than the venv's own
    # pip, and the same files in the same places.
    made = _run(
        [sys.executable, "-m", "venv", "--without-pip", str(venv)], base, _clean_env(), 300.0
    )
    assert made.returncode == 0, made.stderr
    pip = _run(
        [sys.executable, "-m", "pip", "--python", str(venv / "bin" / "python"), "install",
         "-q", "--no-compile", f"{wheel}[vehicle]"],
        base, _clean_env(), 900.0,
    )  # fmt: skip
    times["venv+install"] = time.perf_counter() - t0
    assert pip.returncode == 0, pip.stdout[-3000:] + pip.stderr[-3000:]

    empty = base / "empty"
    empty.mkdir()
    yield Installed(wheel, output, venv.resolve(), empty.resolve(), times)
    sys.stderr.write(
        f"wheel test steps, s: {json.dumps({k: round(v, 1) for k, v in times.items()})}\n"
    )


def test_the_wheel_holds_the_core_its_build_chose(installed: Installed) -> None:
    problem = _mfc_compile().toolchain_problem()
    with zipfile.ZipFile(installed.wheel) as whl:
        names = whl.namelist()
        record = json.loads(whl.read("companion/control/_core.json"))
    compiled = [n for n in names if n.endswith(tuple(EXTENSION_SUFFIXES))]
    if problem is None:
        assert "mfc-companion: compiling the control core with mypyc" in installed.build_output
        assert record == {"compiled": True, "why": "a C compiler and the Python headers were found"}
        assert "companion/control/_compiled.json" in names
        assert len(compiled) == 9, compiled  # 8 control modules and their shared library
        assert not installed.wheel.name.endswith("-py3-none-any.whl")
    else:
        assert "WARNING: the control core is built pure Python" in installed.build_output
        assert record == {"compiled": False, "why": problem}
        assert not compiled
    assert not [n for n in names if n.startswith(("tests/", "_build/", "build/"))]


def test_the_commands_run_from_an_empty_folder(installed: Installed) -> None:
    t0 = time.perf_counter()
    out = installed.run("companion", "--help")
    assert out.returncode == 0, out.stderr
    assert "check-config" in out.stdout and "run" in out.stdout
    sitl = installed.run("sitl", "--help")
    assert sitl.returncode == 0, sitl.stderr
    # [vehicle] brings the telemetry.
    mqtt = installed.run("python", "-c", "import aiomqtt")
    assert mqtt.returncode == 0, mqtt.stderr
    # The lean install has no lab: its commands say which extra brings them.
    assert installed.run("python", "-c", "import matplotlib").returncode != 0
    lab = installed.run("companion", "fly")
    assert lab.returncode == 1
    assert "mfc-companion[lab]" in lab.stderr, lab.stderr
    installed.times_s["help"] = time.perf_counter() - t0


def test_a_bundled_profile_is_found_in_the_installed_package(installed: Installed) -> None:
    t0 = time.perf_counter()
    out = installed.run("companion", "check-config", "--profile", "vehicle_profiles/f450.yaml")
    installed.times_s["check-config"] = time.perf_counter() - t0
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    # companion.options.find_profile: not in the empty folder, so the installed copy.
    bundled = installed.purelib() / "vehicle_profiles" / "f450.yaml"
    assert f"using {bundled}" in out.stderr, out.stderr


def test_the_core_that_runs_is_the_one_built(installed: Installed) -> None:
    problem = _mfc_compile().toolchain_problem()
    code = (
        "import json, companion.control as c; "
        "print(json.dumps({'compiled': c.COMPILED, 'core': c.CORE, 'mfc': c.mfc.__file__}))"
    )
    out = installed.run("python", "-c", code)
    assert out.returncode == 0, out.stderr
    core = json.loads(out.stdout)
    assert Path(core["mfc"]).is_relative_to(installed.venv), core
    if problem is None:
        assert core["compiled"] is True and core["core"] == "compiled (mypyc)", core
        assert core["mfc"].endswith(tuple(EXTENSION_SUFFIXES)), core
    else:
        assert core["compiled"] is False and core["core"] == f"pure Python ({problem})", core


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def sitl_from_the_venv(installed: Installed, tmp_path: Path) -> Iterator[int]:
    """``sitl run`` from the installed environment, a pilot on the ground with the
    engage switch low, sending to a free port on 127.0.0.1; yields the port."""
    port = _free_udp_port()
    sticks = tmp_path / "ground.yaml"
    sticks.write_text(STICKS, encoding="utf-8")
    profile = installed.purelib() / "vehicle_profiles" / "f450.yaml"
    cmd = [
        str(installed.venv / "bin" / "sitl"), "run", "--profile", str(profile),
        "--mavlink", f"udpout:127.0.0.1:{port}", "--pilot", str(sticks), "--no-auto-arm",
        # COM_OF_LOSS_T as docs/failsafes.md says to set it (PX4's 1 s fails preflight).
        "--offboard-timeout", "0.3", "--duration", "120",
    ]  # fmt: skip
    err = tmp_path / "sitl.stderr"
    with err.open("wb") as f:
        proc = subprocess.Popen(
            cmd, cwd=installed.empty, env=installed.env, stdout=subprocess.DEVNULL, stderr=f
        )
    try:
        yield port
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)


def test_preflight_passes_against_the_sitl(installed: Installed, sitl_from_the_venv: int) -> None:
    problem = _mfc_compile().toolchain_problem()
    t0 = time.perf_counter()
    out = installed.run(
        "companion", "preflight", "--connect", f"udpin:127.0.0.1:{sitl_from_the_venv}",
        "--profile", "vehicle_profiles/f450.yaml", "--json",
    )  # fmt: skip
    installed.times_s["preflight"] = time.perf_counter() - t0
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
    report = json.loads(out.stdout)
    # "which core runs", as preflight reports it
    assert report["core"]["compiled"] is (problem is None), report["core"]


def test_the_quickstart_flight_runs_from_the_venv(installed: Installed, tmp_path: Path) -> None:
    """docs/quickstart.md's two terminals, from the installed environment and an
    empty folder: sitl run waits for the companion to arm it, companion run
    engages, flies, hands back and exits 0; the recorded flight replays. (In
    lockstep, not real time: a loaded test machine stalls a real-time SITL past
    the companion's stale-IMU failsafe.)"""
    port = _free_udp_port()
    t0 = time.perf_counter()
    cmd = [
        str(installed.venv / "bin" / "sitl"), "run", "--profile", "vehicle_profiles/f450.yaml",
        "--scenario", "paper-acro", "--clock", "lockstep", "--pilot-from-arm", "--no-auto-arm",
        "--mode", "MANUAL", "--mavlink", f"udpout:127.0.0.1:{port}", "--duration", "60",
    ]  # fmt: skip
    err = tmp_path / "sitl.stderr"
    with err.open("wb") as f:
        sitl = subprocess.Popen(
            cmd, cwd=installed.empty, env=installed.env, stdout=subprocess.DEVNULL, stderr=f
        )
    try:
        out = installed.run(
            "companion", "run", "--connect", f"udpin:127.0.0.1:{port}",
            "--profile", "vehicle_profiles/f450.yaml", "--engage", "auto", "--duration", "2",
            "--log-dir", "runs/quickstart",
        )  # fmt: skip
    finally:
        sitl.send_signal(signal.SIGTERM)
        sitl.wait(timeout=10)
    assert out.returncode == 0, out.stderr[-3000:] + err.read_text()[-2000:]
    events = installed.empty / "runs" / "quickstart" / "events.jsonl"
    kinds = [json.loads(x)["kind"] for x in events.read_text().splitlines()]
    assert {"connected", "engaged", "duration", "handed_back"} <= set(kinds), kinds
    replay = installed.run("companion", "replay", "runs/quickstart/control.mcap")
    assert replay.returncode == 0, replay.stdout[-2000:] + replay.stderr[-2000:]
    installed.times_s["quickstart"] = time.perf_counter() - t0


# ------------------------------------------- the compiled core against the pure one

FLIGHT = """
import sys
import numpy as np
from pathlib import Path
import companion.control as control
from companion.config import load_controller
from companion.profile import load_profile
from sitl.lab.simulate import simulate_flight
from sitl.scenario import load_scenario

sc = load_scenario("paper-acro").model_copy(update={"duration_s": 8.0})
profile = load_profile(Path(sys.argv[1]) / "vehicle_profiles" / "f450_cut_props.yaml")
rec = simulate_flight(profile, load_controller(), sc)
np.savez(sys.argv[2], compiled=control.COMPILED, mfc=control.mfc.__file__,
         **{k: v for k, v in rec.columns.items() if v.dtype.kind in "fiub"})
"""


def _with_the_wheels_core(installed: Installed, *args: str) -> subprocess.CompletedProcess[str]:
    """This interpreter (with the test tools) in the checkout, importing the project
    from the wheel's installed package (its compiled core) instead of the checkout."""
    assert _mfc_compile().toolchain_problem() is None, "no C toolchain: nothing was compiled"
    env = {**os.environ, "PYTHONPATH": str(installed.purelib())}
    return _run([sys.executable, *args], ROOT, env, 600.0)


PURE_ONLY_TESTS = (
    "test_quaternion.py",
    "test_attitude.py",
    "test_vertical.py",
    "test_horizontal.py",
    "test_outer.py",
    "test_angle_mode.py",
    "test_hold_modes.py",
    "test_mission.py",
)
"""Control tests of modules the build does not compile (the outer loops and the flight
modes): the checkout's run covers them."""


def test_the_control_tests_pass_on_the_compiled_core(installed: Installed) -> None:
    # pytest.main in an interpreter that has just imported the compiled core (and
    # said so), so the tests run against it.
    # ('' off the path first: python -c would put the checkout ahead of PYTHONPATH.)
    main = (
        "import sys; sys.path[:] = [p for p in sys.path if p not in ('', '.')]; "
        "import pytest, companion.control as c; print('compiled', c.COMPILED); "
        "sys.exit(pytest.main(['-q', '-p', 'no:cacheprovider', '-p', 'no:xdist', "
        "'tests/control', '--deselect', 'tests/control/test_compiled.py', '--deselect', "
        "'tests/control/test_gain_set.py::test_default_controller_points_at_the_shipped_set', "
        + ", ".join(f"'--ignore', 'tests/control/{f}'" for f in PURE_ONLY_TESTS)
        + "]))"
    )  # (that one checks the checkout's file is the default: here the wheel's is)
    run = _with_the_wheels_core(installed, "-c", main)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]
    assert run.stdout.startswith("compiled True"), run.stdout[:200]
    assert " passed" in run.stdout.splitlines()[-1], run.stdout[-500:]


def test_a_compiled_flight_matches_the_pure_python_one(
    installed: Installed, tmp_path: Path
) -> None:
    import numpy as np

    script = tmp_path / "flight.py"
    script.write_text(FLIGHT, encoding="utf-8")
    compiled_out, pure_out = tmp_path / "compiled.npz", tmp_path / "pure.npz"
    run = _with_the_wheels_core(installed, str(script), str(ROOT), str(compiled_out))
    assert run.returncode == 0, run.stderr[-3000:]
    run = _run([sys.executable, str(script), str(ROOT), str(pure_out)], ROOT, dict(os.environ),
               600.0)  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    compiled, pure = np.load(compiled_out), np.load(pure_out)
    suffix = EXTENSION_SUFFIXES[0]
    assert bool(compiled["compiled"]) and str(compiled["mfc"]).endswith(suffix)
    assert not bool(pure["compiled"]) and str(pure["mfc"]).endswith(".py")
    keys = set(pure.files) - {"compiled", "mfc"}
    assert keys == set(compiled.files) - {"compiled", "mfc"}
    assert len(pure["t_s"]) > 1500  # 8 s at 250 Hz
    for k in sorted(keys):
        np.testing.assert_array_equal(compiled[k], pure[k], err_msg=k)
