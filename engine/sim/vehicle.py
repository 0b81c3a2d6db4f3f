"""Simulated MAVLink 2 vehicle: deterministic telemetry plus a TUNNEL echo service.

It stands in for an autopilot and its companion computer at the far end of a radio link, so tests
can check the engine's telemetry decoding against known values and its TUNNEL transport against
a byte-exact echo::

    python -m engine.sim.vehicle --device /tmp/uav --baud 57600 --duration 30
    python -m engine.sim.vehicle --device udpin:127.0.0.1:14550 --signing-key 00ff...

Streams (``common`` dialect, MAVLink 2): HEARTBEAT and SYS_STATUS at 1 Hz, GLOBAL_POSITION_INT
and ATTITUDE at 4 Hz, all taken from :func:`expected_state` at the ``time_boot_ms`` they carry,
so a receiver can recompute every field. A TUNNEL with ``payload_type >= 32768`` addressed to this
system (or broadcast) is sent back unchanged to its sender; with ``--store`` its payload is also
appended to a file as one hex line. With ``--signing-key`` every outgoing frame is signed and
only correctly signed frames are accepted, except RADIO_STATUS, which SiK radios inject unsigned.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import signal
import socket
import sys
import termios
import time
import tty
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

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
    tunnels_ignored: int = 0


class _Sink:
    """File-like target for ``MAVLink.send`` so pymavlink keeps seq and signing state itself."""

    def __init__(self, link: Link) -> None:
        self.link = link

    def write(self, data: bytes) -> None:
        self.link.send(data)


class SimVehicle:
    """The vehicle's behaviour over an opened :class:`Link`; see the module docstring."""

    def __init__(self, link: Link, *, system_id: int = 1, component_id: int = 1,
                 store: Path | None = None, signing_key: bytes | None = None, link_id: int = 0,
                 position_rate_hz: float = 4.0) -> None:
        self.link = link
        self.mav = mavlink2.MAVLink(_Sink(link), system_id, component_id)
        self.mav.robust_parsing = True
        self.store = store
        self.position_period = 1.0 / position_rate_hz
        self.stats = VehicleStats()
        self.link_closed = False
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
        """Parse a chunk and answer the TUNNEL frames in it."""
        for msg in self.mav.parse_buffer(data) or ():
            if msg.get_type() == "BAD_DATA":
                self.stats.bad_frames += 1
                continue
            self.stats.frames_received += 1
            if msg.get_type() == "TUNNEL":
                self._echo(msg)

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

    def _send(self, msg: Any) -> None:
        self.mav.send(msg)
        self.stats.frames_sent += 1

    async def run(self, stop: asyncio.Event, duration: float | None = None) -> None:
        """Stream telemetry and serve echoes until ``stop`` is set, ``duration`` passes or EOF.

        A closed link (the radio emulator going away makes the pty read fail) sets ``stop`` and
        ``link_closed``, so a vehicle never outlives its link.
        """
        loop = asyncio.get_running_loop()
        self._boot = loop.time()
        fd = self.link.fileno()
        writing = False

        def on_readable() -> None:
            try:
                while data := self.link.recv():
                    self.handle(data)
            except (EOFError, OSError):
                self.link_closed = True
                stop.set()
            sync_writer()

        def on_writable() -> None:
            self.link.flush()
            sync_writer()

        def sync_writer() -> None:
            nonlocal writing
            if self.link.pending() != writing:
                writing = not writing
                if writing:
                    loop.add_writer(fd, on_writable)
                else:
                    loop.remove_writer(fd)

        loop.add_reader(fd, on_readable)
        deadline = math.inf if duration is None else self._boot + duration
        per_slow = max(1, round(1 / self.position_period))
        tick = 0
        try:
            while not stop.is_set() and loop.time() < deadline:
                self.send_telemetry(loop.time(), with_slow=tick % per_slow == 0)
                sync_writer()
                tick += 1
                wake = min(self._boot + tick * self.position_period, deadline)
                try:
                    await asyncio.wait_for(stop.wait(), max(0.0, wake - loop.time()))
                except asyncio.TimeoutError:
                    pass
        finally:
            loop.remove_reader(fd)
            if writing:
                loop.remove_writer(fd)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m engine.sim.vehicle", description=__doc__.split("\n")[0])
    parser.add_argument("--device", required=True,
                        help="serial device path, udpin:HOST:PORT, udpout:HOST:PORT or tcp:HOST:PORT")
    parser.add_argument("--baud", type=int, default=57600)
    parser.add_argument("--system-id", type=int, default=1)
    parser.add_argument("--component-id", type=int, default=1)
    parser.add_argument("--store", type=Path, default=None, help="append received TUNNEL payloads as hex lines")
    parser.add_argument("--signing-key", default=None, help="32-byte MAVLink 2 signing key as 64 hex digits")
    parser.add_argument("--link-id", type=int, default=0, help="signing link id")
    parser.add_argument("--duration", type=float, default=None, help="exit after this many seconds")
    return parser


async def _amain(args: argparse.Namespace) -> VehicleStats:
    key = bytes.fromhex(args.signing_key) if args.signing_key else None
    link = open_link(args.device, args.baud)
    try:
        vehicle = SimVehicle(link, system_id=args.system_id, component_id=args.component_id,
                             store=args.store, signing_key=key, link_id=args.link_id)
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
