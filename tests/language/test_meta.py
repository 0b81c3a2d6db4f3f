"""``meta(name)``: where a message came from, in the mapping (issue 20).

Compiled (a slot read per message, a template variable folded to a constant), checked against
what the route's source gives (``Transport.meta_names``), given by route tests as ``meta:``,
and read from a real RabbitMQ delivery (routing key, exchange, correlation id, reply-to).
"""

from __future__ import annotations

import asyncio
import json
import uuid
from pathlib import Path

import aio_pika
import pytest

from engine.common.placeholders import MappingError
from engine.common.schemas import SchemaRegistry
from engine.language.mapping import compile_mapping, meta_names
from engine.language.routes import RoutesInvalid, load_routes
from engine.ops.route_tests import load_checked, run_tests
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector


@pytest.mark.fast
def test_meta_reads_the_message_metadata_and_folds_variables() -> None:
    mapping = compile_mapping("{key: meta('routing_key'), agent: meta('agent'), x: x}", {"agent": "robot1"})
    assert mapping({"x": 1}, {"routing_key": "fix.robot1"}) == {"key": "fix.robot1", "agent": "robot1", "x": 1}
    assert mapping({"x": 2}) == {"key": None, "agent": "robot1", "x": 2}  # no metadata: null, as a missing field
    assert meta_names("{a: meta('topic'), b: meta(topic)}") == ["topic", None]
    with pytest.raises(MappingError, match="one name in quotes"):
        compile_mapping("meta(topic)")


ROUTES = """
connections:
  gcs: {amqp: "amqp://localhost:1/"}
  ros: {ros2: {node: meta_test}}
routes:
  - name: by-key
    source: {amqp: {connection: gcs, queue: q-meta}}
    mapping: "{key: meta('routing_key'), origin: meta('exchange'), value: v}"
    schema: raw_json
    sink: {amqp: {connection: gcs, exchange: out, routing_key: "k"}}
  - name: by-topic
    source: {ros2: {connection: ros, topic: /robot1/battery, type: std_msgs/msg/Float32}}
    mapping: "{topic: meta('topic'), level: data}"
    schema: raw_json
    sink: {amqp: {connection: gcs, exchange: out, routing_key: "k"}}
"""


def _write(directory: Path, routes: str, tests: str | None = None) -> Path:
    directory.mkdir(exist_ok=True)
    (directory / "routes.yaml").write_text(routes)
    if tests is not None:
        (directory / "routes.test.yaml").write_text(tests)
    return directory


@pytest.mark.fast
def test_check_names_meta_a_source_does_not_give(tmp_path: Path, schemas_dir: Path) -> None:
    bad = ROUTES.replace("meta('routing_key')", "meta('routing_kye')").replace("meta('topic')", "meta('routing_key')")
    with pytest.raises(RoutesInvalid) as caught:
        load_routes(_write(tmp_path / "r", bad), SchemaRegistry(schemas_dir))
    messages = [problem.message for problem in caught.value.problems]
    assert any("route 'by-key': meta('routing_kye'): the amqp source gives no 'routing_kye'; did you mean 'routing_key'?" in m
               for m in messages), messages
    assert any("route 'by-topic': meta('routing_key'): the ros2 source gives no 'routing_key' (it gives topic)" in m
               for m in messages), messages
    assert len(messages) == 2, messages
    load_routes(_write(tmp_path / "ok", ROUTES), SchemaRegistry(schemas_dir))  # the names each source gives pass


TESTS = """
tests:
  - route: by-key
    input: {v: 3}
    meta: {routing_key: fix.robot7, exchange: farm}
    expect: {key: fix.robot7, origin: farm, value: 3}
  - route: by-topic
    input: {data: 0.5}
    meta: {topic: /robot1/battery}
    expect: {topic: /robot1/battery, level: 0.5}
"""


@pytest.mark.fast
def test_route_tests_give_meta(tmp_path: Path, schemas_dir: Path) -> None:
    schemas = SchemaRegistry(schemas_dir)
    config, cases, problems, _ = load_checked(_write(tmp_path / "r", ROUTES, TESTS), schemas)
    assert config is not None and not problems, problems
    results = list(run_tests(cases, config, schemas))
    assert [r.reason for r in results if not r.passed] == []
    assert len(results) == 2

    misspelt = TESTS.replace("meta: {topic:", "meta: {topik:")
    _, _, problems, _ = load_checked(_write(tmp_path / "r2", ROUTES, misspelt), schemas)
    assert [p.message for p in problems] == [
        "meta 'topik': the ros2 source of route 'by-topic' gives no 'topik'; did you mean 'topic'?"]


AMQP_ROUTES = """
connections:
  gcs: {{amqp: "{url}"}}
routes:
  - name: origin
    source: {{amqp: {{connection: gcs, exchange: {inbox}, binding_key: "fix.#", queue: {queue}}}}}
    mapping: "{{agent: meta('routing_key'), via: meta('exchange'), correlation: meta('correlation_id'),
               reply: meta('reply_to'), id: meta('message_id'), source: meta('headers').source, lat: lat}}"
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: {outbox}, routing_key: "out"}}}}
"""


def test_meta_from_a_real_amqp_delivery(tmp_path: Path, schemas_dir: Path, amqp_url: str) -> None:
    tag = uuid.uuid4().hex[:8]
    names = {"inbox": f"in-{tag}", "outbox": f"out-{tag}", "queue": f"q-{tag}"}
    directory = _write(tmp_path / "routes", AMQP_ROUTES.format(url=amqp_url, **names))

    async def scenario() -> list[dict]:
        engine = Engine(directory, schemas_dir)
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            output = await Collector.bind(channel, names["outbox"], "out")
            inbox = await channel.declare_exchange(names["inbox"], aio_pika.ExchangeType.TOPIC, durable=True)
            for robot in range(3):
                await inbox.publish(aio_pika.Message(
                    json.dumps({"lat": robot}).encode(), message_id=f"m{robot}", correlation_id=f"c{robot}",
                    reply_to="replies", headers={"source": f"field-{robot}"}), f"fix.robot{robot}")
            received = await output.wait_for(3)
        finally:
            await connection.close()
            await engine.stop()
        return [json.loads(m.body) for m in received]

    got = sorted(asyncio.run(scenario()), key=lambda m: m["lat"])
    assert got == [{"agent": f"fix.robot{i}", "via": names["inbox"], "correlation": f"c{i}", "reply": "replies",
                    "id": f"m{i}", "source": f"field-{i}", "lat": i} for i in range(3)]
