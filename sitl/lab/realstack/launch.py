"""Start the real PX4 and ArduCopter SITL as processes, and find them.

The real firmware (PX4 v1.16 with its SIH quadrotor, ArduCopter 4.5 with its
built-in multicopter physics) is started by the launchers its distribution
ships (``px4-sitl``, ``arducopter-sitl``): where ``MFC_PX4_SITL`` and
``MFC_ARDUCOPTER_SITL`` point, else ``../shared/stacks/`` beside the checkout.
Everything else talks to them only over MAVLink, as a companion computer and a
ground station would.

PX4's POSIX build runs its modules' commands (``px4-param``, ``px4-commander``)
as symbolic links to the ``px4`` binary. A copy of the tree that lost those
links (a plain file holding the word ``px4`` instead) cannot start: its start-up
script fails on the first ``param`` call. :func:`px4_tree` then builds a shadow
tree with the links restored, pointing at the unmodified binary and ``etc/``.

Ports, for instance ``I`` (each stack's README):

=============  ====================================  ===========================================
stack          companion link                        ground station / pilot
=============  ====================================  ===========================================
PX4            ``udpin:127.0.0.1:14540+I``           MAVLink to UDP ``18570+I`` (it answers the
                                                     sender); the pilot is ``MANUAL_CONTROL``
ArduCopter     ``udpin:127.0.0.1:GCS`` (``--gcs``)   MAVLink on TCP ``5760+10*I``; RC pulses to
                                                     UDP ``5501+10*I``
=============  ====================================  ===========================================
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from sitl.lab import children

__all__ = [
    "ARDUCOPTER_ENV",
    "PX4_ENV",
    "RunningStack",
    "StackMissingError",
    "find_launcher",
    "free_instance",
    "px4_tree",
    "start_arducopter",
    "start_px4",
]

PX4_ENV = "MFC_PX4_SITL"
ARDUCOPTER_ENV = "MFC_ARDUCOPTER_SITL"
_DEFAULT_DIR = Path(__file__).resolve().parents[3].parent / "shared" / "stacks"
_LAUNCHERS = {"px4": ("px4-sitl", PX4_ENV), "ardupilot": ("arducopter-sitl", ARDUCOPTER_ENV)}


class StackMissingError(RuntimeError):
    """The launcher of a real stack is not where it is looked for."""


def find_launcher(stack: str) -> Path:
    """The launcher of ``stack`` (``"px4"`` or ``"ardupilot"``).

    Raises
    ------
    StackMissingError
        Saying where it was looked for.
    """
    name, env = _LAUNCHERS[stack]
    given = os.environ.get(env)
    path = Path(given) if given else _DEFAULT_DIR / name
    if not (path.is_file() and os.access(path, os.X_OK)):
        where = f"{env}={given}" if given else f"{path} (set {env} to its launcher)"
        raise StackMissingError(f"the real {stack} SITL is not installed: no launcher at {where}")
    return path


def px4_tree(launcher: Path, into: Path) -> Path:
    """A launcher whose PX4 tree has its command links, building a shadow in
    ``into`` when the original lost them; returns the launcher to run."""
    tree = launcher.parent / "px4-1.16.0"
    bin_dir = tree / "bin"
    probe = bin_dir / "px4-param"
    if probe.is_symlink() or os.access(probe, os.X_OK):
        return launcher
    shadow = into / "px4-shadow"
    shutil.rmtree(shadow, ignore_errors=True)  # one left by an earlier launch into ``into``
    shadow_bin = shadow / "px4-1.16.0" / "bin"
    shadow_bin.mkdir(parents=True, exist_ok=True)
    (shadow / "px4-1.16.0" / "etc").symlink_to(tree / "etc")
    for f in bin_dir.iterdir():
        dest = shadow_bin / f.name
        if f.name != "px4" and f.name.startswith("px4-") and _is_lost_link(f):
            dest.symlink_to("px4")
        else:
            dest.symlink_to(f)
    shutil.copy2(launcher, shadow / launcher.name)
    return shadow / launcher.name


def _is_lost_link(path: Path) -> bool:
    try:
        return path.stat().st_size < 16 and path.read_bytes().strip() == b"px4"
    except OSError:
        return False


def _port_free(port: int, kind: int) -> bool:
    with socket.socket(socket.AF_INET, kind) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def free_instance(stack: str, *, first: int = 1, last: int = 9) -> int:
    """An instance number whose fixed ports are all free now."""
    for i in range(first, last + 1):
        if stack == "px4":
            udp = [14540 + i, 14580 + i, 18570 + i, 14280 + i, 13030 + i, 19450 + i]
            tcp: list[int] = []
        else:
            udp = [5501 + 10 * i]
            tcp = [5760 + 10 * i, 5762 + 10 * i, 5763 + 10 * i]
        if all(_port_free(p, socket.SOCK_DGRAM) for p in udp) and all(
            _port_free(p, socket.SOCK_STREAM) for p in tcp
        ):
            return i
    raise RuntimeError(f"no free {stack} SITL instance between {first} and {last}")


@dataclass
class RunningStack:
    """A real SITL running as a process (its own process group)."""

    name: str
    instance: int
    proc: subprocess.Popen[bytes]
    workdir: Path
    log_path: Path
    companion_url: str
    """What ``companion run --connect`` takes."""
    gcs_url: str
    """Where a ground station reaches it (pymavlink's ``mavutil`` form)."""
    rc_port: int | None = None
    """ArduCopter: the UDP port its RC input listens on."""
    started_wall_s: float = field(default_factory=time.monotonic)

    def log(self) -> str:
        return self.log_path.read_text(encoding="utf-8", errors="replace")

    def wait_log(self, text: str, timeout_s: float) -> bool:
        """Wait until the stack's console shows ``text``; False on timeout or exit."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if text in self.log():
                return True
            if self.proc.poll() is not None:
                return False
            time.sleep(0.2)
        return False

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, timeout_s: float = 10.0) -> None:
        """SIGTERM to its group, then SIGKILL if it lingers."""
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(timeout=timeout_s)


def _spawn(cmd: list[str], log_path: Path, cwd: Path) -> subprocess.Popen[bytes]:
    with log_path.open("wb") as out:
        return children.start(
            cmd,
            cwd=cwd,
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )


def start_px4(workdir: Path | None = None, *, instance: int | None = None) -> RunningStack:
    """Start the real PX4 SITL (SIH quadrotor) with fresh parameters in ``workdir``."""
    launcher = find_launcher("px4")
    base = Path(workdir) if workdir else Path(tempfile.mkdtemp(prefix="mfc-px4-"))
    base.mkdir(parents=True, exist_ok=True)
    launcher = px4_tree(launcher, base)
    i = free_instance("px4") if instance is None else instance
    work = base / f"px4-{i}"
    log_path = base / f"px4-{i}.log"
    proc = _spawn([str(launcher), "-i", str(i), "-w", str(work)], log_path, base)
    return RunningStack(
        name="px4",
        instance=i,
        proc=proc,
        workdir=work,
        log_path=log_path,
        companion_url=f"udpin:127.0.0.1:{14540 + i}",
        gcs_url=f"udpout:127.0.0.1:{18570 + i}",
    )


def start_arducopter(
    workdir: Path | None = None,
    *,
    params: dict[str, float] | None = None,
    companion_port: int,
    instance: int | None = None,
    speedup: float = 1.0,
) -> RunningStack:
    """Start the real ArduCopter SITL (``--model quad``) with fresh parameters
    (its defaults, then ``params``), its MAVLink serial1 sent to ``companion_port``."""
    launcher = find_launcher("ardupilot")
    base = Path(workdir) if workdir else Path(tempfile.mkdtemp(prefix="mfc-arducopter-"))
    base.mkdir(parents=True, exist_ok=True)
    i = free_instance("ardupilot") if instance is None else instance
    work = base / f"arducopter-{i}"
    log_path = base / f"arducopter-{i}.log"
    cmd = [str(launcher), "-I", str(i), "-w", str(work), "--gcs", str(companion_port)]
    cmd += ["--speedup", f"{speedup:g}"]
    for name, value in (params or {}).items():
        cmd += ["--param", f"{name}={value:g}"]
    proc = _spawn(cmd, log_path, base)
    return RunningStack(
        name="ardupilot",
        instance=i,
        proc=proc,
        workdir=work,
        log_path=log_path,
        companion_url=f"udpin:127.0.0.1:{companion_port}",
        gcs_url=f"tcp:127.0.0.1:{5760 + 10 * i}",
        rc_port=5501 + 10 * i,
    )
