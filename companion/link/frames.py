"""MAVLink 2 on the wire: the checksum, reading a frame's header, struct layouts.

Pure functions and constants, shared by the link's sending and receiving.
"""

from __future__ import annotations

import os
import re
import struct
from collections.abc import Callable, Sequence
from typing import Any

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink2
from pymavlink.generator import mavcrc

__all__ = [
    "ACTUATOR",
    "ATTITUDE_TARGET",
    "EXTRA_ACTUATOR",
    "EXTRA_ATTITUDE_TARGET",
    "HEADER",
    "ID_ACTUATOR",
    "ID_ATTITUDE_TARGET",
    "MAGIC_V1",
    "MAGIC_V2",
    "U16",
    "crc16",
    "crc_ok",
    "fast_layout",
    "next_start",
    "read_header",
]


def _crc16_py(data: bytes, crc: int = 0xFFFF) -> int:
    acc = mavcrc.x25crc_slow()
    acc.crc = crc
    acc.accumulate(bytes(data))
    return int(acc.crc)


# CRC-16/MCRF4XX (MAVLink's X.25 checksum) as a function: fastcrc's, which
# pymavlink requires and uses itself, or pymavlink's pure-Python one.
crc16: Callable[..., int] = mavcrc.mcrf4xx if mavcrc.mcrf4xx is not None else _crc16_py

MAGIC_V2 = 0xFD
MAGIC_V1 = 0xFE
_IFLAG_SIGNED = 0x01
_SIGNATURE_LEN = 13
_NUMERIC_FORMATS = frozenset("bBhHiIqQfd")

# A MAVLink 2 header: magic, length, incompat and compat flags, seq, sysid, compid,
# msg id (low 16 bits, high 8 bits).
HEADER = struct.Struct("<BBBBBBBHB")
U16 = struct.Struct("<H")

# The two messages sent once per control sample, packed without pymavlink's
# generic path (wire order: fields sorted by type size, as the generator does).
ACTUATOR = struct.Struct("<Q8fBBB")  # time_usec, controls[8], group_mlx, target sys, comp
ID_ACTUATOR = mavlink2.MAVLINK_MSG_ID_SET_ACTUATOR_CONTROL_TARGET
_CRC_ACTUATOR = mavlink2.MAVLink_set_actuator_control_target_message.crc_extra
# time_boot_ms, q[4], body rates, thrust, target sys, comp, type_mask (thrust_body, an
# extension, is all zeros and so dropped with the trailing zeros)
ATTITUDE_TARGET = struct.Struct("<I4fffffBBB")
ID_ATTITUDE_TARGET = mavlink2.MAVLINK_MSG_ID_SET_ATTITUDE_TARGET
_CRC_ATTITUDE_TARGET = mavlink2.MAVLink_set_attitude_target_message.crc_extra
EXTRA_ACTUATOR = bytes((_CRC_ACTUATOR,))
EXTRA_ATTITUDE_TARGET = bytes((_CRC_ATTITUDE_TARGET,))


def next_start(data: bytes, i: int) -> int:
    """Index of the first MAVLink start byte (0xFD or 0xFE) at or after ``i``, or -1.

    ``bytes.find`` skips garbage at C speed, where pymavlink walks it byte by byte.
    """
    v2 = data.find(b"\xfd", i)
    v1 = data.find(b"\xfe", i, v2 if v2 >= 0 else len(data))
    return v1 if v1 >= 0 else v2


def read_header(data: bytes, j: int) -> tuple[Any, int, int] | None:
    """``(message class or None, crc_at, end)`` of the frame whose start byte is
    ``data[j]``, from its header; ``None`` if the header is cut off; ``crc_at``
    -1 for MAVLink 2 incompatibility flags other than "signed" (not a frame we
    can read)."""
    v2 = data[j] == MAGIC_V2
    header_len = 10 if v2 else 6
    if j + header_len > len(data):
        return None
    if v2:
        flags = data[j + 2]
        if flags & ~_IFLAG_SIGNED:
            return None, -1, 0
        msg_id = data[j + 7] | data[j + 8] << 8 | data[j + 9] << 16
        signature_len = _SIGNATURE_LEN if flags else 0
    else:
        msg_id = data[j + 5]
        signature_len = 0
    crc_at = j + header_len + data[j + 1]
    return mavlink2.mavlink_map.get(msg_id), crc_at, crc_at + 2 + signature_len


def crc_ok(data: bytes, j: int, crc_at: int, msgtype: Any) -> bool:
    """Whether the CRC at ``data[crc_at]`` is right for the frame starting at ``data[j]``."""
    crc = crc16(bytes((msgtype.crc_extra,)), crc16(data[j + 1 : crc_at]))
    return bool(crc == data[crc_at] | data[crc_at + 1] << 8)


def fast_layout(msg_id: int, fields: Sequence[str]) -> tuple[struct.Struct, int]:
    """The ``struct`` reading ``fields`` (in wire order) from a payload of ``msg_id``,
    and the message's full payload length.

    Raises
    ------
    ValueError
        For an unknown id, an unknown or non-scalar field, or fields out of wire order.
    """
    msgtype = mavlink2.mavlink_map.get(msg_id)
    if msgtype is None:
        raise ValueError(f"message id {msg_id} is not in the common dialect")
    if not fields:
        raise ValueError("at least one field is needed")
    wire = list(msgtype.ordered_fieldnames)
    # The unpacker's format is in wire order: one code (with a count for arrays) per field.
    codes = re.findall(r"(\d*)([a-zA-Z])", msgtype.unpacker.format.lstrip("<"))
    if len(codes) != len(wire):
        raise ValueError(f"{msgtype.msgname}: cannot map its fields to its wire format")
    want = list(fields)
    fmt = ["<"]
    pos = 0
    for name in want:
        if name not in wire:
            raise ValueError(f"{msgtype.msgname} has no field {name!r}")
        j = wire.index(name)
        if j < pos:
            raise ValueError(f"{msgtype.msgname}: fields must be in wire order {wire}")
        for count, code in codes[pos:j]:
            fmt.append(f"{struct.calcsize(count + code)}x")
        count, code = codes[j]
        if count not in ("", "1") or code not in _NUMERIC_FORMATS:
            raise ValueError(f"{msgtype.msgname}.{name}: only scalar numeric fields")
        fmt.append(code)
        pos = j + 1
    return struct.Struct("".join(fmt)), int(msgtype.unpacker.size)
