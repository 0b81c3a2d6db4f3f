"""Simulated MAVLink 2 vehicle: deterministic telemetry plus the robot agent's JSON tunnel.

It stands in for an autopilot and its companion computer at the far end of a radio link, so tests
can check the engine's telemetry decoding against known values and its TUNNEL transport end to
end (the robot agent of the RabbitROS paper)::

    python -m engine.sim.vehicle --device /tmp/uav --baud 57600 --store robot.jsonl --duration 30
    python -m engine.sim.vehicle --device udpin:127.0.0.1:14550 --signing-key 00ff...

Streams (``common`` dialect, MAVLink 2): HEARTBEAT and SYS_STATUS at 1 Hz, GLOBAL_POSITION_INT
and ATTITUDE at 4 Hz, all taken from :func:`expected_state` at the ``time_boot_ms`` they carry,
so a receiver can recompute every field.

JSON tunnel (default): the vehicle speaks the engine's own protocol
(:mod:`engine.endpoints.mavlink_tunnel`, ``payload_type`` 0xA900 unless ``--payload-type``). It
reassembles each message, acknowledges it as the protocol requires, appends it to ``--store`` as
one line (the message's bytes, then ``\n``), acknowledges it DELIVERED only after that write, and
sends it back to its sender as a new reliable message (retransmitted on SACK and timeout). Its
DATA frames are paced (``--tunnel-rate``, half the serial rate by default on serial links, slower
while the radio's RADIO_STATUS reports a filling buffer) so they do not overflow a SiK radio.

``--echo-frames`` instead sends every TUNNEL with ``payload_type >= 32768`` addressed to this
system (or broadcast) back unchanged, frame by frame; ``--store`` then gets each payload as a
hex line. With ``--signing-key`` every outgoing frame is signed and only correctly signed frames
are accepted, except RADIO_STATUS, which SiK radios inject unsigned.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import os
import signal
import socket
import sys
import termios
import time
import tty
from collections import deque
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from engine.endpoints.base import EndpointError, Inbound  # noqa: E402
from engine.endpoints.mavlink_tunnel import (  # noqa: E402
    DEFAULT_PAYLOAD_TYPE,
    TUNNEL_PAYLOAD,
    TunnelHub,
    TunnelSettings,
    TunnelSink,
    TunnelSource,
    radio_pacing_factor,
)

CENTER_LAT_DEG = -22.0
CENTER_LON_DEG = -47.9
RADIUS_M = 100.0
PERIOD_S = 60.0
HOME_ALT_M = 600.0
CRUISE_REL_ALT_M = 50.0
ALT_SWING_M = 5.0
EARTH_RADIUS_M = 6_378_137.0
GRAVITY = 9.80665
BATTERY_FULL_MV = 12_600
BATTERY_EMPTY_MV = 10_500
BATTERY_DRAIN_MV_PER_S = 2.0
BATTERY_CURRENT_CA = 1_500
BATTERY_PERCENT_PER_S = 1 / 36
PRIVATE_TUNNEL_TYPE_MIN = 32768
SIGNING_EPOCH = 1_420_070_400
SERIAL_TUNNEL_RATE = 57_600 / 10 / 2
"""Bytes/s of tunnel DATA frames on a 57,600 baud radio: half the serial rate, as the engine
paces its own (the rest carries telemetry and acknowledgements)."""
ECHO_ATTEMPTS = 3
"""Times a JSON echo is offered again after the tunnel gave up on it (a long outage)."""
GCS_ADDRESS = (255, 190)
"""The engine's default MAVLink system and component: where unsolicited JSON goes."""

_SENSORS = (mavlink2.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink2.MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | mavlink2.MAV_SYS_STATUS_SENSOR_3D_MAG | mavlink2.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
            | mavlink2.MAV_SYS_STATUS_SENSOR_GPS | mavlink2.MAV_SYS_STATUS_SENSOR_BATTERY)
_BAUDS = {rate: getattr(termios, f"B{rate}") for rate in
          (9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600) if hasattr(termios, f"B{rate}")}
