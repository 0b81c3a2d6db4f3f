"""AMQP -> mapping -> schema -> AMQP through a real RabbitMQ node."""

from __future__ import annotations

import asyncio
import json
import uuid
from pathlib import Path

import aio_pika
import pytest

from engine.common.schemas import canonical_bytes
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector, header_text, publish

ROUTES = """
connections:
  gcs: {{amqp: "${{TEST_AMQP_URL}}"}}
routes:
  - name: weeds
    source:
      amqp: {{connection: gcs, exchange: {inbox}, binding_key: "weeds.#", queue: {queue}}}
    mapping: "{{agent_id: agent, points: detections[].{{lat: lat, lon: lon, p: confidence}}}}"
    schema: weed_detection
    sink:
      amqp: {{connection: gcs, exchange: {outbox}, routing_key: "canonical.weeds.{{agent_id}}"}}
  - name: passthrough
    source:
      amqp: {{connection: gcs, exchange: {inbox}, binding_key: "raw.#", queue: {queue}-raw}}
    schema: raw_json
    sink:
      amqp: {{connection: gcs, exchange: {outbox}, routing_key: "raw.out"}}
"""


def detection(index: int) -> dict:
    return {
        "agent": f"uav{index % 3}",
        "seq": index,
        "detections": [
            {"lat": -22.0 + index * 1e-6, "lon": -47.9, "confidence": 0.5 + (index % 50) / 100, "bbox": [1, 2]},
        ],
    }


def expected_canonical(message: dict) -> bytes:
    """Computed here independently of the engine's mapping code."""
    points = [{"lat": d["lat"], "lon": d["lon"], "p": d["confidence"]} for d in message["detections"]]
    return json.dumps({"agent_id": message["agent"], "points": points}, sort_keys=True, separators=(",", ":")).encode()


@pytest.fixture
def routes_dir(tmp_path: Path, amqp_url: str, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, dict[str, str]]:
    monkeypatch.setenv("TEST_AMQP_URL", amqp_url)
    tag = uuid.uuid4().hex[:8]
    names = {"inbox": f"in-{tag}", "outbox": f"out-{tag}", "queue": f"q-{tag}"}
    directory = tmp_path / "routes"
    directory.mkdir()
    (directory / "farm.yaml").write_text(ROUTES.format(**names))
    return directory, names


def test_hundred_messages_mapped_validated_and_routed(routes_dir, schemas_dir, amqp_url):
    directory, names = routes_dir

    async def scenario() -> None:
        engine = Engine(directory, schemas_dir)
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            output = await Collector.bind(channel, names["outbox"], "canonical.weeds.#")
            dead = await Collector.bind(channel, "rabbitros.dead-letter", "weeds")
            messages = [detection(i) for i in range(100)]
            bad_schema = {"agent": "uav9", "detections": [{"lat": 95.0, "lon": 0, "confidence": 0.4}]}
            bodies = [json.dumps(m).encode() for m in messages[:50]]
            bodies += [json.dumps(bad_schema).encode(), b"{not json"]
            bodies += [json.dumps(m).encode() for m in messages[50:]]
            await publish(channel, names["inbox"], "weeds.uav", bodies)

            received = await output.wait_for(100)
            dead_letters = await dead.wait_for(2)
            await asyncio.sleep(0.3)  # quiet window: nothing more may arrive (the behaviour under test; no event says 'nothing')
        finally:
            await connection.close()
            await engine.stop()

        assert len(received) == 100
        got = {m.message_id: m for m in received}
        for index, message in enumerate(messages):
            wire_index = index if index < 50 else index + 2
            out = got[f"m{wire_index}"]
            assert out.body == expected_canonical(message)
            assert out.routing_key == f"canonical.weeds.{message['agent']}"
            assert out.content_type == "application/json"
            assert out.delivery_mode == aio_pika.DeliveryMode.PERSISTENT
        assert len(dead_letters) == 2
        stages = sorted(header_text(m, "x-rabbitros-stage") for m in dead_letters)
        assert stages == ["decode", "schema"]
        schema_failure = next(m for m in dead_letters if m.headers["x-rabbitros-stage"] == "schema")
        assert schema_failure.body == json.dumps(bad_schema).encode()
        assert "$.points[0].lat" in header_text(schema_failure, "x-rabbitros-error")
        assert schema_failure.headers["x-rabbitros-route"] == "weeds"
        stats = engine.status()
        assert stats["generation"] == 1

    asyncio.run(scenario())


def test_identity_route_forwards_original_bytes(routes_dir, schemas_dir, amqp_url):
    directory, names = routes_dir
    original = b'{ "z": 1,  "a": [1.50, "\\u00e9"] }'

    async def scenario() -> list[aio_pika.abc.AbstractIncomingMessage]:
        engine = Engine(directory, schemas_dir)
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            output = await Collector.bind(channel, names["outbox"], "raw.out")
            await publish(channel, names["inbox"], "raw.x", [original])
            return await output.wait_for(1)
        finally:
            await connection.close()
            await engine.stop()

    received = asyncio.run(scenario())
    assert [m.body for m in received] == [original]


def test_messages_queued_while_engine_is_down_are_delivered_after_restart(routes_dir, schemas_dir, amqp_url):
    """Acks follow the sink: stopping mid-stream loses nothing, the queue keeps the rest."""
    TOTAL = 3000
    directory, names = routes_dir

    async def scenario() -> set[str | None]:
        connection = await aio_pika.connect(amqp_url)
        channel = await connection.channel()
        output = await Collector.bind(channel, names["outbox"], "canonical.weeds.#")
        engine = Engine(directory, schemas_dir)
        await engine.start()
        await engine.stop()
        await publish(channel, names["inbox"], "weeds.a", [json.dumps(detection(i)).encode() for i in range(TOTAL)])
        engine = Engine(directory, schemas_dir)
        await engine.start()
        await output.wait_for(50)
        await engine.stop()
        partial = len(output.messages)
        engine = Engine(directory, schemas_dir)
        await engine.start()
        try:
            await output.wait_for(TOTAL)
        finally:
            await engine.stop()
            await connection.close()
        assert partial < TOTAL, "engine stopped after all messages: the test proves nothing"
        return {m.message_id for m in output.messages}

    assert asyncio.run(scenario()) == {f"m{i}" for i in range(TOTAL)}


def test_canonical_bytes_are_deterministic():
    assert canonical_bytes({"b": 1, "a": "é"}) == '{"a":"é","b":1}'.encode()
    with pytest.raises(ValueError):
        canonical_bytes({"x": float("nan")})
