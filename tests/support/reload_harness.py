"""A steady stream through the engine while its route files are rewritten, for the hot-reload
test and its benchmark. Every message carries a sequence number; every mapping stamps the
generation that wrote it, so the consumer can tell which configuration converted each copy."""

from __future__ import annotations

import asyncio
import json
import os
import statistics
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import aio_pika

from tests.support.engine_process import EngineProcess
from tests.support.workers import ros_domain
from tests.support.waiting import probe_until, wait_for

ROUTE = """
connections:
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
routes:
  - name: stream
    source:
      amqp: {{exchange: {inbox}, binding_key: "s.#", queue: {queue}, prefetch: {prefetch}}}
    mapping: "{{seq: seq, agent_id: agent, gen: `{gen}`}}"
    schema: raw_json
    sink:
      amqp: {{exchange: {outbox}, routing_key: "out.{{agent_id}}"}}
  - name: to-ros
    source:
      amqp: {{exchange: {inbox}, binding_key: "r.#", queue: {queue}-ros}}
    mapping: "{{seq: seq, gen: `{gen}`}}"
    schema: raw_json
    sink:
      ros2: {{topic: /{tag}/down}}
  - name: from-ros
    source:
      ros2: {{topic: /{tag}/up}}
    mapping: "{{seq: seq, gen: `{gen}`}}"
    schema: raw_json
    sink:
      amqp: {{exchange: {outbox}, routing_key: "up.x"}}
"""
EXTRA = """
routes:
  - name: extra
    source:
      amqp: {{exchange: {inbox}, binding_key: "x.#", queue: {queue}-extra}}
    schema: raw_json
    sink:
      amqp: {{exchange: {outbox}, routing_key: "extra"}}
"""
FLOWS = ("amqp->amqp", "amqp->ros2", "ros2->amqp")
INVALID = ROUTE.replace("mapping: \"{{seq: seq", "mapping: \"{{seq: seq(")


@dataclass
class Flow:
    sent: int = 0
    copies: dict[int, list[int]] = field(default_factory=dict)
    probes: int = 0
    """Arrivals of seq -1, the warm-up's probes: counted apart, so one still in flight when the
    stream starts is not a copy of the flow (no quiet window before it starts)."""

    @property
    def duplicates(self) -> int:
        return sum(len(gens) - 1 for gens in self.copies.values())

    def record(self, body: bytes) -> int:
        message = json.loads(body)
        if message["seq"] < 0:
            self.probes += 1
        else:
            self.copies.setdefault(message["seq"], []).append(message["gen"])
        return int(message["gen"])


@dataclass
class ReloadRun:
    flows: dict[str, Flow] = field(default_factory=lambda: {name: Flow() for name in FLOWS})
    latencies: list[float] = field(default_factory=list)
    written_generations: list[int] = field(default_factory=list)
    rejected_reported: bool = False
    status: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> str:
        lat = sorted(self.latencies)
        flows = "; ".join(
            f"{name}: sent={flow.sent} unique={len(flow.copies)} duplicates={flow.duplicates}"
            for name, flow in self.flows.items()
        )
        return (
            f"{flows}; rewrites={len(self.written_generations)} save_to_live_ms "
            f"median={statistics.median(lat) * 1e3:.0f} max={max(lat) * 1e3:.0f}"
        )


