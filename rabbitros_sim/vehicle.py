"""Simulated MAVLink 2 vehicle: deterministic telemetry plus the robot agent's JSON tunnel.

It stands in for an autopilot and its companion computer at the far end of a radio link, so tests
can check the engine's telemetry decoding against known values and its TUNNEL transport end to
end (the robot agent of the RabbitROS paper)::

    python -m rabbitros_sim.vehicle --device /tmp/uav --baud 57600 --store robot.jsonl --duration 30
    python -m rabbitros_sim.vehicle --device udpin:127.0.0.1:14550 --signing-key 00ff...

Streams (``common`` dialect, MAVLink 2): HEARTBEAT and SYS_STATUS at 1 Hz, GLOBAL_POSITION_INT
and ATTITUDE at 4 Hz, all taken from :func:`expected_state` at the ``time_boot_ms`` they carry,
so a receiver can recompute every field.

JSON tunnel (default): the vehicle speaks the engine's own protocol
(:mod:`engine.endpoints.mavlink.tunnel`, ``payload_type`` 0xA900 unless ``--payload-type``). It
reassembles each message, acknowledges it as the protocol requires, appends it to ``--store`` as
one line (the message's bytes, then ``\n``), acknowledges it DELIVERED only after that write, and
sends it back to its sender as a new reliable message (retransmitted on SACK and timeout). Its
DATA frames are paced (``--tunnel-rate``, half the serial rate by default on serial links, slower
while the radio's RADIO_STATUS reports a filling buffer) so they do not overflow a SiK radio.
With ``--weeds-every N`` it also sends a canonical weed detection every N s; with
``--weeds-on-command`` too, it is the farm demo's companion computer: the detector starts when
the ground station's command ``detect_weeds`` arrives through the tunnel, and JSON commands are
acted on instead of echoed.

``--echo-frames`` instead sends every TUNNEL with ``payload_type >= 32768`` addressed to this
system (or broadcast) back unchanged, frame by frame; ``--store`` then gets each payload as a
hex line. With ``--signing-key`` every outgoing frame is signed and only correctly signed frames
are accepted, except RADIO_STATUS, which SiK radios inject unsigned.

Autopilot side of the transactions (:mod:`rabbitros_sim.autopilot`): it accepts mission uploads
(MISSION_COUNT, then MISSION_REQUEST_INT per item, re-requested on timeout, MISSION_ACK) and
answers COMMAND_LONG/COMMAND_INT with COMMAND_ACK; ``--mission-result`` and ``--command-result``
make it reject (with a MAV_MISSION_RESULT / MAV_RESULT name) or stay ``silent``.

The link, its pacing and signing are the engine's own (:class:`engine.endpoints.mavlink.port.MavlinkPort`),
so the vehicle behaves on the radio as the engine does.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import json
import math
import os
import signal
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from engine.endpoints.base import EndpointError, Inbound  # noqa: E402
from engine.endpoints.mavlink.links import configure_tty  # noqa: E402
from engine.endpoints.mavlink.port import MavlinkPort  # noqa: E402
from engine.endpoints.mavlink.options import MavlinkTunnel  # noqa: E402
from engine.endpoints.mavlink.settings import LinkConfig, SigningConfig, parse_address  # noqa: E402
from engine.endpoints.mavlink.tunnel import (  # noqa: E402
    DEFAULT_PAYLOAD_TYPE,
    TunnelHub,
    TunnelSettings,
    TunnelSink,
    TunnelSource,
)
from rabbitros_sim.autopilot import Autopilot  # noqa: E402
from rabbitros_sim.deliver import FunctionDeliver  # noqa: E402

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
ECHO_ATTEMPTS = 3
"""Times a JSON echo is offered again after the tunnel gave up on it (a long outage)."""
ECHO_BATCH = 64
"""Most stored messages one echo worker sends back together."""
GCS_ADDRESS = (255, 190)
"""The engine's default MAVLink system and component: where unsolicited JSON goes."""

_SENSORS = (mavlink2.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink2.MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | mavlink2.MAV_SYS_STATUS_SENSOR_3D_MAG | mavlink2.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
            | mavlink2.MAV_SYS_STATUS_SENSOR_GPS | mavlink2.MAV_SYS_STATUS_SENSOR_BATTERY)

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


