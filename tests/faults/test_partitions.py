"""A partitioned ordered route (``ordered: {partitions: 4}``) on the real three-node cluster:
three engine instances spread the partitions, one is killed with -9 mid-stream, and every
agent's sequence still arrives in order with nothing lost.

What "in order" means with at-least-once delivery: the instance killed had messages in flight
(sent to the sink, not yet acknowledged at the source); the broker gives them to the next
instance, which sends them again. So each agent's arrivals at the sink are asserted to be runs
of consecutive sequence numbers where every run after the first starts at or below the highest
number seen so far plus one: a run that starts below is a replay of what was in flight (at
most ``prefetch`` long, at most once per agent, for the one kill); the first arrival of every
number comes after the first arrival of every smaller one (no message overtakes an older
one); and every number 0..N-1 arrives (0 lost).
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import time
import uuid
from pathlib import Path
from typing import Any

import aio_pika
import pytest

from engine.endpoints.amqp.broker import LocalCluster
from tests.support.engine_process import EngineProcess
from tests.support.waiting import wait_for

CLIENT_NODE = 2
AGENTS, PER_AGENT, PREFETCH, PARTITIONS = 24, 400, 20, 4

ROUTE = """connections:
  gcs: {{amqp: {{urls: {urls}, queue_type: quorum}}}}
routes:
  - name: parts-{tag}
    ordered: {{partitions: {partitions}}}
    source: {{amqp: {{connection: gcs, exchange: in-{tag}, binding_key: "agent.#", prefetch: {prefetch}}}}}
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: out-{tag}, routing_key: "out"}}}}
"""


def replay_problems(arrivals: list[int], total: int, prefetch: int) -> list[str]:
    """What breaks the order asserted (module docstring) in one agent's arrivals."""
    problems: list[str] = []
    highest, replays, seen_first = -1, 0, []
    previous: int | None = None
    for seq in arrivals:
        if previous is not None and seq != previous + 1:  # a new run
            if seq > highest + 1:
                problems.append(f"{seq} arrived before {highest + 1}")
            elif seq <= highest:
                replays += 1
                if highest - seq + 1 > prefetch:
                    problems.append(f"replay of {highest - seq + 1} messages from {seq} (more than the prefetch)")
        elif previous is None and seq != 0:
            problems.append(f"first arrival {seq}")
        if seq > highest:
            seen_first.append(seq)
        highest = max(highest, seq)
        previous = seq
    if seen_first != list(range(total)):
        problems.append(f"first arrivals are not 0..{total - 1} in order (missing {sorted(set(range(total)) - set(seen_first))[:10]})")
    if replays > 1:
        problems.append(f"{replays} replays for one kill")
    return problems


def active_partitions(engine: EngineProcess, route: str) -> list[int]:
    status = engine.status() or {}
    return list(status.get("routes", {}).get(route, {}).get("source", {}).get("active", []))


def spread(engines: list[EngineProcess], route: str) -> bool:
    """Every engine active on at least one partition, each partition on exactly one engine."""
    actives = [active_partitions(engine, route) for engine in engines]
    flat = sorted(index for indices in actives for index in indices)
    return all(actives) and flat == list(range(PARTITIONS))


async def publish_agents(channel: Any, exchange: str, rate: float) -> None:
    """Each agent's seq 0..PER_AGENT-1, round robin over the agents, routing key agent.<n>.
    A confirmed batch holds one message per agent, and batches follow one another: concurrent
    publishes may reach the exchange in any order, so an agent's messages are never concurrent."""
    target = await channel.declare_exchange(exchange, aio_pika.ExchangeType.TOPIC, durable=True)
    began = time.monotonic()
    for seq in range(PER_AGENT):
        await asyncio.gather(*(
            target.publish(aio_pika.Message(json.dumps({"agent": agent, "seq": seq}).encode(),
                                            delivery_mode=aio_pika.DeliveryMode.PERSISTENT), f"agent.{agent}")
            for agent in range(AGENTS)))
        ahead = (seq + 1) * AGENTS / rate - (time.monotonic() - began)
        if ahead > 0:
            await asyncio.sleep(ahead)  # pacing: the load generator, not waiting for an outcome


