"""Partitioned ordered routes on one real RabbitMQ node: the key taken from a header spreads the
agents over the partitions and keeps each agent's order; the topology follows a reload (fewer
partitions: the extra queues go; another key: another exchange, the old one goes; no route: the
exchange and the queues go); two engine
processes share the partitions, and one stopped cleanly mid-stream hands its partitions over
without a single duplicate or a message out of order."""

from __future__ import annotations

import asyncio
import json
import time
import uuid
from pathlib import Path
from typing import Any

import aio_pika
import aiormq.exceptions
import pytest

from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector, started_with_client
from tests.support.engine_process import EngineProcess
from tests.support.waiting import wait_for

ROUTES = """
connections:
  gcs: {{amqp: "${{TEST_AMQP_URL}}"}}
routes:
  - name: parts-{tag}
    ordered: {{partitions: {partitions}, key: {key}}}
    source: {{amqp: {{exchange: in-{tag}, prefetch: 20}}}}
    schema: raw_json
    sink: {{amqp: {{exchange: out-{tag}, routing_key: out}}}}
"""


async def publish_agents(channel: Any, exchange: str, agents: int, seqs: range, rate: float | None = None) -> None:
    """``{"agent", "seq"}`` round robin over the agents, header ``agent`` and routing key
    ``agent.<n>``; a confirmed batch holds one message per agent (an agent's messages are never
    published concurrently, which could reorder them)."""
    target = await channel.declare_exchange(exchange, aio_pika.ExchangeType.TOPIC, durable=True)
    began = time.monotonic()
    for count, seq in enumerate(seqs, 1):
        await asyncio.gather(*(
            target.publish(aio_pika.Message(json.dumps({"agent": agent, "seq": seq}).encode(), headers={"agent": f"a{agent}"},
                                            delivery_mode=aio_pika.DeliveryMode.PERSISTENT), f"agent.{agent}")
            for agent in range(agents)))
        if rate is not None and (ahead := count * agents / rate - (time.monotonic() - began)) > 0:
            await asyncio.sleep(ahead)  # pacing: the load generator, not waiting for an outcome


def per_agent(messages: list[aio_pika.abc.AbstractIncomingMessage]) -> dict[int, list[int]]:
    arrivals: dict[int, list[int]] = {}
    for message in messages:
        body = json.loads(message.body)
        arrivals.setdefault(body["agent"], []).append(body["seq"])
    return arrivals


async def exists(connection: aio_pika.abc.AbstractConnection, kind: str, name: str) -> bool:
    channel = await connection.channel()
    try:
        if kind == "queue":
            await channel.declare_queue(name, passive=True)
        else:
            await channel.get_exchange(name, ensure=True)
        return True
    except aiormq.exceptions.ChannelNotFoundEntity:
        return False
    finally:
        if not channel.is_closed:
            await channel.close()


