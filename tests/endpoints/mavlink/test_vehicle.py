"""The simulated vehicle must stream the documented trajectory, speak the engine's JSON tunnel
protocol as the robot agent (store, then send back), and echo raw TUNNEL frames exactly on request."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import math
import os
import select
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from rabbitros_sim.sik_radio import SikRadioPair  # noqa: E402
from rabbitros_sim.vehicle import (  # noqa: E402
    CENTER_LAT_DEG,
    CENTER_LON_DEG,
    expected_state,
    open_serial,
)
from rabbitros_sim.deliver import FunctionDeliver  # noqa: E402
from tests.support.udp_vehicle import free_udp_port  # noqa: E402
from tests.support.repo import REPO
from tests.support.waiting import wait_for

TUNNEL_TYPE = 0xA900
KEY = bytes(range(32))
GPI_FIELDS = ("lat", "lon", "alt", "relative_alt", "vx", "vy", "vz", "hdg")
ATT_FIELDS = ("roll", "pitch", "yaw", "rollspeed", "pitchspeed", "yawspeed")


@contextlib.contextmanager
def vehicle(*args: str) -> Iterator[subprocess.Popen[str]]:
    """Run the vehicle CLI in its own process group, bounded by ``timeout``; yield once ready."""
    proc = subprocess.Popen(
        ["timeout", "-s", "KILL", "30", sys.executable, "-m", "rabbitros_sim.vehicle", *args],
        cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, stdout=subprocess.PIPE,
        start_new_session=True, text=True)
    try:
        assert proc.stdout is not None
        assert select.select([proc.stdout], [], [], 10)[0], "vehicle printed no ready line"
        assert json.loads(proc.stdout.readline())["event"] == "ready"
        yield proc
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def stop(proc: subprocess.Popen[str], sig: int = signal.SIGTERM) -> dict[str, Any]:
    """Signal the vehicle; it must exit 0 within seconds and report its counters."""
    os.kill(proc.pid, sig)
    out, _ = proc.communicate(timeout=5)
    assert proc.returncode == 0
    last = json.loads(out.strip().splitlines()[-1])
    assert last["event"] == "stopped"
    stats: dict[str, Any] = last["stats"]
    return stats


class Peer:
    """The ground side: a MAVLink 2 parser on a byte transport, recording what it decodes."""

    def __init__(self, recv: Callable[[], bytes], send: Callable[[bytes], object], fd: int,
                 key: bytes | None = None) -> None:
        self.recv, self._send, self.fd = recv, send, fd
        self.mav = mavlink2.MAVLink(None, 255, 190)
        self.mav.robust_parsing = True
        if key:
            self.mav.signing.secret_key = key
            self.mav.signing.link_id = 9
            self.mav.signing.timestamp = int((time.time() - 1_420_070_400) * 100_000)
            self.mav.signing.sign_outgoing = True
        self.received: list[Any] = []

    def send(self, msg: Any) -> None:
        data = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        self._send(data)

    def run(self, seconds: float, until: Callable[[], bool] = lambda: False) -> None:
        end = time.monotonic() + seconds
        while (now := time.monotonic()) < end and not until():
            if select.select([self.fd], [], [], min(0.05, end - now))[0]:
                chunk = self.recv()
                self.received.extend(self.mav.parse_buffer(chunk) or ())

    def of_type(self, kind: str) -> list[Any]:
        return [m for m in self.received if m.get_type() == kind]


def tunnel(peer: Peer, payload: bytes, payload_type: int = TUNNEL_TYPE, target: int = 1) -> Any:
    return peer.mav.tunnel_encode(target, 1, payload_type, len(payload),
                                  list(payload) + [0] * (128 - len(payload)))


def payload_of(msg: Any) -> bytes:
    return bytes(msg.payload[:msg.payload_length])


def wire_payload(msg: Any) -> bytes:
    """MAVLink 2 payload as sent (zero-truncated); pymavlink's get_payload() is off by 4 on receipt."""
    frame = msg.get_msgbuf()
    return bytes(frame[10:10 + frame[1]])


