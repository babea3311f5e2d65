"""MAVLink 2 signing end to end: the SITL and the companion share a key, or do not."""

from __future__ import annotations

from pathlib import Path

import pytest

from sitl.lab.fly import fly_mavlink

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
PROFILE = ROOT / "vehicle_profiles" / "f450.yaml"
_SIGNED = 0x01  # MAVLink 2 incompat flag: the frame carries a signature


def tlog_frames(path: Path) -> list[tuple[int, int, bool]]:
    """(system id, component id, signed?) of every MAVLink 2 frame in a .tlog."""
    data = path.read_bytes()
    out = []
    i = 0
    while i + 8 + 10 <= len(data):
        i += 8  # timestamp
        if data[i] != 0xFD:
            break
        length, incompat = data[i + 1], data[i + 2]
        signed = bool(incompat & _SIGNED)
        out.append((data[i + 5], data[i + 6], signed))
        i += 10 + length + 2 + (13 if signed else 0)
    return out


def key_file(tmp_path: Path, name: str, byte: int) -> Path:
    p = tmp_path / name
    p.write_text(bytes([byte] * 32).hex() + "\n", encoding="ascii")
    p.chmod(0o600)
    return p


def test_a_shared_key_flies_and_every_frame_is_signed(tmp_path: Path) -> None:
    key = key_file(tmp_path, "key", 0x5A)
    flight = fly_mavlink(
        PROFILE, "paper-acro", tmp_path / "flight", duration_s=5.0,
        sitl_args=("--signing-key", str(key)), companion_args=("--signing-key", str(key)),
    )  # fmt: skip
    assert flight.companion_rc == 0, flight.why()
    assert "engaged" in [e["kind"] for e in flight.companion_events]
    assert flight.sitl_summary["setpoints_received"] > 1000
    frames = tlog_frames(flight.out_dir / "companion" / "flight.tlog")
    assert len(frames) > 2000
    ours = [f for f in frames if f[1] == 191]
    theirs = [f for f in frames if f[:2] == (1, 1)]
    assert ours and theirs
    assert all(signed for _, _, signed in ours + theirs)


def test_a_wrong_key_connects_to_nothing(tmp_path: Path) -> None:
    flight = fly_mavlink(
        PROFILE, "paper-acro", tmp_path / "flight", duration_s=5.0,
        sitl_args=("--signing-key", str(key_file(tmp_path, "a", 0x11)), "--duration", "6"),
        companion_args=(
            "--signing-key", str(key_file(tmp_path, "b", 0x22)), "--heartbeat-timeout-s", "2",
        ),
    )  # fmt: skip
    # The companion drops every frame from the SITL (bad signature), so it never
    # learns an autopilot and exits with an error; the SITL never got a setpoint.
    assert flight.companion_rc == 1
    assert "heartbeat" in flight.text("companion.stderr").lower()
    assert flight.sitl_summary["setpoints_received"] == 0
