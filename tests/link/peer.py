"""A minimal "autopilot" built from pymavlink directly, on the far end of a MemoryTransport."""

from __future__ import annotations

import asyncio
import os
from collections.abc import Callable
from typing import Any

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink2

from companion.link.transport import MemoryTransport, Transport


class FakeAutopilot:
    """Speaks for ``sysid``/``compid``; answers COMMAND_LONG with ``ack_policy(msg)``.

    ``ack_policy`` returns a MAV_RESULT, or None to stay silent (a lost ack).
    ``key`` set: signs what it sends (pymavlink's own signing).
    """

    def __init__(
        self,
        transport: Transport,
        sysid: int = 1,
        compid: int = 1,
        *,
        key: bytes | None = None,
        ack_policy: Callable[[Any], int | None] | None = None,
    ) -> None:
        self.transport = transport
        self.mav = mavlink2.MAVLink(self, srcSystem=sysid, srcComponent=compid)
        if key is not None:
            self.mav.signing.secret_key = key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.link_id = 3
            from companion.link.signing import signing_timestamp_now

            self.mav.signing.timestamp = signing_timestamp_now()
        self.parser = mavlink2.MAVLink(None)
        self.parser.robust_parsing = True
        self.received: list[Any] = []
        self.raw_received: list[bytes] = []
        self.ack_policy = ack_policy or (lambda msg: mavlink2.MAV_RESULT_ACCEPTED)
        self.new_message = asyncio.Event()

    def write(self, buf: bytes) -> None:  # pymavlink's output file
        self.transport.write(buf)

    async def open(self) -> FakeAutopilot:
        await self.transport.open(self._on_bytes)
        return self

    def _on_bytes(self, chunk: bytes) -> None:
        self.raw_received.append(chunk)
        for msg in self.parser.parse_buffer(chunk) or []:
            self.received.append(msg)
            self.new_message.set()
            if msg.get_type() == "COMMAND_LONG":
                result = self.ack_policy(msg)
                if result is not None:
                    self.mav.command_ack_send(
                        msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
                    )

    def heartbeat(
        self,
        mav_type: int = mavlink2.MAV_TYPE_QUADROTOR,
        autopilot: int = mavlink2.MAV_AUTOPILOT_PX4,
    ) -> None:
        self.mav.heartbeat_send(mav_type, autopilot, 1, 0, mavlink2.MAV_STATE_STANDBY)

    def of_type(self, mtype: str) -> list[Any]:
        return [m for m in self.received if m.get_type() == mtype]

    async def wait_for(self, mtype: str, n: int = 1, timeout_s: float = 2.0) -> list[Any]:
        async def _wait() -> list[Any]:
            while len(self.of_type(mtype)) < n:
                self.new_message.clear()
                await self.new_message.wait()
            return self.of_type(mtype)

        return await asyncio.wait_for(_wait(), timeout_s)


def memory_pair() -> tuple[MemoryTransport, MemoryTransport]:
    return MemoryTransport.pair()


async def settle() -> None:
    """Let call_soon deliveries run (a few loop iterations)."""
    for _ in range(5):
        await asyncio.sleep(0)
