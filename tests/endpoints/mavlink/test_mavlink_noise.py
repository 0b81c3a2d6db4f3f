"""Frames that survive noise (issue 31): good GLOBAL_POSITION_INT frames among noise reach
RabbitMQ, every one of them, and the noise is counted as bad frames in ``/metrics``.

Real parts: the engine (in process, with its admin endpoint), a private RabbitMQ node, a plain
UDP socket and pymavlink as the vehicle, the emulated SiK radio pair (rabbitros_sim/sik_radio.py).

* ``udpin``: 500 good frames among 20,000 noise datagrams (random bytes, frames with a damaged
  byte, frames cut short, lone start bytes ``FD 1E``), the datagram just before each good frame
  always a partial frame. Before the engine cut frames itself, the partial frame at the end of
  one datagram was joined to the next and swallowed the good frame in it: 1 of 500 arrived with
  a lone ``FD 1E`` after each frame (issue 31).
* The SiK radio: 500 good frames written to the far radio's serial port with noise bytes
  between them (random bytes, damaged and cut frames, lone start bytes); pymavlink's stream
  parser threw a good frame away whenever a false start byte's length reached into it (34 of
  500 arrived). The radio injects no RADIO_STATUS here: noise misleads its MAVLink-aware packet
  forming, and a RADIO_STATUS injected between two air packets then lands inside a good frame,
  which no parser can mend (with one every 0.5 s, 490-497 of 500 arrived; the same bytes
  captured and parsed offline gave 495, and with the RADIO_STATUS frames cut out they were
  exactly the bytes written).
"""

from __future__ import annotations

import asyncio
import json
import os
import random
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import aiohttp
import aio_pika
from prometheus_client.parser import text_string_to_metric_families

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from engine.ops.admin import AdminServer  # noqa: E402
from engine.running.runtime import Engine  # noqa: E402
from rabbitros_sim.sik_radio import SikRadioPair  # noqa: E402
from rabbitros_sim.vehicle import open_serial  # noqa: E402
from tests.support.amqp_helpers import Collector  # noqa: E402
from tests.support.udp_vehicle import free_udp_port, mavlink_connection, telemetry_routes  # noqa: E402
from tests.support.waiting import wait_for  # noqa: E402

GOOD = 500
NOISE_PER_FRAME = 40
BAD_FRAMES = ("bad_crc", "bad_data", "truncated")
LONE_STARTS = (b"\xfd\x1e", b"\xfd", b"\xfe", b"\xfd\x1e\x00")


class Vehicle:
    """A pymavlink sender (system 1, component 1): good frames carry their index in
    ``time_boot_ms``; damaged copies carry 1,000,000 + index, so one that got through shows."""

    def __init__(self, seed: int) -> None:
        self.mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
        self.rng = random.Random(seed)
        self.made: dict[str, int] = dict.fromkeys(("random", "damaged", "cut", "lone"), 0)

    def frame(self, index: int) -> bytes:
        msg = self.mav.global_position_int_encode(index, -220000000, -479000000, 10000, 5000, 1, 2, 3, 9000)
        data: bytes = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        return data

    def noise(self, partial: bool = False) -> bytes:
        """One piece of noise; ``partial``: a frame cut short or a lone start byte."""
        kind = self.rng.choice(("cut", "lone") if partial else ("random", "damaged", "cut", "lone"))
        self.made[kind] += 1
        rng = self.rng
        if kind == "random":  # never starting with a start byte, so each is one bad run at least
            return bytes([rng.randrange(0xFD)]) + rng.randbytes(rng.randrange(0, 80))
        if kind == "lone":
            return rng.choice(LONE_STARTS)
        frame = bytearray(self.frame(1_000_000 + rng.randrange(1000)))
        if kind == "cut":
            return bytes(frame[:rng.randrange(1, len(frame))])
        at = rng.randrange(10, len(frame))  # a payload or checksum byte: the CRC must fail
        frame[at] ^= rng.randrange(1, 256)
        return bytes(frame)


async def scrape(admin: AdminServer) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    async with aiohttp.ClientSession() as session:
        async with session.get(f"http://127.0.0.1:{admin.port}/metrics") as response:
            assert response.status == 200
            text = await response.text()
    return {(sample.name, tuple(sorted(sample.labels.items()))): sample.value
            for family in text_string_to_metric_families(text) for sample in family.samples}


def bad_frames(metrics: dict[tuple[str, tuple[tuple[str, str], ...]], float], connection: str) -> dict[str, float]:
    found = {dict(labels)["reason"]: value for (name, labels), value in metrics.items()
             if name == "rabbitros_link_bad_frames_total" and dict(labels).get("connection") == connection}
    assert set(found) == set(BAD_FRAMES), f"/metrics has no bad frames of {connection!r} by reason: {found}"
    return found


def delivered(collector: Collector) -> list[int]:
    return sorted(json.loads(m.body)["seq"] for m in collector.messages)


