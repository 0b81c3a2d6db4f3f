"""Discovery latency (issue 20): a robot's topic appears -> its first message at RabbitMQ.

The engine runs alone in a child process (``bench.systems engine``) on one route whose ROS 2
source topic is a pattern (``/{agent}/fix_<tag>``, NavSatFix) and whose AMQP sink's routing key
is ``farm.{agent}.fix``. Once it runs, this process creates the robots' publishers (rclpy, a
context of its own) and publishes each robot's NavSatFix at ``rate`` Hz from the moment its
publisher exists, as a robot does; an aiormq consumer bound to ``farm.#`` records when each
robot's first message arrives. Both clocks are this process's monotonic clock.

* appear -> delivered: publisher created -> first message at the consumer (what the issue asks);
* appear -> matched: publisher created -> its ``get_subscription_count()`` first > 0 (DDS
  discovery of the publisher, up to one graph scan, the subscription created, DDS matching);
* matched -> delivered: the rest (next publish tick, the route, RabbitMQ).

Two scenarios: ``staggered`` (one robot every ``stagger`` s: each discovery alone) and
``burst`` (every robot at once: a fleet switched on together). The engine's CPU while nothing
is published, before the robots appear and once it follows all their topics, is the cost of
reading the graph.

    .venv/bin/python -m bench.bench_discovery                # a private RabbitMQ node
    .venv/bin/python -m bench.bench_discovery --url amqp://...
"""

from __future__ import annotations

import argparse
import asyncio
import json
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

from bench import throughput as tp

ROUTES = """
connections:
  ros: {{ros2: {{domain_id: {domain}, node: bench_discovery_{tag}}}}}
  farm: {{amqp: {{url: "{url}"}}}}
routes:
  - name: fleet-fix
    source:
      ros2: {{topic: "/{{agent}}/fix_{tag}", type: sensor_msgs/msg/NavSatFix}}
    mapping: "{{agent_id: meta('agent'), lat: latitude, lon: longitude, alt_msl: altitude}}"
    schema: position
    sink:
      amqp: {{exchange: {exchange}, routing_key: "farm.{{agent}}.fix"}}
"""


