"""A signal that lands while the SITL writes its log leaves a whole log.

``companion fly`` stops the SITL with SIGINT; landing during the log's write it
used to raise KeyboardInterrupt there and leave ``sitl.npz.part.npz`` behind
(``FileNotFoundError: .../sitl.npz`` for the report, about one run in two).
Here the signal is sent from inside the write, in a process of its own.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

CHILD = """
import os, signal, sys
import numpy as np
import sitl.flight_log as flight_log
import sitl.runner as runner
from sitl.lab.fly import free_udp_port
from companion.profile import load_profile
from sitl.mavlink_link import parse_endpoint

real = np.savez_compressed

def savez_with_a_signal(*args, **kwargs):
    os.kill(os.getpid(), signal.SIGINT)  # the driver's SIGINT, mid-write
    return real(*args, **kwargs)

flight_log.np.savez_compressed = savez_with_a_signal
profile = load_profile(sys.argv[1], simulated=True)
config = runner.RunConfig(
    mavlink=parse_endpoint(f"udpout:127.0.0.1:{free_udp_port()}"),
    duration_s=0.2, clock="lockstep", log_path=runner.Path(sys.argv[2]),
)
summary = runner.Runner(profile, config, profile_name="f450").run()
print(summary.status)
"""


def test_a_signal_during_the_log_write_leaves_a_whole_log(tmp_path: Path) -> None:
    log = tmp_path / "sitl.npz"
    done = subprocess.run(
        [sys.executable, "-c", CHILD, str(ROOT / "vehicle_profiles" / "f450.yaml"), str(log)],
        cwd=ROOT, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["completed"]
    assert log.exists()
    assert not list(tmp_path.glob("*.part*"))
    from sitl.flight_log import read_log

    assert read_log(log).arrays["t_s"].size > 100
