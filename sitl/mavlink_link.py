"""The SITL's MAVLink 2 transport: UDP socket, peers, datagram parsing, signing.

:class:`MavlinkLink` is the part of a MAVLink face that moves bytes; what the
messages mean is :class:`sitl.mavlink_face.MavlinkFace`, which derives from it.

Networking (``--mavlink``)
--------------------------
``udpout:HOST:PORT``
    Send to HOST:PORT (PX4's offboard convention: the SITL sends to 14540) from an
    ephemeral local port, and also answer whoever talks to us.
``udpin:HOST:PORT``
    Bind HOST:PORT and answer whoever talks to us.

Every sender seen is added to the peer list (bounded, most recent kept), and all
outgoing messages go to every peer. A datagram is parsed on its own: whole frames
only, garbage skipped (see :func:`_parse_datagram`).

Through a modelled link (``--link``)
-------------------------------------
With a :class:`~sitl.link_model.LinkModel` that is not ideal (:meth:`MavlinkLink.set_link`),
the companion link sits between the autopilot and the socket. Each frame sent
is queued with its arrival times (``arrivals(UP, msgid, t)``, ``t`` the
simulation time it was sent at) and goes to the socket at the first
:meth:`~MavlinkLink.flush` at or after its arrival; each frame read is queued
with ``arrivals(DOWN, msgid, t)`` and handled at the first
:meth:`~MavlinkLink.poll` at or after its arrival. A setpoint read while the
lockstep clock waits for the answer to an IMU sample counts as sent when that
sample arrived (:meth:`~MavlinkLink.expect_answers`), as the in-process
simulation (``sitl.lab.simulate``) has it. With an ideal link nothing is
queued: every frame goes out and is handled at once, as before links were
modelled.
"""

from __future__ import annotations

import errno
import heapq
import itertools
import logging
import math
import os
import select
import socket
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal, TypeVar

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink

from sitl.answers import AnswerJudge
from sitl.link_model import DOWN, UP, LinkModel

__all__ = ["Endpoint", "MavlinkLink", "enable_signing", "frame_msgid", "parse_endpoint"]

logger = logging.getLogger(__name__)

_MAX_PEERS = 8
_MAX_DATAGRAM_BYTES = 4096
"""A datagram longer than this is garbage (a MAVLink 2 frame is at most 280
bytes; routers pack a few per datagram): dropped unread."""
_RECV_BYTES = 2 * _MAX_DATAGRAM_BYTES  # room to see that a datagram is too long
_DEFERRED_TYPES = frozenset(
    ("COMMAND_LONG", "COMMAND_INT", "SET_MODE", "PARAM_SET", "PARAM_REQUEST_READ",
     "PARAM_REQUEST_LIST")
)  # fmt: skip
"""What ``poll(defer_commands=True)`` keeps for the start of the next step."""
_DUE_TOLERANCE_S = 1e-12
"""A queued frame is due at a step ``t`` when its arrival is at most ``t`` plus
this (the in-process simulation's rule)."""


def frame_msgid(buf: bytes) -> int:
    """The message id of one packed MAVLink frame (-1 if ``buf`` is not one).

    MAVLink 2 (start byte 0xFD): bytes 7..9, little-endian; MAVLink 1 (0xFE): byte 5.
    """
    if len(buf) >= 10 and buf[0] == 0xFD:
        return int.from_bytes(buf[7:10], "little")
    if len(buf) >= 6 and buf[0] == 0xFE:
        return buf[5]
    return -1


def _parse_datagram(mav: Any, data: bytes) -> list[Any]:
    """The frames of one UDP datagram, parsed from a clean parser state.

    A datagram carries whole frames: a frame cut off at its end is dropped, not
    joined to the next datagram (which a parser fed datagram after datagram
    would do, losing the good frame that follows garbage). Garbage before the
    first start byte is skipped at C speed."""
    v2, v1 = data.find(b"\xfd"), data.find(b"\xfe")
    start = min(i for i in (v2, v1, len(data)) if i >= 0)
    mav.buf = bytearray()
    mav.buf_index = 0
    mav.expected_length = mavlink.HEADER_LEN_V1 + 2
    mav.have_prefix_error = False
    msgs = mav.parse_buffer(data[start:]) if start < len(data) else None
    mav.buf = bytearray()  # what is left is a frame cut short
    mav.buf_index = 0
    return list(msgs or [])


@dataclass(frozen=True)
class Endpoint:
    """A parsed ``--mavlink`` address."""

    kind: Literal["udpout", "udpin"]
    host: str
    port: int

    def __str__(self) -> str:
        return f"{self.kind}:{self.host}:{self.port}"


