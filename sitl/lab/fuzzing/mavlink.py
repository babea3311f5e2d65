"""Seeded MAVLink fuzzing: the companion and the SITL as two processes, garbage in between.

``scripts/fuzz.py`` is the entry point; this module is the harness. It is lab
equipment (it flies the bundled SITL): the product imports nothing of it, and
``scripts/`` holds only thin entry points.

Topology (127.0.0.1, real UDP, as ``companion fly`` but with a relay)::

    sitl run --mavlink udpout:R      relay (a thread here)        companion run --connect udpin:C
         S  --------------------->  R | A  ------------------------->  C
         S  <---------------------  R | A  <-------------------------  C
                                    fuzzer's own socket X  --> C and --> S

The companion sees the autopilot at A, the SITL sees the companion at R.
Each case goes one of three ways (drawn from the kind's generator):

``autopilot``  from A into C: on the autopilot's path, interleaved with its stream;
``companion``  from R into S: on the companion's path into the SITL;
``other``      from X: another UDP address (whoever X reaches starts answering X:
               the harness drains and counts it).

Clock: real time. In lockstep the SITL waits for each setpoint, so simulated
time runs at whatever pace the loop (relay included) allows, garbage sent at a
wall-clock rate lands at an arbitrary density per sample, and a flooded
companion merely slows the simulation instead of missing samples: the real-time
budget (a stale IMU, samples lost, latency) could not be seen at all. On the
real-time clock the SITL streams at 250 Hz whatever the companion does, as a
vehicle would.

The flight: ``paper-acro`` (its first ``duration`` s: a wiggle, a roll flip, a
reversal), engaged with ``--engage auto`` as ``companion fly`` does (the SITL
arms in MANUAL with ``--pilot-from-arm``, so the pilot's timeline starts at the
companion's arming). A clean flight of the same seed through the same relay
comes first; then the fuzz flights: injection starts when the companion logs
``engaged`` and spreads the flight's cases over the engaged time less 1.5 s, at
most ``--rate`` datagrams per second; more cases than a flight holds make more
flights. ``--split mixed`` (the default) flies all kinds in one flight (plus one
for the kinds carrying valid IMU samples); ``--split kind`` (the default of
``--cases full``, 100,000 cases) one flight per kind, which says which kind a
failure belongs to. ``--root`` flies another checkout (e.g. ``git archive`` of a
commit) with this harness.

Kinds (each a :class:`CaseKind` with its own generator,
``np.random.default_rng([seed, crc32(kind)])``: same seed, same cases; the IMU
kinds take their timestamps relative to the last real sample the relay saw,
so only that base follows the live stream):

companion
    ``random_bytes``, ``truncated``, ``bad_crc``, ``imu_nonfinite`` (HIGHRES_IMU
    from the autopilot's ids, NaN/inf/1e30 gyro, fresh timestamps),
    ``foreign_sysid``, ``mavlink1``, ``burst`` (5-30 datagrams back to back),
    ``huge`` (10-60 kB datagrams), ``spoofed_heartbeat`` (the autopilot's ids,
    OFFBOARD and armed, from X), ``imu_timestamps`` (valid samples, repeated or
    older timestamps), ``imu_ahead`` (one sample, its gyro valid or not, stamped
    30 ms to 1 s ahead: dropped, so judged as garbage); opt-in: ``imu_time_jump``
    (a valid sample seconds ahead).
sitl
    ``sitl_random``, ``sitl_truncated``, ``sitl_bad_crc``, ``sitl_huge``,
    ``sitl_foreign``.

Targets (exit 0 when all hold): no crash (a process that died, exited with a
code no documented failsafe explains, hung, or printed a ``Traceback``), no
vehicle crash, no non-finite or out-of-range command in the companion's
``flight.tlog``, and for flights whose garbage carries no valid IMU sample
(every kind but ``imu_timestamps`` and ``imu_time_jump``): no failsafe (but
``failsafe_invalid_imu`` where NaN samples arrive under the autopilot's ids:
see :class:`CaseKind`) and a per-axis MAE
within 1.2x of the clean flight's (over the same stretch of the programme if
a failsafe cut the flight short); an MAE above that in a flight whose relay
held the IMU stream more than ``RELAY_STALL_S`` measures the harness, and one
where the machine held more than ``LATE_COMMANDS_SUSPECT`` commands past their
IMU period (in it or in the clean flight) while the companion's own budget was
kept measures the machine: both are listed under ``mae_unmeasured`` instead.
Reported beside them: the real-time budget
(``budget``: valid samples against 250 Hz, the ``latency_us`` column's
percentiles, the longest gap between samples, ``late_commands``; ``kept`` when no stale-IMU
failsafe, >= 98 % of the samples and a p99 latency within one IMU period), the
MAE against the SITL's true rates, the companion's counters, the cases a
failsafe left unsent, and what the companion sent to the fuzzer's address
(``answered_the_fuzzer``: setpoints there are setpoints the vehicle lost).
"""

from __future__ import annotations

import abc
import argparse
import json
import logging
import math
import os
import select
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import common as mavlink2

from companion.failsafe import THRESHOLD_MAX
from companion.options import SEED, SIM_DURATION_MAX_S, Finite, argparse_type
from sitl.lab.fly import free_udp_port

__all__ = [
    "DEFAULT_KINDS",
    "KINDS",
    "Case",
    "CaseKind",
    "StreamState",
    "generate_cases",
    "kind_rng",
    "main",
    "run_fuzz",
]

_log = logging.getLogger("fuzz")

ROOT = Path(__file__).resolve().parents[3]
PROFILE = ROOT / "vehicle_profiles" / "f450.yaml"
SCENARIO = "paper-acro"
IMU_RATE_HZ = 250.0
IMU_PERIOD_US = 4000
AUTOPILOT_IDS = (1, 1)
COMPANION_IDS = (1, mavlink2.MAV_COMP_ID_ONBOARD_COMPUTER)
PX4_OFFBOARD = 6 << 16  # PX4 custom_mode: main mode 6 in bits 16..23
PX4_POSCTL = 3 << 16
ARMED_CUSTOM = mavlink2.MAV_MODE_FLAG_SAFETY_ARMED | mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
FULL_RUN_CASES = 100_000
MAX_CASES = 10 * FULL_RUN_CASES
"""``--cases``: ten full runs in one go; a longer campaign is several runs."""
MAX_RATE_HZ = 100_000.0
"""``--rate``: more datagrams a second than loopback UDP delivers to a Python reader."""
MAE_RATIO_MAX = 1.2
EXIT_FAILSAFE = 3  # companion.app.EXIT_FAILSAFE
MAX_UDP_PAYLOAD = 65_507
BUDGET_SAMPLE_RATIO = 0.98
SITL_LAG_SUSPECT_S = 0.02
"""A SITL that fell this far behind the wall clock was starved of CPU (seen with
other flights on the same 2-core machine); its MAE ratio is flagged as such."""
RELAY_STALL_S = 0.02
"""The harness's relay held the IMU stream this long (five samples at 250 Hz):
a flight's MAE above the target then measures the relay, not the companion,
and is reported under ``mae_unmeasured`` instead of failing the run. Seen:
holes of 48-111 ms in 4 of 8 flights on this 2-core machine, the companion's
arrival gaps equal to the relay's within 1.3 ms, the SITL on time."""

LATE_COMMANDS_SUSPECT = 10
"""More commands than this reaching the SITL after their IMU period (of about
750 in a 3 s flight) measure a loaded machine: on a quiet one, 0-1 (8 clean
flights); with the long checks running beside, 9-89 in 5 clean flights, whose
roll MAE then ranged 0.484-0.793 deg/s against 0.486 on the quiet machine."""

Path_ = Literal["autopilot", "companion", "other"]

# --------------------------------------------------------------------------- frames


@dataclass
class StreamState:
    """What the relay last saw of the autopilot's IMU stream (the IMU kinds' base)."""

    imu_time_usec: int = 0
    gyro_rad_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    imu_frames: int = 0


class _Packer:
    """Packs messages as frames from any ids, MAVLink 2 or 1, with any sequence number."""

    def __init__(self) -> None:
        self._mav: dict[tuple[int, int], Any] = {}

    def frame(self, msg: Any, ids: tuple[int, int], seq: int, *, v1: bool = False) -> bytes:
        mav = self._mav.get(ids)
        if mav is None:
            mav = self._mav[ids] = mavlink2.MAVLink(None, srcSystem=ids[0], srcComponent=ids[1])
        mav.seq = seq & 0xFF
        return bytes(msg.pack(mav, force_mavlink1=v1))