async def run_engine(routes: str, tmp_path: Path, schemas_dir: Path, amqp_url: str, exchange: str,
                     traffic: Callable[[Engine], Any]) -> tuple[list[int], dict[Any, float]]:
    """Start the engine on ``routes`` with its admin endpoint, run ``traffic(engine)``, wait for
    the telemetry on ``exchange``; the sequence numbers delivered and /metrics after."""
    directory = tmp_path / "routes"
    directory.mkdir()
    (directory / "noise.yaml").write_text(routes)
    engine = Engine(directory, schemas_dir)
    admin = AdminServer(engine, "127.0.0.1", 0)
    client = await aio_pika.connect(amqp_url)
    try:
        collector = await Collector.bind(await client.channel(), exchange, "telemetry")
        await engine.start()
        await admin.start()
        try:
            await traffic(engine)
            await collector.wait_for(GOOD, timeout=5)
            return delivered(collector), await scrape(admin)
        finally:
            await admin.stop()
            await engine.stop(drain_timeout=2.0)
    finally:
        await client.close()


def test_udpin_delivers_every_good_frame_among_20000_noise_datagrams(tmp_path: Path, schemas_dir: Path,
                                                                     amqp_url: str) -> None:
    port = free_udp_port()
    exchange = f"noise-{os.getpid()}-{port}"
    vehicle = Vehicle(seed=31)
    sent = {"bytes": 0, "datagrams": 0}

    async def traffic(engine: Engine) -> None:
        radio = mavlink_connection(engine, "radio")
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.setblocking(False)
            for index in range(GOOD):
                noise = [vehicle.noise() for _ in range(NOISE_PER_FRAME - 1)] + [vehicle.noise(partial=True)]
                for datagram in (vehicle.frame(index), *noise):
                    sock.sendto(datagram, ("127.0.0.1", port))
                    sent["bytes"] += len(datagram)
                    sent["datagrams"] += 1
                # flow control instead of a rate: what the kernel dropped would not be noise's doing
                await wait_for(lambda: sent["bytes"] - radio.stats["bytes_received"] < 32_768, 30, "the engine reading")
            await wait_for(lambda: radio.stats["bytes_received"] == sent["bytes"], 30, "every datagram read")

    routes = telemetry_routes(amqp_url, exchange, port, heartbeat=0)
    seqs, metrics = asyncio.run(asyncio.wait_for(
        run_engine(routes, tmp_path, schemas_dir, amqp_url, exchange, traffic), 240))

    assert len(seqs) == GOOD and seqs == list(range(GOOD)), \
        f"{len(seqs)} of {GOOD} good frames delivered ({len(set(seqs))} distinct)"
    bad = bad_frames(metrics, "radio")
    made = vehicle.made
    assert sent["datagrams"] == GOOD * (NOISE_PER_FRAME + 1)
    assert bad["bad_crc"] >= made["damaged"], (bad, made)
    assert bad["truncated"] >= made["cut"] + made["lone"], (bad, made)
    assert bad["bad_data"] >= made["random"], (bad, made)
    assert sum(bad.values()) >= GOOD * NOISE_PER_FRAME, (bad, made)
    accepted = metrics[("rabbitros_link_frames_accepted_total", (("connection", "radio"),))]
    assert accepted == GOOD, accepted


SERIAL_ROUTES = """
connections:
  gcs: {{amqp: "{amqp}"}}
  radio: {{mavlink: "{device}", baud: 57600, heartbeat: 0}}
routes:
  - name: telemetry
    source: {{mavlink: {{connection: radio, message: GLOBAL_POSITION_INT}}}}
    mapping: "{{seq: time_boot_ms}}"
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: {exchange}, routing_key: telemetry}}}}
"""
HELD_AT_MOST = 1.5
"""Seconds a good frame behind a false start byte may wait on a quiet link: the 0.5 s after
which a stream gives a frame up, and slack for a loaded machine."""
RADIO_BACKLOG = 1024
"""Bytes written to the far radio that it has not put on the air yet, at most: below its 2 KB
buffer, so nothing is lost to an overflowing radio (a rate would depend on the machine's load)."""