def parse_endpoint(url: str) -> Endpoint:
    """Parse ``udpout:HOST:PORT`` or ``udpin:HOST:PORT``.

    Raises
    ------
    ValueError
        On any other form, naming what was expected.
    """
    parts = url.strip().split(":")
    if len(parts) != 3 or parts[0] not in ("udpout", "udpin"):
        raise ValueError(f"expected udpout:HOST:PORT or udpin:HOST:PORT, got {url!r}")
    kind, host, port_s = parts
    try:
        port = int(port_s)
    except ValueError:
        raise ValueError(f"expected an integer port in {url!r}") from None
    if not 0 < port < 65536 or not host:
        raise ValueError(f"expected a host and a port in 1..65535, got {url!r}")
    return Endpoint(kind, host, port)  # type: ignore[arg-type]


class _Sink:
    """File-like object pymavlink writes packed messages to: one sendto per peer."""

    def __init__(self, link: MavlinkLink) -> None:
        self._link = link

    def write(self, buf: bytes) -> None:
        self._link._send_bytes(buf)


def enable_signing(mav: Any, key: bytes, *, link_id: int = 0) -> None:
    """Sign what ``mav`` sends and accept only validly signed frames (MAVLink 2).

    Once ``secret_key`` is set, pymavlink drops unsigned frames
    (``allow_unsigned_callback`` is left unset) and asks ``mav.check_signature``
    about each signed one. pymavlink's own ``check_signature`` stores a frame's
    timestamp for its stream *before* verifying the signature, so a single forged
    frame with a far-future timestamp would block the real sender's stream for
    good. It is replaced here by :class:`companion.link.signing.SignatureChecker`
    (the companion's checker): the signature is verified first, and only a valid
    frame moves its stream's timestamp, and ours, forward. Frames with a bad
    signature, replays and new streams more than a minute behind our clock are
    dropped.
    """
    from companion.link.signing import SignatureChecker, signing_timestamp_now

    if len(key) != 32:
        raise ValueError("a MAVLink signing key is 32 bytes")
    signing = mav.signing
    signing.secret_key = key
    signing.link_id = link_id
    signing.timestamp = signing_timestamp_now()
    signing.sign_outgoing = True
    checker = SignatureChecker(key)

    def check_signature(msgbuf: bytearray, src_system: int, src_component: int) -> bool:
        # src_system/src_component are the frame's header bytes, which the checker reads itself.
        verdict, timestamp = checker.check(msgbuf, signing.timestamp)
        if verdict != SignatureChecker.OK:
            return False
        if timestamp > signing.timestamp:  # spec: follow the newest valid timestamp
            signing.timestamp = timestamp
        return True

    # pymavlink's decode() calls self.check_signature: an instance attribute wins.
    mav.check_signature = check_signature


_L = TypeVar("_L", bound="MavlinkLink")


