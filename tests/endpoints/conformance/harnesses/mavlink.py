"""MAVLink: a vehicle of the test's own, a pymavlink codec on a UDP socket (as
tests/endpoints/mavlink/test_mavlink_endpoint.py's ``UdpPeer``), speaking to the engine's
``udpin`` link on a port drawn for it. Robot N
is system id N: it sends NAMED_VALUE_INT (``time_boot_ms`` = seq, ``value`` = the command to
send back); the route reads the system id from the source's metadata and sends a COMMAND_LONG
whose ``target_system`` its sink renders from it (``target_system: "{robot}"``), with the seq,
edition and origin in its params (the sink mapping). The vehicle reads the robot back from
``target_system``."""

from __future__ import annotations

import asyncio
import os
from typing import Any

import socket

from engine.common.processes import listening_port
from tests.endpoints.conformance.harness import Harness, Seen

COMMAND = 31010
"""MAV_CMD_USER_1: a command no autopilot acts on."""


class VehicleSocket(asyncio.DatagramProtocol):
    """Collects the COMMAND_LONGs the engine sends (its HEARTBEATs are dropped)."""

    def __init__(self) -> None:
        from pymavlink.dialects.v20 import common as mavlink2

        self.parser = mavlink2.MAVLink(None)
        self.commands: list[Any] = []
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: Any) -> None:
        self.transport = transport

    def datagram_received(self, data: bytes, addr: Any) -> None:
        for message in self.parser.parse_buffer(data) or ():
            if message.get_type() == "COMMAND_LONG":
                self.commands.append(message)


class MavlinkHarness(Harness):
    PROTOCOL = "mavlink"
    BAD_STAGE = "sink"
    EXCLUDED = {
        "health": "a UDP link has no session to lose: the connection is its socket, up whether a vehicle speaks "
                  "or not (the status lists the vehicles heard and how long ago); tcp links reconnect, shown in "
                  "tests/endpoints/mavlink/test_mavlink_endpoint.py",
        "kill9": "MAVLink messages are telemetry with nothing to acknowledge: a message source cannot redeliver "
                 "and promises no at-least-once across an engine's death (docs/route-language.md, Delivery "
                 "semantics: MAVLink source; the JSON tunnel's own at-least-once is tested in its tests)",
        "cancel": "a MAVLink link has no broker and no subscription to revoke: a source hears whatever reaches "
                  "the link",
    }

    async def open(self, fixtures: dict[str, Any], case: str) -> None:
        os.environ.setdefault("MAVLINK20", "1")
        from pymavlink.dialects.v20 import common as mavlink2

        self.port = listening_port(kind=socket.SOCK_DGRAM)  # as tests/support/udp_vehicle.py free_udp_port, without importing pymavlink here
        loop = asyncio.get_running_loop()
        _, self.vehicle = await loop.create_datagram_endpoint(VehicleSocket, local_addr=("127.0.0.1", 0))
        self.packers = {robot: mavlink2.MAVLink(None, srcSystem=robot, srcComponent=1) for robot in (1, 2)}

    async def close(self) -> None:
        assert self.vehicle.transport is not None
        self.vehicle.transport.close()

    def connection(self, case: str) -> str:
        return f'{{mavlink: "udpin:127.0.0.1:{self.port}", heartbeat: 1}}'

    def source(self) -> str:
        return "message: NAMED_VALUE_INT"

    def sink(self) -> str:
        return 'message: COMMAND_LONG, target_system: "{robot}", target_component: 1'

    def mapping(self, edition: int) -> str:
        return (f"merge(@, {{robot: {self.origin_expression()}, origin: to_string({self.origin_expression()}), "
                f"edition: `{edition}`}})")

    def sink_mapping(self) -> str:
        # a value out of range for COMMAND_LONG's command (uint16) is refused by the sink: the bad payload
        return "{command: value, param1: time_boot_ms, param2: edition, param3: robot}"

    def origin_expression(self) -> str:
        return "meta('system_id')"

    def expected_origin(self, robot: int) -> str:
        return str(robot)

    def _send(self, robot: int, seq: int, value: int) -> None:
        packer = self.packers[robot]
        frame = packer.named_value_int_encode(seq, b"conf", value).pack(packer)
        assert self.vehicle.transport is not None
        self.vehicle.transport.sendto(frame, ("127.0.0.1", self.port))

    async def inject(self, robot: int, seq: int) -> None:
        self._send(robot, seq, COMMAND)

    async def inject_bad(self, robot: int) -> None:
        self._send(robot, 10**6, -1)

    def seen(self) -> list[Seen]:
        return [Seen(c.target_system, int(c.param1), str(int(c.param3)), int(c.param2)) for c in self.vehicle.commands]

    def session_of(self, connection: Any) -> Any:
        return connection.port  # the link (its socket) of the connection (engine/endpoints/mavlink/connection.py)


HARNESS = MavlinkHarness