_MAX_PENDING = 64 * 1024


def expected_state(t: float) -> dict[str, Any]:
    """Vehicle state ``t`` seconds after boot, in the units of the MAVLink fields that carry it.

    Trajectory: a clockwise circle (seen from above) of ``RADIUS_M`` around
    (``CENTER_LAT_DEG``, ``CENTER_LON_DEG``), one lap per ``PERIOD_S``, starting due north of the
    centre. With ``theta = 2*pi*t/PERIOD_S`` and ``w = 2*pi/PERIOD_S``:

    * north = R cos(theta), east = R sin(theta) metres, converted to degrees on a sphere of
      ``EARTH_RADIUS_M`` (east scaled by cos of the centre latitude);
    * height above home = ``CRUISE_REL_ALT_M + ALT_SWING_M * sin(theta)``, home at ``HOME_ALT_M`` AMSL;
    * velocity north/east/down = (-R w sin, R w cos, -A w cos) of theta;
    * yaw = course = atan2(v_east, v_north); roll = atan(R w^2 / g), the coordinated-turn bank;
      pitch = atan(climb / ground speed) = atan(A/R cos theta); the ``*speed`` fields are the
      time derivatives of roll, pitch and yaw;
    * battery: ``BATTERY_FULL_MV`` minus 2 mV/s down to ``BATTERY_EMPTY_MV``, 15 A,
      remaining 100 % minus 1 % per 36 s.

    Integers are rounded as the vehicle encodes them (degE7, mm, cm/s, cdeg, mV, cA, %),
    angles are radians in (-pi, pi]. ``time_boot_ms`` is ``round(t * 1000)``.
    """
    w = 2 * math.pi / PERIOD_S
    theta = w * t
    north, east = RADIUS_M * math.cos(theta), RADIUS_M * math.sin(theta)
    v_north, v_east = -RADIUS_M * w * math.sin(theta), RADIUS_M * w * math.cos(theta)
    rel_alt = CRUISE_REL_ALT_M + ALT_SWING_M * math.sin(theta)
    climb = ALT_SWING_M * w * math.cos(theta)
    k = ALT_SWING_M / RADIUS_M
    yaw = math.atan2(v_east, v_north)
    lat = CENTER_LAT_DEG + math.degrees(north / EARTH_RADIUS_M)
    lon = CENTER_LON_DEG + math.degrees(east / (EARTH_RADIUS_M * math.cos(math.radians(CENTER_LAT_DEG))))
    return {
        "time_boot_ms": round(t * 1000),
        "lat": round(lat * 1e7),
        "lon": round(lon * 1e7),
        "alt": round((HOME_ALT_M + rel_alt) * 1000),
        "relative_alt": round(rel_alt * 1000),
        "vx": round(v_north * 100),
        "vy": round(v_east * 100),
        "vz": round(-climb * 100),
        "hdg": round(math.degrees(yaw) * 100) % 36000,
        "roll": math.atan(RADIUS_M * w * w / GRAVITY),
        "pitch": math.atan(k * math.cos(theta)),
        "yaw": yaw,
        "rollspeed": 0.0,
        "pitchspeed": -k * w * math.sin(theta) / (1 + (k * math.cos(theta)) ** 2),
        "yawspeed": w,
        "voltage_battery": max(BATTERY_EMPTY_MV, round(BATTERY_FULL_MV - BATTERY_DRAIN_MV_PER_S * t)),
        "current_battery": BATTERY_CURRENT_CA,
        "battery_remaining": max(0, 100 - int(t * BATTERY_PERCENT_PER_S)),
    }


def open_serial(path: str, baud: int = 57600) -> int:
    """Open a serial device (or pty) raw, non-blocking, without making it our controlling tty."""
    if baud not in _BAUDS:
        raise ValueError(f"unsupported baud {baud}; use one of {sorted(_BAUDS)}")
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        tty.setraw(fd, termios.TCSANOW)
        attrs = termios.tcgetattr(fd)
        attrs[2] |= termios.CLOCAL | termios.CREAD
        attrs[4] = attrs[5] = _BAUDS[baud]
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
    except BaseException:
        os.close(fd)
        raise
    return fd