def telemetry(ms: int, with_slow: bool) -> list[Any]:
    """The vehicle's streams at ``ms`` after boot: GLOBAL_POSITION_INT and ATTITUDE, plus
    HEARTBEAT and SYS_STATUS first when ``with_slow`` (once a second)."""
    s = expected_state(ms / 1000)
    out: list[Any] = []
    if with_slow:
        mode = mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink2.MAV_MODE_FLAG_SAFETY_ARMED
        out.append(mavlink2.MAVLink_heartbeat_message(
            mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_GENERIC, mode, 0, mavlink2.MAV_STATE_ACTIVE, 3))
        out.append(mavlink2.MAVLink_sys_status_message(
            _SENSORS, _SENSORS, _SENSORS, 250, s["voltage_battery"], s["current_battery"],
            s["battery_remaining"], 0, 0, 0, 0, 0, 0))
    out.append(mavlink2.MAVLink_global_position_int_message(
        ms, s["lat"], s["lon"], s["alt"], s["relative_alt"], s["vx"], s["vy"], s["vz"], s["hdg"]))
    out.append(mavlink2.MAVLink_attitude_message(
        ms, s["roll"], s["pitch"], s["yaw"], s["rollspeed"], s["pitchspeed"], s["yawspeed"]))
    return out


def open_serial(path: str, baud: int = 57600) -> int:
    """Open a serial device (or pty) raw and non-blocking, as the engine's serial link does."""
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        configure_tty(fd, baud)
    except BaseException:
        os.close(fd)
        raise
    return fd


@dataclass
class VehicleStats:
    frames_sent: int = 0
    frames_received: int = 0
    bad_frames: int = 0
    """Bad CRC or framing, and (signing) unsigned, forged or replayed frames."""
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
    missions_accepted: int = 0
    mission_items_received: int = 0
    mission_requests_sent: int = 0
    """MISSION_REQUEST_INT sent, repeats after a timeout included."""
    commands_received: int = 0
    json_commands: int = 0
    """``--weeds-on-command``: JSON commands acted on (not echoed)."""


