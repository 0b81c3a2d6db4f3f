"""Partitioned ordered routes (``ordered: {partitions: 4}``) on a private three-node RabbitMQ
cluster: drain throughput of one vs two engine instances, interleaved in the same run.

    .venv/bin/python -m bench.bench_partitions [--count 20000] [--repeat 3] [--agents 24] [--partitions 4] [--nodes 3]

``--nodes 1`` runs one broker node instead of three: on a small machine the cluster's nodes take
most of the CPU, and one node leaves more of it to the engines.

Each pass fills the route's partitions first (the same topology the engine declares:
engine/endpoints/amqp/partitions.py ``declare_partitions``; ``--agents`` agents, routing key
``agent.<n>``), then starts the engines (separate processes, as in production). Two
instances first spread the partitions (the first one started is active on all of them until
the second takes its share), so the rate is measured from the moment every instance is
active on a partition and the sink has received something, to the last message: the
steady state, not the start-up. The engines' CPU per message is measured over the same span.
Passes alternate the order (1 then 2, 2 then 1) so a neighbour's load on the shared machine
does not always fall on the same side; medians are reported.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import tempfile
import time
import uuid
from pathlib import Path

import aio_pika

from bench.bench_scale import cpu_seconds, engines
from engine.endpoints.amqp.broker import LocalCluster
from engine.endpoints.amqp.options import AmqpSourceOptions
from engine.endpoints.amqp.partitions import declare_partitions
from tests.support.engine_process import EngineProcess

ROUTE = """connections:
  gcs: {{amqp: {{urls: {urls}}}}}
routes:
  - name: parts-{tag}
    ordered: {{partitions: {partitions}}}
    source: {{amqp: {{connection: gcs, exchange: in-{tag}, binding_key: "agent.#", prefetch: {prefetch}}}}}
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: out-{tag}, routing_key: "out"}}}}
"""


async def fill(url: str, tag: str, count: int, agents: int, partitions: int, prefetch: int) -> None:
    """Declare the route's topology as the engine will and publish ``count`` messages, round
    robin over the agents, with confirms in batches; and the sink's queue."""
    connection = await aio_pika.connect(url)
    channel = await connection.channel(publisher_confirms=True)
    options = AmqpSourceOptions(exchange=f"in-{tag}", binding_key="agent.#", prefetch=prefetch, ordered=True,
                                partitions=partitions)
    await declare_partitions(channel, f"parts-{tag}", options)
    source = await channel.declare_exchange(f"in-{tag}", aio_pika.ExchangeType.TOPIC, durable=True)
    out = await channel.declare_exchange(f"out-{tag}", aio_pika.ExchangeType.TOPIC, durable=True)
    sink = await channel.declare_queue(f"sink-{tag}", durable=True)
    await sink.bind(out, "#")
    for first in range(0, count, 500):
        await asyncio.gather(*(
            source.publish(aio_pika.Message(json.dumps({"agent": n % agents, "seq": n // agents}).encode(),
                                            delivery_mode=aio_pika.DeliveryMode.PERSISTENT), f"agent.{n % agents}")
            for n in range(first, min(first + 500, count))))
    await connection.close()


def spread(started: list[EngineProcess], route: str) -> bool:
    def active(engine: EngineProcess) -> list[int]:
        status = engine.status() or {}
        return list(status.get("routes", {}).get(route, {}).get("source", {}).get("active", []))

    return all(active(engine) for engine in started)


async def drain(url: str, tag: str, count: int, started: list[EngineProcess], timeout: float = 600) -> tuple[float, float, float]:
    """``(msg/s, engines' CPU us per message, seconds until spread)`` from the moment every
    engine is active on a partition and the sink has something, to the last message."""
    connection = await aio_pika.connect(url)
    channel = await connection.channel()
    route = f"parts-{tag}"
    began = time.monotonic()
    window: tuple[float, int, float] | None = None
    spread_s = 0.0
    try:
        while time.monotonic() - began < timeout:
            queue = await channel.declare_queue(f"sink-{tag}", passive=True)
            have = queue.declaration_result.message_count or 0
            now = time.monotonic()
            if window is None and have and spread(started, route):
                window, spread_s = (now, have, cpu_seconds(started)), now - began
            if have >= count:
                if window is None:
                    raise RuntimeError(f"{len(started)} instance(s) drained {count} before the partitions spread: "
                                       "raise --count")
                moved = max(count - window[1], 1)
                return moved / max(now - window[0], 1e-3), (cpu_seconds(started) - window[2]) / moved * 1e6, spread_s
            await asyncio.sleep(0.05)  # polling the sink's depth, bounded by the timeout
    finally:
        await connection.close()
    raise TimeoutError(f"sink-{tag} did not reach {count}")


async def one_pass(cluster: LocalCluster, work: Path, args: argparse.Namespace, order: list[int]) -> dict[int, float]:
    rates: dict[int, float] = {}
    for instances in order:
        tag = uuid.uuid4().hex[:8]
        await fill(cluster.urls[-1], tag, args.count, args.agents, args.partitions, args.prefetch)
        directory = work / f"routes-{tag}"
        directory.mkdir()
        (directory / "r.yaml").write_text(ROUTE.format(urls=json.dumps(cluster.urls[:2]), tag=tag, partitions=args.partitions,
                                                       prefetch=args.prefetch))
        started = engines(directory, work, [f"e{i}" for i in range(instances)])
        try:
            rates[instances], cpu_us, spread_s = await drain(cluster.urls[-1], tag, args.count, started)
        finally:
            for engine in started:
                engine.stop()
        print(f"  {instances} instance(s): {rates[instances]:8.0f} msg/s, engines' CPU {cpu_us:5.0f} us/msg "
              f"(spread after {spread_s:.1f} s)", flush=True)
    return rates


async def main(args: argparse.Namespace) -> None:
    cluster = LocalCluster(args.nodes)
    began = time.monotonic()
    await asyncio.to_thread(cluster.start)
    print(f"{args.nodes}-node cluster up in {time.monotonic() - began:.1f} s; {args.count} messages, {args.agents} agents, "
          f"{args.partitions} partitions, prefetch {args.prefetch}", flush=True)
    try:
        with tempfile.TemporaryDirectory(prefix="bench-partitions-") as tmp:
            passes = [await one_pass(cluster, Path(tmp), args, [1, 2] if index % 2 == 0 else [2, 1])
                      for index in range(args.repeat)]
    finally:
        await asyncio.to_thread(cluster.stop)
    ratios = [rates[2] / rates[1] for rates in passes]
    print(f"medians: 1 instance {statistics.median(p[1] for p in passes):.0f} msg/s, "
          f"2 instances {statistics.median(p[2] for p in passes):.0f} msg/s; "
          f"2/1 per pass {', '.join(f'{ratio:.2f}' for ratio in ratios)} (median {statistics.median(ratios):.2f})")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--count", type=int, default=20000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--agents", type=int, default=24)
    parser.add_argument("--partitions", type=int, default=4)
    parser.add_argument("--prefetch", type=int, default=200)
    parser.add_argument("--nodes", type=int, default=3, choices=(1, 3), help="broker nodes (the clients use the last one)")
    asyncio.run(main(parser.parse_args()))
