"""A loop the link makes unflyable is handed back before it reaches the ground.

Through a relay adding 15 ms each way between the SITL (real-time clock) and the
companion, the shipped controller on the F450 falls into a ~6.5 Hz oscillation
with two motors swinging between full and idle, sinks after the pilot's flip
and touches down about 16 s after engaging (3 of 3 flights, with the diverging
failsafe switched off; docs/failsafes.md). The tracking error stays near
75 deg/s, under the envelope's 300: only the diverging-vehicle rule sees it.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from sitl.lab.fly import fly_mavlink, merge_logs
from tests.integration.conftest import free_udp_port
from tests.relay import UdpRelay

ROOT = Path(__file__).resolve().parents[2]

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def test_a_link_too_slow_to_fly_is_handed_back_before_the_ground(tmp_path: Path) -> None:
    port = free_udp_port()
    relay = UdpRelay(("127.0.0.1", 0), ("127.0.0.1", port), delay_s=0.015, seed=1)
    with relay.in_thread():
        flight = fly_mavlink(
            ROOT / "vehicle_profiles" / "f450.yaml",
            "paper-acro",
            tmp_path,
            duration_s=20.0,
            sitl_args=("--mavlink", f"udpout:127.0.0.1:{relay.listen_port}", "--clock", "realtime"),
            companion_args=("--connect", f"udpin:127.0.0.1:{port}"),
        )
    record = merge_logs(flight)
    kinds = [e["kind"] for e in flight.companion_events]
    assert "failsafe_diverging" in kinds, kinds
    assert flight.companion_rc == 3
    fired = next(e["t_s"] for e in flight.companion_events if e["kind"] == "failsafe_diverging")
    engaged = next(e["t_s"] for e in flight.companion_events if e["kind"] == "engaged")
    # Measured without the rule: ground contact 15.8-16.5 s after engaging.
    assert fired - engaged < 12.0
    assert not record.meta["crashed"] or record.meta["crashed_at_s"] > fired + 2.0