class SimVehicle:
    """The vehicle's behaviour on the link ``device`` (serial path, ``udpin:``, ``udpout:``,
    ``tcp:``); see the module docstring.

    ``tunnel_rate`` paces JSON tunnel DATA frames in bytes/s (None: half the serial rate, unpaced
    on networks); ``tunnel_settings`` tunes the protocol as the engine's ``tunnel:`` connection
    setting does; ``mission_result``/``command_results`` set the autopilot's answers.

    ``weeds_on_command``: the companion computer of the farm demo. Its weed detector waits for
    the ground station's canonical command ``{"command": "detect_weeds", "params": {"every_s":
    N}}`` through the tunnel (then sends a detection every N s, default ``weeds_every``), and a
    JSON command is acted on, never echoed back.
    """

    def __init__(self, device: str, *, baud: int = 57600, system_id: int = 1, component_id: int = 1,
                 store: Path | None = None, signing_key: bytes | None = None, link_id: int = 0,
                 position_rate_hz: float = 4.0, echo_frames: bool = False,
                 payload_type: int = DEFAULT_PAYLOAD_TYPE, tunnel_rate: float | None = None,
                 tunnel_settings: TunnelSettings | None = None, weeds_every: float | None = None,
                 mission_result: str = "MAV_MISSION_ACCEPTED", command_results: Sequence[str] = ("MAV_RESULT_ACCEPTED",),
                 legacy_requests: bool = False, weeds_on_command: bool = False,
                 mission_item_seconds: float | None = None) -> None:
        address = parse_address(device, baud if not device.partition(":")[1] else None)
        serial = address.kind == "serial"
        settings = tunnel_settings or TunnelSettings.from_settings(None, serial=serial)
        if tunnel_rate is not None:
            settings = dataclasses.replace(settings, rate=tunnel_rate)
        signing = None
        if signing_key is not None:
            if len(signing_key) != 32:
                raise ValueError("signing key must be 32 bytes")
            signing = SigningConfig(signing_key, link_id)
        self.config = LinkConfig(address, system_id, component_id, signing, rate=address.baud / 10 if serial else 0.0,
                                 heartbeat=0.0, mav_type=mavlink2.MAV_TYPE_QUADROTOR, tunnel=settings)
        self.port_stats: dict[str, int] = {}
        self.port = MavlinkPort(f"vehicle{system_id}", self.config, self._on_message, self.port_stats)
        self.system_id, self.component_id = system_id, component_id
        self.store = store
        self.position_period = 1.0 / position_rate_hz
        self._stats = VehicleStats()
        self.link_closed = False
        self.echo_frames = echo_frames
        self.payload_type = payload_type
        self.weeds_every = weeds_every
        self.weeds_on_command = weeds_on_command
        self._detector: asyncio.Task[None] | None = None
        self.autopilot = Autopilot(self.port, system_id, component_id, mission_result=mission_result,
                                   command_results=command_results, legacy_requests=legacy_requests,
                                   item_seconds=mission_item_seconds)
        self._boot = 0.0
        self._opened = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._hub: TunnelHub | None = None
        self._sinks: dict[tuple[int, int], TunnelSink] = {}
        self._echoes: asyncio.Queue[tuple[tuple[int, int], bytes]] = asyncio.Queue()

    @property
    def stats(self) -> VehicleStats:
        p, a = self.port_stats, self.autopilot.stats
        s = self._stats
        s.frames_sent = p.get("frames_sent", 0)
        s.frames_received = p.get("frames_accepted", 0)
        s.bad_frames = sum(p.get(k, 0) for k in ("bad_crc", "bad_data", "unsigned_rejected", "bad_signature", "replayed"))
        s.tunnel_retransmissions = p.get("tunnel_retransmissions", 0)
        s.missions_accepted, s.mission_items_received = a["missions_accepted"], a["mission_items_received"]
        s.mission_requests_sent, s.commands_received = a["mission_requests_sent"], a["commands_received"]
        return s

    def time_boot_ms(self, now: float) -> int:
        return round((now - self._boot) * 1000)

    def send_telemetry(self, now: float, with_slow: bool) -> None:
        """Send the 4 Hz pair, plus HEARTBEAT and SYS_STATUS when ``with_slow`` (and MISSION_CURRENT
        when the vehicle flies its missions: ``mission_item_seconds``)."""
        for msg in telemetry(self.time_boot_ms(now), with_slow):
            self.port.post(msg)
        self.autopilot.advance(now)
        if with_slow and self.autopilot.item_seconds is not None:
            self.port.post(self.autopilot.mission_current())

    def _on_message(self, msg: Any) -> None:
        """Every accepted frame: TUNNEL to the echo or the tunnel protocol, the rest to the autopilot."""
        if msg.get_type() != "TUNNEL":
            self.autopilot.handle(msg)
        elif self.echo_frames:
            self._echo(msg)
        else:
            self._tunnel_frame(msg)

    def _echo(self, msg: Any) -> None:
        if msg.payload_type < PRIVATE_TUNNEL_TYPE_MIN or msg.target_system not in (0, self.system_id):
            self._stats.tunnels_ignored += 1
            return
        payload = bytes(msg.payload[:msg.payload_length])
        if self.store is not None:
            with self.store.open("a") as f:
                f.write(payload.hex() + "\n")
        self.port.post(mavlink2.MAVLink_tunnel_message(msg.get_srcSystem(), msg.get_srcComponent(),
                                                       msg.payload_type, msg.payload_length, list(msg.payload)))
        self._stats.tunnels_echoed += 1

    def _tunnel_frame(self, msg: Any) -> None:
        """Hand a TUNNEL frame for us to the tunnel protocol (DATA to reassembly, ACK to a sender)."""
        for_us = msg.target_system in (0, self.system_id) and msg.target_component in (0, self.component_id)
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        payload = bytes(msg.payload[:msg.payload_length])
        if self._hub is None or not for_us or not self._hub.on_frame(msg.payload_type, peer, payload):
            self._stats.tunnels_ignored += 1

    async def _received_json(self, inbound: Inbound) -> None:
        """Store a reassembled message, then queue its echo; returning lets the protocol
        acknowledge it DELIVERED, so an acknowledged message is always on disk."""
        body = inbound.body
        assert body is not None
        if self.store is not None:
            with self.store.open("ab") as f:
                f.write(body + b"\n")
        self._stats.json_received += 1
        if self.weeds_on_command and self._command(body):
            return
        self._echoes.put_nowait(((inbound.meta["system_id"], inbound.meta["component_id"]), body))

    def _command(self, body: bytes) -> bool:
        """Act on a canonical command for the companion computer; False if ``body`` is none."""
        try:
            message = json.loads(body)
        except ValueError:
            return False
        if not isinstance(message, dict) or not isinstance(message.get("command"), str):
            return False
        self._stats.json_commands += 1
        given = message.get("params")
        params: dict[str, Any] = given if isinstance(given, dict) else {}
        if message["command"] == "detect_weeds" and self._detector is None and self._loop is not None:
            every = float(params.get("every_s") or self.weeds_every or 6.0)
            self._detector = self._loop.create_task(self._weed_detector(every), name="vehicle-weeds")
        return True

    async def _echo_worker(self) -> None:
        """Send stored messages back, each as a new reliable message to the peer it came from;
        what queued up meanwhile goes together (the tunnel bundles it), as the engine's sink does."""
        assert self._hub is not None
        while True:
            batch = [await self._echoes.get()]
            while not self._echoes.empty() and len(batch) < ECHO_BATCH:
                batch.append(self._echoes.get_nowait())
            by_peer: dict[tuple[int, int], list[bytes]] = {}
            for peer, body in batch:
                by_peer.setdefault(peer, []).append(body)
            await asyncio.gather(*(self._echo_json(peer, bodies) for peer, bodies in by_peer.items()))

    async def _echo_json(self, peer: tuple[int, int], bodies: list[bytes]) -> None:
        assert self._hub is not None
        sink = self._sinks.get(peer)
        if sink is None:
            sink = self._sinks[peer] = TunnelSink(self._hub, payload_type=self.payload_type, target=peer)
        for _ in range(ECHO_ATTEMPTS):
            results = await sink.send_many(bodies)
            self._stats.json_echoed += results.count(None)
            bodies = [body for body, error in zip(bodies, results) if error is not None]
            if not bodies:
                return
        self._stats.json_echo_failed += len(bodies)

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
            now = time.time()
            points = [{"lat": round(state["lat"] / 1e7 + i * 2e-6, 7), "lon": round(state["lon"] / 1e7 - i * 2e-6, 7),
                       "p": round(0.6 + 0.1 * i, 2)} for i in range(3)]
            body = json.dumps({"agent_id": f"uav{self.system_id}", "id": f"weeds-{count}", "type": "weed_detection",
                               "stamp": {"sec": int(now), "nanosec": int(now % 1 * 1e9)}, "points": points}, separators=(",", ":"))
            with contextlib.suppress(EndpointError):
                await sink.send_bytes(body.encode())

    async def open(self) -> None:
        """Open the link (a ``udpin`` socket is bound once this returns); ``run`` does it if needed."""
        if not self._opened:
            self._opened = True
            self.port.on_lost = self._link_lost
            await self.port.open()

    def _link_lost(self) -> None:
        self.link_closed = True
        if self._stop is not None:
            self._stop.set()

    async def run(self, stop: asyncio.Event, duration: float | None = None) -> None:
        """Stream telemetry and serve the tunnel and the autopilot until ``stop`` is set,
        ``duration`` passes or the link is lost.

        A lost serial link (the radio emulator going away makes the pty read fail) sets ``stop``
        and ``link_closed``, so a vehicle never outlives its link.
        """
        loop = self._loop = asyncio.get_running_loop()
        self._stop = stop
        self._boot = loop.time()
        await self.open()
        tasks: list[asyncio.Task[None]] = [loop.create_task(self.autopilot.run(), name="vehicle-autopilot")]
        source: TunnelSource | None = None
        try:
            if not self.echo_frames:
                self._hub = TunnelHub(self.port, self.config.tunnel)
                self._hub.add_sender(self.payload_type)
                source = TunnelSource(self._hub, route="vehicle", payload_type=self.payload_type)
                await source.start(FunctionDeliver(self._received_json))
                tasks += [loop.create_task(self._echo_worker(), name="vehicle-echo")
                          for _ in range(self.config.tunnel.window)]
                if self.weeds_every and not self.weeds_on_command:
                    tasks.append(loop.create_task(self._weed_detector(self.weeds_every), name="vehicle-weeds"))
            deadline = math.inf if duration is None else self._boot + duration
            per_slow = max(1, round(1 / self.position_period))
            tick = 0
            while not stop.is_set() and loop.time() < deadline:
                self.send_telemetry(loop.time(), with_slow=tick % per_slow == 0)
                tick += 1
                wake = min(self._boot + tick * self.position_period, deadline)
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), max(0.0, wake - loop.time()))
        finally:
            if self._detector is not None:
                tasks.append(self._detector)
            for task in tasks:
                task.cancel()
            if source is not None:
                await source.stop()
            await asyncio.gather(*tasks, return_exceptions=True)
            await self.port.close()
            self._loop = None


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m rabbitros_sim.vehicle", description=__doc__.split("\n")[0])
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
    parser.add_argument("--weeds-on-command", action="store_true",
                        help="start the weed detector when the ground station's command detect_weeds arrives "
                             "through the tunnel (JSON commands are acted on, not echoed)")
    parser.add_argument("--signing-key", default=None, help="32-byte MAVLink 2 signing key as 64 hex digits")
    parser.add_argument("--link-id", type=int, default=0, help="signing link id")
    parser.add_argument("--mission-result", default="MAV_MISSION_ACCEPTED",
                        help="MISSION_ACK result of a complete upload (a MAV_MISSION_RESULT name), or 'silent'")
    parser.add_argument("--command-result", default="MAV_RESULT_ACCEPTED",
                        help="COMMAND_ACK results, comma-separated, one per command received (the last repeats), "
                             "or 'silent'")
    parser.add_argument("--legacy-requests", action="store_true", help="request items with MISSION_REQUEST")
    parser.add_argument("--mission-item-seconds", type=float, default=None,
                        help="fly an accepted mission: reach one item every this many seconds (MISSION_ITEM_REACHED), "
                             "and stream MISSION_CURRENT at 1 Hz")
    parser.add_argument("--duration", type=float, default=None, help="exit after this many seconds")
    return parser