class RosPeer:
    """The robot side in the test process: publishes ``/tag/up`` at a steady rate and records
    ``/tag/down``, in its own rclpy context and executor thread."""

    def __init__(self, domain: int, tag: str, flow_up: Flow, flow_down: Flow, on_gen: Callable[[int], object]) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rclpy.signals import SignalHandlerOptions
        from std_msgs.msg import String

        self._String = String
        self.context = rclpy.Context()
        rclpy.init(args=[], context=self.context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(f"peer_{tag}", context=self.context)
        qos = QoSProfile(depth=100_000, reliability=ReliabilityPolicy.RELIABLE)
        self.publisher = self.node.create_publisher(String, f"/{tag}/up", qos)

        def on_down(msg: Any) -> None:
            on_gen(flow_down.record(msg.data.encode()))

        self.node.create_subscription(String, f"/{tag}/down", on_down, qos)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.flow_up = flow_up
        self._stop = threading.Event()
        self._spinner = threading.Thread(target=self._spin, daemon=True)
        self._spinner.start()

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.executor.spin_once(timeout_sec=0.05)

    def publish_steadily(self, rate: float, stop: threading.Event) -> None:
        started = time.monotonic()
        while not stop.is_set():
            self.publisher.publish(self._String(data=json.dumps({"seq": self.flow_up.sent})))
            self.flow_up.sent += 1
            time.sleep(max(0.0, started + self.flow_up.sent / rate - time.monotonic()))  # pacing: the rate

    def close(self) -> None:
        self._stop.set()
        self._spinner.join(5)
        self.executor.shutdown(timeout_sec=1)
        self.node.destroy_node()
        self.context.try_shutdown()


async def _warm_up(inbox: Any, peer: RosPeer, run: ReloadRun) -> None:
    """DDS matching is asynchronous and a volatile writer drops what it publishes before it
    matches a reader: probe both ROS 2 directions (seq -1) until each gets through."""
    down, up = run.flows["amqp->ros2"], run.flows["ros2->amqp"]

    async def probe() -> None:
        await inbox.publish(aio_pika.Message(b'{"seq": -1}'), "r.x")
        peer.publisher.publish(peer._String(data='{"seq": -1}'))

    await probe_until(lambda: down.probes and up.probes, probe, 30,
                      "a probe through each ROS 2 direction (the engine's endpoints matched)", every=0.1)


def _write(path: Path, text: str, atomic: bool) -> None:
    if atomic:
        temporary = path.with_name(f".{path.name}.{uuid.uuid4().hex[:6]}.tmp")
        temporary.write_text(text)
        os.replace(temporary, path)
    else:
        path.write_text(text)


async def run_reloads(
    amqp_url: str, workdir: Path, rewrites: int = 50, rate: float = 500.0, interval: float = 0.25, min_sent: int = 0,
) -> ReloadRun:
    tag = "r" + uuid.uuid4().hex[:8]
    names = {"tag": tag, "inbox": f"in-{tag}", "outbox": f"out-{tag}", "queue": f"q-{tag}",
             "domain": str(ros_domain(5))}
    routes = workdir / "routes"
    routes.mkdir()
    farm = routes / "farm.yaml"
    farm.write_text(ROUTE.format(gen=0, prefetch=256, **names))
    run = ReloadRun()
    first_seen: dict[int, float] = {}

    def seen(gen: int) -> None:
        first_seen.setdefault(gen, time.monotonic())

    loop = asyncio.get_running_loop()
    peer = RosPeer(int(names["domain"]), tag, run.flows["ros2->amqp"], run.flows["amqp->ros2"],
                   lambda gen: loop.call_soon_threadsafe(seen, gen))
    engine = EngineProcess(routes, workdir / "status.json", {"RABBITROS_AMQP_URL": amqp_url})
    connection = await aio_pika.connect(amqp_url)
    stop_publishing = threading.Event()
    try:
        await asyncio.to_thread(engine.wait_started)
        channel = await connection.channel()
        inbox = await channel.declare_exchange(names["inbox"], aio_pika.ExchangeType.TOPIC, durable=True)
        outbox = await channel.declare_exchange(names["outbox"], aio_pika.ExchangeType.TOPIC, durable=True)
        collect = await channel.declare_queue(f"collect-{tag}", exclusive=True)
        await collect.bind(outbox, "out.#")
        await collect.bind(outbox, "up.#")

        async def on_message(message: aio_pika.abc.AbstractIncomingMessage) -> None:
            key = message.routing_key
            assert key is not None, "a Basic.Deliver always carries its routing key"
            flow = run.flows["amqp->amqp" if key.startswith("out.") else "ros2->amqp"]
            seen(flow.record(message.body))

        await collect.consume(on_message, no_ack=True)
        await _warm_up(inbox, peer, run)

        async def publisher() -> None:
            started = time.monotonic()
            amqp, to_ros = run.flows["amqp->amqp"], run.flows["amqp->ros2"]
            while not stop_publishing.is_set():
                for _ in range(10):
                    body = json.dumps({"seq": amqp.sent, "agent": f"a{amqp.sent % 4}"}).encode()
                    await inbox.publish(aio_pika.Message(body), "s.x")
                    amqp.sent += 1
                    await inbox.publish(aio_pika.Message(json.dumps({"seq": to_ros.sent}).encode()), "r.x")
                    to_ros.sent += 1
                await asyncio.sleep(max(0.0, started + amqp.sent / rate - time.monotonic()))  # pacing: the rate

        publishing = asyncio.gather(publisher(), asyncio.to_thread(peer.publish_steadily, rate, stop_publishing))
        written_at: dict[int, float] = {}
        for gen in range(1, rewrites + 1):
            await asyncio.sleep(interval)  # pacing: the rewrites' interval
            applied = _succeeded(engine)
            prefetch = 256 if gen % 7 else 128
            text = ROUTE.format(gen=gen, prefetch=prefetch, **names)
            if gen % 10 == 3:
                (routes / "extra.yaml").write_text(EXTRA.format(**names))
            if gen % 10 == 6:
                (routes / "extra.yaml").unlink()
            if gen % 10 == 8:
                before = (engine.status() or {}).get("reloads", {}).get("rejected", 0)
                _write(farm, INVALID.format(gen=gen, prefetch=prefetch, **names), atomic=False)
                status = await wait_for(lambda: _rejected_since(engine, before), 30, f"the invalid file of generation {gen} rejected",
                                        lambda: (engine.status() or {}).get("reloads"))
                run.rejected_reported = any("farm.yaml:" in p for p in status["reloads"]["last_error"])
            _write(farm, text, atomic=gen % 2 == 0)
            written_at[gen] = time.monotonic()
            run.written_generations.append(gen)
            # Pace the saves by the engine, not by the clock: on a loaded machine a reload takes
            # longer than the interval, and saves made meanwhile share one reload (fewer
            # configurations ever live), which is right for the engine but not what this measures.
            await wait_for(lambda: _succeeded(engine) > applied, 30, f"the reload of generation {gen}",
                           lambda: (engine.status() or {}).get("reloads"))
        await asyncio.sleep(1.0)  # pacing: the stream goes on after the last rewrite (the behaviour under test)
        # The stream outlives the rewrites until every flow carried at least min_sent messages:
        # on a loaded machine the publishers in this process fall behind their nominal rate.
        await wait_for(lambda: min(f.sent for f in (run.flows["amqp->amqp"], run.flows["ros2->amqp"])) >= min_sent, 60,
                       f"{min_sent} sent by each publisher", lambda: {name: f.sent for name, f in run.flows.items()})
        stop_publishing.set()
        await publishing
        # Wait for the backlog while it still drains (a loaded machine drains slowly): give up
        # after 15 s without a new copy, or 120 s in all.
        last_progress, overall, received = time.monotonic(), time.monotonic() + 120, -1
        while any(len(f.copies) < f.sent for f in run.flows.values()):
            now = time.monotonic()
            total = sum(len(f.copies) for f in run.flows.values())
            if total != received:
                received, last_progress = total, now
            if now - last_progress > 15 or now > overall:
                break
            await asyncio.sleep(0.2)  # poll: a drain that ends when the stream stalls 15 s; the test then names what is missing
        await asyncio.sleep(0.5)  # quiet window: nothing more may arrive (the behaviour under test; no event says 'nothing')
        run.latencies = [first_seen[g] - written_at[g] for g in written_at if g in first_seen]
        run.status = engine.status() or {}
    finally:
        stop_publishing.set()
        await connection.close()
        engine.stop()
        peer.close()
    return run


def _rejected_since(engine: EngineProcess, before: int) -> dict[str, Any] | None:
    """The engine's status once it counts more rejected reloads than ``before``, else None."""
    status = engine.status() or {}
    return status if status.get("reloads", {}).get("rejected", 0) > before else None


def _succeeded(engine: EngineProcess) -> int:
    """Reloads the engine has applied so far (its status file), 0 before the first status."""
    return int(((engine.status() or {}).get("reloads") or {}).get("succeeded", 0))