@pytest.mark.soak
@pytest.mark.timeout(600)  # its scenario's bound is 300 s, and the session cluster may start in its setup
def test_three_instances_keep_every_agents_order_when_one_is_killed(amqp_cluster: LocalCluster, tmp_path: Path) -> None:
    cluster = amqp_cluster
    tag = uuid.uuid4().hex[:8]
    route = f"parts-{tag}"
    directory = tmp_path / "routes"
    directory.mkdir()
    (directory / "routes.yaml").write_text(ROUTE.format(urls=json.dumps(cluster.urls), tag=tag, partitions=PARTITIONS,
                                                        prefetch=PREFETCH))
    engines = [EngineProcess(directory, tmp_path / f"status-{name}.json", {}, "--instance", name, "--no-watch")
               for name in ("a", "b", "c")]
    figures: dict[str, Any] = {}
    total = AGENTS * PER_AGENT

    async def scenario() -> None:
        for engine in engines:
            await asyncio.to_thread(engine.wait_started, 90)
        connection = await aio_pika.connect(cluster.urls[CLIENT_NODE])
        try:
            arrivals: dict[int, list[int]] = {agent: [] for agent in range(AGENTS)}
            unique: set[tuple[int, int]] = set()
            channel = await connection.channel()
            out = await channel.declare_exchange(f"out-{tag}", aio_pika.ExchangeType.TOPIC, durable=True)
            queue = await channel.declare_queue(f"collect-{tag}", durable=True, arguments={"x-queue-type": "quorum"})
            await queue.bind(out, "#")

            async def collect(message: aio_pika.abc.AbstractIncomingMessage) -> None:
                body = json.loads(message.body)
                arrivals[body["agent"]].append(body["seq"])
                unique.add((body["agent"], body["seq"]))

            await queue.consume(collect, no_ack=True)
            began = time.monotonic()
            await wait_for(lambda: spread(engines, route), 60, "the four partitions spread over the three instances")
            figures["spread_s"] = round(time.monotonic() - began, 2)
            figures["active_before_kill"] = {engine.status_file.stem: active_partitions(engine, route) for engine in engines}
            publishing = asyncio.create_task(publish_agents(await connection.channel(publisher_confirms=True), f"in-{tag}", 2000))
            await wait_for(lambda: len(unique) >= total // 3, 120, "a third of the stream")
            victim = engines[1]
            figures["killed_active_on"] = active_partitions(victim, route)
            os.killpg(victim.process.pid, signal.SIGKILL)
            killed_at = time.monotonic()
            victim.process.wait()
            figures["delivered_at_kill"] = len(unique)
            survivors = [engines[0], engines[2]]
            await wait_for(lambda: spread(survivors, route), 60, "the four partitions spread over the two survivors")
            figures["respread_s"] = round(time.monotonic() - killed_at, 2)
            await publishing
            figures["publish_s"] = round(time.monotonic() - began, 2)
            await wait_for(lambda: len(unique) >= total, 120, f"all {total} messages at the sink")
            figures.update(
                sent=total,
                delivered=len(unique),
                received=sum(len(seqs) for seqs in arrivals.values()),
                lost=total - len(unique),
                active_after_kill={engine.status_file.stem: active_partitions(engine, route) for engine in survivors},
                handovers={engine.status_file.stem: (engine.status() or {})["routes"][route]["source"]["handovers"]
                           for engine in survivors},
                delivered_per_engine={engine.status_file.stem: (engine.status() or {})["routes"][route]["delivered"]
                                      for engine in survivors},
                problems={agent: found for agent, seqs in arrivals.items()
                          if (found := replay_problems(seqs, PER_AGENT, PREFETCH))},
            )
            figures["duplicates"] = figures["received"] - figures["delivered"]
            figures["agents_replayed"] = sum(1 for seqs in arrivals.values() if len(seqs) > PER_AGENT)
        finally:
            await connection.close()

    try:
        asyncio.run(asyncio.wait_for(scenario(), 300))
    finally:
        for engine in engines:
            engine.stop()
    print(f"\n[cluster] partitioned ordered route, one of three instances killed: {json.dumps(figures)}")
    assert figures["lost"] == 0
    assert figures["problems"] == {}, figures["problems"]
    assert figures["duplicates"] <= PREFETCH * len(figures["killed_active_on"]), "only what was in flight at the kill comes twice"
    assert all(count > 0 for count in figures["delivered_per_engine"].values()), "both survivors carried the route"
