"""``ordered: true`` across a clean stop: two engines on one route (a single-active-consumer
queue on a private RabbitMQ node), the active one stopped (SIGTERM) mid-stream. The stopping
engine settles what it holds before its channel closes, so the broker activates the other
engine's consumer only then: the output is one strictly increasing sequence, nothing twice,
nothing lost. (Cancelling the consumer first, as a shared source does, lets the broker activate
the next engine while the stopping one still sends older messages; here, with a stream paced by
publisher confirms, that window held a message or two at most and this test passed on both.)"""

from __future__ import annotations

import asyncio
import json
import uuid
from pathlib import Path
from typing import Any

import aio_pika

from tests.support.amqp_helpers import Collector
from tests.support.engine_process import EngineProcess
from tests.support.waiting import wait_for

ROUTES = """connections:
  gcs: {{amqp: "{url}"}}
routes:
  - name: ordered
    ordered: true
    source: {{amqp: {{connection: gcs, exchange: in-{tag}, queue: q-{tag}, prefetch: 200}}}}
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: out-{tag}, routing_key: ordered}}}}
"""
TOTAL = 4000


def test_a_clean_stop_of_the_active_engine_hands_the_route_over_in_order(tmp_path: Path, amqp_url: str) -> None:
    tag = uuid.uuid4().hex[:8]
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "r.yaml").write_text(ROUTES.format(url=amqp_url, tag=tag))
    first = EngineProcess(routes, tmp_path / "status-a.json", {}, "--instance", "a", "--no-watch")
    first.wait_started(90)
    second = EngineProcess(routes, tmp_path / "status-b.json", {}, "--instance", "b", "--no-watch")
    second.wait_started(90)

    async def scenario() -> dict[str, Any]:
        connection = await aio_pika.connect(amqp_url)
        async with connection:
            collector = await Collector.bind(await connection.channel(), f"out-{tag}")
            channel = await connection.channel(publisher_confirms=True)
            exchange = await channel.declare_exchange(f"in-{tag}", aio_pika.ExchangeType.TOPIC, durable=True)

            async def publish() -> None:  # in order, as fast as confirms come back, in pipelined groups of one
                for first_seq in range(0, TOTAL, 50):
                    for n in range(first_seq, first_seq + 50):
                        await exchange.publish(aio_pika.Message(json.dumps({"seq": n}).encode()), "data")

            publishing = asyncio.create_task(publish())
            await wait_for(lambda: len(collector.messages) >= TOTAL // 4, 60, "a quarter of the stream",
                           lambda: len(collector.messages))
            assert (second.status() or {})["routes"]["ordered"]["received"] == 0, "single active consumer: b waits"
            stopped = await asyncio.to_thread(first.stop)
            await publishing
            await wait_for(lambda: len(collector.messages) >= TOTAL, 60, "every message", lambda: len(collector.messages))
            return {"stopped": stopped, "seqs": [json.loads(m.body)["seq"] for m in collector.messages],
                    "b": (second.status() or {})["routes"]["ordered"]}

    try:
        result = asyncio.run(asyncio.wait_for(scenario(), 240))
    finally:
        second.stop()
        first.stop()
    seqs = result["seqs"]
    disorder = [(i, seqs[i - 1], seqs[i]) for i in range(1, len(seqs)) if seqs[i] <= seqs[i - 1]]
    assert result["stopped"] == 0, first.log()
    assert disorder == [] and seqs == list(range(TOTAL)), disorder[:10]
    assert result["b"]["delivered"] > 0, result["b"]