class MavlinkLink:
    """A MAVLink 2 endpoint over UDP: socket, peers, reading and sending frames.

    Parameters
    ----------
    endpoint
        Where to send / listen, see :func:`parse_endpoint`.
    sysid, compid
        Our MAVLink ids.

    Notes
    -----
    Nothing touches the network in the constructor: call :meth:`open` (or use the
    object as a context manager). What each frame read means is :meth:`_handle`'s,
    which a subclass implements.
    """

    def __init__(self, endpoint: Endpoint, *, sysid: int = 1, compid: int = 1) -> None:
        self.endpoint = endpoint
        self.sysid = sysid
        self.compid = compid
        self.mav = mavlink.MAVLink(_Sink(self), srcSystem=sysid, srcComponent=compid)
        self.mav.robust_parsing = True
        self.sock: socket.socket | None = None
        self.peers: list[tuple[str, int]] = []
        # Fault injection (sitl.runner --fault): a muted link neither sends nor reads.
        self.muted = False
        self.messages_sent = 0
        self.bad_packets = 0
        self.send_errors = 0
        self._deferred: list[Any] = []
        self._warned: set[str] = set()
        # A modelled link (set_link); None: every frame goes out and is handled at once.
        self.link_model: LinkModel | None = None
        self._t_s = 0.0  # simulation time of what is sent now
        self._order = itertools.count()
        # On their way: (arrival s, order, frame bytes, IMU time of a clock-stream frame).
        self._outbox: list[tuple[float, int, bytes, float | None]] = []
        # On their way in: (arrival s, order, parsed message).
        self._inbox: list[tuple[float, int, Any]] = []
        self._clock_t_s: float | None = None  # set while the clock stream's frame is packed
        self._last_clock_t_s = -math.inf
        self.samples_delivered: list[float] = []
        """Arrival times of the clock-stream frames the last :meth:`flush` gave the
        socket that carry a newer IMU sample than any before (the ones a client answers)."""
        self.samples_delivered_t: list[float] = []
        """Those samples' times, s."""
        self._answers: deque[float] = deque()
        self._setpoints_arrived = 0
        self.answers = AnswerJudge()
        """Which sample each setpoint answers (:mod:`sitl.answers`)."""

    # -------------------------------------------------------------- lifecycle

    def open(self: _L) -> _L:
        """Create and bind the UDP socket.

        Raises
        ------
        OSError
            If the address cannot be bound.
        """
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if self.endpoint.kind == "udpin":
            sock.bind((self.endpoint.host, self.endpoint.port))
        else:
            sock.bind(("0.0.0.0", 0))
            self.peers.append((socket.gethostbyname(self.endpoint.host), self.endpoint.port))
        sock.setblocking(False)
        self.sock = sock
        logger.info("MAVLink %s (local %s)", self.endpoint, sock.getsockname())
        return self

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None

    def __enter__(self: _L) -> _L:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------- link

    def set_link(self, model: LinkModel | None, *, restart: bool = False) -> None:
        """Send and read through ``model`` (None or an ideal link: at once).

        With ``restart`` (the runner's, at the pilot's start), the samples and
        setpoints still on their way are lost: they belong to the time before
        the flight, which they would otherwise reach into, at moments that
        depend on the wall clock. Everything else on its way arrives as drawn.
        """
        self.link_model = None if model is None or model.spec.ideal else model
        if restart:
            self._outbox = [e for e in self._outbox if e[3] is None]
            heapq.heapify(self._outbox)
            self._inbox = [e for e in self._inbox if not self._is_setpoint(e[2])]
            heapq.heapify(self._inbox)
            self._answers.clear()

    def expect_answers(self, arrivals_s: Sequence[float], oldest_t_s: float | None = None) -> None:
        """The lockstep clock waits for the answers to samples from ``oldest_t_s``
        (their time; None: the wait ends) on; through a modelled link, to the ones
        that arrived at ``arrivals_s`` (in order): the setpoints that arrive
        meanwhile count as sent then.

        A client that stamps its setpoints with the time of the sample they
        answer may still be answering older samples: those answers are handled
        but not counted (:mod:`sitl.answers`), so the wait ends on this sample's
        answer whatever the wall clock did."""
        self._answers = deque(arrivals_s)
        self.answers.await_from(oldest_t_s)

    @property
    def stale_setpoints(self) -> int:
        """Answers to samples older than the ones the lockstep clock waited for."""
        return self.answers.stale

    def lockstep_timed_out(self) -> None:
        """The client did not answer in time: count what it sends again, whatever
        its stamps (a client that stopped stamping samples' times is not stuck)."""
        self.answers.forget()

    def _setpoint_stamp(self, msg: Any) -> tuple[int, float] | None:
        """A setpoint's time field and its unit (s), if it has one (a face says)."""
        return None

    def _counts_as_answer(self, msg: Any) -> bool:
        """Whether a setpoint counts towards the lockstep clock's wait."""
        stamp = self._setpoint_stamp(msg)
        return stamp is None or self.answers.counts(*stamp)

    def given_to_client(self, t_s: float) -> None:
        """A clock-stream sample of time ``t_s`` reached the socket (the ideal link:
        when the face sent it; a modelled link: when :meth:`flush` delivered it)."""
        self.answers.sample_given(t_s)

    def flush(self, t_s: float) -> int:
        """Give the socket what the link delivers by simulation time ``t_s``; return
        how many of those frames are clock-stream samples newer than any before
        (their arrival times in :attr:`samples_delivered`)."""
        self.samples_delivered = delivered = []
        self.samples_delivered_t = []
        outbox = self._outbox
        due = t_s + _DUE_TOLERANCE_S
        while outbox and outbox[0][0] <= due:
            arrival, _, buf, clock_t = heapq.heappop(outbox)
            sent = self._transmit(buf)
            # A client drops a duplicate or a sample older than one it had, without
            # answering: only a newer one is waited for.
            if sent and clock_t is not None and clock_t > self._last_clock_t_s:
                self._last_clock_t_s = clock_t
                delivered.append(arrival)
                self.samples_delivered_t.append(clock_t)
                self.given_to_client(clock_t)
        return len(delivered)

    def _queue_out(self, buf: bytes, model: LinkModel) -> None:
        if self.sock is None:
            return
        for arrival in model.arrivals(UP, frame_msgid(buf), self._t_s):
            heapq.heappush(self._outbox, (arrival, next(self._order), buf, self._clock_t_s))

    def _queue_in(self, msg: Any, t_s: float, model: LinkModel) -> None:
        t_sent = t_s
        if self._is_setpoint(msg) and self._counts_as_answer(msg):
            self._setpoints_arrived += 1
            if self._answers:
                t_sent = self._answers.popleft()
        for arrival in model.arrivals(DOWN, msg.get_msgId(), t_sent):
            heapq.heappush(self._inbox, (arrival, next(self._order), msg))

    def _deliver_in(self, t_s: float, defer_commands: bool) -> None:
        inbox = self._inbox
        due = t_s + _DUE_TOLERANCE_S
        while inbox and inbox[0][0] <= due:
            msg = heapq.heappop(inbox)[2]
            if self.muted:
                continue  # a dropped link loses what is on its way too
            if defer_commands and msg.get_type() in _DEFERRED_TYPES:
                self._deferred.append(msg)
            else:
                self._handle(msg, t_s)

    def _is_setpoint(self, msg: Any) -> bool:
        """A setpoint the lockstep clock waits for (a face says which)."""
        return False

    # ------------------------------------------------------------------ I/O

    def _send_bytes(self, buf: bytes) -> None:
        model = self.link_model
        if model is not None:
            self._queue_out(buf, model)
            return
        self._transmit(buf)

    def _transmit(self, buf: bytes) -> bool:
        """Send one frame to every peer now; False if the link is closed or muted."""
        sock = self.sock
        if sock is None or self.muted:
            return False
        for peer in self.peers:
            try:
                sock.sendto(buf, peer)
            except OSError as exc:
                self.send_errors += 1
                if exc.errno not in (errno.ECONNREFUSED, errno.EAGAIN):
                    self._warn_once("send", "send to %s failed: %s", peer, exc)
        self.messages_sent += 1
        return True

    def _warn_once(self, key: str, fmt: str, *args: Any) -> None:
        if key not in self._warned:
            self._warned.add(key)
            logger.warning(fmt, *args)

    def wait_readable(self, timeout_s: float) -> bool:
        """Block until a datagram is waiting or ``timeout_s`` (wall) passes."""
        if self.sock is None:
            return False
        r, _, _ = select.select([self.sock], [], [], max(0.0, timeout_s))
        return bool(r)

    def poll(self, t_s: float, *, defer_commands: bool = False) -> int:
        """Read and handle every waiting datagram; return how many were read.

        Parameters
        ----------
        t_s
            Current simulation time, stamped on setpoints and commands (and,
            through a modelled link, when what is read was sent).
        defer_commands
            Keep commands (arm, mode, parameters) for the next poll without it
            (the lockstep clock's wait for a setpoint uses it): a command then
            takes effect at the start of a step, whichever moment of the wait it
            arrived in, so a lockstep flight does not depend on wall-clock timing.
        """
        sock = self.sock
        if sock is None:
            return 0
        self._t_s = t_s
        if not defer_commands and self._deferred:
            deferred, self._deferred = self._deferred, []
            for msg in deferred:
                self._handle(msg, t_s)
        model = self.link_model
        n = 0
        while True:
            try:
                data, addr = sock.recvfrom(_RECV_BYTES)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:  # e.g. ECONNREFUSED reported by an ICMP error
                self._warn_once("recv", "receive failed: %s", exc)
                break
            n += 1
            if self.muted:
                continue  # a dropped link loses what arrives too
            if len(data) > _MAX_DATAGRAM_BYTES:
                self.bad_packets += 1
                continue
            self._add_peer(addr)
            try:
                msgs = _parse_datagram(self.mav, data)
            except mavlink.MAVError as exc:
                self.bad_packets += 1
                self._warn_once("parse", "bad MAVLink data from %s: %s", addr, exc)
                continue
            for msg in msgs:
                if model is not None and msg.get_type() != "BAD_DATA":
                    self._queue_in(msg, t_s, model)
                    continue
                if self._is_setpoint(msg) and self._counts_as_answer(msg):
                    self._setpoints_arrived += 1
                if defer_commands and msg.get_type() in _DEFERRED_TYPES:
                    self._deferred.append(msg)
                else:
                    self._handle(msg, t_s)
        if self._inbox:
            self._deliver_in(t_s, defer_commands)
        return n

    def _add_peer(self, addr: tuple[str, int]) -> None:
        if addr in self.peers:
            return
        logger.info("new MAVLink peer %s:%d", *addr)
        self.peers.append(addr)
        if len(self.peers) > _MAX_PEERS:
            # Keep the configured udpout target (first), drop the oldest other peer.
            del self.peers[1 if self.endpoint.kind == "udpout" else 0]

    def _handle(self, msg: Any, t_s: float) -> None:
        """Act on one frame read (or kept by ``defer_commands``) at simulation time ``t_s``."""
        raise NotImplementedError
