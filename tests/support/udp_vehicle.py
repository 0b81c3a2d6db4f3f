"""A pymavlink telemetry sender over UDP and the routes that carry its telemetry to AMQP, for
the udpin handover and key-file tests and the handover benchmark."""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from typing import TYPE_CHECKING

from pymavlink.dialects.v20 import common as mavlink2

from engine.common.processes import listening_port
from engine.endpoints.mavlink.connection import MavlinkConnection

if TYPE_CHECKING:  # the engine only as a type: a simulated vehicle needs no runtime loaded
    from engine.running.runtime import Engine


class Vehicle(threading.Thread):
    """A pymavlink sender: GLOBAL_POSITION_INT at ``rate`` Hz, ``time_boot_ms`` = sequence,
    signed with ``key`` if given."""

    def __init__(self, port: int, rate: float, key: bytes | None = None) -> None:
        super().__init__(daemon=True)
        self.port, self.rate, self.key = port, rate, key
        self.sent = 0
        self.stop = threading.Event()

    def run(self) -> None:
        mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
        if self.key is not None:  # MAVLink 2 signing, link 0, timestamps from now
            mav.signing.secret_key, mav.signing.sign_outgoing = self.key, True
            mav.signing.timestamp = int((time.time() - 1420070400) * 100_000)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            started = time.monotonic()
            while not self.stop.is_set():
                frame = mav.global_position_int_encode(self.sent, -220000000, -479000000, 10000, 5000, 0, 0, 0, 0)
                try:
                    sock.sendto(frame.pack(mav), ("127.0.0.1", self.port))
                except OSError:
                    pass  # nobody listening during the handover: UDP telemetry is lost, as over the air
                self.sent += 1
                time.sleep(max(0.0, started + self.sent / self.rate - time.monotonic()))  # pacing: the vehicle's rate


def free_udp_port() -> int:
    """A free UDP port for an engine's ``udpin`` link (below the ephemeral range, as every server's)."""
    return listening_port(kind=socket.SOCK_DGRAM)


def telemetry_routes(amqp_url: str, outbox: str, port: int, host: str = "127.0.0.1", heartbeat: float = 1,
                     key_file: str | None = None) -> str:
    """A route file: GLOBAL_POSITION_INT from a ``udpin`` connection (signed with ``key_file``
    if given) to the exchange ``outbox``, key ``telemetry``; ``{seq: time_boot_ms}``. A route
    ``other`` on another connection can be added by the caller."""
    signing = f", signing: {{key_file: \"{key_file}\"}}" if key_file else ""
    return f"""
connections:
  gcs: {{amqp: "{amqp_url}"}}
  radio: {{mavlink: "udpin:{host}:{port}", heartbeat: {heartbeat}{signing}}}
routes:
  - name: telemetry
    source: {{mavlink: {{connection: radio, message: GLOBAL_POSITION_INT}}}}
    mapping: "{{seq: time_boot_ms}}"
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: {outbox}, routing_key: telemetry}}}}
"""