class Link(Protocol):
    """A byte pipe the vehicle reads in chunks and writes whole frames to."""

    def fileno(self) -> int: ...
    def recv(self) -> bytes: ...
    def send(self, data: bytes) -> None: ...
    def flush(self) -> None: ...
    def pending(self) -> bool: ...
    def close(self) -> None: ...


class _StreamLink:
    """Serial device or TCP socket: keeps what the kernel would not take yet, drops past 64 KiB."""

    def __init__(self, fd: int, sock: socket.socket | None = None) -> None:
        self._fd = fd
        self._sock = sock
        self._out = bytearray()
        self.dropped = 0

    def fileno(self) -> int:
        return self._fd

    def recv(self) -> bytes:
        try:
            data = self._sock.recv(4096) if self._sock else os.read(self._fd, 4096)
        except (BlockingIOError, InterruptedError):
            return b""
        if not data:
            raise EOFError("link closed")
        return data

    def send(self, data: bytes) -> None:
        if len(self._out) + len(data) > _MAX_PENDING:
            self.dropped += len(data)
            return
        self._out += data
        self.flush()

    def flush(self) -> None:
        """Write what the kernel takes; on a dead link drop it all and let the reader see EOF."""
        while self._out:
            try:
                n = self._sock.send(self._out) if self._sock else os.write(self._fd, self._out)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self.dropped += len(self._out)
                self._out.clear()
                return
            del self._out[:n]

    def pending(self) -> bool:
        return bool(self._out)

    def close(self) -> None:
        if self._sock:
            self._sock.close()
        else:
            os.close(self._fd)


class _UdpLink:
    """UDP socket; ``udpin`` answers whoever spoke last, ``udpout`` always sends to its target."""

    def __init__(self, sock: socket.socket, peer: tuple[str, int] | None, learn_peer: bool) -> None:
        self._sock = sock
        self._peer = peer
        self._learn = learn_peer

    def fileno(self) -> int:
        return self._sock.fileno()

    def recv(self) -> bytes:
        try:
            data, addr = self._sock.recvfrom(65535)
        except (BlockingIOError, InterruptedError, ConnectionRefusedError):
            return b""
        if self._learn:
            self._peer = addr
        return data

    def send(self, data: bytes) -> None:
        if self._peer is None:
            return
        try:
            self._sock.sendto(data, self._peer)
        except OSError:
            pass

    def flush(self) -> None:
        return None

    def pending(self) -> bool:
        return False

    def close(self) -> None:
        self._sock.close()