_PACKER = _Packer()


def _crc(buf: bytes, extra: int) -> int:
    acc = mavlink2.x25crc(buf)
    acc.accumulate(bytes((extra,)))
    return int(acc.crc)


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _i(rng: np.random.Generator, lo: int, hi: int) -> int:
    """An integer in [lo, hi]."""
    return int(rng.integers(lo, hi + 1))


_BAD_FLOATS = (math.nan, math.inf, -math.inf, 1e30, -1e30, 3.4e38)


def _bad_gyro(rng: np.random.Generator, st: StreamState) -> tuple[float, float, float]:
    """At least one axis non-finite or absurd, the others as the real gyro read."""
    g = list(st.gyro_rad_s)
    axes = [a for a in range(3) if rng.random() < 0.5] or [_i(rng, 0, 2)]
    for a in axes:
        g[a] = _BAD_FLOATS[_i(rng, 0, len(_BAD_FLOATS) - 1)]
    return g[0], g[1], g[2]


def _fresh_usec(rng: np.random.Generator, st: StreamState) -> int:
    """A timestamp after the last real sample and before the next (4 ms later)."""
    return st.imu_time_usec + _i(rng, 1, IMU_PERIOD_US - 1000)


def _highres_imu(t_usec: int, gyro: Sequence[float], rng: np.random.Generator) -> Any:
    acc = (_u(rng, -2, 2), _u(rng, -2, 2), -9.81 + _u(rng, -2, 2))
    return mavlink2.MAVLink_highres_imu_message(
        t_usec, *acc, *gyro, 0.2, 0.0, 0.4, 1013.0, 0.0, 400.0, 25.0, 0b111111, 0
    )


def _heartbeat(custom_mode: int, base_mode: int, mav_type: int = 2, autopilot: int = 12) -> Any:
    return mavlink2.MAVLink_heartbeat_message(
        mav_type, autopilot, base_mode, custom_mode, mavlink2.MAV_STATE_ACTIVE, 3
    )


def _rc_channels(rng: np.random.Generator) -> Any:
    # The engage switch (channel 5) low and the sticks anywhere: obeyed, it would
    # hand back (rc-switch) or fling the vehicle.
    chans = [_i(rng, 900, 2100) for _ in range(18)]
    chans[4] = 1000
    return mavlink2.MAVLink_rc_channels_message(_i(rng, 0, 2**32 - 1), 18, *chans, 255)