class CommandVehicle(threading.Thread):
    """A vehicle on plain pymavlink (system 1, component 1) behind a UDP socket: it sends its
    HEARTBEAT every 0.2 s to whoever wrote to it last, records every COMMAND_LONG and
    COMMAND_INT it receives (with ``time.monotonic()`` of arrival) and acknowledges each with
    MAV_RESULT_ACCEPTED. Nothing of the engine is used to parse, so what it records is what
    went over the wire."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port: int = self.sock.getsockname()[1]
        self.commands: list[tuple[float, mavlink2.MAVLink_message]] = []
        self.lock = threading.Lock()
        self.stop = threading.Event()

    def received(self) -> list[tuple[float, mavlink2.MAVLink_message]]:
        with self.lock:
            return list(self.commands)

    def run(self) -> None:
        mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
        peer: tuple[str, int] | None = None
        beat = 0.0
        with self.sock:
            while not self.stop.is_set():
                if peer is not None and time.monotonic() >= beat:
                    beat = time.monotonic() + 0.2
                    heartbeat = mav.heartbeat_encode(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_GENERIC,
                                                     0, 0, mavlink2.MAV_STATE_STANDBY)
                    self.sock.sendto(heartbeat.pack(mav), peer)
                try:
                    data, peer = self.sock.recvfrom(65535)
                except TimeoutError:
                    continue
                for msg in mav.parse_buffer(data) or ():
                    if msg.get_type() in ("COMMAND_LONG", "COMMAND_INT") and msg.target_system == 1:
                        with self.lock:
                            self.commands.append((time.monotonic(), msg))
                        ack = mav.command_ack_encode(msg.command, mavlink2.MAV_RESULT_ACCEPTED, 0, 0,
                                                     msg.get_srcSystem(), msg.get_srcComponent())
                        self.sock.sendto(ack.pack(mav), peer)


class FleetVehicle(threading.Thread):
    """One of several vehicles sharing a link: system ``system_id`` (component 1) sends HEARTBEAT
    and GLOBAL_POSITION_INT (``time_boot_ms`` = sequence) at ``rate`` Hz from its own UDP socket
    to the engine's ``udpin`` port, records the COMMAND_LONGs addressed to it (``arrivals``: their
    ``time.monotonic()``) and acknowledges each with ``answer`` (MAV_RESULT_ACCEPTED; None: it never
    answers, a vehicle whose uplink is lost while its telemetry still comes), counts those
    addressed to another system (which a vehicle ignores, as MAVLink routing says) and the
    engine's HEARTBEATs (``heartbeats``). Parsed with pymavlink alone."""

    def __init__(self, system_id: int, port: int, rate: float = 20.0,
                 answer: int | None = mavlink2.MAV_RESULT_ACCEPTED) -> None:
        super().__init__(daemon=True)
        self.system_id, self.engine, self.rate, self.answer = system_id, ("127.0.0.1", port), rate, answer
        self.arrivals: list[float] = []
        self.heartbeats = 0
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.01)
        self.sent = 0
        self.commands: list[mavlink2.MAVLink_command_long_message] = []
        self.foreign = 0
        self.lock = threading.Lock()
        self.stop = threading.Event()

    def received(self) -> list[mavlink2.MAVLink_command_long_message]:
        with self.lock:
            return list(self.commands)

    def run(self) -> None:
        mav = mavlink2.MAVLink(None, srcSystem=self.system_id, srcComponent=1)
        started = time.monotonic()
        with self.sock:
            while not self.stop.is_set():
                if time.monotonic() >= started + self.sent / self.rate:
                    heartbeat = mav.heartbeat_encode(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_GENERIC,
                                                     0, 0, mavlink2.MAV_STATE_STANDBY)
                    position = mav.global_position_int_encode(self.sent, -220000000 - self.system_id, -479000000,
                                                              10000, 5000, 0, 0, 0, 0)
                    for frame in (heartbeat, position):
                        with contextlib.suppress(OSError):
                            self.sock.sendto(frame.pack(mav), self.engine)
                    self.sent += 1
                try:
                    data, peer = self.sock.recvfrom(65535)
                except (TimeoutError, OSError):
                    continue
                for msg in mav.parse_buffer(data) or ():
                    if msg.get_type() == "HEARTBEAT":
                        self.heartbeats += 1
                    if msg.get_type() != "COMMAND_LONG":
                        continue
                    if msg.target_system != self.system_id:
                        self.foreign += 1
                        continue
                    with self.lock:
                        self.commands.append(msg)
                        self.arrivals.append(time.monotonic())
                    if self.answer is None:
                        continue
                    ack = mav.command_ack_encode(msg.command, self.answer, 0, 0,
                                                 msg.get_srcSystem(), msg.get_srcComponent())
                    self.sock.sendto(ack.pack(mav), peer)


def mavlink_connection(engine: Engine, name: str) -> MavlinkConnection:
    """The engine's MAVLink connection ``name``, for a test that reads its counters or port."""
    connection = next(c for c in engine.connections if c.name == name)
    assert isinstance(connection, MavlinkConnection), f"connection {name} is not a MAVLink one"
    return connection
