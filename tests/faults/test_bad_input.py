"""Bad input at every source kind (hypothesis), against a real broker, real rclpy and a real
MAVLink UDP link: the engine never crashes, every bad message is dead-lettered exactly once
with its stage, the valid messages interleaved with them all arrive, exactly once."""

from __future__ import annotations

import asyncio
import json
import math
import socket
import uuid
from collections import Counter
from pathlib import Path
from typing import Any, Iterator

import aio_pika
import pytest
import rclpy
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink2
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rclpy.signals import SignalHandlerOptions

from engine.endpoints.mavlink.connection import MavlinkConnection
from engine.endpoints.ros2.rosmsg import resolve_type
from tests.support.amqp_helpers import Collector
from tests.support.faults_harness import (
    LoopThread, dead_letter_key, outputs_by_route, ros_domain, start_engine,
)
from tests.support.udp_vehicle import free_udp_port
from tests.support.waiting import wait_for

LIMIT = 16384
"""max_message_bytes of every connection here, small so oversized bodies stay cheap."""
DOMAIN = ros_domain()
String = resolve_type("std_msgs/msg/String")
NavSatFix = resolve_type("sensor_msgs/msg/NavSatFix")

ROUTES = """
connections:
  gcs: {{amqp: "{url}", max_message_bytes: {limit}}}
  ros: {{ros2: {{domain_id: {domain}, node: faults_engine}}, max_message_bytes: {limit}}}
  uav: {{mavlink: "udpin:127.0.0.1:{port}", heartbeat: 0}}
dead_letters: {{connection: gcs}}
routes:
  - name: amqp-in
    source: {{amqp: {{exchange: {inbox}, binding_key: "f.#", queue: {inbox}-q}}}}
    mapping: "{{agent_id: agent, seq: seq, lat: mul(lat, `1`), lon: lon}}"
    schema: position
    sink: {{amqp: {{exchange: {outbox}, routing_key: amqp}}}}
  - name: ros-string
    source: {{ros2: {{topic: /{tag}/json}}}}
    mapping: "{{agent_id: agent, seq: seq, lat: mul(lat, `1`), lon: lon}}"
    schema: position
    sink: {{amqp: {{exchange: {outbox}, routing_key: ros}}}}
  - name: ros-fix
    source: {{ros2: {{topic: /{tag}/fix, type: sensor_msgs/msg/NavSatFix}}}}
    mapping: "{{agent_id: header.frame_id, seq: header.stamp.sec, lat: mul(latitude, `1`), lon: longitude}}"
    schema: position
    sink: {{amqp: {{exchange: {outbox}, routing_key: fix}}}}
  - name: mav-position
    source: {{mavlink: {{connection: uav, message: GLOBAL_POSITION_INT}}}}
    mapping: "{{agent_id: 'uav7', seq: time_boot_ms, lat: deg_e7_to_deg(lat), lon: deg_e7_to_deg(lon)}}"
    schema: position
    sink: {{amqp: {{exchange: {outbox}, routing_key: mav}}}}
"""


