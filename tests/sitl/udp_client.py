"""A ground station on a real UDP socket for the face tests: it sends frames to a
face (in this process) and reads what the face sends back."""

from __future__ import annotations

import os
import socket
from typing import Any

os.environ["MAVLINK20"] = "1"

from pymavlink.dialects.v20 import common as mavlink2

from sitl.mavlink_face import MavlinkFace

__all__ = ["Client", "Collect"]


class Collect:
    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, buf: bytes) -> None:
        self.frames.append(bytes(buf))


class Client:
    """The other end of a face opened with ``udpout:127.0.0.1:<port>``."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.port: int = self.sock.getsockname()[1]
        self.out = Collect()
        self.mav = mavlink2.MAVLink(self.out, srcSystem=255, srcComponent=190)
        self.parser = mavlink2.MAVLink(None)
        self.parser.robust_parsing = True

    def close(self) -> None:
        self.sock.close()

    def received(self, wait_s: float = 0.05) -> list[Any]:
        """Every message that arrived until none came for ``wait_s``."""
        self.sock.settimeout(wait_s)
        msgs: list[Any] = []
        while True:
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                return msgs
            msgs += self.parser.parse_buffer(data) or []

    def send_last(self, face: MavlinkFace[Any]) -> None:
        """Send the frame packed last to ``face``, and let it reach its socket."""
        assert face.sock is not None
        self.sock.sendto(self.out.frames[-1], face.sock.getsockname())
        assert face.wait_readable(1.0)

    def exchange(self, face: MavlinkFace[Any], t_s: float = 0.0) -> list[Any]:
        """Send the frame packed last to ``face``, let it handle it, return its answers."""
        self.send_last(face)
        face.poll(t_s)
        return [m for m in self.received() if m.get_type() != "BAD_DATA"]

    def params(self, face: MavlinkFace[Any]) -> list[Any]:
        """The PARAM_VALUEs ``face`` answers the frame packed last with."""
        return [m for m in self.exchange(face) if m.get_type() == "PARAM_VALUE"]

    def autopilot_version(self, face: MavlinkFace[Any]) -> Any:
        """AUTOPILOT_VERSION, asked for with MAV_CMD_REQUEST_MESSAGE as MAVSDK does."""
        self.mav.command_long_send(
            1, 1, mavlink2.MAV_CMD_REQUEST_MESSAGE, 0,
            mavlink2.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0,
        )  # fmt: skip
        acks = self.exchange(face)
        assert [a.result for a in acks if a.get_type() == "COMMAND_ACK"] == [0]
        face.publish(0.0, imu_sample=False, wall_s=0.0)
        (ver,) = [m for m in self.received() if m.get_type() == "AUTOPILOT_VERSION"]
        return ver