def test_expected_state_is_the_documented_circle() -> None:
    metres_per_deg_lat = 6_378_137.0 * math.pi / 180
    for t in (0.0, 7.5, 15.0, 33.3, 45.0, 59.999, 1234.5):
        s = expected_state(t)
        north = (s["lat"] / 1e7 - CENTER_LAT_DEG) * metres_per_deg_lat
        east = (s["lon"] / 1e7 - CENTER_LON_DEG) * metres_per_deg_lat * math.cos(math.radians(CENTER_LAT_DEG))
        assert math.hypot(north, east) == pytest.approx(100.0, abs=0.05)
        assert math.hypot(s["vx"], s["vy"]) == pytest.approx(100 * 2 * math.pi * 100 / 60, abs=2)
        course = math.degrees(math.atan2(s["vy"], s["vx"])) % 360
        assert abs((course - s["hdg"] / 100 + 180) % 360 - 180) < 1
        assert s["alt"] - s["relative_alt"] == 600_000
        assert 45_000 <= s["relative_alt"] <= 55_000
        assert s["roll"] == pytest.approx(math.atan((2 * math.pi / 60) ** 2 * 100 / 9.80665))
        assert s["time_boot_ms"] == round(t * 1000)
    start, quarter = expected_state(0.0), expected_state(15.0)
    assert start["lat"] > round(CENTER_LAT_DEG * 1e7) and start["lon"] == round(CENTER_LON_DEG * 1e7)
    assert quarter["lon"] > round(CENTER_LON_DEG * 1e7), "clockwise: north point, then east point"
    assert expected_state(20.0)["voltage_battery"] == 12_560
    assert expected_state(72.0)["battery_remaining"] == 98


@pytest.fixture
def radio(tmp_path: Path) -> Iterator[SikRadioPair]:
    with SikRadioPair(str(tmp_path / "gcs"), str(tmp_path / "uav"), seed=11) as pair:
        yield pair


def serial_peer(path: str) -> Peer:
    fd = open_serial(path)
    return Peer(lambda: os.read(fd, 4096), lambda data: os.write(fd, data), fd)