class Harness:
    def __init__(self, url: str, workdir: Path, schemas: Path) -> None:
        self.tag = "f" + uuid.uuid4().hex[:8]
        self.inbox, self.outbox = f"{self.tag}-in", f"{self.tag}-out"
        self.port = free_udp_port()
        routes = workdir / "routes"
        routes.mkdir()
        (routes / "faults.yaml").write_text(ROUTES.format(
            url=url, limit=LIMIT, domain=DOMAIN, port=self.port, inbox=self.inbox, outbox=self.outbox, tag=self.tag))
        self.loop = LoopThread()
        self.url = url
        self.loop.run(self._clients())
        self.engine = start_engine(self.loop, routes, schemas)
        self.seq = 0
        self.expected_out: Counter[tuple[str, int]] = Counter()
        self.expected_dead: Counter[tuple[str, str, bytes]] = Counter()
        self.bad_frames = 0
        self.context = rclpy.Context()
        rclpy.init(args=[], context=self.context, domain_id=DOMAIN, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("faults_peer", context=self.context)
        qos = QoSProfile(depth=10_000, reliability=ReliabilityPolicy.RELIABLE)
        self.json_pub = self.node.create_publisher(String, f"/{self.tag}/json", qos)
        self.fix_pub = self.node.create_publisher(NavSatFix, f"/{self.tag}/fix", qos)
        self.udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.mav = mavlink2.MAVLink(None, 7, 1)
        self.loop.run(wait_for(lambda: self.json_pub.get_subscription_count() > 0
                               and self.fix_pub.get_subscription_count() > 0, 30, "ROS discovery"))

    async def _clients(self) -> None:
        self.connection = await aio_pika.connect(self.url)
        self.channel = await self.connection.channel()
        self.inbox_exchange = await self.channel.declare_exchange(self.inbox, aio_pika.ExchangeType.TOPIC, durable=True)
        self.out = await Collector.bind(self.channel, self.outbox, "#")
        self.dead = await Collector.bind(self.channel, "rabbitros.dead-letter", "#")

    def next_seq(self) -> int:
        self.seq += 1
        return self.seq

    def close(self) -> None:
        self.loop.run(self.engine.stop())
        self.loop.run(self.connection.close())
        self.loop.close()
        self.udp.close()
        self.node.destroy_node()
        self.context.try_shutdown()

    # -- checks

    def begin(self) -> None:
        """Each example is checked on its own messages, so one failure does not cascade."""
        self.out_mark, self.dead_mark = len(self.out.messages), len(self.dead.messages)
        self.example_out: Counter[tuple[str, int]] = Counter()
        self.example_dead: Counter[tuple[str, str, bytes]] = Counter()

    def settle(self, timeout: float = 60.0) -> None:
        """Wait until every expected output and dead letter arrived, then check nothing else did."""
        self.expected_out += self.example_out
        self.expected_dead += self.example_dead

        def got() -> tuple[Counter[tuple[str, int]], Counter[tuple[str, str, bytes]]]:
            return (outputs_by_route(self.out.messages[self.out_mark:]),
                    Counter(map(dead_letter_key, self.dead.messages[self.dead_mark:])))

        async def arrived() -> None:
            await wait_for(lambda: got()[0] >= self.example_out and got()[1] >= self.example_dead,
                           timeout, "every valid message and every dead letter")
            await asyncio.sleep(0.2)  # quiet window: time for a duplicate to show up

        try:
            self.loop.run(arrived(), timeout + 10)
        finally:
            got_out, got_dead = got()
            assert got_out - self.example_out == Counter(), "messages delivered that were not sent, or twice"
            assert got_dead - self.example_dead == Counter(), "dead letters that were not expected, or twice"
            assert self.example_out - got_out == Counter(), "valid messages missing"
            assert self.example_dead - got_dead == Counter(), "dead letters missing"


@pytest.fixture(scope="module")
def harness(amqp_url: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Harness]:
    from tests.support.repo import REPO

    h = Harness(amqp_url, tmp_path_factory.mktemp("faults"), REPO / "schemas")
    yield h
    h.close()


# ---------------------------------------------------------------- JSON bodies (AMQP, ROS String)

def _valid(seq: int, lat: float, lon: float, **extra: Any) -> bytes:
    return json.dumps({"agent": "uav1", "seq": seq, "lat": lat, "lon": lon, **extra}).encode()


latitudes = st.floats(-89.9, 89.9, allow_nan=False)
longitudes = st.floats(-179.9, 179.9, allow_nan=False)


@st.composite
def json_cases(draw: Any) -> tuple[str, Any]:
    """(expected stage or "ok", body builder taking the sequence number)."""
    kind = draw(st.sampled_from(["ok", "ok", "nested", "utf8", "nan", "truncated", "empty", "array",
                                 "wrong_type", "wrong_agent", "schema", "oversized"]))
    lat, lon = draw(latitudes), draw(longitudes)
    if kind == "ok":
        return "ok", lambda seq: _valid(seq, lat, lon)
    if kind == "nested":
        opener = draw(st.sampled_from([b"[", b'{"a":']))
        closer = b"]" if opener == b"[" else b"}"
        depth = draw(st.integers(500, LIMIT // (len(opener) + 1)))
        body = opener * depth + closer * depth
        return _nested_stage(body), lambda seq: body
    if kind == "utf8":
        bad = draw(st.sampled_from([b"\xff", b"\xc3\x28", b"\xed\xa0\x80", b"\xf8\x88\x80\x80\x80"]))
        return "decode", lambda seq: _valid(seq, lat, lon).replace(b'"uav1"', b'"uav' + bad + b'"')
    if kind == "nan":
        constant = draw(st.sampled_from([b"NaN", b"Infinity", b"-Infinity"]))
        return "decode", lambda seq: b'{"agent":"uav1","seq":%d,"lat":%s,"lon":0}' % (seq, constant)
    if kind == "truncated":
        cut = draw(st.floats(0.05, 0.95))
        return "decode", lambda seq: (lambda b: b[: max(1, int(len(b) * cut))])(_valid(seq, lat, lon))
    if kind == "empty":
        blank = draw(st.sampled_from([b"", b" ", b"\n"]))
        return "decode", lambda seq: blank
    if kind == "array":
        return "mapping", lambda seq: b"[" + _valid(seq, lat, lon) + b"]"
    if kind == "wrong_type":
        return "mapping", lambda seq: json.dumps({"agent": "uav1", "seq": seq, "lat": str(lat), "lon": lon}).encode()
    if kind == "wrong_agent":
        return "schema", lambda seq: json.dumps({"agent": seq, "seq": seq, "lat": lat, "lon": lon}).encode()
    if kind == "schema":
        bad_lat = draw(st.floats(90.01, 1e6, allow_nan=False))
        return "schema", lambda seq: _valid(seq, bad_lat, lon)
    size = draw(st.integers(LIMIT + 1, 4 * LIMIT))
    return "size", lambda seq: _valid(seq, lat, lon, pad="x" * size)


def _nested_stage(body: bytes) -> str:
    """Whether the engine's parser gives up (decode) or returns a value that has no fields
    for the mapping (mapping) depends on its depth limit (stdlib json, orjson's 1024), so ask it."""
    from engine.common.schemas import parse_json

    try:
        parse_json(body)
    except Exception:  # SchemaError, RecursionError: the pipeline calls both "decode"
        return "decode"
    return "mapping"


def _expect(h: Harness, route: str, out_key: str, stage: str, seq: int, body: bytes) -> None:
    if len(body) > LIMIT:
        stage = "size"  # never parsed, whatever else is wrong with it
    if stage == "ok":
        h.example_out[(out_key, seq)] += 1
    else:
        h.example_dead[(route, stage, body[:LIMIT])] += 1


FUZZ = settings(max_examples=20, deadline=None, suppress_health_check=list(HealthCheck),
                phases=(Phase.explicit, Phase.generate))
"""No shrinking: the engine's state carries over between examples, so shrinking would not
converge; a failure prints the example as generated."""


@FUZZ
@given(cases=st.lists(json_cases(), min_size=1, max_size=10))
def test_amqp_source_bad_bodies(harness: Harness, cases: list[tuple[str, Any]]) -> None:
    h = harness
    h.begin()
    messages = []
    for stage, build in cases:
        seq = h.next_seq()
        body = build(seq)
        messages.append((seq, body))
        _expect(h, "amqp-in", "amqp", stage, seq, body)

    async def publish() -> None:
        for seq, body in messages:
            await h.inbox_exchange.publish(aio_pika.Message(body, message_id=f"m{seq}"), "f.x")

    h.loop.run(publish())
    h.settle()


@FUZZ
@given(cases=st.lists(json_cases(), min_size=1, max_size=10))
def test_ros_string_source_bad_bodies(harness: Harness, cases: list[tuple[str, Any]]) -> None:
    """Serialized String messages carry any bytes, invalid UTF-8 included (as a C++ node can)."""
    h = harness
    h.begin()
    for stage, build in cases:
        seq = h.next_seq()
        body = build(seq)
        _expect(h, "ros-string", "ros", stage, seq, body)
        cdr = b"\x00\x01\x00\x00" + (len(body) + 1).to_bytes(4, "little") + body + b"\x00"
        h.json_pub.publish(cdr)
    h.settle()


@st.composite
def fix_cases(draw: Any) -> tuple[str, float, float]:
    kind = draw(st.sampled_from(["ok", "ok", "nan", "inf", "schema", "lon"]))
    lat, lon = draw(latitudes), draw(longitudes)
    if kind == "nan":
        return "mapping", math.nan, lon          # NaN becomes null (rosbridge), mul(null) fails
    if kind == "inf":
        return "mapping", draw(st.sampled_from([math.inf, -math.inf])), lon
    if kind == "schema":
        return "schema", draw(st.floats(90.01, 1e9, allow_nan=False)), lon
    if kind == "lon":
        return "schema", lat, math.nan           # null longitude: the schema wants a number
    return "ok", lat, lon


@FUZZ
@given(cases=st.lists(fix_cases(), min_size=1, max_size=10))
def test_ros_typed_source_fields_that_break_mapping_or_schema(harness: Harness, cases: list[tuple[str, float, float]]) -> None:
    h = harness
    h.begin()
    for stage, lat, lon in cases:
        seq = h.next_seq()
        msg = NavSatFix()
        msg.header.frame_id = "uav2"
        msg.header.stamp.sec = seq
        msg.latitude, msg.longitude = lat, lon
        if stage == "ok":
            h.example_out[("fix", seq)] += 1
        else:
            # the dead letter keeps the message rendered as JSON, exactly as the engine took it
            h.example_dead[("ros-fix", stage, _fix_json(serialize_message(msg)))] += 1
        h.fix_pub.publish(msg)
    h.settle()


def _fix_json(cdr: bytes) -> bytes:
    from rclpy.serialization import deserialize_message

    from engine.endpoints.ros2.rosmsg import to_dict

    return json.dumps(to_dict(deserialize_message(cdr, NavSatFix)), default=str, ensure_ascii=False).encode()


@st.composite
def mavlink_cases(draw: Any) -> tuple[str, int, int, str]:
    """(stage, lat in 1e-7 degrees, lon, damage): damage = none | crc | truncated."""
    kind = draw(st.sampled_from(["ok", "ok", "schema", "crc", "truncated"]))
    lat = draw(st.integers(-899_000_000, 899_000_000))
    lon = draw(st.integers(-1_799_000_000, 1_799_000_000))
    if kind == "schema":
        return "schema", draw(st.sampled_from([900_000_001, 2_000_000_000, -950_000_000])), lon, "none"
    if kind in ("crc", "truncated"):
        return "none", lat, lon, kind
    return "ok", lat, lon, "none"


@FUZZ
@given(cases=st.lists(mavlink_cases(), min_size=1, max_size=10))
def test_mavlink_source_bad_values_and_damaged_frames(harness: Harness, cases: list[tuple[str, int, int, str]]) -> None:
    """Frames that fail their CRC never become messages (counted on the connection); a
    truncated frame is followed by filler without a start byte, so the next frame parses."""
    h = harness
    connection = next(c for _, c in h.engine.connections.items() if c.name == "uav")
    assert isinstance(connection, MavlinkConnection), "the uav connection is the MAVLink one"
    damaged_before = connection.stats["bad_crc"] + connection.stats["bad_data"]
    damaged = 0
    h.begin()
    for stage, lat, lon, damage in cases:
        seq = h.next_seq()
        msg = h.mav.global_position_int_encode(seq, lat, lon, 1000, 500, 0, 0, 0, 0)
        frame = bytearray(msg.pack(h.mav))
        h.mav.seq = (h.mav.seq + 1) % 256
        if damage == "crc":
            frame[12] ^= 0x55
            damaged += 1
        elif damage == "truncated":
            frame = frame[: len(frame) // 2] + b"\x00" * 300
            damaged += 1
        elif stage == "ok":
            h.example_out[("mav", seq)] += 1
        else:
            fields = {"time_boot_ms": seq, "lat": lat, "lon": lon, "alt": 1000, "relative_alt": 500,
                      "vx": 0, "vy": 0, "vz": 0, "hdg": 0}
            h.example_dead[("mav-position", stage, json.dumps(fields).encode())] += 1
        h.udp.sendto(bytes(frame), ("127.0.0.1", h.port))
    h.settle()
    after = connection.stats["bad_crc"] + connection.stats["bad_data"]
    assert after - damaged_before >= damaged


def test_engine_survived_and_counted(harness: Harness) -> None:
    """After every example: all routes still run, and the counters add up."""
    h = harness
    status = h.loop.run(_status(h))
    routes = status["routes"]
    assert set(routes) == {"amqp-in", "ros-string", "ros-fix", "mav-position"}
    dead = sum(h.expected_dead.values())
    out = sum(h.expected_out.values())
    assert sum(r["failed"] for r in routes.values()) == dead
    assert sum(r["delivered"] for r in routes.values()) == out
    assert all(r["sink_errors"] == 0 and r["dropped"] == 0 for r in routes.values())
    stages: Counter[str] = Counter()
    for r in routes.values():
        stages.update(r["dead_lettered"])
    assert stages == Counter(stage for (_, stage, _), n in h.expected_dead.items() for _ in range(n))
    print(f"\nfuzz totals: {out} valid delivered, {dead} dead-lettered by stage {dict(stages)}")


async def _status(h: Harness) -> dict[str, Any]:
    """The engine's status once its routes' counters account for every example (a counter is
    updated once its message is settled, a moment after the test saw it arrive)."""
    dead, out = sum(h.expected_dead.values()), sum(h.expected_out.values())

    def counted() -> bool:
        routes = h.engine.status()["routes"].values()
        return sum(r["failed"] for r in routes) == dead and sum(r["delivered"] for r in routes) == out

    await wait_for(counted, 30, f"the routes to count {out} delivered and {dead} failed", detail=lambda: h.engine.status()["routes"])
    return h.engine.status()