class Fleet:
    """The robots: publishers created on demand, each publishing at ``rate`` until its first
    message has arrived."""

    def __init__(self, domain: int, tag: str, rate: float) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rclpy.signals import SignalHandlerOptions
        from sensor_msgs.msg import NavSatFix

        self.context = Context()
        rclpy.init(args=[], context=self.context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(f"bench_fleet_{tag}", context=self.context, start_parameter_services=False)
        self.qos = QoSProfile(depth=10_000, reliability=ReliabilityPolicy.RELIABLE)
        self.cls, self.tag, self.period = NavSatFix, tag, 1.0 / rate
        self.publishers: dict[str, Any] = {}
        self.appeared: dict[str, float] = {}
        self.matched: dict[str, float] = {}
        self.delivered: dict[str, float] = {}

    def appear(self, agent: str) -> None:
        self.publishers[agent] = self.node.create_publisher(self.cls, f"/{agent}/fix_{self.tag}", self.qos)
        self.appeared[agent] = time.monotonic()

    async def publish(self, stop: asyncio.Event) -> None:
        message = self.cls(latitude=1.0, longitude=2.0, altitude=3.0)
        while not stop.is_set():
            now = time.monotonic()
            for agent, publisher in list(self.publishers.items()):
                if agent not in self.matched and publisher.get_subscription_count() > 0:
                    self.matched[agent] = now
                if agent not in self.delivered:
                    publisher.publish(message)
            await asyncio.sleep(self.period)

    def close(self) -> None:
        self.node.destroy_node()
        self.context.try_shutdown()


async def _consume(url: str, exchange: str, fleet: Fleet) -> Any:
    import aiormq

    connection = await aiormq.connect(url)
    channel = await connection.channel()
    await channel.exchange_declare(exchange, exchange_type="topic", durable=True)
    queue = (await channel.queue_declare("", exclusive=True)).queue
    assert queue is not None, "Queue.DeclareOk always names the server-named queue"
    await channel.queue_bind(queue, exchange, routing_key="farm.#")

    async def on_message(message: Any) -> None:
        agent = message.delivery.routing_key.split(".")[1]
        fleet.delivered.setdefault(agent, time.monotonic())

    await channel.basic_consume(queue, on_message, no_ack=True)
    return connection


async def _scenario(fleet: Fleet, agents: list[str], stagger: float, timeout: float) -> dict[str, Any]:
    stop = asyncio.Event()
    publishing = asyncio.create_task(fleet.publish(stop))
    try:
        for agent in agents:
            fleet.appear(agent)
            if stagger:
                await asyncio.sleep(stagger)
        deadline = time.monotonic() + timeout
        while not all(agent in fleet.delivered for agent in agents) and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
    finally:
        stop.set()
        await publishing

    def ms(start: dict[str, float], end: dict[str, float]) -> list[float]:
        return [(end[a] - start[a]) * 1e3 for a in agents if a in start and a in end]

    return {"robots": len(agents), "stagger_s": stagger,
            "delivered": sum(agent in fleet.delivered for agent in agents),
            "appear_to_delivered_ms": tp.summary(ms(fleet.appeared, fleet.delivered)),
            "appear_to_matched_ms": tp.summary(ms(fleet.appeared, fleet.matched)),
            "matched_to_delivered_ms": tp.summary(ms(fleet.matched, fleet.delivered))}


async def _idle_cpu(engine: tp.Child, topics: int, seconds: float) -> dict[str, Any]:
    """The engine's CPU while it follows ``topics`` topics and nothing is published."""
    began, cpu = time.monotonic(), engine.cpu_seconds()
    await asyncio.sleep(seconds)
    return {"topics": topics, "seconds": seconds,
            "engine_cpu_percent": 100 * (engine.cpu_seconds() - cpu) / (time.monotonic() - began)}


async def measure(url: str, domain: int, robots: int = 20, stagger: float = 0.37, rate: float = 100.0,
                  idle_s: float = 5.0) -> dict[str, Any]:
    from engine.endpoints.ros2.discovery import DISCOVERY_INTERVAL

    tag = uuid.uuid4().hex[:8]
    exchange = f"bench-discovery-{tag}"
    fleet = Fleet(domain, tag, rate)
    out: dict[str, Any] = {"rate_hz": rate, "scan_interval_s": DISCOVERY_INTERVAL}
    consumer = await _consume(url, exchange, fleet)
    try:
        with tempfile.TemporaryDirectory() as work:
            (Path(work) / "routes.yaml").write_text(ROUTES.format(domain=domain, tag=tag, url=url, exchange=exchange))
            async with tp.child("engine", {"routes": work}) as engine:
                out["idle_following_none"] = await _idle_cpu(engine, 0, idle_s)
                out["staggered"] = await _scenario(fleet, [f"robot{i}" for i in range(robots)], stagger, 60)
                out["burst"] = await _scenario(fleet, [f"burst{i}" for i in range(robots)], 0.0, 60)
                out["idle_following"] = await _idle_cpu(engine, 2 * robots, idle_s)
    finally:
        await consumer.close()
        fleet.close()
    return out


async def _main(args: argparse.Namespace) -> dict[str, Any]:
    if args.url:
        return await measure(args.url, tp.domain_id(), args.robots, args.stagger, args.rate)
    from engine.endpoints.amqp.broker import LocalBroker

    node = LocalBroker()
    url = await asyncio.to_thread(node.start)
    try:
        return await measure(url, tp.domain_id(), args.robots, args.stagger, args.rate)
    finally:
        await asyncio.to_thread(node.stop)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--url", help="a RabbitMQ to use (default: a private node)")
    parser.add_argument("--robots", type=int, default=20)
    parser.add_argument("--stagger", type=float, default=0.37,
                        help="seconds between two robots of the staggered scenario (not a multiple of the scan interval, so robots appear at every phase of it)")
    parser.add_argument("--rate", type=float, default=100.0, help="each robot's publishing rate (Hz)")
    parser.add_argument("--out", type=Path, help="write the results as JSON here too")
    args = parser.parse_args()
    result = asyncio.run(_main(args))
    text = json.dumps(result, indent=1)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