def _host_port(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host or "0.0.0.0", int(port)


def open_link(device: str, baud: int = 57600) -> Link:
    """Open ``udpin:H:P``, ``udpout:H:P``, ``tcp:H:P`` (client) or a serial device path."""
    kind, sep, rest = device.partition(":")
    if sep and kind == "udpin":
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(_host_port(rest))
        sock.setblocking(False)
        return _UdpLink(sock, None, learn_peer=True)
    if sep and kind == "udpout":
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setblocking(False)
        return _UdpLink(sock, _host_port(rest), learn_peer=False)
    if sep and kind == "tcp":
        sock = socket.create_connection(_host_port(rest), timeout=5)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setblocking(False)
        return _StreamLink(sock.fileno(), sock)
    return _StreamLink(open_serial(device, baud))


@dataclass
class VehicleStats:
    frames_sent: int = 0
    frames_received: int = 0
    bad_frames: int = 0
    tunnels_echoed: int = 0
    """``--echo-frames``: TUNNEL frames sent back unchanged."""
    tunnels_ignored: int = 0
    """TUNNEL frames for another system, or of a payload type this vehicle does not serve."""
    json_received: int = 0
    """JSON messages reassembled and stored (each once, however often its fragments came)."""
    json_echoed: int = 0
    """JSON messages sent back and acknowledged DELIVERED by their receiver."""
    json_echo_failed: int = 0
    """JSON messages given up after :data:`ECHO_ATTEMPTS` failed tunnel transfers."""
    tunnel_retransmissions: int = 0
    """DATA fragments the vehicle sent again (after a SACK showed a gap, or a timeout)."""


class _Sink:
    """File-like target for ``MAVLink.send`` so pymavlink keeps seq and signing state itself."""

    def __init__(self, link: Link) -> None:
        self.link = link

    def write(self, data: bytes) -> None:
        self.link.send(data)


_Queued = tuple[int, tuple[int, int], bytes, "asyncio.Future[float]"]


class _TunnelPort:
    """The ``TunnelLink`` the engine's tunnel drivers need, on top of the vehicle's link.

    Acknowledgements go out at once. DATA frames are paced to ``rate`` bytes/s, and slowed
    while the radio's RADIO_STATUS reports less than half of its buffer free, because a SiK
    radio silently drops serial input that overflows its 2 KB buffer (the engine's writer
    does the same on its side of the link)."""

    def __init__(self, vehicle: SimVehicle, rate: float) -> None:
        self.vehicle = vehicle
        self.rate = rate
        self.stats: dict[str, int] = {}
        self.radio_txbuf: tuple[float, int] | None = None
        self._urgent: deque[_Queued] = deque()
        self._bulk: deque[_Queued] = deque()
        self._wake = asyncio.Event()
        self._bulk_ready = 0.0

    def send_tunnel(self, payload_type: int, target: tuple[int, int], payload: bytes, *,
                    bulk: bool) -> asyncio.Future[float]:
        future: asyncio.Future[float] = asyncio.get_running_loop().create_future()
        (self._bulk if bulk else self._urgent).append((payload_type, target, payload, future))
        self._wake.set()
        return future

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            now = loop.time()
            if self._urgent:
                item, bulk = self._urgent.popleft(), False
            elif self._bulk and now >= self._bulk_ready:
                item, bulk = self._bulk.popleft(), True
            else:
                self._wake.clear()
                timeout = max(0.0, self._bulk_ready - now) if self._bulk else None
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._wake.wait(), timeout)
                continue
            payload_type, target, payload, future = item
            if future.done():
                continue
            size = self.vehicle.send_tunnel(payload_type, target, payload)
            if bulk and self.rate:
                self._bulk_ready = max(self._bulk_ready, now) + size / (self.rate * radio_pacing_factor(self.radio_txbuf, now))
            future.set_result(loop.time())


