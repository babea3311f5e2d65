"""MAVLink 2 message signing: key files, and checking the signatures of incoming frames.

The protocol (https://mavlink.io/en/guide/message_signing.html): a signed frame
has bit 0x01 of ``incompat_flags`` set and 13 bytes appended after the CRC:
``link_id`` (1), ``timestamp`` (6, little-endian, 10 us units since
2015-01-01 00:00 UTC) and ``signature`` (6) = the first 6 bytes of
``SHA-256(secret_key + frame_without_signature)``. Replay protection is per
stream ``(link_id, sysid, compid)``: timestamps must increase; the first
timestamp of a new stream must not be more than one minute behind ours.

Outgoing frames are signed by pymavlink itself (``MAVLink.signing``). Incoming
frames are checked here, not by pymavlink, because pymavlink 2.4.50

* folds unsigned, badly signed and replayed frames into one ``BAD_DATA``
  ("Invalid signature"), so they cannot be counted apart, and
* stores a frame's timestamp for its stream *before* checking the signature, so
  one forged frame with a large timestamp would block the real sender's stream
  (``MAVLink.check_signature`` in the generated dialect).

:class:`SignatureChecker` verifies first and only then moves the stream forward.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import stat
import time
from dataclasses import dataclass, field
from pathlib import Path

from companion.errors import SigningError

__all__ = [
    "SIGNING_EPOCH_UNIX_S",
    "SignatureChecker",
    "SigningConfig",
    "load_signing_key",
    "passphrase_to_key",
    "signing_timestamp_now",
]

logger = logging.getLogger(__name__)

SIGNING_EPOCH_UNIX_S = 1420070400
"""2015-01-01 00:00:00 UTC, the zero of MAVLink signing timestamps."""
NEW_STREAM_MAX_LAG = 6_000_000
"""A new stream may start at most one minute (in 10 us units) behind our timestamp."""

_MAGIC_V2 = 0xFD
_IFLAG_SIGNED = 0x01
_SIGNATURE_LEN = 13
_HEX_KEY = re.compile(r"[0-9a-fA-F]{64}")


@dataclass(frozen=True)
class SigningConfig:
    """How a link signs and checks MAVLink 2 frames.

    Attributes
    ----------
    key
        The 32-byte shared secret (never shown in ``repr``).
    link_id
        Our link id in outgoing signatures (0..255).
    allow_unsigned
        Accept unsigned incoming frames (still counted). Badly signed and replayed
        frames are rejected either way.
    """

    key: bytes = field(repr=False)
    link_id: int = 0
    allow_unsigned: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.key, bytes) or len(self.key) != 32:
            raise ValueError("signing key must be exactly 32 bytes")
        if not 0 <= self.link_id <= 255:
            raise ValueError(f"signing link_id must be in 0..255, got {self.link_id}")

    @property
    def fingerprint(self) -> str:
        """First 8 hex digits of SHA-256(key): safe to log, tells two keys apart."""
        return hashlib.sha256(self.key).hexdigest()[:8]


def passphrase_to_key(passphrase: str) -> bytes:
    """SHA-256 of the ASCII passphrase, as MAVProxy's ``signing setup PASSPHRASE`` does.

    Raises
    ------
    ValueError
        For a non-ASCII passphrase (MAVProxy encodes passphrases as ASCII and could
        not reproduce the key).
    """
    try:
        raw = passphrase.encode("ascii")
    except UnicodeEncodeError:
        raise ValueError("passphrase must be ASCII (as MAVProxy requires)") from None
    return hashlib.sha256(raw).digest()


def load_signing_key(
    path: str | os.PathLike[str], *, link_id: int = 0, allow_unsigned: bool = False
) -> SigningConfig:
    """Read a signing key file.

    The file holds one line: either 64 hexadecimal characters (the 32-byte key
    itself), or any other text, taken as a passphrase and hashed with SHA-256 the
    way MAVProxy's ``signing setup PASSPHRASE`` does. Surrounding whitespace and
    a trailing newline are ignored. A file readable by group or others is
    accepted with a warning.

    Raises
    ------
    SigningError
        Naming the file and what was expected, if it is missing, unreadable,
        empty, has more than one line, or holds a non-ASCII passphrase.
    """
    p = Path(path)
    expected = "expected one line: 64 hex characters (a 32-byte key) or an ASCII passphrase"
    from companion.errors import ConfigError
    from companion.schema import read_text

    if not p.exists():
        raise SigningError(f"{p}: signing key file not found; {expected}")
    try:
        # Bounded: a regular file of at most 1 MiB (a FIFO would hang, /dev/zero fill memory).
        text = read_text(p)
        mode = p.stat().st_mode
    except (ConfigError, OSError) as exc:
        why = "; ".join(exc.problems) if isinstance(exc, ConfigError) else str(exc)
        raise SigningError(f"{p}: {why}; {expected}") from exc
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    if not lines:
        raise SigningError(f"{p}: signing key file is empty; {expected}")
    if len(lines) > 1:
        raise SigningError(f"{p}: signing key file has {len(lines)} lines; {expected}")
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        logger.warning("%s: signing key file is accessible by others (chmod 600 it)", p)
    line = lines[0]
    if _HEX_KEY.fullmatch(line):
        key = bytes.fromhex(line)
    else:
        try:
            key = passphrase_to_key(line)
        except ValueError as exc:
            raise SigningError(f"{p}: {exc}; {expected}") from None
    try:
        return SigningConfig(key, link_id=link_id, allow_unsigned=allow_unsigned)
    except ValueError as exc:
        raise SigningError(f"{p}: {exc}") from exc


def signing_timestamp_now(unix_time_s: float | None = None) -> int:
    """The signing timestamp (10 us units since 2015-01-01 UTC) of a wall-clock time."""
    t = time.time() if unix_time_s is None else unix_time_s
    return max(0, int((t - SIGNING_EPOCH_UNIX_S) * 100_000))


class SignatureChecker:
    """Classifies incoming frames: accepted, unsigned, bad signature, or replayed.

    Parameters
    ----------
    key
        The 32-byte shared secret.

    Attributes
    ----------
    stream_timestamps
        Last accepted timestamp per ``(link_id, sysid, compid)``.
    """

    OK = 0
    UNSIGNED = 1
    BAD_SIGNATURE = 2
    REPLAY = 3

    def __init__(self, key: bytes) -> None:
        if len(key) != 32:
            raise ValueError("signing key must be exactly 32 bytes")
        self._key = bytes(key)
        self.stream_timestamps: dict[tuple[int, int, int], int] = {}

    def check(self, frame: bytes | bytearray, local_timestamp: int) -> tuple[int, int]:
        """Check one whole frame (as on the wire).

        Parameters
        ----------
        frame
            The frame, signature included.
        local_timestamp
            Our current signing timestamp (the new-stream rule compares to it).

        Returns
        -------
        (verdict, timestamp)
            ``verdict`` is one of the class constants; ``timestamp`` is the frame's
            signing timestamp when it had a valid signature, else 0.
        """
        if len(frame) < 12 + _SIGNATURE_LEN or frame[0] != _MAGIC_V2:
            return self.UNSIGNED, 0
        if not frame[2] & _IFLAG_SIGNED:
            return self.UNSIGNED, 0
        if hashlib.sha256(self._key + bytes(frame[:-6])).digest()[:6] != frame[-6:]:
            return self.BAD_SIGNATURE, 0
        timestamp = int.from_bytes(frame[-12:-6], "little")
        stream = (frame[-13], frame[5], frame[6])
        last = self.stream_timestamps.get(stream)
        if last is None:
            if timestamp + NEW_STREAM_MAX_LAG < local_timestamp:
                return self.REPLAY, 0
        elif timestamp <= last:
            return self.REPLAY, 0
        self.stream_timestamps[stream] = timestamp
        return self.OK, timestamp
