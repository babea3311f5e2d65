"""Byte transports under the MAVLink link, and the link URL that names one.

A transport moves opaque chunks of bytes; the
:class:`~companion.link.mavlink.MavlinkLink` above it parses what arrives and
packs what leaves. Every transport has the same shape::

    t = open_transport("udpin:0.0.0.0:14540")   # nothing is opened yet
    await t.open(on_bytes)                       # on_bytes(chunk) runs in the loop thread
    t.write(data)                                # never blocks; may drop (counted)
    await t.close()                              # idempotent

That shape, the counters and what a chunk holds are :class:`Transport`'s
(:mod:`companion.link.transport_base`). The transports:
:class:`UdpInTransport` and :class:`UdpOutTransport`
(:mod:`companion.link.udp_transport`), :class:`SerialTransport`
(:mod:`companion.link.serial_transport`) and :class:`MemoryTransport`
(:mod:`companion.link.memory_transport`). :func:`open_transport`, here, builds
the one a link URL names.
"""

from __future__ import annotations

from companion.link.memory_transport import MemoryTransport
from companion.link.serial_transport import SerialTransport
from companion.link.transport_base import Transport
from companion.link.udp_transport import UdpInTransport, UdpOutTransport

__all__ = [
    "MemoryTransport",
    "SerialTransport",
    "Transport",
    "UdpInTransport",
    "UdpOutTransport",
    "open_transport",
]

_URL_FORMS = "udpin:HOST:PORT, udpout:HOST:PORT or serial:DEVICE:BAUD"


def _bad_url(url: str, why: str) -> ValueError:
    return ValueError(f"bad link URL {url!r}: {why}; expected {_URL_FORMS}")


def _parse_port(url: str, text: str, *, allow_zero: bool) -> int:
    try:
        port = int(text)
    except ValueError:
        raise _bad_url(url, f"port {text!r} is not an integer") from None
    if not (0 if allow_zero else 1) <= port <= 65535:
        raise _bad_url(url, f"port {port} outside {0 if allow_zero else 1}..65535")
    return port


def open_transport(url: str) -> Transport:
    """Build (but do not open) the transport a link URL names.

    Parameters
    ----------
    url
        ``udpin:HOST:PORT`` (bind; port 0 = ephemeral), ``udpout:HOST:PORT``, or
        ``serial:DEVICE:BAUD`` (DEVICE may contain ``/`` and ``:``; the baud rate
        is after the last ``:``). An IPv6 HOST goes in brackets: ``udpin:[::]:14540``.

    Raises
    ------
    ValueError
        Naming the URL and the expected forms.
    """
    if not isinstance(url, str):
        raise TypeError(f"link URL must be a str, got {type(url).__name__}")
    kind, sep, rest = url.strip().partition(":")
    if not sep:
        raise _bad_url(url, "no scheme")
    if kind in ("udpin", "udpout"):
        host, sep, port_s = rest.rpartition(":")
        if not sep or not host:
            raise _bad_url(url, "missing HOST or PORT")
        if host.startswith("[") and host.endswith("]"):
            host = host[1:-1]
        elif ":" in host:
            raise _bad_url(url, f"host {host!r} has ':' (put an IPv6 address in brackets)")
        if not host:
            raise _bad_url(url, "empty host")
        port = _parse_port(url, port_s, allow_zero=kind == "udpin")
        return UdpInTransport(host, port) if kind == "udpin" else UdpOutTransport(host, port)
    if kind == "serial":
        device, sep, baud_s = rest.rpartition(":")
        if not sep or not device:
            raise _bad_url(url, "missing DEVICE or BAUD")
        try:
            baud = int(baud_s)
        except ValueError:
            raise _bad_url(url, f"baud rate {baud_s!r} is not an integer") from None
        if baud <= 0:
            raise _bad_url(url, f"baud rate {baud} must be > 0")
        return SerialTransport(device, baud)
    raise _bad_url(url, f"unknown scheme {kind!r}")