class SimVehicle:
    """The vehicle's behaviour over an opened :class:`Link`; see the module docstring.

    ``tunnel_rate`` paces JSON tunnel DATA frames in bytes/s (None: :data:`SERIAL_TUNNEL_RATE`,
    0: unpaced, for network links); ``tunnel_settings`` tunes the protocol as the engine's
    ``tunnel:`` connection setting does.
    """

    def __init__(self, link: Link, *, system_id: int = 1, component_id: int = 1,
                 store: Path | None = None, signing_key: bytes | None = None, link_id: int = 0,
                 position_rate_hz: float = 4.0, echo_frames: bool = False,
                 payload_type: int = DEFAULT_PAYLOAD_TYPE, tunnel_rate: float | None = None,
                 tunnel_settings: TunnelSettings | None = None, weeds_every: float | None = None) -> None:
        self.link = link
        self.mav = mavlink2.MAVLink(_Sink(link), system_id, component_id)
        self.mav.robust_parsing = True
        self.store = store
        self.position_period = 1.0 / position_rate_hz
        self.stats = VehicleStats()
        self.link_closed = False
        self.echo_frames = echo_frames
        self.payload_type = payload_type
        self.tunnel_rate = SERIAL_TUNNEL_RATE if tunnel_rate is None else tunnel_rate
        self.tunnel_settings = tunnel_settings or TunnelSettings()
        self.weeds_every = weeds_every
        if signing_key is not None:
            if len(signing_key) != 32:
                raise ValueError("signing key must be 32 bytes")
            self.mav.signing.secret_key = signing_key
            self.mav.signing.link_id = link_id
            self.mav.signing.timestamp = int((max(time.time(), SIGNING_EPOCH) - SIGNING_EPOCH) * 100_000)
            self.mav.signing.sign_outgoing = True
            self.mav.signing.allow_unsigned_callback = \
                lambda _mav, msg_id: msg_id == mavlink2.MAVLINK_MSG_ID_RADIO_STATUS
        self._boot = 0.0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._writing = False
        self._port: _TunnelPort | None = None
        self._hub: TunnelHub | None = None
        self._sinks: dict[tuple[int, int], TunnelSink] = {}
        self._echoes: asyncio.Queue[tuple[tuple[int, int], bytes]] = asyncio.Queue()

    def time_boot_ms(self, now: float) -> int:
        return round((now - self._boot) * 1000)

    def send_telemetry(self, now: float, with_slow: bool) -> None:
        """Send the 4 Hz pair, plus HEARTBEAT and SYS_STATUS when ``with_slow``."""
        ms = self.time_boot_ms(now)
        s = expected_state(ms / 1000)
        mav = self.mav
        if with_slow:
            self._send(mav.heartbeat_encode(
                mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_GENERIC,
                mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink2.MAV_MODE_FLAG_SAFETY_ARMED,
                0, mavlink2.MAV_STATE_ACTIVE))
            self._send(mav.sys_status_encode(
                _SENSORS, _SENSORS, _SENSORS, 250, s["voltage_battery"], s["current_battery"],
                s["battery_remaining"], 0, 0, 0, 0, 0, 0))
        self._send(mav.global_position_int_encode(
            ms, s["lat"], s["lon"], s["alt"], s["relative_alt"], s["vx"], s["vy"], s["vz"], s["hdg"]))
        self._send(mav.attitude_encode(
            ms, s["roll"], s["pitch"], s["yaw"], s["rollspeed"], s["pitchspeed"], s["yawspeed"]))

    def handle(self, data: bytes) -> None:
        """Parse a chunk and answer the TUNNEL frames in it (JSON mode needs the running loop)."""
        for msg in self.mav.parse_buffer(data) or ():
            kind = msg.get_type()
            if kind == "BAD_DATA":
                self.stats.bad_frames += 1
                continue
            self.stats.frames_received += 1
            if kind == "TUNNEL":
                if self.echo_frames:
                    self._echo(msg)
                else:
                    self._tunnel_frame(msg)
            elif kind == "RADIO_STATUS" and self._port is not None and self._loop is not None:
                self._port.radio_txbuf = (self._loop.time(), msg.txbuf)

    def _echo(self, msg: Any) -> None:
        if msg.payload_type < PRIVATE_TUNNEL_TYPE_MIN or msg.target_system not in (0, self.mav.srcSystem):
            self.stats.tunnels_ignored += 1
            return
        payload = list(msg.payload)
        if self.store is not None:
            with self.store.open("a") as f:
                f.write(bytes(payload[:msg.payload_length]).hex() + "\n")
        self._send(self.mav.tunnel_encode(msg.get_srcSystem(), msg.get_srcComponent(),
                                          msg.payload_type, msg.payload_length, payload))
        self.stats.tunnels_echoed += 1

    def _tunnel_frame(self, msg: Any) -> None:
        """Hand a TUNNEL frame for us to the tunnel protocol (DATA to reassembly, ACK to a sender)."""
        for_us = msg.target_system in (0, self.mav.srcSystem) and msg.target_component in (0, self.mav.srcComponent)
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        payload = bytes(msg.payload[:msg.payload_length])
        if self._hub is None or not for_us or not self._hub.on_frame(msg.payload_type, peer, payload):
            self.stats.tunnels_ignored += 1

    def send_tunnel(self, payload_type: int, target: tuple[int, int], payload: bytes) -> int:
        """Write one TUNNEL frame now; returns its size on the wire."""
        msg = self.mav.tunnel_encode(target[0], target[1], payload_type, len(payload),
                                     payload.ljust(TUNNEL_PAYLOAD, b"\0"))
        self._send(msg)
        return len(msg.get_msgbuf())

    async def _received_json(self, inbound: Inbound) -> None:
        """Store a reassembled message, then queue its echo; returning lets the protocol
        acknowledge it DELIVERED, so an acknowledged message is always on disk."""
        body = inbound.body
        assert body is not None
        if self.store is not None:
            with self.store.open("ab") as f:
                f.write(body + b"\n")
        self.stats.json_received += 1
        self._echoes.put_nowait(((inbound.meta["system_id"], inbound.meta["component_id"]), body))

    async def _echo_worker(self) -> None:
        """Send stored messages back, each as a new reliable message to the peer it came from."""
        assert self._hub is not None
        while True:
            peer, body = await self._echoes.get()
            sink = self._sinks.get(peer)
            if sink is None:
                sink = self._sinks[peer] = TunnelSink(self._hub, payload_type=self.payload_type, target=peer)
            for _ in range(ECHO_ATTEMPTS):
                try:
                    await sink.send_bytes(body)
                except EndpointError:
                    continue
                self.stats.json_echoed += 1
                break
            else:
                self.stats.json_echo_failed += 1

    async def _weed_detector(self, every: float) -> None:
        """The UAV's onboard detector of the farm demo: every ``every`` s, the weeds under the
        vehicle as canonical weed_detection JSON, sent to the ground station over the tunnel."""
        assert self._hub is not None and self._loop is not None
        sink = TunnelSink(self._hub, payload_type=self.payload_type, target=GCS_ADDRESS)
        count = 0
        while True:
            await asyncio.sleep(every)
            state = expected_state(self._loop.time() - self._boot)
            count += 1
            points = [{"lat": round(state["lat"] / 1e7 + i * 2e-6, 7), "lon": round(state["lon"] / 1e7 - i * 2e-6, 7),
                       "p": round(0.6 + 0.1 * i, 2)} for i in range(3)]
            body = json.dumps({"agent_id": f"uav{self.mav.srcSystem}", "id": f"weeds-{count}", "type": "weed_detection",
                               "stamp": round(time.time(), 3), "points": points}, separators=(",", ":"))
            with contextlib.suppress(EndpointError):
                await sink.send_bytes(body.encode())

    def _send(self, msg: Any) -> None:
        self.mav.send(msg)
        self.stats.frames_sent += 1
        if self._loop is not None:
            self._sync_writer()

    def _on_readable(self) -> None:
        try:
            while data := self.link.recv():
                self.handle(data)
        except (EOFError, OSError):
            self.link_closed = True
            if self._stop is not None:
                self._stop.set()
        self._sync_writer()

    def _on_writable(self) -> None:
        self.link.flush()
        self._sync_writer()

    def _sync_writer(self) -> None:
        """Watch for writability exactly while the link holds bytes the kernel would not take."""
        assert self._loop is not None
        if self.link.pending() != self._writing:
            self._writing = not self._writing
            if self._writing:
                self._loop.add_writer(self.link.fileno(), self._on_writable)
            else:
                self._loop.remove_writer(self.link.fileno())

    async def run(self, stop: asyncio.Event, duration: float | None = None) -> None:
        """Stream telemetry and serve the tunnel until ``stop`` is set, ``duration`` passes or EOF.

        A closed link (the radio emulator going away makes the pty read fail) sets ``stop`` and
        ``link_closed``, so a vehicle never outlives its link.
        """
        loop = self._loop = asyncio.get_running_loop()
        self._stop = stop
        self._boot = loop.time()
        fd = self.link.fileno()
        tasks: list[asyncio.Task[None]] = []
        source: TunnelSource | None = None
        if not self.echo_frames:
            self._port = _TunnelPort(self, self.tunnel_rate)
            self._hub = TunnelHub(self._port, self.tunnel_settings)
            self._hub.add_sender(self.payload_type)
            source = TunnelSource(self._hub, route="vehicle", payload_type=self.payload_type)
            await source.start(self._received_json)
            tasks.append(loop.create_task(self._port.run(), name="vehicle-tunnel-writer"))
            tasks += [loop.create_task(self._echo_worker(), name="vehicle-echo")
                      for _ in range(self.tunnel_settings.window)]
            if self.weeds_every:
                tasks.append(loop.create_task(self._weed_detector(self.weeds_every), name="vehicle-weeds"))
        loop.add_reader(fd, self._on_readable)
        deadline = math.inf if duration is None else self._boot + duration
        per_slow = max(1, round(1 / self.position_period))
        tick = 0
        try:
            while not stop.is_set() and loop.time() < deadline:
                self.send_telemetry(loop.time(), with_slow=tick % per_slow == 0)
                tick += 1
                wake = min(self._boot + tick * self.position_period, deadline)
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), max(0.0, wake - loop.time()))
        finally:
            loop.remove_reader(fd)
            for task in tasks:
                task.cancel()
            if source is not None:
                await source.stop()
            await asyncio.gather(*tasks, return_exceptions=True)
            if self._port is not None:
                self.stats.tunnel_retransmissions = self._port.stats.get("tunnel_retransmissions", 0)
            if self._writing:
                loop.remove_writer(fd)
                self._writing = False
            self._loop = None


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m engine.sim.vehicle", description=__doc__.split("\n")[0])
    parser.add_argument("--device", required=True,
                        help="serial device path, udpin:HOST:PORT, udpout:HOST:PORT or tcp:HOST:PORT")
    parser.add_argument("--baud", type=int, default=57600)
    parser.add_argument("--system-id", type=int, default=1)
    parser.add_argument("--component-id", type=int, default=1)
    parser.add_argument("--store", type=Path, default=None,
                        help="append each received JSON message as one line (--echo-frames: TUNNEL payloads as hex)")
    parser.add_argument("--echo-frames", action="store_true",
                        help="echo private TUNNEL frames unchanged instead of speaking the JSON tunnel protocol")
    parser.add_argument("--payload-type", type=int, default=DEFAULT_PAYLOAD_TYPE, help="JSON tunnel channel")
    parser.add_argument("--tunnel-rate", type=float, default=None,
                        help="bytes/s of tunnel DATA frames (default: half the serial rate; unpaced on networks)")
    parser.add_argument("--tunnel-window", type=int, default=None,
                        help="JSON messages the vehicle sends back concurrently (default: the engine's default)")
    parser.add_argument("--weeds-every", type=float, default=None,
                        help="send a weed detection (canonical JSON over the tunnel) every this many seconds")
    parser.add_argument("--signing-key", default=None, help="32-byte MAVLink 2 signing key as 64 hex digits")
    parser.add_argument("--link-id", type=int, default=0, help="signing link id")
    parser.add_argument("--duration", type=float, default=None, help="exit after this many seconds")
    return parser