def test_header_key_spreads_agents_in_order_and_the_topology_follows_reloads(
        amqp_url: str, tmp_path: Path, schemas_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TEST_AMQP_URL", amqp_url)
    tag = uuid.uuid4().hex[:8]
    routes = tmp_path / "routes"
    routes.mkdir()
    farm = routes / "farm.yaml"
    farm.write_text(ROUTES.format(tag=tag, partitions=3, key="headers.agent"))
    route, base = f"parts-{tag}", f"rabbitros.parts-{tag}"

    async def scenario() -> None:
        engine = Engine(routes, schemas_dir)
        engine.retire_after_s = 0.05
        async with started_with_client(engine, amqp_url) as connection:
            out = await Collector.bind(await connection.channel(), f"out-{tag}")
            publisher = await connection.channel(publisher_confirms=True)
            await publish_agents(publisher, f"in-{tag}", 12, range(30))
            await out.wait_for(360)
            arrivals = per_agent(out.messages)
            assert arrivals == {agent: list(range(30)) for agent in range(12)}, "each agent in order, once"
            source = engine.status()["routes"][route]["source"]
            assert engine.status()["routes"][route]["role"] == "partitioned"
            assert sorted(source["taken"]) != [0, 0, 360] and sum(source["taken"]) == 360, source  # the header spread them
            await wait_for(lambda: engine.status()["routes"][route]["source"]["active"] == [0, 1, 2], 10,
                           "one instance active on every partition")

            farm.write_text(ROUTES.format(tag=tag, partitions=2, key="headers.agent"))
            assert await engine.reload(), engine.reloads.last_error
            await engine.topology_settled()
            assert await exists(connection, "queue", f"{base}.p1") and not await exists(connection, "queue", f"{base}.p2")
            await publish_agents(publisher, f"in-{tag}", 12, range(30, 40))
            await out.wait_for(480)
            assert per_agent(out.messages) == {agent: list(range(40)) for agent in range(12)}

            # another key: RabbitMQ would keep the old exchange's hash-header, so it is another exchange
            assert await exists(connection, "exchange", f"{base}.partitions.header.agent")
            farm.write_text(ROUTES.format(tag=tag, partitions=2, key="routing_key"))
            assert await engine.reload(), engine.reloads.last_error
            await engine.topology_settled()
            assert not await exists(connection, "exchange", f"{base}.partitions.header.agent"), "the old key's exchange left behind"
            assert await exists(connection, "exchange", f"{base}.partitions")
            await publish_agents(publisher, f"in-{tag}", 12, range(40, 50))
            await out.wait_for(600)
            assert per_agent(out.messages) == {agent: list(range(50)) for agent in range(12)}
            assert len(out.messages) == 600, "nothing through both exchanges"

            farm.write_text("routes: []\n")
            assert await engine.reload(), engine.reloads.last_error
            await engine.topology_settled()
            assert not await exists(connection, "queue", f"{base}.p0") and not await exists(connection, "queue", f"{base}.p1")
            assert not await exists(connection, "exchange", f"{base}.partitions"), "the hash exchange left behind"

    asyncio.run(asyncio.wait_for(scenario(), 120))


def active(engine: EngineProcess, route: str) -> list[int]:
    return list(((engine.status() or {}).get("routes", {}).get(route, {}).get("source", {}) or {}).get("active", []))


@pytest.mark.soak
@pytest.mark.timeout(300)
def test_an_instance_stopped_cleanly_hands_its_partitions_over_without_a_duplicate(amqp_url: str, tmp_path: Path) -> None:
    tag = uuid.uuid4().hex[:8]
    route, agents, per = f"parts-{tag}", 16, 250
    directory = tmp_path / "routes"
    directory.mkdir()
    (directory / "farm.yaml").write_text(ROUTES.format(tag=tag, partitions=4, key="routing_key"))
    first = EngineProcess(directory, tmp_path / "status-a.json", {"TEST_AMQP_URL": amqp_url}, "--instance", "a", "--no-watch")
    second = EngineProcess(directory, tmp_path / "status-b.json", {"TEST_AMQP_URL": amqp_url}, "--instance", "b", "--no-watch")
    figures: dict[str, Any] = {}

    async def scenario() -> None:
        await asyncio.to_thread(first.wait_started, 90)
        await asyncio.to_thread(second.wait_started, 90)
        connection = await aio_pika.connect(amqp_url)
        try:
            out = await Collector.bind(await connection.channel(), f"out-{tag}")
            await wait_for(lambda: active(first, route) and active(second, route)
                           and sorted(active(first, route) + active(second, route)) == [0, 1, 2, 3], 60,
                           "the four partitions spread over the two instances")
            figures["before"] = {"a": active(first, route), "b": active(second, route)}
            publishing = asyncio.create_task(publish_agents(await connection.channel(publisher_confirms=True),
                                                            f"in-{tag}", agents, range(per), rate=800))
            await wait_for(lambda: len(out.messages) >= agents * per // 3, 60, "a third of the stream")
            figures["stopped_at"] = len(out.messages)
            figures["exit"] = await asyncio.to_thread(second.stop)
            await publishing
            await out.wait_for(agents * per)
            await wait_for(lambda: active(first, route) == [0, 1, 2, 3], 10, "the survivor active on every partition")
            figures["arrivals"] = per_agent(out.messages)
            figures["received"] = len(out.messages)
        finally:
            await connection.close()

    try:
        asyncio.run(asyncio.wait_for(scenario(), 240))
    finally:
        first.stop()
        second.stop()
    assert figures["exit"] == 0, second.log()
    assert figures["received"] == agents * per, "no duplicate, none lost"
    assert figures["arrivals"] == {agent: list(range(per)) for agent in range(agents)}, "every agent strictly in order"
