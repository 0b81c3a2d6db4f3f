"""Nothing delivered to nobody (issue 32): an AMQP sink publishing to an exchange no queue is
bound to. Before, 10 messages were counted delivered, acknowledged at the source, and gone
(RabbitMQ drops an unroutable message unless it is published ``mandatory``). Now the sink
publishes mandatory: a returned message is never counted delivered nor acknowledged, it is
counted ``unroutable`` and held (the default) until a queue is bound, then delivered, none
lost; ``unroutable: dead_letter`` dead-letters it naming the exchange and routing key;
``mandatory: false`` keeps fire-and-forget. A real RabbitMQ, the engine in process."""

from __future__ import annotations

import asyncio
import json
import uuid
from pathlib import Path
from typing import Any

import aio_pika
import pytest

from engine.ops.admin import EngineCollector
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector, started_with_client
from tests.support.waiting import wait_for

N = 10
DEADLINE_S = 30.0

ROUTES = """
connections:
  gcs: {{amqp: "{url}"}}
dead_letters: {{connection: gcs}}
routes:
  - name: held
    source: {{amqp: {{connection: gcs, queue: {tag}-in-held}}}}
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: {tag}-out-held, routing_key: "robot.{{seq}}"}}}}
  - name: refused
    source: {{amqp: {{connection: gcs, queue: {tag}-in-refused}}}}
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: {tag}-out-refused, routing_key: refused.key, unroutable: dead_letter}}}}
  - name: forgotten
    source: {{amqp: {{connection: gcs, queue: {tag}-in-forgotten}}}}
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: {tag}-out-forgotten, routing_key: any, mandatory: false}}}}
"""


@pytest.mark.soak
def test_an_unroutable_message_is_held_until_a_queue_is_bound_or_dead_lettered(
        tmp_path: Path, amqp_url: str, schemas_dir: Path) -> None:
    tag = f"unroutable-{uuid.uuid4().hex[:8]}"
    (tmp_path / "routes").mkdir()
    (tmp_path / "routes" / "routes.yaml").write_text(ROUTES.format(tag=tag, url=amqp_url))

    async def scenario() -> dict[str, Any]:
        engine = Engine(tmp_path / "routes", schemas_dir)
        async with started_with_client(engine, amqp_url) as client:
            channel = await client.channel()
            letters = await channel.declare_queue(f"{tag}-letters", exclusive=True)
            await letters.bind("rabbitros.dead-letter", "refused")
            dead = (await Collector.consume(letters)).messages

            def route(name: str) -> dict[str, Any]:
                return engine.status()["routes"][name]

            for name in ("held", "refused", "forgotten"):
                for seq in range(N):
                    await channel.default_exchange.publish(
                        aio_pika.Message(json.dumps({"seq": seq}).encode()), f"{tag}-in-{name}")

            # held: returned, counted, never delivered nor acknowledged; the status says why
            await wait_for(lambda: route("held")["unroutable"] >= N and route("held")["sink_not_ready"], DEADLINE_S, "held unroutable")
            held = route("held")
            await wait_for(lambda: len(dead) >= N, DEADLINE_S, "the refused route's dead letters")
            await wait_for(lambda: route("forgotten")["delivered"] >= N, DEADLINE_S, "the fire-and-forget route")
            metrics = {(sample.name, sample.labels.get("route")): sample.value
                       for family in EngineCollector(engine).collect() for sample in family.samples}

            # a queue bound: every held message arrives, none lost
            out = await Collector.bind(channel, f"{tag}-out-held", "robot.#")
            await out.wait_for(N, timeout=DEADLINE_S)
            await wait_for(lambda: route("held")["delivered"] == N and not route("held")["sink_not_ready"], DEADLINE_S, "held delivered")
            return {"held": held, "after": route("held"), "refused": route("refused"),
                    "forgotten": route("forgotten"), "dead": [dict(m.headers) for m in dead], "metrics": metrics,
                    "arrived": sorted(json.loads(m.body)["seq"] for m in out.messages),
                    "keys": sorted({m.routing_key for m in out.messages})}

    result = asyncio.run(scenario())
    print(result["arrived"], result["held"]["sink_not_ready"])
    held = result["held"]
    assert held["delivered"] == 0 and held["dead_lettered"] == {} and held["unroutable"] >= N, held
    reason = held["sink_not_ready"]
    assert "-out-held'" in reason and "routing key 'robot." in reason and "NO_ROUTE" in reason, reason
    assert result["metrics"][("rabbitros_unroutable_total", "held")] >= N, result["metrics"]
    after = result["after"]  # every one arrives once bound: none was acknowledged at the source meanwhile
    assert result["arrived"] == list(range(N)) and after["delivered"] == N and after["dead_lettered"] == {}, after
    refused = result["refused"]
    assert refused["delivered"] == 0 and refused["dead_lettered"] == {"sink": N} and refused["unroutable"] == N, refused
    errors = {headers["x-rabbitros-error"] for headers in result["dead"]}
    assert all("-out-refused'" in error and "'refused.key'" in error and "NO_ROUTE" in error for error in errors), errors
    forgotten = result["forgotten"]
    assert forgotten["delivered"] == N and forgotten["unroutable"] == 0, forgotten