async def _amain(args: argparse.Namespace) -> VehicleStats:
    key = bytes.fromhex(args.signing_key) if args.signing_key else None
    network = args.device.partition(":")[0] in ("udpin", "udpout", "tcp")
    rate = args.tunnel_rate
    if rate is None:
        rate = 0.0 if network else args.baud / 10 / 2
    settings = TunnelSettings.from_settings(
        {"window": args.tunnel_window} if args.tunnel_window else None, serial=not network)
    link = open_link(args.device, args.baud)
    try:
        vehicle = SimVehicle(link, system_id=args.system_id, component_id=args.component_id,
                             store=args.store, signing_key=key, link_id=args.link_id,
                             echo_frames=args.echo_frames, payload_type=args.payload_type, tunnel_rate=rate,
                             tunnel_settings=settings, weeds_every=args.weeds_every)
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        print(json.dumps({"event": "ready", "device": args.device, "system_id": args.system_id}), flush=True)
        await vehicle.run(stop, args.duration)
        return vehicle.stats
    finally:
        link.close()


def main(argv: Sequence[str] | None = None) -> int:
    """CLI entry: prints a ready line, then the counters as JSON when it stops."""
    args = _parser().parse_args(argv)
    stats = asyncio.run(_amain(args))
    print(json.dumps({"event": "stopped", "stats": asdict(stats)}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
