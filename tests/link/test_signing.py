"""Signing: key files, and a signed link against pymavlink peers with the same or another key."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any

import pytest

from companion.errors import LinkError, SigningError
from companion.link.mavlink import MavlinkLink, mavlink2
from companion.link.signing import (
    SignatureChecker,
    SigningConfig,
    load_signing_key,
    passphrase_to_key,
    signing_timestamp_now,
)
from companion.link.transport import MemoryTransport

from .peer import FakeAutopilot, settle

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))

# ---------------------------------------------------------------------- key files


def write(tmp_path: Path, text: str, name: str = "key") -> Path:
    p = tmp_path / name
    p.write_text(text)
    p.chmod(0o600)
    return p


def test_hex_key_file(tmp_path: Path) -> None:
    cfg = load_signing_key(write(tmp_path, KEY.hex().upper() + "\n"), link_id=5)
    assert cfg.key == KEY and cfg.link_id == 5 and cfg.allow_unsigned is False


def test_passphrase_file_is_sha256_like_mavproxy(tmp_path: Path) -> None:
    cfg = load_signing_key(write(tmp_path, "  correct-horse-battery  \n\n"))
    # MAVProxy: hashlib.sha256(passphrase.encode('ascii')).digest()
    assert cfg.key == hashlib.sha256(b"correct-horse-battery").digest()
    assert cfg.key == passphrase_to_key("correct-horse-battery")
    # 63 hex digits is not a key: it is a passphrase
    cfg = load_signing_key(write(tmp_path, KEY.hex()[:-1]))
    assert cfg.key == hashlib.sha256(KEY.hex()[:-1].encode()).digest()


def test_missing_key_file_names_the_file(tmp_path: Path) -> None:
    p = tmp_path / "nope.key"
    with pytest.raises(SigningError, match=r"nope\.key.*not found.*64 hex") as info:
        load_signing_key(p)
    assert isinstance(info.value, LinkError)


@pytest.mark.parametrize(
    ("text", "what"),
    [("", "empty"), ("\n  \n", "empty"), ("one\ntwo\n", "2 lines"), ("pässword", "ASCII")],
)
def test_bad_key_files(tmp_path: Path, text: str, what: str) -> None:
    p = write(tmp_path, text, "bad.key")
    with pytest.raises(SigningError, match=rf"bad\.key.*{what}"):
        load_signing_key(p)


def test_unreadable_key_file(tmp_path: Path) -> None:
    if os.geteuid() == 0:
        d = tmp_path / "dir.key"  # root reads anything: use a directory instead
        d.mkdir()
        p = d
    else:
        p = write(tmp_path, "secret", "locked.key")
        p.chmod(0)
    with pytest.raises(SigningError, match=p.name):
        load_signing_key(p)


def test_config_validates_and_hides_key() -> None:
    with pytest.raises(ValueError):
        SigningConfig(b"short")
    with pytest.raises(ValueError):
        SigningConfig(KEY, link_id=256)
    assert KEY.hex() not in repr(SigningConfig(KEY)) and "key" not in repr(SigningConfig(KEY))


# ---------------------------------------------------------------------- the link


async def signed_link(
    *, allow_unsigned: bool = False, open_peer: bool = True
) -> tuple[MavlinkLink, MemoryTransport, list[Any]]:
    """A started signed link, and the far end (opened, discarding input, unless not open_peer)."""
    ours, theirs = MemoryTransport.pair()
    got: list[Any] = []
    link = MavlinkLink(
        ours,
        heartbeat_hz=0,
        signing=SigningConfig(KEY, link_id=2, allow_unsigned=allow_unsigned),
        on_message=got.append,
    )
    await link.start()
    if open_peer:
        await theirs.open(lambda chunk: None)
    return link, theirs, got


async def test_outgoing_frames_carry_a_valid_signature() -> None:
    link, theirs, _ = await signed_link(open_peer=False)
    ap = await FakeAutopilot(theirs, key=KEY).open()  # its parser has no key yet
    link.mav.heartbeat_send(18, 8, 0, 0, 4)
    link.send(link.mav.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0))
    await settle()
    frames = ap.raw_received
    assert len(frames) == 2
    for f in frames:
        assert f[0] == 0xFD and f[2] & 0x01  # MAVLink 2, IFLAG_SIGNED
        assert f[-13] == 2  # our link id
    # A pymavlink peer with the same key accepts them as signed ...
    good = mavlink2.MAVLink(None)
    good.signing.secret_key = KEY
    msgs = [m for f in frames for m in good.parse_buffer(f) or []]
    assert [m.get_type() for m in msgs] == ["HEARTBEAT", "COMMAND_LONG"]
    assert all(m.get_signed() for m in msgs)
    assert good.signing.goodsig_count == 2
    # ... and one with another key does not.
    bad = mavlink2.MAVLink(None)
    bad.signing.secret_key = OTHER_KEY
    bad.robust_parsing = True
    assert [m.get_type() for f in frames for m in bad.parse_buffer(f) or []] == ["BAD_DATA"] * 2
    # Timestamps: wall-clock based, increasing.
    ts = [int.from_bytes(f[-12:-6], "little") for f in frames]
    assert ts[1] == ts[0] + 1
    assert abs(ts[0] - signing_timestamp_now()) < 100_000 * 5
    await link.close()


async def test_signed_autopilot_is_accepted() -> None:
    link, theirs, got = await signed_link()
    ap = FakeAutopilot(theirs, key=KEY)
    ap.mav.signing.timestamp = link.mav.signing.timestamp + 1000
    ap.heartbeat()
    await link.wait_heartbeat(1.0)
    assert link.target == (1, 1) and len(got) == 1
    # Our outgoing timestamp follows the newest valid incoming one (spec rule).
    assert link.mav.signing.timestamp >= ap.mav.signing.timestamp - 1
    await link.close()


async def test_unsigned_incoming_is_rejected_and_counted() -> None:
    link, theirs, got = await signed_link()
    ap = FakeAutopilot(theirs)  # no key
    ap.heartbeat()
    ap.mav.highres_imu_send(1, 0, 0, -9.8, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 63)
    await settle()
    assert link.counters["unsigned_rejected"] == 2
    assert link.target is None and got == []
    with pytest.raises(LinkError):
        await link.wait_heartbeat(0.05)
    await link.close()


async def test_forged_signature_is_rejected_and_counted() -> None:
    link, theirs, got = await signed_link()
    forger = FakeAutopilot(theirs, key=OTHER_KEY)
    forger.mav.signing.timestamp = link.mav.signing.timestamp + 10**9  # far future
    forger.heartbeat()
    await settle()
    assert link.counters["bad_signature_rejected"] == 1
    assert link.target is None and got == []
    # The forged far-future timestamp must not poison the real stream (same link id 3).
    real = FakeAutopilot(theirs, key=KEY)
    real.heartbeat()
    await link.wait_heartbeat(1.0)
    assert link.target == (1, 1) and link.counters["replay_rejected"] == 0
    await link.close()


async def test_replayed_frame_is_rejected_and_counted() -> None:
    link, theirs, got = await signed_link()
    ap = FakeAutopilot(theirs, key=KEY)
    frame = ap.mav.heartbeat_encode(2, 12, 0, 0, 3).pack(ap.mav)
    theirs.write(frame)
    theirs.write(frame)  # byte-for-byte replay
    await settle()
    assert link.counters["accepted"] == 1
    assert link.counters["replay_rejected"] == 1
    assert len(got) == 1
    # An older (but validly signed) timestamp on the same stream is a replay too.
    ap.mav.signing.timestamp -= 10
    ap.heartbeat()
    await settle()
    assert link.counters["replay_rejected"] == 2
    await link.close()


async def test_new_stream_more_than_a_minute_behind_is_rejected() -> None:
    link, theirs, _ = await signed_link()
    stale = FakeAutopilot(theirs, key=KEY)
    stale.mav.signing.timestamp = link.mav.signing.timestamp - 7_000_000  # 70 s behind
    stale.heartbeat()
    await settle()
    assert link.counters["replay_rejected"] == 1 and link.target is None
    await link.close()


async def test_allow_unsigned_accepts_unsigned() -> None:
    link, theirs, got = await signed_link(allow_unsigned=True)
    ap = FakeAutopilot(theirs)
    ap.heartbeat()
    await link.wait_heartbeat(1.0)
    assert link.target == (1, 1) and len(got) == 1
    assert link.counters["unsigned_accepted"] == 1
    assert link.counters["unsigned_rejected"] == 0
    # Forgeries are still refused.
    FakeAutopilot(theirs, key=OTHER_KEY).heartbeat()
    await settle()
    assert link.counters["bad_signature_rejected"] == 1 and len(got) == 1
    await link.close()


async def test_command_long_round_trip_signed_both_ways() -> None:
    link, theirs, _ = await signed_link(open_peer=False)
    ap = await FakeAutopilot(theirs, key=KEY).open()
    ap.parser.signing.secret_key = KEY  # the autopilot checks our signatures too
    ap.heartbeat()
    await link.wait_heartbeat(1.0)
    assert await link.command_long(400, 1) == mavlink2.MAV_RESULT_ACCEPTED
    assert ap.parser.signing.goodsig_count >= 1 and ap.parser.signing.badsig_count == 0
    await link.close()


async def test_setup_signing_is_sent_but_not_logged() -> None:
    raw: list[tuple[float, bytes, bool]] = []
    ours, theirs = MemoryTransport.pair()
    link = MavlinkLink(ours, heartbeat_hz=0, on_raw=lambda t, b, o: raw.append((t, b, o)))
    ap = await FakeAutopilot(theirs).open()
    async with link:
        with pytest.raises(LinkError):
            link.send_setup_signing(KEY)  # no target yet
        ap.heartbeat()
        await link.wait_heartbeat(1.0)
        link.send_setup_signing(KEY, initial_timestamp=12345)
        msg = (await ap.wait_for("SETUP_SIGNING"))[0]
    assert bytes(msg.secret_key) == KEY and msg.initial_timestamp == 12345
    assert (msg.target_system, msg.target_component) == (1, 1)
    assert all(not o for _, _, o in raw)  # only the incoming heartbeat was logged


def test_checker_verdicts_directly() -> None:
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    mav.signing.secret_key = KEY
    mav.signing.sign_outgoing = True
    mav.signing.timestamp = 1000
    f1 = mav.heartbeat_encode(2, 12, 0, 0, 3).pack(mav)
    f2 = mav.heartbeat_encode(2, 12, 0, 0, 3).pack(mav)
    chk = SignatureChecker(KEY)
    assert chk.check(f1, 0) == (SignatureChecker.OK, 1000)
    assert chk.check(f1, 0) == (SignatureChecker.REPLAY, 0)
    assert chk.check(f2, 0) == (SignatureChecker.OK, 1001)
    tampered = bytearray(f2)
    tampered[12] ^= 1
    assert chk.check(tampered, 0)[0] == SignatureChecker.BAD_SIGNATURE
    plain = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    assert chk.check(plain.heartbeat_encode(2, 12, 0, 0, 3).pack(plain), 0)[0] == (
        SignatureChecker.UNSIGNED
    )


@pytest.mark.parametrize("kind", ["fifo", "device", "folder"])
def test_a_key_that_is_not_a_regular_file_is_refused_without_blocking(
    tmp_path: Path, kind: str
) -> None:
    """A FIFO would block the read forever; /dev/zero would fill memory."""
    if kind == "fifo":
        path = tmp_path / "key.fifo"
        os.mkfifo(path)
    elif kind == "device":
        path = Path("/dev/zero")
    else:
        path = tmp_path
    with pytest.raises(SigningError, match=r"expected a regular file.*64 hex"):
        load_signing_key(path)