def test_telemetry_over_the_radio_matches_the_trajectory(radio: SikRadioPair) -> None:
    with vehicle("--device", radio.link_b, "--baud", "57600", "--duration", "15") as proc:
        gcs = serial_peer(radio.link_a)
        try:
            gcs.run(3.0)
        finally:
            os.close(gcs.fd)
        radio.stop()
        proc.wait(timeout=5)
        assert proc.returncode == 0, "the vehicle must exit when its serial link goes away"

    assert not gcs.of_type("BAD_DATA")
    heartbeats, statuses = gcs.of_type("HEARTBEAT"), gcs.of_type("SYS_STATUS")
    positions, attitudes = gcs.of_type("GLOBAL_POSITION_INT"), gcs.of_type("ATTITUDE")
    assert len(heartbeats) >= 2 and len(statuses) >= 2
    assert len(positions) >= 8 and len(attitudes) >= 8
    assert all((m.get_srcSystem(), m.get_srcComponent()) == (1, 1) for m in heartbeats + positions)
    assert heartbeats[0].type == mavlink2.MAV_TYPE_QUADROTOR
    assert heartbeats[0].system_status == mavlink2.MAV_STATE_ACTIVE

    for m in positions:
        expected = expected_state(m.time_boot_ms / 1000)
        assert {f: getattr(m, f) for f in GPI_FIELDS} == {f: expected[f] for f in GPI_FIELDS}
    for m in attitudes:
        expected = expected_state(m.time_boot_ms / 1000)
        for f in ATT_FIELDS:
            assert getattr(m, f) == pytest.approx(expected[f], abs=1e-6), f
    for m in statuses:
        assert m.voltage_battery == pytest.approx(expected_state(0)["voltage_battery"], abs=20)
        assert m.battery_remaining == 100

    stamps = [m.time_boot_ms for m in positions]
    assert stamps == sorted(stamps)
    gaps = sorted(b - a for a, b in itertools.pairwise(stamps))
    assert 150 <= gaps[len(gaps) // 2] <= 400, "GLOBAL_POSITION_INT should come at about 4 Hz"


def test_tunnel_echo_over_the_radio_is_byte_identical(radio: SikRadioPair, tmp_path: Path) -> None:
    store = tmp_path / "tunnel.hex"
    payloads = [bytes(range(1, 61)) + bytes(8), bytes((7 * k) % 256 for k in range(128)), b"\x00"]
    with vehicle("--device", radio.link_b, "--echo-frames", "--store", str(store), "--duration", "15") as proc:
        gcs = serial_peer(radio.link_a)
        try:
            sent = [gcs.mav.tunnel_encode(1, 1, TUNNEL_TYPE + i, len(p), list(p) + [0] * (128 - len(p)))
                    for i, p in enumerate(payloads)]
            for msg in sent:
                gcs.send(msg)
            gcs.send(tunnel(gcs, b"public type", payload_type=200))
            gcs.send(tunnel(gcs, b"for another system", target=7))
            gcs.run(4.0, until=lambda: len(gcs.of_type("TUNNEL")) >= len(payloads))
            gcs.run(0.5)
        finally:
            os.close(gcs.fd)
        stats = stop(proc)

    echoes = gcs.of_type("TUNNEL")
    assert [payload_of(m) for m in echoes] == payloads
    assert [(m.payload_type, m.payload_length) for m in echoes] == \
        [(TUNNEL_TYPE + i, len(p)) for i, p in enumerate(payloads)]
    for original, echo in zip(sent, echoes):
        wire_echo, wire_sent = wire_payload(echo), wire_payload(original)
        assert wire_echo[:2] + wire_echo[4:] == wire_sent[:2] + wire_sent[4:], "only the address differs"
        assert list(echo.payload) == list(original.payload)
        assert (echo.target_system, echo.target_component) == (255, 190)
        assert (echo.get_srcSystem(), echo.get_srcComponent()) == (1, 1)
    assert store.read_text().split() == [p.hex() for p in payloads]
    assert stats["tunnels_echoed"] == 3 and stats["tunnels_ignored"] == 2


@pytest.mark.parametrize("transport", ["udpin", "udpout", "tcp"])
def test_network_transports_carry_telemetry_and_echo(transport: str) -> None:
    payload = b"over " + transport.encode()
    with contextlib.ExitStack() as stack:
        if transport == "udpin":
            port = free_udp_port()
            sock = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
            proc = stack.enter_context(vehicle("--device", f"udpin:127.0.0.1:{port}", "--echo-frames", "--duration", "15"))
            peer = Peer(lambda: sock.recv(65535), lambda d: sock.sendto(d, ("127.0.0.1", port)), sock.fileno())
        elif transport == "udpout":
            sock = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
            sock.bind(("127.0.0.1", 0))
            target = f"udpout:127.0.0.1:{sock.getsockname()[1]}"
            proc = stack.enter_context(vehicle("--device", target, "--echo-frames", "--duration", "15"))
            source: dict[str, Any] = {}

            def recv_udp() -> bytes:
                data, source["addr"] = sock.recvfrom(65535)
                return data
            peer = Peer(recv_udp, lambda d: sock.sendto(d, source["addr"]), sock.fileno())
            peer.run(3.0, until=lambda: "addr" in source)
        else:
            server = stack.enter_context(socket.create_server(("127.0.0.1", 0)))
            proc = stack.enter_context(vehicle("--device", f"tcp:127.0.0.1:{server.getsockname()[1]}",
                                               "--echo-frames", "--duration", "15"))
            server.settimeout(5)
            conn = stack.enter_context(server.accept()[0])
            peer = Peer(lambda: conn.recv(4096), conn.sendall, conn.fileno())
        peer.send(tunnel(peer, payload))
        peer.run(3.0, until=lambda: bool(peer.of_type("TUNNEL")) and bool(peer.of_type("HEARTBEAT")))
        stats = stop(proc, signal.SIGINT if transport == "tcp" else signal.SIGTERM)

    assert [payload_of(m) for m in peer.of_type("TUNNEL")] == [payload]
    assert peer.of_type("HEARTBEAT") and not peer.of_type("BAD_DATA")
    assert stats["tunnels_echoed"] == 1


def test_signing_signs_everything_and_rejects_unsigned_tunnels() -> None:
    port = free_udp_port()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock, \
            vehicle("--device", f"udpin:127.0.0.1:{port}", "--echo-frames", "--signing-key", KEY.hex(),
                    "--link-id", "5", "--duration", "15") as proc:
        peer = Peer(lambda: sock.recv(65535), lambda d: sock.sendto(d, ("127.0.0.1", port)), sock.fileno(),
                    key=KEY)
        outsider = mavlink2.MAVLink(None, 255, 190)
        sock.sendto(tunnel(peer, b"unsigned").pack(outsider), ("127.0.0.1", port))
        peer.send(tunnel(peer, b"signed"))
        peer.run(3.0, until=lambda: bool(peer.of_type("TUNNEL")) and len(peer.of_type("HEARTBEAT")) >= 2)
        peer.run(0.3)
        stats = stop(proc)

    assert [payload_of(m) for m in peer.of_type("TUNNEL")] == [b"signed"]
    frames = [m for m in peer.received if m.get_type() != "BAD_DATA"]
    assert frames and all(m.get_signed() and m.get_link_id() == 5 for m in frames)
    assert not peer.of_type("BAD_DATA")
    assert peer.mav.signing.goodsig_count == len(frames) and peer.mav.signing.badsig_count == 0
    assert stats["tunnels_echoed"] == 1 and stats["bad_frames"] == 1

    wrong_key = mavlink2.MAVLink(None)
    wrong_key.robust_parsing = True
    wrong_key.signing.secret_key = bytes(32)
    decoded = wrong_key.parse_buffer(frames[0].get_msgbuf()) or []
    assert [m.get_type() for m in decoded] == ["BAD_DATA"]


def test_json_tunnel_peer_stores_before_acknowledging_and_sends_back(tmp_path: Path) -> None:
    """The engine's own tunnel endpoint on one side, the vehicle process on the other: each
    message is on the robot's disk by the time the engine's send returns, comes back once and
    unchanged, and a malformed or foreign TUNNEL frame is neither stored nor answered."""
    from engine.endpoints import mavlink
    from engine.endpoints.base import Outbound
    from engine.endpoints.mavlink.tunnel import fragment

    port = free_udp_port()
    bodies = [b"{}", json.dumps({"agent_id": "uav1", "pad": "x" * 230}).encode(),
              json.dumps({"big": list(range(700))}, separators=(",", ":")).encode()]
    store = tmp_path / "robot.jsonl"

    async def scenario() -> list[bytes]:
        gcs = mavlink.TRANSPORT.connect("gcs", {"url": f"udpout:127.0.0.1:{port}"})
        await gcs.open()
        echoes: list[bytes] = []

        async def collect(inbound: Any) -> None:
            echoes.append(inbound.body)

        source = gcs.source("back", {"json_tunnel": True, "system_id": 1})
        await source.start(FunctionDeliver(collect))
        sink = gcs.sink("out", {"json_tunnel": True, "target_system": 1, "target_component": 1})
        try:
            junk = b"bad".ljust(128, b"\0")
            await gcs.send_message(mavlink2.MAVLink_tunnel_message(1, 1, 0xA900, 3, junk))
            foreign = fragment(4321, b'{"for":"uav7"}')[0]
            await gcs.send_message(mavlink2.MAVLink_tunnel_message(
                7, 1, 0xA900, len(foreign), foreign.ljust(128, b"\0")))
            for index, body in enumerate(bodies):
                await sink.send(Outbound(body, None, None, f"m{index}", {}))
                assert store.read_bytes().splitlines() == bodies[:index + 1], "stored before DELIVERED"
            await wait_for(lambda: len(echoes) >= len(bodies), 10, f"{len(bodies)} echoes", lambda: len(echoes))
            await asyncio.sleep(0.5)  # quiet window: nothing more may arrive (the behaviour under test; no event says 'nothing')
            return echoes
        finally:
            await source.stop()
            await gcs.close()

    with vehicle("--device", f"udpin:127.0.0.1:{port}", "--store", str(store), "--duration", "20") as proc:
        echoes = asyncio.run(asyncio.wait_for(scenario(), 30))
        stats = stop(proc)
    assert sorted(echoes) == sorted(bodies), "each message back exactly once, unchanged"
    assert store.read_bytes() == b"".join(body + b"\n" for body in bodies)
    assert stats["json_received"] == stats["json_echoed"] == len(bodies)
    assert stats["json_echo_failed"] == 0 and stats["tunnels_echoed"] == 0
    assert stats["tunnels_ignored"] == 1, "the frame for system 7 is not ours"