def _autopilot_message(rng: np.random.Generator, st: StreamState) -> Any:
    """Something the autopilot sends, with content that would do harm if believed."""
    pick = _i(rng, 0, 5)
    if pick <= 1:
        return _highres_imu(_fresh_usec(rng, st), _bad_gyro(rng, st), rng)
    if pick == 2:  # "left OFFBOARD, disarmed": a hand-back if believed
        return _heartbeat(PX4_POSCTL, mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
    if pick == 3:
        return _rc_channels(rng)
    if pick == 4:
        return mavlink2.MAVLink_command_ack_message(
            mavlink2.MAV_CMD_DO_SET_MODE, mavlink2.MAV_RESULT_DENIED, 0, 0, *COMPANION_IDS
        )
    return mavlink2.MAVLink_attitude_message(
        st.imu_time_usec // 1000, *(_u(rng, -4, 4) for _ in range(6))
    )


def _companion_message(rng: np.random.Generator) -> Any:
    """Something the companion sends the SITL, with content that would do harm."""
    pick = _i(rng, 0, 4)
    if pick <= 1:
        controls = [
            _BAD_FLOATS[_i(rng, 0, 5)] if rng.random() < 0.5 else _u(rng, -5, 5) for _ in range(8)
        ]
        return mavlink2.MAVLink_set_actuator_control_target_message(
            _i(rng, 0, 2**40), 0, *AUTOPILOT_IDS, controls
        )
    if pick == 2:  # force disarm
        return mavlink2.MAVLink_command_long_message(
            *AUTOPILOT_IDS, mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 21196, 0, 0, 0, 0, 0
        )
    if pick == 3:  # to MANUAL
        return mavlink2.MAVLink_command_long_message(
            *AUTOPILOT_IDS, mavlink2.MAV_CMD_DO_SET_MODE, 0, 1, 1, 0, 0, 0, 0, 0
        )
    return mavlink2.MAVLink_set_attitude_target_message(
        0, *AUTOPILOT_IDS, 128, [1.0, 0.0, 0.0, 0.0], math.nan, math.inf, 1e30, 5.0
    )


def _foreign_ids(rng: np.random.Generator) -> tuple[int, int]:
    return _i(rng, 2, 255), _i(rng, 0, 255)


def _foreign_to_companion(rng: np.random.Generator, st: StreamState) -> bytes:
    """A valid MAVLink 2 frame from another system (what the autopilot would send)."""
    pick = _i(rng, 0, 2)
    if pick == 0:  # another vehicle's autopilot, in OFFBOARD or not
        msg = _heartbeat(PX4_OFFBOARD if rng.random() < 0.5 else PX4_POSCTL, ARMED_CUSTOM)
    else:
        msg = _autopilot_message(rng, st)
    return _PACKER.frame(msg, _foreign_ids(rng), _i(rng, 0, 255))


def _foreign_to_sitl(rng: np.random.Generator) -> bytes:
    """A valid frame from another system, addressed to another vehicle (or a heartbeat)."""
    other = (_i(rng, 2, 255), _i(rng, 0, 255))
    pick = _i(rng, 0, 4)
    if pick == 0:
        msg = _heartbeat(0, 0, mavlink2.MAV_TYPE_GCS, mavlink2.MAV_AUTOPILOT_INVALID)
    elif pick == 1:
        msg = mavlink2.MAVLink_set_actuator_control_target_message(
            0, 0, *other, [math.nan, 1e30, -1e30, math.inf, 0, 0, 0, 0]
        )
    elif pick == 2:
        msg = mavlink2.MAVLink_command_long_message(
            *other, mavlink2.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 21196, 0, 0, 0, 0, 0
        )
    elif pick == 3:
        msg = mavlink2.MAVLink_command_long_message(
            *other, mavlink2.MAV_CMD_DO_SET_MODE, 0, 1, 1, 0, 0, 0, 0, 0
        )
    else:
        msg = mavlink2.MAVLink_set_attitude_target_message(
            0, *other, 128, [1.0, 0.0, 0.0, 0.0], math.nan, math.inf, 1e30, 5.0
        )
    return _PACKER.frame(msg, _foreign_ids(rng), _i(rng, 0, 255))


def _random_bytes(rng: np.random.Generator, lo: int, hi: int) -> bytes:
    n = _i(rng, lo, hi)
    data = bytearray(rng.bytes(n))
    r = rng.random()
    if r < 0.3:
        data[0] = 0xFD  # looks like the start of a MAVLink 2 frame
    elif r < 0.45:
        data[0] = 0xFE  # ... or a MAVLink 1 frame
    return bytes(data)


def _truncate(frame: bytes, rng: np.random.Generator) -> bytes:
    return frame[: _i(rng, 1, len(frame) - 1)]


def _corrupt(frame: bytes, rng: np.random.Generator) -> bytes:
    """The frame with its CRC wrong: the CRC bytes flipped, a payload byte flipped,
    or a CRC computed with the wrong CRC_EXTRA (another dialect's message)."""
    b = bytearray(frame)
    how = _i(rng, 0, 2)
    if how == 0 or len(b) <= 12:
        b[-2] ^= _i(rng, 1, 255)
    elif how == 1:
        j = _i(rng, 10, len(b) - 3)
        b[j] ^= _i(rng, 1, 255)
    else:
        crc = _crc(bytes(b[1:-2]), _i(rng, 0, 255))  # header and payload, no magic
        good = b[-2] | b[-1] << 8
        if crc == good:
            crc ^= 1
        b[-2], b[-1] = crc & 0xFF, crc >> 8
    return bytes(b)


# --------------------------------------------------------------------------- kinds


@dataclass(frozen=True)
class Case:
    """One fuzz case: the datagrams to send back to back, and from where."""

    kind: str
    path: Path_
    datagrams: tuple[bytes, ...]


class CaseKind(abc.ABC):
    """One kind of malformed input, with its seeded generator.

    Attributes
    ----------
    name
        The kind's name on the command line and in the report.
    target
        Which process it is aimed at (``companion`` or ``sitl``).
    paths
        Where its cases may come from (one is drawn per case).
    carries_valid_imu
        Its frames hold valid, in-range IMU samples: the failsafe and MAE
        targets do not apply to a flight that includes it.
    explained_failsafes
        Failsafes its cases may rightly cause: NaN samples under the
        autopilot's ids, frequent enough, are a failing gyro to the companion
        (docs/failsafes.md: invalid IMU in more than 20 % of the samples) and
        nothing can tell them apart. Such a failsafe is reported, not failed,
        and the MAE of a flight it cut short is not judged.
    """

    name: str
    target: Literal["companion", "sitl"]
    paths: tuple[Path_, ...]
    carries_valid_imu: bool = False
    explained_failsafes: frozenset[str] = frozenset()
    description: str = ""

    def prepare(self) -> None:
        """Build what the generator needs once (frame pools): called before a
        flight, so that the relay thread never pauses the IMU stream to do it."""
        return None

    def generate(self, rng: np.random.Generator, st: StreamState) -> Case:
        path = self.paths[_i(rng, 0, len(self.paths) - 1)]
        return Case(self.name, path, tuple(self.datagrams(rng, st)))

    @abc.abstractmethod
    def datagrams(self, rng: np.random.Generator, st: StreamState) -> list[bytes]:
        """The case's datagrams (``st``: the live stream, for timestamps)."""


_ACTED_ON_IDS = frozenset({0, 22, 30, 65, 77, 105, 245, 253})
"""HEARTBEAT, PARAM_VALUE, ATTITUDE, RC_CHANNELS, COMMAND_ACK, HIGHRES_IMU,
EXTENDED_SYS_STATE, STATUSTEXT: what the companion reads from the autopilot."""

_TO_COMPANION: tuple[Path_, ...] = ("autopilot", "other")
_TO_SITL: tuple[Path_, ...] = ("companion", "other")


class RandomBytes(CaseKind):
    name, target, paths = "random_bytes", "companion", _TO_COMPANION
    description = "1-300 random bytes, some starting with a MAVLink 2 or 1 magic byte"

    def datagrams(self, rng: np.random.Generator, st: StreamState) -> list[bytes]:
        return [_random_bytes(rng, 1, 300)]


class Truncated(CaseKind):
    name, target, paths = "truncated", "companion", _TO_COMPANION
    description = "a frame from the autopilot's ids cut short (the rest never comes)"

    def datagrams(self, rng: np.random.Generator, st: StreamState) -> list[bytes]:
        frame = _PACKER.frame(_autopilot_message(rng, st), AUTOPILOT_IDS, _i(rng, 0, 255))
        return [_truncate(frame, rng)]


class BadCrc(CaseKind):
    name, target, paths = "bad_crc", "companion", _TO_COMPANION
    description = "a whole frame from the autopilot's ids with a wrong CRC"

    def datagrams(self, rng: np.random.Generator, st: StreamState) -> list[bytes]:
        frame = _PACKER.frame(_autopilot_message(rng, st), AUTOPILOT_IDS, _i(rng, 0, 255))
        return [_corrupt(frame, rng)]


class ImuNonFinite(CaseKind):
    name, target, paths = "imu_nonfinite", "companion", _TO_COMPANION
    explained_failsafes = frozenset({"failsafe_invalid_imu"})
    description = (
        "a valid HIGHRES_IMU from the autopilot's ids, timestamped between two real "
        "samples, with NaN, inf or 1e30 gyro values"
    )

    def datagrams(self, rng: np.random.Generator, st: StreamState) -> list[bytes]:
        msg = _highres_imu(_fresh_usec(rng, st), _bad_gyro(rng, st), rng)
        return [_PACKER.frame(msg, AUTOPILOT_IDS, _i(rng, 0, 255))]


class ForeignSysid(CaseKind):
    name, target, paths = "foreign_sysid", "companion", _TO_COMPANION
    description = "valid frames (heartbeats, IMU, RC, ACKs) from systems 2-255"

    def datagrams(self, rng: np.random.Generator, st: StreamState) -> list[bytes]:
        return [_foreign_to_companion(rng, st)]


class Mavlink1(CaseKind):
    name, target, paths = "mavlink1", "companion", _TO_COMPANION
    explained_failsafes = frozenset({"failsafe_invalid_imu"})
    description = (
        "MAVLink 1 frames: NaN IMU samples from the autopilot's ids, other systems' "
        "messages, random message ids with a good CRC"
    )

    def datagrams(self, rng: np.random.Generator, st: StreamState) -> list[bytes]:
        pick = _i(rng, 0, 2)
        seq = _i(rng, 0, 255)
        if pick == 0:
            msg = _highres_imu(_fresh_usec(rng, st), _bad_gyro(rng, st), rng)
            return [_PACKER.frame(msg, AUTOPILOT_IDS, seq, v1=True)]
        if pick == 1:
            return [_PACKER.frame(_autopilot_message(rng, st), _foreign_ids(rng), seq, v1=True)]
        # Any message id the companion does not act on, any payload, CRC with that
        # id's CRC_EXTRA when it has one (a good frame of what the autopilot sends
        # would be believed, rightly).
        msg_id = _i(rng, 0, 255)
        while msg_id in _ACTED_ON_IDS:
            msg_id = _i(rng, 0, 255)
        payload = rng.bytes(_i(rng, 0, 255))
        head = bytes((0xFE, len(payload), seq, *AUTOPILOT_IDS, msg_id))
        spec = mavlink2.mavlink_map.get(msg_id)
        crc = _crc(head[1:] + payload, spec.crc_extra if spec is not None else 0)
        return [head + payload + struct.pack("<H", crc)]


class Burst(CaseKind):
    name, target, paths = "burst", "companion", _TO_COMPANION
    description = "5-30 datagrams back to back: junk, other systems' frames, bad CRCs"

    def datagrams(self, rng: np.random.Generator, st: StreamState) -> list[bytes]:
        out = []
        for _ in range(_i(rng, 5, 30)):
            pick = _i(rng, 0, 2)
            if pick == 0:
                out.append(_random_bytes(rng, 1, 120))
            elif pick == 1:
                out.append(_foreign_to_companion(rng, st))
            else:
                frame = _PACKER.frame(_autopilot_message(rng, st), AUTOPILOT_IDS, _i(rng, 0, 255))
                out.append(_corrupt(frame, rng))
        return out


def _huge(rng: np.random.Generator, pool: list[bytes]) -> bytes:
    """10-60 kB: random bytes, frame-start junk, or other systems' frames end to end."""
    n = _i(rng, 10_000, 60_000)
    pick = _i(rng, 0, 2)
    if pick == 0:
        return rng.bytes(n)
    if pick == 1:  # every 16 bytes a MAVLink 2 start with a random header: parser work
        block = bytearray(rng.bytes(n))
        block[::16] = b"\xfd" * len(block[::16])
        return bytes(block)
    idx = rng.integers(0, len(pool), size=n // 40 + 1)
    return b"".join(pool[int(j)] for j in idx)[:n]


def _frame_pool(make: Callable[[np.random.Generator], bytes], seed: int) -> list[bytes]:
    rng = np.random.default_rng([seed, 0x9001])
    return [make(rng) for _ in range(256)]


class _HugeKind(CaseKind):
    """10-60 kB datagrams drawn from a pool of frames built once (:meth:`prepare`)."""

    pool_seed: int

    def __init__(self) -> None:
        self._pool: list[bytes] = []

    @abc.abstractmethod
    def frame(self, rng: np.random.Generator) -> bytes:
        """One frame of the pool."""

    def prepare(self) -> None:
        if not self._pool:
            self._pool = _frame_pool(self.frame, self.pool_seed)

    def datagrams(self, rng: np.random.Generator, st: StreamState) -> list[bytes]:
        self.prepare()
        return [_huge(rng, self._pool)]


class Huge(_HugeKind):
    name, target, paths = "huge", "companion", _TO_COMPANION
    description = "10-60 kB datagrams: random, frame-start junk, or other systems' frames"
    pool_seed = 1

    def frame(self, rng: np.random.Generator) -> bytes:
        return _foreign_to_companion(rng, StreamState())


class SpoofedHeartbeat(CaseKind):
    name, target, paths = "spoofed_heartbeat", "companion", ("other",)
    description = "HEARTBEAT with the autopilot's ids, OFFBOARD and armed, from another address"

    def datagrams(self, rng: np.random.Generator, st: StreamState) -> list[bytes]:
        return [
            _PACKER.frame(_heartbeat(PX4_OFFBOARD, ARMED_CUSTOM), AUTOPILOT_IDS, _i(rng, 0, 255))
        ]


class ImuTimestamps(CaseKind):
    name, target, paths = "imu_timestamps", "companion", _TO_COMPANION
    carries_valid_imu = True
    description = (
        "valid HIGHRES_IMU from the autopilot's ids, in-range gyro, with the last real "
        "sample's timestamp (repeated) or an older one (out of order)"
    )

    def datagrams(self, rng: np.random.Generator, st: StreamState) -> list[bytes]:
        if rng.random() < 0.5:
            t = st.imu_time_usec
        else:
            t = max(0, st.imu_time_usec - _i(rng, 1, 50) * IMU_PERIOD_US - _i(rng, 0, 3999))
        gyro = [g + float(rng.normal(0.0, 0.5)) for g in st.gyro_rad_s]
        return [_PACKER.frame(_highres_imu(t, gyro, rng), AUTOPILOT_IDS, _i(rng, 0, 255))]


class ImuTimeJump(CaseKind):
    name, target, paths = "imu_time_jump", "companion", _TO_COMPANION
    carries_valid_imu = True
    description = "a valid HIGHRES_IMU from the autopilot's ids, 1 s to 1 day ahead"

    def datagrams(self, rng: np.random.Generator, st: StreamState) -> list[bytes]:
        t = st.imu_time_usec + int(10 ** _u(rng, 6.0, 11.0))
        return [_PACKER.frame(_highres_imu(t, st.gyro_rad_s, rng), AUTOPILOT_IDS, 0)]


class ImuAhead(CaseKind):
    name, target, paths = "imu_ahead", "companion", _TO_COMPANION
    description = (
        "a HIGHRES_IMU from the autopilot's ids stamped 30 ms to 1 s ahead of the last "
        "real sample (a serial link, a radio modem, a glitching autopilot), its gyro as "
        "the real one read or NaN, inf or 1e30: the companion drops it (its time is "
        "unknown), so the targets apply"
    )

    def datagrams(self, rng: np.random.Generator, st: StreamState) -> list[bytes]:
        t = st.imu_time_usec + int(10 ** _u(rng, 4.5, 6.0))
        gyro = _bad_gyro(rng, st) if rng.random() < 0.5 else st.gyro_rad_s
        return [_PACKER.frame(_highres_imu(t, gyro, rng), AUTOPILOT_IDS, _i(rng, 0, 255))]


class SitlRandom(CaseKind):
    name, target, paths = "sitl_random", "sitl", _TO_SITL
    description = "1-300 random bytes into the SITL's port"

    def datagrams(self, rng: np.random.Generator, st: StreamState) -> list[bytes]:
        return [_random_bytes(rng, 1, 300)]


class SitlTruncated(CaseKind):
    name, target, paths = "sitl_truncated", "sitl", _TO_SITL
    description = "a frame from the companion's ids (setpoint, disarm, mode) cut short"

    def datagrams(self, rng: np.random.Generator, st: StreamState) -> list[bytes]:
        frame = _PACKER.frame(_companion_message(rng), COMPANION_IDS, _i(rng, 0, 255))
        return [_truncate(frame, rng)]


class SitlBadCrc(CaseKind):
    name, target, paths = "sitl_bad_crc", "sitl", _TO_SITL
    description = "a frame from the companion's ids (NaN setpoint, disarm, mode) with a wrong CRC"

    def datagrams(self, rng: np.random.Generator, st: StreamState) -> list[bytes]:
        frame = _PACKER.frame(_companion_message(rng), COMPANION_IDS, _i(rng, 0, 255))
        return [_corrupt(frame, rng)]


class SitlHuge(_HugeKind):
    name, target, paths = "sitl_huge", "sitl", _TO_SITL
    description = "10-60 kB datagrams into the SITL's port"
    pool_seed = 2

    def frame(self, rng: np.random.Generator) -> bytes:
        return _foreign_to_sitl(rng)


class SitlForeign(CaseKind):
    name, target, paths = "sitl_foreign", "sitl", _TO_SITL
    description = "valid frames from other systems, addressed to other vehicles"

    def datagrams(self, rng: np.random.Generator, st: StreamState) -> list[bytes]:
        return [_foreign_to_sitl(rng)]


KINDS: dict[str, CaseKind] = {
    k.name: k
    for k in (
        RandomBytes(),
        Truncated(),
        BadCrc(),
        ImuNonFinite(),
        ForeignSysid(),
        Mavlink1(),
        Burst(),
        Huge(),
        SpoofedHeartbeat(),
        ImuTimestamps(),
        ImuTimeJump(),
        ImuAhead(),
        SitlRandom(),
        SitlTruncated(),
        SitlBadCrc(),
        SitlHuge(),
        SitlForeign(),
    )
}
OPT_IN_KINDS = frozenset({"imu_time_jump"})
DEFAULT_KINDS = tuple(k for k in KINDS if k not in OPT_IN_KINDS)


def kind_rng(seed: int, kind: str) -> np.random.Generator:
    """The generator of ``kind``'s cases for ``--seed seed``."""
    return np.random.default_rng([seed, zlib.crc32(kind.encode())])


def generate_cases(seed: int, kind: str, n: int, st: StreamState | None = None) -> list[Case]:
    """The first ``n`` cases of ``kind`` for ``seed`` against a fixed stream state."""
    rng = kind_rng(seed, kind)
    st = st or StreamState(imu_time_usec=10_000_000, gyro_rad_s=(0.1, -0.2, 0.05))
    return [KINDS[kind].generate(rng, st) for _ in range(n)]


# --------------------------------------------------------------------------- relay


@dataclass
class InjectionStats:
    cases: dict[str, int] = field(default_factory=dict)
    datagrams: dict[str, int] = field(default_factory=dict)
    bytes: dict[str, int] = field(default_factory=dict)
    by_path: dict[str, dict[str, int]] = field(default_factory=dict)
    send_errors: int = 0
    started_s: float | None = None
    ended_s: float | None = None

    def count(self, case: Case, sent: int, nbytes: int) -> None:
        self.cases[case.kind] = self.cases.get(case.kind, 0) + 1
        self.datagrams[case.kind] = self.datagrams.get(case.kind, 0) + sent
        self.bytes[case.kind] = self.bytes.get(case.kind, 0) + nbytes
        p = self.by_path.setdefault(case.kind, {})
        p[case.path] = p.get(case.path, 0) + 1


class Relay(threading.Thread):
    """Forwards SITL <-> companion datagrams and injects the fuzz cases.

    One thread and ``select``: the forwarding and the injection share it, so a
    case is never sent in the middle of a forwarded datagram, and the IMU
    kinds see the last real sample before the next one is forwarded.
    """

    def __init__(self, companion_port: int) -> None:
        super().__init__(name="fuzz-relay", daemon=True)
        self.sitl_side = self._bind()  # R: the SITL sends here
        self.companion_side = self._bind()  # A: the autopilot, as the companion sees it
        self.other = self._bind()  # X: the fuzzer's own address
        self.port = self.sitl_side.getsockname()[1]
        self.companion_addr = ("127.0.0.1", companion_port)
        self.sitl_addr: tuple[str, int] | None = None
        self.state = StreamState()
        self.stats = InjectionStats()
        self.forwarded = {"sitl_to_companion": 0, "companion_to_sitl": 0}
        self.forward_gap_max_s = 0.0
        """The longest wait between two IMU samples forwarded from the SITL to the
        companion while cases go out: a hole the companion then sees in its
        samples' arrival was the relay's (or the SITL's) if it is here too."""
        self._last_forward_s: float | None = None
        self.to_other = {"from_companion": 0, "companion_setpoints": 0, "from_sitl": 0}
        self._halt = threading.Event()
        self._lock = threading.Lock()
        self._plan: list[str] = []
        self._rngs: dict[str, np.random.Generator] = {}
        self._rate_hz = 1.0
        self._next_i = 0
        self._due_s = 0.0

    @staticmethod
    def _bind() -> socket.socket:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        s.bind(("127.0.0.1", 0))
        s.setblocking(False)
        return s

    def inject(self, plan: list[str], rngs: dict[str, np.random.Generator], rate_hz: float) -> None:
        """Start sending ``plan`` (kind names in order) at ``rate_hz`` datagrams/s."""
        with self._lock:
            self._plan, self._rngs, self._rate_hz = plan, rngs, rate_hz
            self._next_i = 0
            self._due_s = time.monotonic()
            self.stats.started_s = self._due_s

    def halt_injection(self) -> None:
        """Send no more cases (the companion has exited: nobody would read them)."""
        with self._lock:
            if self._next_i < len(self._plan) and self.stats.ended_s is None:
                self.stats.ended_s = time.monotonic()
            self._plan = self._plan[: self._next_i]

    def stop(self) -> None:
        self._halt.set()
        self.join(timeout=5.0)
        for s in (self.sitl_side, self.companion_side, self.other):
            s.close()

    def run(self) -> None:
        socks = [self.sitl_side, self.companion_side, self.other]
        while not self._halt.is_set():
            wait = 0.05
            if self._next_i < len(self._plan):
                wait = max(0.0, min(wait, self._due_s - time.monotonic()))
            try:
                ready, _, _ = select.select(socks, [], [], wait)
            except (OSError, ValueError):
                return
            for s in ready:
                self._drain(s)
            self._inject_due()

    def _drain(self, s: socket.socket) -> None:
        for _ in range(64):
            try:
                data, addr = s.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # ICMP port unreachable from a peer that went away
                continue
            if s is self.sitl_side:
                if self.sitl_addr is None:
                    self.sitl_addr = addr
                if addr != self.sitl_addr:
                    continue
                self._watch_imu(data)
                self._send(self.companion_side, data, self.companion_addr)
                self.forwarded["sitl_to_companion"] += 1
                if data[7:9] == b"\x69\x00" and self.stats.started_s is not None:
                    # IMU samples forwarded while the cases go out (the stream is up).
                    now = time.monotonic()
                    last = self._last_forward_s
                    if last is not None and now - last > self.forward_gap_max_s:
                        self.forward_gap_max_s = now - last
                    self._last_forward_s = now
            elif s is self.companion_side:
                if self.sitl_addr is not None and addr == self.companion_addr:
                    self._send(self.sitl_side, data, self.sitl_addr)
                    self.forwarded["companion_to_sitl"] += 1
            elif addr == self.companion_addr:
                # The companion answering the fuzzer: it took it for the autopilot.
                self.to_other["from_companion"] += 1
                if len(data) > 9 and data[0] == 0xFD and data[7] in (139, 82):
                    self.to_other["companion_setpoints"] += 1
            else:
                self.to_other["from_sitl"] += 1

    def _watch_imu(self, data: bytes) -> None:
        # The SITL sends one frame per datagram; HIGHRES_IMU (105), MAVLink 2.
        if len(data) >= 12 + 32 and data[0] == 0xFD and data[7] == 105 and data[8] == 0:
            t_usec, gx, gy, gz = struct.unpack_from("<Q12xfff", data, 10)
            st = self.state
            st.imu_time_usec = t_usec
            st.gyro_rad_s = (gx, gy, gz)
            st.imu_frames += 1

    def _send(self, s: socket.socket, data: bytes, addr: tuple[str, int]) -> bool:
        try:
            s.sendto(data, addr)
            return True
        except OSError:
            self.stats.send_errors += 1
            return False

    def _inject_due(self) -> None:
        with self._lock:
            plan = self._plan
            sent_now = 0
            while self._next_i < len(plan) and time.monotonic() >= self._due_s and sent_now < 64:
                kind = KINDS[plan[self._next_i]]
                case = kind.generate(self._rngs[kind.name], self.state)
                self._next_i += 1
                n, nbytes = self._send_case(case)
                self.stats.count(case, n, nbytes)
                sent_now += len(case.datagrams)
                self._due_s += len(case.datagrams) / self._rate_hz
            if self._next_i >= len(plan) and plan and self.stats.ended_s is None:
                self.stats.ended_s = time.monotonic()

    def _send_case(self, case: Case) -> tuple[int, int]:
        addr: tuple[str, int] | None
        if case.path == "autopilot":
            sock, addr = self.companion_side, self.companion_addr
        elif case.path == "companion":
            sock, addr = self.sitl_side, self.sitl_addr
        else:
            sock = self.other
            addr = self.companion_addr if KINDS[case.kind].target == "companion" else self.sitl_addr
        if addr is None:
            return 0, 0
        n = nbytes = 0
        for d in case.datagrams:
            if self._send(sock, d[:MAX_UDP_PAYLOAD], addr):
                n += 1
                nbytes += len(d)
        return n, nbytes


# --------------------------------------------------------------------------- flights


@dataclass
class FlightSpec:
    name: str
    kinds: tuple[str, ...]
    plan: list[str]
    gated: bool
    """The failsafe and MAE targets apply (no kind carries valid IMU samples)."""
    rate_hz: float
    """Datagrams per second: ``--rate``, or less to spread the plan over the window."""


@dataclass
class Options:
    seed: int
    cases: int
    rate_hz: float
    kinds: tuple[str, ...]
    split: Literal["mixed", "kind"]
    duration_s: float
    output: str
    stale_imu_s: float
    out_dir: Path
    root: Path = ROOT
    """The checkout whose ``companion`` and ``sitl`` are flown."""


def hung_after_s(opts: Options) -> float:
    """Wall time after which a companion still running is taken as hung."""
    return 40.0 + 3.0 * opts.duration_s


def _read_jsonl(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    out = []
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return out


def _fly(
    spec: FlightSpec | None,
    opts: Options,
    rngs: dict[str, np.random.Generator],
    out: Path,
) -> dict[str, Any]:
    """One flight through the relay, injecting ``spec``'s plan once engaged."""
    out.mkdir(parents=True, exist_ok=True)
    port = free_udp_port()
    relay = Relay(port)
    py = sys.executable
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "MAVLINK20": "1", "PYTHONPATH": str(opts.root)}
    sitl_cmd = [
        py, "-m", "sitl", "run", "--profile", str(PROFILE),
        "--mavlink", f"udpout:127.0.0.1:{relay.port}",
        "--scenario", SCENARIO, "--seed", str(opts.seed), "--clock", "realtime",
        "--pilot-from-arm", "--no-auto-arm", "--mode", "manual",
        "--log", str(out / "sitl.npz"),
    ]  # fmt: skip
    comp_cmd = [
        py, "-m", "companion", "run", "--connect", f"udpin:127.0.0.1:{port}",
        "--profile", str(PROFILE), "--engage", "auto", "--output", opts.output,
        "--rate-hz", str(int(IMU_RATE_HZ)), "--duration", str(opts.duration_s),
        "--log-dir", str(out / "companion"), "--stale-imu-s", str(opts.stale_imu_s),
    ]  # fmt: skip
    t0 = time.monotonic()
    wall0 = time.time()  # events older than this are an earlier run's in the same --out
    relay.start()
    hung: set[str] = set()
    engaged_wall: float | None = None
    with (out / "companion.stderr").open("wb") as c_err, (out / "sitl.stderr").open("wb") as s_err:
        comp = subprocess.Popen(
            comp_cmd, cwd=opts.root, stdout=subprocess.DEVNULL, stderr=c_err, env=env
        )
        sitl = subprocess.Popen(
            sitl_cmd, cwd=opts.root, stdout=subprocess.DEVNULL, stderr=s_err, env=env
        )
        events_path = out / "companion" / "events.jsonl"
        try:
            while comp.poll() is None:
                if time.monotonic() - t0 > hung_after_s(opts):
                    hung.add("companion")
                    comp.kill()
                    break
                if engaged_wall is None and any(
                    e.get("kind") == "engaged" and e.get("wall", 0.0) >= wall0
                    for e in _read_jsonl(events_path)
                ):
                    engaged_wall = time.monotonic()
                    if spec is not None and spec.plan:
                        relay.inject(spec.plan, rngs, spec.rate_hz)
                time.sleep(0.05)
            comp_rc = comp.wait()
        finally:
            relay.halt_injection()
            try:
                sitl.wait(timeout=3.0)
            except subprocess.TimeoutExpired:
                sitl.send_signal(signal.SIGINT)
                try:
                    sitl.wait(timeout=15.0)
                except subprocess.TimeoutExpired:
                    hung.add("sitl")
                    sitl.kill()
                    sitl.wait()
            if comp.poll() is None:
                comp.kill()
                comp.wait()
            relay.stop()
    return _judge(
        spec, opts, out, relay, comp_rc, int(sitl.returncode), hung, time.monotonic() - t0
    )


# --------------------------------------------------------------------------- checks


def _stderr_crash(text: str) -> str | None:
    """The last lines of the first traceback in ``text``, or None."""
    i = text.find("Traceback")
    if i < 0:
        return None
    lines = text[i:].splitlines()
    tail = next((j for j, ln in enumerate(lines[1:], 1) if ln and not ln.startswith(" ")), 0)
    return "\n".join(lines[max(0, tail - 2) : tail + 1])[-600:]


def check_commands(tlog: Path) -> dict[str, Any]:
    """The companion's setpoints in ``tlog`` (read with mavutil), and the bad ones.

    SET_ACTUATOR_CONTROL_TARGET: controls[0..2] in [-1, 1], controls[3] in
    [0, 1], all finite; SET_ATTITUDE_TARGET: body rates finite, thrust in [0, 1].
    Only frames from the companion's ids count (the fuzzer never uses them).
    """
    from pymavlink import mavutil

    out: dict[str, Any] = {"setpoints": 0, "bad": 0, "examples": []}
    if not tlog.exists():
        return out
    conn = mavutil.mavlink_connection(str(tlog), dialect="common", robust_parsing=True)
    types = ["SET_ACTUATOR_CONTROL_TARGET", "SET_ATTITUDE_TARGET"]
    try:
        while True:
            m = conn.recv_match(type=types)
            if m is None:
                break
            if (m.get_srcSystem(), m.get_srcComponent()) != COMPANION_IDS:
                continue
            out["setpoints"] += 1
            if m.get_type() == "SET_ACTUATOR_CONTROL_TARGET":
                c = list(m.controls)
                ok = (
                    all(math.isfinite(x) for x in c)
                    and all(-1.0 <= x <= 1.0 for x in c[:3])
                    and 0.0 <= c[3] <= 1.0
                )
                what: dict[str, Any] = {"controls": [_finite_or_text(x) for x in c]}
            else:
                rates = (m.body_roll_rate, m.body_pitch_rate, m.body_yaw_rate)
                ok = all(math.isfinite(x) for x in rates) and 0.0 <= m.thrust <= 1.0
                what = {
                    "rates": [_finite_or_text(x) for x in rates],
                    "thrust": _finite_or_text(m.thrust),
                }
            if not ok:
                out["bad"] += 1
                if len(out["examples"]) < 3:
                    out["examples"].append({"type": m.get_type(), **what})
    finally:
        conn.close()
    return out


def _finite_or_text(x: float) -> float | str:
    """A value for strict JSON: NaN and infinities as text."""
    return x if math.isfinite(x) else repr(x)


def _percentile(x: np.ndarray, q: float) -> float | None:
    return round(float(np.percentile(x, q)), 1) if len(x) else None


def late_commands(sitl_log: Path) -> int | None:
    """IMU samples after which no new actuator command reached the SITL within
    one IMU period: answers the machine or the link held up.

    On a quiet machine the companion's answer to every sample is applied at the
    SITL's next IMU tick (0-1 exceptions in 3 s). Read from the SITL's log: the
    first change of ``motor_cmd`` after each sample (so of a run of late
    answers, the first is counted for sure). None when the log cannot tell (the
    rates output, where the SITL's own rate loop moves the motors every step).
    """
    try:
        with np.load(sitl_log, allow_pickle=False) as z:
            t, cmd, imu_t = z["t_s"], z["motor_cmd"], z["imu_t_s"]
    except (OSError, ValueError, KeyError):
        return None
    changed = np.r_[False, np.any(np.diff(cmd, axis=0) != 0, axis=1)]
    t_cmd = t[changed]
    if len(t_cmd) < 2 or len(t_cmd) > 1.5 * len(imu_t):
        return None
    inside = (imu_t > t_cmd[0] + 0.1) & (imu_t < t_cmd[-1] - 0.1)
    nxt = t_cmd[np.minimum(np.searchsorted(t_cmd, imu_t[inside] + 1e-9), len(t_cmd) - 1)]
    return int((nxt - imu_t[inside] > IMU_PERIOD_US * 1e-6 + 1e-6).sum())


def _flight_metrics(out: Path, flight: Any) -> dict[str, Any]:
    """MAE (sitl.lab.report's definition, on the samples the law really measured)
    and the loop's real-time budget, from control.mcap and the SITL's log."""
    from companion.records import read_control_log
    from sitl.lab.fly import merge_logs
    from sitl.lab.report import compute_metrics
    from sitl.lab.simulate import FlightRecord

    res: dict[str, Any] = {}
    try:
        cols, _ = read_control_log(flight.control_log)
    except (OSError, ValueError) as exc:
        return {"error": f"control.mcap: {exc}"}
    eng = cols["engaged"] > 0.5
    meas = np.stack([cols[f"meas_{a}_rad_s"] for a in ("roll", "pitch", "yaw")], axis=1)
    finite = np.isfinite(meas).all(axis=1)
    t = cols["t_s"][eng]
    span_s = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    expected = span_s * IMU_RATE_HZ + 1 if len(t) else 0
    good = int((eng & finite).sum())
    lat = cols["latency_us"][eng & finite]
    wall = cols["wall_s"][eng & finite]
    res["budget"] = {
        "engaged_samples": int(eng.sum()),
        "engaged_valid_samples": good,
        "held_samples": int((eng & (cols["held"] > 0.5)).sum()),
        "expected_samples_250hz": round(expected),
        "sample_ratio": round(good / expected, 4) if expected else None,
        "latency_us_p50": _percentile(lat, 50),
        "latency_us_p99": _percentile(lat, 99),
        "latency_us_max": _percentile(lat, 100),
        "max_imu_gap_ms": round(float(np.diff(wall).max()) * 1e3, 1) if len(wall) > 1 else None,
    }
    try:
        rec = merge_logs(flight)
    except (OSError, ValueError, KeyError) as exc:
        res["mae_error"] = f"merge: {exc}"
        return res
    keep = ~rec.columns["held"] & np.isfinite(rec.columns["meas_rad_s"]).all(axis=1)
    rows = FlightRecord({k: v[keep] for k, v in rec.columns.items()}, rec.meta)
    m = compute_metrics(rows)
    res["mae_deg_s"] = m["mae_deg_s"]
    res["mae_true_deg_s"] = m["mae_true_deg_s"]
    res["airborne_time_s"] = m["airborne_time_s"]
    res["crashed_vehicle"] = m["crashed"]
    res["_record"] = rows  # for the clean flight's MAE over the same window; not reported
    return res


def _mae_within(record: Any, span_s: float) -> dict[str, Any]:
    """sitl.lab.report's MAE over the first ``span_s`` of engaged flight."""
    from sitl.lab.report import compute_metrics
    from sitl.lab.simulate import FlightRecord

    t = record.columns["t_s"]
    keep = t - t[0] <= span_s + 1e-9 if len(t) else np.zeros(0, dtype=bool)
    rows = FlightRecord({k: v[keep] for k, v in record.columns.items()}, record.meta)
    m = compute_metrics(rows)
    return {"mae_deg_s": m["mae_deg_s"], "mae_true_deg_s": m["mae_true_deg_s"]}


def _span_s(record: Any) -> float:
    """Engaged flight time of a record, s."""
    t = record.columns["t_s"]
    return float(t[-1] - t[0]) if len(t) > 1 else 0.0


def _judge(
    spec: FlightSpec | None,
    opts: Options,
    out: Path,
    relay: Relay,
    comp_rc: int,
    sitl_rc: int,
    hung: set[str],
    wall_s: float,
) -> dict[str, Any]:
    from sitl.lab.fly import FlightProcesses

    comp_events = _read_jsonl(out / "companion" / "events.jsonl")
    sitl_events = _read_jsonl(out / "sitl.events.jsonl")
    summary: dict[str, Any] = next(
        (e for e in reversed(sitl_events) if e.get("kind") == "summary"), {}
    )
    flight = FlightProcesses(out, comp_rc, sitl_rc, wall_s, comp_events, sitl_events, summary)
    failsafes = [
        {"t_s": e.get("t_s"), "kind": e.get("kind"), "detail": e.get("detail")}
        for e in comp_events
        if str(e.get("kind", "")).startswith("failsafe") or e.get("kind") == "link_lost"
    ]
    crashes: list[dict[str, Any]] = []
    for proc, rc, explained in (
        ("companion", comp_rc, comp_rc == 0 or (comp_rc == EXIT_FAILSAFE and bool(failsafes))),
        ("sitl", sitl_rc, sitl_rc == 0),
    ):
        tb = _stderr_crash(flight.text(f"{proc}.stderr"))
        why = [
            w
            for w, bad in (
                (f"hung: killed after {hung_after_s(opts):.0f} s", proc in hung),
                (f"exit {rc} (no failsafe explains it)", not explained),
                ("Traceback on stderr", tb is not None),
            )
            if bad
        ]
        if why:
            crashes.append(
                {"process": proc, "exit_code": rc, "reason": "; ".join(why), "traceback": tb}
            )
    counters = next((e["detail"] for e in reversed(comp_events) if e.get("kind") == "counters"), "")
    res: dict[str, Any] = {
        "name": spec.name if spec else "clean",
        "kinds": list(spec.kinds) if spec else [],
        "gated": spec.gated if spec else True,
        "cases_sent": dict(relay.stats.cases),
        "datagrams_sent": dict(relay.stats.datagrams),
        "bytes_sent": dict(relay.stats.bytes),
        "cases_by_path": relay.stats.by_path,
        "cases_planned": len(spec.plan) if spec else 0,
        "rate_hz": round(spec.rate_hz, 1) if spec else 0.0,
        # Planned but not sent: the companion had exited (a failsafe ended the flight).
        "cases_undelivered": (len(spec.plan) if spec else 0) - sum(relay.stats.cases.values()),
        "injection_s": (
            round(relay.stats.ended_s - relay.stats.started_s, 2)
            if relay.stats.ended_s and relay.stats.started_s
            else None
        ),
        "companion_exit_code": comp_rc,
        "sitl_exit_code": sitl_rc,
        "crashes": crashes,
        "vehicle_crashed": summary.get("status") == "crashed",
        "failsafes": failsafes,
        "engaged": any(e.get("kind") == "engaged" for e in comp_events),
        "commands": check_commands(out / "companion" / "flight.tlog"),
        "companion_counters": counters,
        "answered_the_fuzzer": dict(relay.to_other),
        "relay_forwarded": dict(relay.forwarded),
        "relay_forward_gap_max_ms": round(relay.forward_gap_max_s * 1e3, 1),
        "sitl": {
            k: summary.get(k)
            for k in ("status", "realtime_factor", "max_lag_s", "setpoints_received", "final_mode")
        },
        "wall_time_s": round(wall_s, 1),
    }
    res.update(_flight_metrics(out, flight))
    b = res.get("budget")
    if b is not None:
        b["late_commands"] = late_commands(out / "sitl.npz") if opts.output == "actuator" else None
        # Kept: no stale-IMU failsafe, no more than 2 % of the 250 Hz samples lost,
        # and 99 % of the commands out within one IMU period of their sample.
        b["kept"] = bool(
            not any(f["kind"] == "failsafe_stale_imu" for f in failsafes)
            and (b["sample_ratio"] or 0.0) >= BUDGET_SAMPLE_RATIO
            and (b["latency_us_p99"] or math.inf) <= IMU_PERIOD_US
        )
    return res


# --------------------------------------------------------------------------- run


def plan_flights(opts: Options) -> list[FlightSpec]:
    """Split the cases into flights: per kind, or mixed (kinds carrying valid IMU
    samples in a flight of their own, so the others keep their targets).

    A flight holds at most what ``rate_hz`` sends in its injection window
    (the engaged duration less 1.5 s); more cases make more flights. Fewer go
    out at a lower rate, spread over the window: a kind whose effect needs
    time (a spoofed heartbeat against the real one's 1 Hz) gets the whole flight.
    """
    kinds = list(opts.kinds)
    per_kind = {
        k: opts.cases // len(kinds) + (1 if i < opts.cases % len(kinds) else 0)
        for i, k in enumerate(kinds)
    }
    groups: list[tuple[str, list[str]]]
    if opts.split == "kind":
        groups = [(k, [k]) for k in kinds]
    else:
        plain = [k for k in kinds if not KINDS[k].carries_valid_imu]
        imu = [k for k in kinds if KINDS[k].carries_valid_imu]
        groups = [(n, g) for n, g in (("mixed", plain), ("mixed_valid_imu", imu)) if g]
    # Datagrams per case, roughly (a burst is ~18): what fits in one flight.
    window_s = max(1.0, opts.duration_s - 1.5)
    sched = np.random.default_rng([opts.seed, zlib.crc32(b"schedule")])
    flights = []
    for name, group in groups:
        plan = [k for k in group for _ in range(per_kind[k])]
        plan = [plan[i] for i in sched.permutation(len(plan))]
        dgrams = sum(18 if k == "burst" else 1 for k in plan)
        n_flights = max(1, math.ceil(dgrams / (opts.rate_hz * window_s)))
        gated = not any(KINDS[k].carries_valid_imu for k in group)
        for j in range(n_flights if plan else 0):
            part = plan[j::n_flights]
            label = name if n_flights == 1 else f"{name}_{j + 1}"
            rate = min(opts.rate_hz, dgrams / n_flights / window_s)
            flights.append(FlightSpec(label, tuple(group), part, gated, rate))
    return flights


def _ratio(a: dict[str, Any] | None, b: dict[str, Any] | None) -> dict[str, float | None]:
    out: dict[str, float | None] = {}
    for axis in ("roll", "pitch", "yaw"):
        x = (a or {}).get(axis)
        y = (b or {}).get(axis)
        out[axis] = round(x / y, 3) if x is not None and y else None
    return out


def _machine_late(r: dict[str, Any], clean: dict[str, Any]) -> str | None:
    """ "N (clean flight: M)" when the machine, not the companion, held commands
    late in this flight or the clean one: more than :data:`LATE_COMMANDS_SUSPECT`
    commands reached the SITL after their IMU period while the companion's own
    latency stayed within budget. None otherwise."""
    b, cb = r.get("budget", {}), clean.get("budget", {})
    late, clean_late = b.get("late_commands"), cb.get("late_commands")
    if late is None or clean_late is None or not b.get("kept"):
        return None
    if max(late, clean_late) <= LATE_COMMANDS_SUSPECT:
        return None
    return f"{late} (clean flight: {clean_late})"


def run_fuzz(opts: Options) -> dict[str, Any]:
    """The clean flight, then the fuzz flights; the report (see the module docstring)."""
    t0 = time.monotonic()
    flights = plan_flights(opts)
    rngs = {k: kind_rng(opts.seed, k) for k in opts.kinds}
    for k in opts.kinds:
        KINDS[k].prepare()
    _log.info("clean flight (seed %d, %.0f s)", opts.seed, opts.duration_s)
    clean = _fly(None, opts, rngs, opts.out_dir / "clean")
    clean_rec = clean.pop("_record", None)
    results = []
    for spec in flights:
        _log.info("flight %s: %d cases of %s", spec.name, len(spec.plan), ",".join(spec.kinds))
        r = _fly(spec, opts, rngs, opts.out_dir / spec.name)
        rec = r.pop("_record", None)
        base = clean
        if clean_rec is not None and rec is not None and _span_s(rec) < _span_s(clean_rec) - 0.1:
            # A flight cut short (a failsafe) is compared with the same stretch of
            # the clean one: the pilot's programme is not equally hard throughout.
            base = r["clean_same_window"] = _mae_within(clean_rec, _span_s(rec))
        r["mae_ratio"] = _ratio(r.get("mae_deg_s"), base.get("mae_deg_s"))
        r["mae_true_ratio"] = _ratio(r.get("mae_true_deg_s"), base.get("mae_true_deg_s"))
        base_p99 = clean.get("budget", {}).get("latency_us_p99")
        if (b := r.get("budget")) is not None:  # None: the flight left no control log
            p99 = b.get("latency_us_p99")
            b["latency_p99_ratio"] = round(p99 / base_p99, 2) if p99 and base_p99 else None
        results.append(r)

    failures: list[str] = []
    clean_ok = (
        not clean["crashes"]
        and not clean["failsafes"]
        and not clean["vehicle_crashed"]
        and None not in clean.get("mae_deg_s", {None: None}).values()
    )
    if not clean_ok:
        failures.append(f"clean flight: crashes {clean['crashes']}, failsafes {clean['failsafes']}")
    failing_flights: dict[str, list[str]] = {}
    unmeasured: list[str] = []
    for r in results:
        why = []
        if r["crashes"]:
            why.append(
                f"{len(r['crashes'])} crash(es): "
                + "; ".join(f"{c['process']} {c['reason']}" for c in r["crashes"])
            )
        if r["vehicle_crashed"]:
            why.append("the vehicle crashed (SITL)")
        if r["commands"]["bad"]:
            why.append(f"{r['commands']['bad']} non-finite or out-of-range commands")
        explained = frozenset().union(*(KINDS[k].explained_failsafes for k in r["kinds"]))
        r["explained_failsafes"] = [f["kind"] for f in r["failsafes"] if f["kind"] in explained]
        if r["gated"]:
            unexplained = [f["kind"] for f in r["failsafes"] if f["kind"] not in explained]
            if unexplained:
                why.append("failsafe: " + ", ".join(unexplained))
            worst = [v for v in r["mae_ratio"].values() if v is not None]
            if r["explained_failsafes"] and not unexplained:
                pass  # cut short by a failsafe its garbage rightly causes: nothing to compare
            elif len(worst) < 3:
                why.append("no MAE (the flight ended before the vehicle was airborne)")
            elif max(worst) > MAE_RATIO_MAX and r["relay_forward_gap_max_ms"] > RELAY_STALL_S * 1e3:
                unmeasured.append(
                    f"{r['name']}: MAE ratio {max(worst):.2f}, but the relay held the IMU "
                    f"stream {r['relay_forward_gap_max_ms']:.0f} ms"
                )
            elif max(worst) > MAE_RATIO_MAX and (late := _machine_late(r, clean)):
                unmeasured.append(
                    f"{r['name']}: MAE ratio {max(worst):.2f}, but the SITL applied {late} "
                    "commands after their IMU period (the companion's own latency kept)"
                )
            elif max(worst) > MAE_RATIO_MAX:
                lag_s = r["sitl"].get("max_lag_s") or 0.0
                why.append(
                    f"MAE ratio {max(worst):.2f} > {MAE_RATIO_MAX}"
                    + (
                        f" (the SITL fell {lag_s * 1e3:.0f} ms behind real time: a loaded "
                        "machine can do that alone)"
                        if lag_s > SITL_LAG_SUSPECT_S
                        else ""
                    )
                )
        if why:
            failures.append(f"{r['name']}: " + "; ".join(why))
            failing_flights[r["name"]] = r["kinds"]
        r["targets_met"] = not why

    def total(key: str) -> dict[str, int]:
        acc: dict[str, int] = {}
        for r in results:
            for k, v in r[key].items():
                acc[k] = acc.get(k, 0) + v
        return acc

    cases = total("cases_sent")
    report = {
        "seed": opts.seed,
        "clock": "realtime",
        "scenario": SCENARIO,
        "profile": PROFILE.name,
        "output": opts.output,
        "duration_s": opts.duration_s,
        "rate_hz": opts.rate_hz,
        "split": opts.split,
        "kinds": list(opts.kinds),
        "cases_requested": opts.cases,
        "cases_total": sum(cases.values()),
        "cases_sent": cases,
        "datagrams_sent": total("datagrams_sent"),
        "crashes": sum(len(r["crashes"]) for r in results) + len(clean["crashes"]),
        "vehicle_crashes": sum(r["vehicle_crashed"] for r in [clean, *results]),
        "nonfinite_commands": sum(r["commands"]["bad"] for r in results),
        "cases_undelivered": sum(r["cases_undelivered"] for r in results),
        "budget_kept": {r["name"]: r.get("budget", {}).get("kept") for r in results},
        "setpoints_to_the_fuzzer": {
            r["name"]: r["answered_the_fuzzer"]["companion_setpoints"] for r in results
        },
        "failsafes": {r["name"]: [f["kind"] for f in r["failsafes"]] for r in results},
        "explained_failsafes": {
            r["name"]: r["explained_failsafes"] for r in results if r["explained_failsafes"]
        },
        "mae_ratio": {r["name"]: r["mae_ratio"] for r in results},
        "clean": clean,
        "flights": results,
        # A kind fails when a flight of that kind alone fails (--split kind); a
        # mixed flight's failure names its kinds as suspects only.
        "failing_kinds": sorted({k[0] for k in failing_flights.values() if len(k) == 1}),
        "failing_flights": failing_flights,
        "failures": failures,
        "mae_unmeasured": unmeasured,
        "targets": {
            "crashes": 0,
            "vehicle_crashes": 0,
            "nonfinite_commands": 0,
            "failsafes_without_valid_imu": 0,
            "mae_ratio_max": MAE_RATIO_MAX,
        },
        "targets_met": not failures,
        "out_dir": str(opts.out_dir),
        "wall_time_s": round(time.monotonic() - t0, 1),
    }
    return report


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="fuzz.py",
        description="Fly the companion against the SITL (real time, separate processes, real "
        "UDP) while injecting malformed MAVLink; exit 0 when the targets are met.",
    )
    p.add_argument("--json", action="store_true", help="Print the report as JSON.")
    p.add_argument(
        "--seed", type=argparse_type(SEED), default=1, help="Seed of the flight and of every case."
    )
    p.add_argument(
        "--cases",
        default="2000",
        help=f"Cases in all, split evenly over the kinds; 'full' = {FULL_RUN_CASES} "
        "(with --split kind unless given).",
    )
    p.add_argument(
        "--rate",
        type=argparse_type(Finite(min=0.0, min_open=True, max=MAX_RATE_HZ)),
        default=2000.0,
        help="Datagrams per second, at most (fewer cases than a flight holds are spread over it).",
    )
    p.add_argument(
        "--kinds",
        default=None,
        help=f"Comma-separated, from {','.join(KINDS)} [default: all of --target's but "
        f"the opt-in {','.join(sorted(OPT_IN_KINDS))}].",
    )
    p.add_argument("--target", choices=["companion", "sitl", "both"], default="both")
    p.add_argument(
        "--split",
        choices=["mixed", "kind"],
        default=None,
        help="One flight per kind, or kinds mixed (default; 'kind' with --cases full).",
    )
    p.add_argument(
        "--duration",
        type=argparse_type(Finite(min=2.0, min_open=True, max=SIM_DURATION_MAX_S)),
        default=12.0,
        help="Engaged flight time per flight, s.",
    )
    p.add_argument("--output", choices=["actuator", "rates"], default="actuator")
    p.add_argument(
        "--stale-imu-s",
        type=argparse_type(Finite(min=0.0, min_open=True, max=THRESHOLD_MAX["--stale-imu-s"][0])),
        default=0.5,
        help="The companion's stale-IMU watchdog (companion fly's setting).",
    )
    p.add_argument("--out", type=Path, default=None, help="Keep the flights' records here.")
    p.add_argument(
        "--root",
        type=Path,
        default=ROOT,
        help="Fly this checkout's companion and sitl (e.g. a `git archive` of HEAD).",
    )
    p.add_argument("-v", "--verbose", action="store_true")
    return p


def _options(p: argparse.ArgumentParser, a: argparse.Namespace) -> Options:
    """Checked options; a bad one exits 2 with the parser's message."""
    full = a.cases == "full"
    try:
        cases = FULL_RUN_CASES if full else int(a.cases)
    except ValueError:
        p.error(f"--cases: an integer or 'full', got {a.cases!r}")
    if not 0 <= cases <= MAX_CASES:
        p.error(f"--cases: expected 0..{MAX_CASES} or 'full', got {cases}")
    if a.kinds:
        kinds = tuple(k.strip() for k in a.kinds.split(",") if k.strip())
        unknown = [k for k in kinds if k not in KINDS]
        if unknown:
            p.error(f"--kinds: unknown {unknown}; known: {list(KINDS)}")
    else:
        kinds = tuple(k for k in DEFAULT_KINDS if a.target in ("both", KINDS[k].target))
    if not (a.root / "companion").is_dir() or not (a.root / "sitl").is_dir():
        p.error(f"--root {a.root}: no companion/ and sitl/ there")
    out = a.out or Path(tempfile.mkdtemp(prefix="fuzz-"))
    return Options(
        seed=a.seed,
        cases=cases,
        rate_hz=a.rate,
        kinds=kinds,
        split=a.split or ("kind" if full else "mixed"),
        duration_s=a.duration,
        output=a.output,
        stale_imu_s=a.stale_imu_s,
        out_dir=out,
        root=a.root.resolve(),
    )


def _text(report: dict[str, Any]) -> str:
    lines = [
        f"seed {report['seed']}: {report['cases_total']} cases, "
        f"{report['crashes']} crashes, {report['nonfinite_commands']} bad commands"
    ]
    for r in [report["clean"], *report["flights"]]:
        lines.append(
            f"  {r['name']:<18} cases {sum(r['cases_sent'].values()):>6}  "
            f"failsafes {[f['kind'] for f in r['failsafes']]}  MAE {r.get('mae_deg_s')}  "
            f"ratio {r.get('mae_ratio', '-')}"
        )
    lines += [f"  FAIL {f}" for f in report["failures"]]
    lines += [f"  UNMEASURED {u}" for u in report["mae_unmeasured"]]
    lines.append("targets met" if report["targets_met"] else "targets NOT met")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = _parser()
    a = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if a.verbose else logging.WARNING,
        format="%(asctime)s %(name)s %(message)s",
        stream=sys.stderr,
    )
    opts = _options(parser, a)
    opts.out_dir.mkdir(parents=True, exist_ok=True)
    report = run_fuzz(opts)
    print(json.dumps(report, indent=1) if a.json else _text(report))
    return 0 if report["targets_met"] else 1
