"""MAVLink transport and protocol: byte transports, the link to the autopilot, signing.

See :mod:`companion.link.transport` (the transports, in
:mod:`~companion.link.udp_transport`, :mod:`~companion.link.serial_transport`
and :mod:`~companion.link.memory_transport`), :mod:`companion.link.mavlink` (the link;
its parts in :mod:`~companion.link.receive`, :mod:`~companion.link.accept`,
:mod:`~companion.link.requests`, :mod:`~companion.link.send` and
:mod:`~companion.link.frames`) and
:mod:`companion.link.signing`; ``docs/signing.md`` explains key set-up.
"""

from companion.link.mavlink import MavlinkLink, mavlink2
from companion.link.signing import (
    SignatureChecker,
    SigningConfig,
    load_signing_key,
    passphrase_to_key,
    signing_timestamp_now,
)
from companion.link.transport import (
    MemoryTransport,
    SerialTransport,
    Transport,
    UdpInTransport,
    UdpOutTransport,
    open_transport,
)

__all__ = [
    "MavlinkLink",
    "MemoryTransport",
    "SerialTransport",
    "SignatureChecker",
    "SigningConfig",
    "Transport",
    "UdpInTransport",
    "UdpOutTransport",
    "load_signing_key",
    "mavlink2",
    "open_transport",
    "passphrase_to_key",
    "signing_timestamp_now",
]