def test_sik_radio_delivers_good_frames_with_noise_bytes_between_them(tmp_path: Path, schemas_dir: Path,
                                                                      amqp_url: str) -> None:
    exchange = f"sik-noise-{os.getpid()}-{time.monotonic_ns()}"
    vehicle = Vehicle(seed=57)
    written = {"bytes": 0}
    radio_stats: dict[str, Any] = {}

    async def traffic(engine: Engine, pair: SikRadioPair) -> None:
        fd = open_serial(pair.link_b)

        async def write(data: bytes) -> None:
            view = memoryview(data)
            while view:
                with_room = lambda: written["bytes"] - pair.stats()["b"].air_bytes < RADIO_BACKLOG  # noqa: E731
                await wait_for(with_room, 30, "the radio sending")
                try:
                    count = os.write(fd, view)
                except BlockingIOError:
                    count = 0
                written["bytes"] += count
                view = view[count:]
                try:
                    os.read(fd, 4096)  # nothing is sent this way, but keep the pty drained
                except OSError:
                    pass

        try:
            for index in range(GOOD):
                gap = b"".join(vehicle.noise() for _ in range(vehicle.rng.randrange(0, 3)))
                await write(vehicle.frame(index) + gap + vehicle.noise(partial=True))
            # a start byte in the last noise claims up to 280 bytes: a stream parser waits for them
            await write(bytes(300))
            await wait_for(lambda: pair.stats()["b"].air_bytes >= written["bytes"], 30, "everything on the air")
        finally:
            os.close(fd)
        radio_stats.update(pair.stats()["b"].__dict__)

    async def scenario() -> tuple[list[int], dict[Any, float]]:
        async with SikRadioPair(str(tmp_path / "gcs"), str(tmp_path / "uav"), loss=0.0, seed=5,
                                radio_status_interval=None) as pair:
            routes = SERIAL_ROUTES.format(amqp=amqp_url, device=pair.link_a, exchange=exchange)
            return await run_engine(routes, tmp_path, schemas_dir, amqp_url, exchange,
                                    lambda engine: traffic(engine, pair))

    seqs, metrics = asyncio.run(asyncio.wait_for(scenario(), 240))
    print(f"SiK radio with noise: {len(seqs)}/{GOOD} delivered; radio: {radio_stats}; noise made {vehicle.made}")
    assert radio_stats["serial_rx_dropped"] == 0 and radio_stats["air_packets_lost"] == 0, radio_stats
    assert len(seqs) == GOOD and seqs == list(range(GOOD)), \
        f"{len(seqs)} of {GOOD} good frames delivered ({len(set(seqs))} distinct)"
    bad = bad_frames(metrics, "radio")
    print(f"bad frames {bad}")
    assert sum(bad.values()) >= sum(vehicle.made.values()) * 0.5, (bad, vehicle.made)


def test_a_false_start_byte_on_a_quiet_serial_link_holds_the_frame_behind_it_briefly(
        tmp_path: Path, schemas_dir: Path, amqp_url: str) -> None:
    """``FD FF 00`` claims a 267-byte frame: on a link that carries a frame a second, a stream
    parser that waits for those bytes holds the good frames behind them for seconds (pymavlink
    does, for as long as it takes). The engine gives the waiting frame up after 0.5 s
    (engine/endpoints/mavlink/port.py ``STALE_FRAME_S``) and finds the good frame inside it."""
    exchange = f"quiet-{os.getpid()}-{time.monotonic_ns()}"
    vehicle = Vehicle(seed=3)
    master, slave = os.openpty()
    found: dict[str, Any] = {}

    async def scenario() -> None:
        directory = tmp_path / "routes"
        directory.mkdir()
        (directory / "quiet.yaml").write_text(
            SERIAL_ROUTES.format(amqp=amqp_url, device=os.ttyname(slave), exchange=exchange))
        engine = Engine(directory, schemas_dir)
        client = await aio_pika.connect(amqp_url)
        try:
            collector = await Collector.bind(await client.channel(), exchange, "telemetry")
            await engine.start()
            try:
                radio = mavlink_connection(engine, "radio")
                for index in range(3):
                    written = time.monotonic()
                    os.write(master, b"\xfd\xff\x00" + vehicle.frame(index))
                    arrived = lambda count=index + 1: len(collector.messages) >= count  # noqa: E731
                    await wait_for(arrived, 5, f"frame {index} behind a false start byte")
                    found.setdefault("held", []).append(time.monotonic() - written)
                found["truncated"] = radio.stats["truncated"]
                status = vehicle.mav.radio_status_encode(190, 180, 80, 40, 42, 17, 3)  # rxerrors 17, fixed 3
                os.write(master, status.pack(vehicle.mav))
                samples = lambda: {m.name: m.value for m in radio.metrics() if m.name.startswith("link_radio")}  # noqa: E731
                await wait_for(lambda: bool(samples()), 5, "the radio's RADIO_STATUS")
                found["radio"] = samples()
                found["seqs"] = delivered(collector)
            finally:
                await engine.stop(drain_timeout=1.0)
        finally:
            await client.close()

    try:
        asyncio.run(asyncio.wait_for(scenario(), 60))
    finally:
        os.close(master)
        os.close(slave)
    print(f"held behind a false start byte: {[round(h, 2) for h in found['held']]} s")
    assert found["seqs"] == [0, 1, 2]
    assert all(held < HELD_AT_MOST for held in found["held"]), found["held"]
    assert found["truncated"] == 3
    assert found["radio"] == {"link_radio_rxerrors": 17, "link_radio_fixed": 3}
