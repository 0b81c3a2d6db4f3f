"""10,000 messages AMQP -> AMQP while the engine is killed with -9 and restarted twice:
none lost (the batch path acks only the settled prefix), duplicates counted."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import uuid
from collections import Counter
from pathlib import Path
from typing import Any

import aio_pika
import pytest

from tests.support.engine_process import EngineProcess
from tests.support.amqp_helpers import Collector, message_count
from tests.support.waiting import wait_for

TOTAL = 10_000
ROUTES = """
connections:
  gcs: {{amqp: "{url}"}}
routes:
  - name: kill-weeds
    source:
      amqp: {{exchange: {inbox}, binding_key: "k.#", queue: {inbox}-q, prefetch: 500}}
    mapping: "{{agent_id: agent, seq: seq, points: detections[].{{lat: lat, lon: lon, p: confidence}}}}"
    schema: weed_detection
    sink:
      amqp: {{exchange: {outbox}, routing_key: "out.{{agent_id}}"}}
"""


def kill(engine: EngineProcess) -> None:
    os.killpg(engine.process.pid, signal.SIGKILL)
    engine.process.wait(30)


@pytest.mark.soak
def test_engine_killed_twice_loses_nothing(tmp_path: Path, amqp_url: str) -> None:
    tag = uuid.uuid4().hex[:8]
    inbox, outbox = f"k-in-{tag}", f"k-out-{tag}"
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "r.yaml").write_text(ROUTES.format(url=amqp_url, inbox=inbox, outbox=outbox))

    async def scenario() -> dict[str, Any]:
        connection = await aio_pika.connect(amqp_url)
        channel = await connection.channel()
        out = await Collector.bind(channel, outbox, "#")
        dead = await Collector.bind(channel, "rabbitros.dead-letter", "kill-weeds")
        fast = await connection.channel(publisher_confirms=False)
        queue = await fast.declare_queue(f"{inbox}-q", durable=True)
        exchange = await fast.declare_exchange(inbox, aio_pika.ExchangeType.TOPIC, durable=True)
        await queue.bind(exchange, "k.#")
        for seq in range(TOTAL):
            body = {"agent": f"uav{seq % 3}", "seq": seq,
                    "detections": [{"lat": -22.0, "lon": -47.9, "confidence": 0.5 + (seq % 40) / 100}]}
            await exchange.publish(aio_pika.Message(json.dumps(body).encode(), delivery_mode=2), "k.x")

        async def all_queued() -> bool:
            return message_count(await fast.declare_queue(f"{inbox}-q", passive=True)) >= TOTAL

        await wait_for(all_queued, 60, f"all {TOTAL} messages in the source queue")

        def seen() -> int:
            return len({json.loads(m.body)["seq"] for m in out.messages})

        kills: list[int] = []
        for kill_at in (TOTAL // 4, TOTAL * 3 // 5, None):
            engine = EngineProcess(routes, tmp_path / f"status-{len(kills)}.json", {})
            try:
                await asyncio.to_thread(engine.wait_started)
                if kill_at is None:
                    await wait_for(lambda: seen() == TOTAL, 240, f"all {TOTAL} messages")
                    await asyncio.sleep(1.0)  # quiet window: let any duplicate in flight arrive
                    break
                kill_after: int = kill_at
                await wait_for(lambda: seen() >= kill_after, 240, f"{kill_after} messages before the kill")
                kill(engine)
                kills.append(seen())
            finally:
                if engine.process.poll() is None:
                    engine.stop()
        await connection.close()
        counts = Counter(json.loads(m.body)["seq"] for m in out.messages)
        return {
            "sent": TOTAL,
            "delivered": len(counts),
            "duplicates": sum(counts.values()) - len(counts),
            "dead_lettered": len(dead.messages),
            "lost": TOTAL - len(set(counts) & set(range(TOTAL))),
            "killed_after": kills,
        }

    figures = asyncio.run(scenario())
    print(f"\nengine kill -9 x2: {figures}")
    assert figures["lost"] == 0 and figures["delivered"] == TOTAL
    assert figures["dead_lettered"] == 0
    assert len(figures["killed_after"]) == 2 and all(n < TOTAL for n in figures["killed_after"])
