"""Conditions (``when:``): a route sends only what its condition accepts; the rest is settled
(acknowledged at the source), counted ``filtered`` in the one counter set, never dead-lettered.

Real parts: a private RabbitMQ node (tests/conftest.py), the engine in process; ``check`` and
``rabbitros-engine test`` as an operator runs them."""

from __future__ import annotations

import asyncio
import json
import uuid
from pathlib import Path
from typing import Any

import aio_pika
import pytest
from prometheus_client import CollectorRegistry, generate_latest

from engine.common.schemas import SchemaRegistry
from engine.language.routes import RoutesInvalid, load_routes
from engine.ops.admin import EngineCollector, status_document
from engine.ops.cli import main
from engine.running.observe import COUNTERS, Tap
from engine.running.pipeline import passes
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector, message_count
from tests.support.repo import REPO
from tests.support.waiting import wait_for

ROUTE = """
connections:
  broker: {{amqp: "{url}"}}
routes:
  - name: confident
    source: {{amqp: {{exchange: {tag}-in, binding_key: "d.#", queue: {tag}-q}}}}
    mapping: "{{agent_id: agent, confidence: confidence}}"
    schema: raw_json
    when: {when}
    sink: {{amqp: {{exchange: {tag}-out, routing_key: "out.{{agent_id}}"}}}}
"""


@pytest.mark.fast
def test_jmespath_truth_is_the_specifications() -> None:
    falsy: tuple[Any, ...] = (None, False, "", [], {})
    truthy: tuple[Any, ...] = (0, 0.0, True, "x", [0], {"a": None})
    assert [passes(v) for v in falsy] == [False] * 5
    assert [passes(v) for v in truthy] == [True] * 6


@pytest.mark.parametrize(("when", "expected"), [
    ("'confidence >'", "bad JMESPath"),
    ("'confidance_max(confidence)'", "unknown function confidance_max()"),
    ("\"meta('topik')\"", "meta('topik'): the amqp source gives no 'topik'"),
])
@pytest.mark.fast
def test_check_refuses_a_bad_condition_with_file_and_line(tmp_path: Path, when: str, expected: str) -> None:
    (tmp_path / "r.yaml").write_text(ROUTE.format(url="amqp://127.0.0.1:1", tag="t", when=when))
    with pytest.raises(RoutesInvalid) as raised:
        load_routes(tmp_path, SchemaRegistry(REPO / "schemas"))
    problems = [str(p) for p in raised.value.problems]
    assert any(p.startswith(f"{tmp_path / 'r.yaml'}:9: route 'confident': ") and expected in p for p in problems), problems


@pytest.mark.fast
def test_a_route_test_expresses_a_filtered_case(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "r.yaml").write_text(ROUTE.format(url="amqp://127.0.0.1:1", tag="t", when="'confidence > `0.8`'"))
    (tmp_path / "r.test.yaml").write_text("""
tests:
  - name: a sure one is sent
    route: confident
    input: {agent: uav1, confidence: 0.9}
    expect: {agent_id: uav1, confidence: 0.9}
  - name: a doubtful one is filtered
    route: confident
    input: {agent: uav1, confidence: 0.5}
    expect_filtered: true
  - name: wrong on purpose
    route: confident
    input: {agent: uav1, confidence: 0.95}
    expect_filtered: true
  - name: wrong the other way
    route: confident
    input: {agent: uav1, confidence: 0.1}
    expect: {agent_id: uav1, confidence: 0.1}
""")
    assert main(["test", "--routes", str(tmp_path), "--schemas", str(REPO / "schemas")]) == 1
    out = capsys.readouterr().out
    assert "ok    " in out and "a doubtful one is filtered" in out
    assert "wrong on purpose: expected the route's when: to reject the message, but it passed" in out
    assert "wrong the other way: the route's when: rejected the message (filtered: nothing sent)" in out
    assert "2 passed, 2 failed" in out


def test_filtered_messages_are_settled_counted_and_never_dead_lettered(tmp_path: Path, amqp_url: str) -> None:
    tag = "w" + uuid.uuid4().hex[:8]
    (tmp_path / "r.yaml").write_text(ROUTE.format(url=amqp_url, tag=tag, when="'confidence > `0.7` && agent_id != ''uav9'''"))
    sent: list[dict[str, Any]] = [{"agent": f"uav{i % 10}", "confidence": (i % 10) / 10} for i in range(100)]
    passing = [m for m in sent if m["confidence"] > 0.7 and m["agent"] != "uav9"]  # uav8 only: 10 of 100
    assert len(passing) == 10

    async def scenario() -> tuple[list[dict], dict, str, int, int]:
        engine = Engine(tmp_path, REPO / "schemas")
        await engine.start()
        try:
            connection = await aio_pika.connect(amqp_url)
            async with connection:
                channel = await connection.channel(publisher_confirms=True)
                out = await Collector.bind(channel, f"{tag}-out")
                dead = await Collector.bind(channel, "rabbitros.dead-letter", "confident")
                exchange = await channel.declare_exchange(f"{tag}-in", aio_pika.ExchangeType.TOPIC, durable=True)
                tap = Tap("confident")
                engine.observers.get("confident").attach(tap)
                for message in sent:
                    await exchange.publish(aio_pika.Message(json.dumps(message).encode()), "d.x")
                observer = engine.observers.get("confident")
                await wait_for(lambda: observer.filtered + observer.delivered == len(sent), 30,
                               f"all {len(sent)} messages filtered or delivered",
                               lambda: f"filtered {observer.filtered}, delivered {observer.delivered}")
                await out.wait_for(len(passing), 10)
                status = status_document(engine)["routes"]["confident"]
                registry = CollectorRegistry()
                registry.register(EngineCollector(engine))
                metrics = generate_latest(registry).decode()
                queue = await channel.declare_queue(f"{tag}-q", passive=True)
                left = message_count(queue)
                lines = [json.loads(tap.lines.get_nowait()) for _ in range(tap.lines.qsize())]
                filtered = [line["canonical"] for line in lines if line["outcome"] == "filtered"]
                assert filtered == [{"agent_id": m["agent"], "confidence": m["confidence"]} for m in sent if m not in passing], filtered
                return [json.loads(m.body) for m in out.messages], status, metrics, left, len(dead.messages)
        finally:
            await engine.stop()

    delivered, status, metrics, left, dead = asyncio.run(asyncio.wait_for(scenario(), 120))
    assert delivered == [{"agent_id": m["agent"], "confidence": m["confidence"]} for m in passing]
    assert (status["received"], status["delivered"], status["filtered"], status["failed"]) == (100, 10, 90, 0), status
    assert status["messages"]["filtered"] == 90 and "filtered" in COUNTERS
    assert 'rabbitros_messages_total{outcome="filtered",route="confident"} 90.0' in metrics, metrics
    assert left == 0 and dead == 0  # every filtered message acknowledged at the source, none dead-lettered