async def _amain(args: argparse.Namespace) -> SimVehicle:
    key = bytes.fromhex(args.signing_key) if args.signing_key else None
    network = args.device.partition(":")[0] in ("udpin", "udpout", "tcp")
    settings = TunnelSettings.from_settings(
        MavlinkTunnel(window=args.tunnel_window) if args.tunnel_window else None, serial=not network)
    vehicle = SimVehicle(args.device, baud=args.baud, system_id=args.system_id, component_id=args.component_id,
                         store=args.store, signing_key=key, link_id=args.link_id,
                         echo_frames=args.echo_frames, payload_type=args.payload_type, tunnel_rate=args.tunnel_rate,
                         tunnel_settings=settings, weeds_every=args.weeds_every,
                         mission_result=args.mission_result, command_results=args.command_result.split(","),
                         legacy_requests=args.legacy_requests, weeds_on_command=args.weeds_on_command,
                         mission_item_seconds=args.mission_item_seconds)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    await vehicle.open()
    print(json.dumps({"event": "ready", "device": args.device, "system_id": args.system_id}), flush=True)
    await vehicle.run(stop, args.duration)
    # Stopped: a further SIGINT/SIGTERM changes nothing. Under ``timeout`` the signal it gets
    # goes to this process and to its process group, so a second copy may arrive after asyncio
    # put the default handlers back and turn a clean exit into death by signal. (Only the
    # CLI runs this; the mask would be inherited by processes started afterwards.)
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    return vehicle



def main(argv: Sequence[str] | None = None) -> int:
    """CLI entry: prints a ready line, then the counters and the mission it holds (the items'
    frame, x, y, z, as uploaded) as JSON when it stops."""
    args = _parser().parse_args(argv)
    vehicle = asyncio.run(_amain(args))
    mission = [{key: item[key] for key in ("seq", "command", "frame", "x", "y", "z")} for item in vehicle.autopilot.mission]
    print(json.dumps({"event": "stopped", "stats": asdict(vehicle.stats), "mission": mission}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
