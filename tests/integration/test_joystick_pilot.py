"""A PX4 flown by a ground station's joystick, as PX4 SIH is: the SITL as a process.

``sitl run --pilot-input joystick`` gives the autopilot the pilot's sticks as
``MANUAL_CONTROL`` (aux1 the pilot's channel 5) and sends no ``RC_CHANNELS``, as the
real PX4 v1.16 SIH does; ``companion run --engage rc-switch`` reads the pilot from
PX4's own ``MANUAL_CONTROL`` stream (``companion/samples.py``) and engages on aux1.
"""

from __future__ import annotations

import signal
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from sitl.flight_log import read_log
from tests.integration import test_failsafe_cases as _cases
from tests.integration.conftest import SitlProcess, free_udp_port
from tests.integration.test_failsafe_cases import (
    COMPANION_IDS,
    ID_SETPOINT,
    CompanionProcess,
    kinds,
    modes,
    read_tlog,
    times,
    write_stick_script,
)

pytestmark = pytest.mark.integration

start_companion = _cases.start_companion
"""The fixture that runs ``companion run`` (tests/integration/test_failsafe_cases.py)."""

AUTOPILOT_IDS = (1, 1)
ID_MANUAL_CONTROL = 69
ID_RC_CHANNELS = 65

SWITCH_AT_S = 2.0
JOYSTICK_SCRIPT = f"""\
duration_s: 8
altitude_m: 5
aux_us: [1000]
segments:
  - {{t_s: 0.0, level: true}}
  - {{t_s: {SWITCH_AT_S}, level: true, aux_us: [2000]}}
"""


def test_the_companion_flies_a_joystick_pilot_and_engages_on_aux1(
    tmp_path: Path,
    start_sitl: Callable[..., SitlProcess],
    start_companion: Callable[..., CompanionProcess],
) -> None:
    port = free_udp_port()
    script = write_stick_script(tmp_path / "joystick.yaml", JOYSTICK_SCRIPT)
    comp = start_companion(
        port, "--engage", "rc-switch", "--rate-hz", "250",
        # Wall-clock watchdog, as fly_mavlink sets it for a SITL on a loaded machine.
        "--stale-imu-s", "0.5",
    )  # fmt: skip
    sitl = start_sitl(
        port, "--pilot", str(script), "--pilot-input", "joystick", "--clock", "realtime",
        duration_s=8.0,
    )  # fmt: skip
    deadline = time.monotonic() + 20.0
    while time.monotonic() < deadline and comp.proc.poll() is None:
        if "engaged" in kinds(comp.events()):
            break
        time.sleep(0.1)
    ev = comp.events()
    assert "engaged" in kinds(ev), (kinds(ev), comp.stderr()[-2000:], sitl.stderr()[-2000:])
    time.sleep(0.5)
    comp.proc.send_signal(signal.SIGTERM)
    assert comp.proc.wait(timeout=15) == 0, comp.stderr()[-2000:]
    sitl.stop()

    assert modes(read_log(sitl.log_path).events)[:1] == ["OFFBOARD"]
    frames = read_tlog(comp.log_dir / "flight.tlog")
    ids = {(f.sysid, f.compid, f.msg_id) for f in frames}
    # PX4's own MANUAL_CONTROL reached the companion; no RC_CHANNELS at all.
    assert (*AUTOPILOT_IDS, ID_MANUAL_CONTROL) in ids
    assert not [f for f in frames if f.msg_id == ID_RC_CHANNELS]
    # The companion engaged on the joystick's aux1 and commanded.
    assert [f for f in frames if (f.sysid, f.compid) == COMPANION_IDS]


def test_px4s_one_frame_without_a_joystick_is_not_taken_for_a_pilot(
    start_sitl: Callable[..., SitlProcess],
    start_companion: Callable[..., CompanionProcess],
) -> None:
    """PX4 v1.16 answers the request for its MANUAL_CONTROL stream with one frame at
    once (x 0, y 0, z 500, r 0), a ground station's joystick there or not. With none
    there, ``--engage auto`` must not take that frame for a pilot: it waits for the
    pilot's input through ``--arm-timeout-s`` and gives up, having flown nothing."""
    port = free_udp_port()
    comp = start_companion(
        port, "--engage", "auto", "--arm-timeout-s", "2", "--rate-hz", "250",
        "--stale-imu-s", "0.5",
    )  # fmt: skip
    sitl = start_sitl(port, "--pilot-input", "joystick", "--clock", "realtime", duration_s=30.0)
    try:
        rc = comp.proc.wait(timeout=30)
    finally:
        sitl.stop()
    assert rc == 1, (kinds(comp.events()), comp.stderr()[-2000:])
    failed = [e["detail"] for e in comp.events() if e["kind"] == "engage_failed"]
    assert failed and failed[0].startswith("no valid pilot input"), kinds(comp.events())
    frames = read_tlog(comp.log_dir / "flight.tlog")
    (mc,) = [
        f for f in frames if (f.sysid, f.compid, f.msg_id) == (*AUTOPILOT_IDS, ID_MANUAL_CONTROL)
    ]
    m = mc.decode()
    assert (m.x, m.y, m.z, m.r, m.enabled_extensions) == (0, 0, 500, 0, 252)
    assert times(frames, COMPANION_IDS, ID_SETPOINT) == []  # nothing flown
    assert "OFFBOARD" not in modes(read_log(sitl.log_path).events)
