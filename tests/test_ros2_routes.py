"""Routes through the ros2 endpoint inside the engine: typed conversion both ways, failures
counted while valid messages keep flowing, and check errors that name the route."""

from __future__ import annotations

import asyncio
import json
import os
import uuid
from pathlib import Path

import aio_pika
import pytest

import rclpy  # noqa: F401,E402  (a missing rclpy fails the run, never skips it)

from engine.schemas import canonical_bytes  # noqa: E402
from engine.runtime import Engine  # noqa: E402
from tests.amqp_helpers import Collector, publish  # noqa: E402
from tests.test_cli import cli  # noqa: E402
from tests.conftest import REPO  # noqa: E402

TYPED = """
connections:
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
routes:
  - name: position-to-ros
    source:
      amqp: {{exchange: {inbox}, binding_key: position, queue: {inbox}-q}}
    schema: position
    sink:
      ros2: {{topic: /{tag}/fix, type: sensor_msgs/msg/NavSatFix}}
      mapping: "{{header: {{frame_id: agent_id}}, latitude: lat, longitude: lon, altitude: alt_msl}}"
  - name: position-from-ros
    source:
      ros2: {{topic: /{tag}/fix, type: sensor_msgs/NavSatFix}}
    mapping: "{{agent_id: header.frame_id, lat: latitude, lon: longitude, alt_msl: altitude}}"
    schema: position
    sink:
      amqp: {{exchange: {outbox}, routing_key: "canonical.position.{{agent_id}}"}}
"""


@pytest.fixture
def typed_routes(tmp_path: Path, amqp_url: str, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, dict[str, str]]:
    monkeypatch.setenv("RABBITROS_AMQP_URL", amqp_url)
    tag = "t" + uuid.uuid4().hex[:8]
    names = {"tag": tag, "inbox": f"in-{tag}", "outbox": f"out-{tag}", "domain": str(101 + os.getpid() % 100)}
    (tmp_path / "typed.yaml").write_text(TYPED.format(**names))
    return tmp_path, names


def test_canonical_position_through_navsatfix_and_back_is_byte_identical(typed_routes, amqp_url):
    directory, names = typed_routes
    positions = [
        {"agent_id": f"uav{i % 2}", "alt_msl": 600.0 + i / 3, "lat": -22.0 + i * 1.1e-7, "lon": -47.9 - 1 / (i + 3)}
        for i in range(50)
    ]
    originals = [canonical_bytes(p) for p in positions]

    async def scenario() -> list[bytes]:
        engine = Engine(directory, REPO / "schemas")
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            output = await Collector.bind(channel, names["outbox"], "canonical.position.#")
            await asyncio.sleep(1.0)
            await publish(channel, names["inbox"], "position", originals)
            received = await output.wait_for(len(originals), timeout=30)
        finally:
            await connection.close()
            await engine.stop()
        return [m.body for m in received]

    assert sorted(asyncio.run(scenario())) == sorted(originals)


def test_unmappable_ros_message_is_counted_and_the_next_one_flows(typed_routes, amqp_url):
    """A NavSatFix with a NaN latitude becomes null, which the position schema rejects."""
    directory, names = typed_routes
    good = canonical_bytes({"agent_id": "uav1", "alt_msl": 1.5, "lat": 1.25, "lon": 2.5})
    bad_fix_source = json.dumps({"agent_id": "uav1", "alt_msl": 1.5, "lat": 1.25, "lon": 2.5}).encode()

    async def scenario() -> tuple[list[bytes], list[aio_pika.abc.AbstractIncomingMessage], dict]:
        engine = Engine(directory, REPO / "schemas")
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            output = await Collector.bind(channel, names["outbox"], "canonical.position.#")
            dead = await Collector.bind(channel, "rabbitros.dead-letter", "position-from-ros")
            await asyncio.sleep(1.0)
            sink = engine.runners["position-to-ros"].pipeline.sink
            from engine.endpoints.base import Outbound

            nan_fix = {"header": {"frame_id": "uav1"}, "latitude": float("nan"), "longitude": 2.5, "altitude": 1.5}
            await sink.send(Outbound(bad_fix_source, {}, nan_fix, "bad", {"route": "t", "generation": 0}))
            await publish(channel, names["inbox"], "position", [good])
            received = await output.wait_for(1, timeout=20)
            dead_letters = await dead.wait_for(1, timeout=10)
            return [m.body for m in received], dead_letters, engine.status()
        finally:
            await connection.close()
            await engine.stop()

    received, dead_letters, status = asyncio.run(scenario())
    assert received == [good]
    assert status["routes"]["position-from-ros"]["failed"] == 1
    assert len(dead_letters) == 1
    assert dead_letters[0].headers["x-rabbitros-stage"] == "schema"
    assert "$.lat" in dead_letters[0].headers["x-rabbitros-error"]


def test_check_names_the_route_for_uninstalled_type_and_bad_field(tmp_path: Path):
    (tmp_path / "ros.yaml").write_text("""
routes:
  - name: no-such-type
    source: {amqp: {queue: q1}}
    schema: raw_json
    sink: {ros2: {topic: /x, type: farm_msgs/msg/Weed}}
  - name: bad-field
    source: {amqp: {queue: q2}}
    schema: position
    sink:
      ros2: {topic: /fix, type: sensor_msgs/msg/NavSatFix}
      mapping: "{latitude: lat, longtitude: lon}"
""")
    result = cli("check", "--routes", str(tmp_path), "--schemas", str(REPO / "schemas"))
    assert result.returncode != 0
    lines = result.stderr.strip().splitlines()
    assert any("'no-such-type'" in line and "farm_msgs/msg/Weed" in line and "ros.yaml:6:" in line for line in lines), lines
    assert any("'bad-field'" in line and "longtitude" in line for line in lines), lines
