"""AMQP -> mapping -> schema -> AMQP throughput and processing latency of one route.

Fills the source queue first, then starts the engine and times how long it takes to move
everything to the sink exchange, with publisher confirms on (at-least-once) and off (the
paper's final configuration). Prints msg/s and the mean/max time from reception to the
sink's acceptance (the paper's t2 - t1).

    .venv/bin/python -m bench.bench_amqp_throughput [--count 20000] [--url amqp://...]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import tempfile
import time
import uuid
from pathlib import Path

import aio_pika

from engine.endpoints.amqp.broker import LocalBroker
from engine.running.runtime import Engine

REPO = Path(__file__).resolve().parent.parent
ROUTE = """
connections:
  gcs: {{amqp: {{url: "{url}", publisher_confirms: {confirms}}}}}
routes:
  - name: weeds
    source:
      amqp: {{exchange: {inbox}, binding_key: "w.#", queue: {queue}, prefetch: 1000}}
    mapping: "{{agent_id: agent, points: detections[].{{lat: lat, lon: lon, p: confidence}}}}"
    schema: weed_detection
    sink:
      amqp: {{exchange: {outbox}, routing_key: "canonical.weeds.{{agent_id}}"}}
"""


async def measure(url: str, count: int, confirms: bool) -> dict[str, float]:
    tag = uuid.uuid4().hex[:8]
    names = {"inbox": f"bin-{tag}", "outbox": f"bout-{tag}", "queue": f"bq-{tag}"}
    body = json.dumps({"agent": "uav1", "detections": [{"lat": -22.0, "lon": -47.9, "confidence": 0.8}] * 2}).encode()
    connection = await aio_pika.connect(url)
    channel = await connection.channel(publisher_confirms=False)
    inbox = await channel.declare_exchange(names["inbox"], aio_pika.ExchangeType.TOPIC, durable=True)
    outbox = await channel.declare_exchange(names["outbox"], aio_pika.ExchangeType.TOPIC, durable=True)
    queue = await channel.declare_queue(names["queue"], durable=True)
    await queue.bind(inbox, "w.#")
    sink_queue = await channel.declare_queue(f"bsink-{tag}", durable=False, auto_delete=True)
    await sink_queue.bind(outbox, "#")
    for _ in range(count):
        await inbox.publish(aio_pika.Message(body), "w.x")
    while ((await channel.declare_queue(names["queue"], passive=True)).declaration_result.message_count or 0) < count:
        await asyncio.sleep(0.05)
    with tempfile.TemporaryDirectory() as routes:
        Path(routes, "r.yaml").write_text(ROUTE.format(url=url, confirms=str(confirms).lower(), **names))
        engine = Engine(Path(routes), REPO / "schemas")
        started = time.perf_counter()
        await engine.start()
        runner = engine.runners["weeds"]
        while runner.observer.delivered < count:
            await asyncio.sleep(0.01)
        elapsed = time.perf_counter() - started
        stats = runner.observer
        await engine.stop()
    await connection.close()
    return {
        "msg_per_s": count / elapsed,
        "mean_ms": stats.latency_ns_total / stats.delivered / 1e6,
        "max_ms": stats.latency_ns_max / 1e6,
    }


async def main(url: str | None, count: int) -> None:
    broker = None
    if url is None:
        broker = LocalBroker()
        url = await asyncio.to_thread(broker.start)
    try:
        for confirms in (True, False):
            result = await measure(url, count, confirms)
            print(f"publisher_confirms={str(confirms):5}  {count} msgs  {result['msg_per_s']:8.0f} msg/s  "
                  f"reception->sink accepted mean {result['mean_ms']:.3f} ms  max {result['max_ms']:.1f} ms")
    finally:
        if broker:
            await asyncio.to_thread(broker.stop)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--url")
    parser.add_argument("--count", type=int, default=20000)
    args = parser.parse_args()
    asyncio.run(main(args.url, args.count))
