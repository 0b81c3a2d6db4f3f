"""Scale-out on a real three-node RabbitMQ cluster: two engine processes share routes while a
broker node or an engine is killed with -9.

One session cluster serves every test (``amqp_cluster``); a test that kills a node restarts
it before it ends. Test clients (publisher, collector) use the third node, which is never
killed, so what they see is what the engines did. The figures each test measured are
printed (run with ``-s``) for the issue's closing note.
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
from tests.support.amqp_helpers import Collector
from tests.support.engine_process import EngineProcess
from tests.support.workers import ros_domain
from tests.support.waiting import wait_for

CLIENT_NODE = 2
"""Index of the node the test's own clients use; only node 0 is ever killed."""


class TimedCollector(Collector):
    """The one collector on a quorum queue bound to the engines' output exchange, with each
    arrival's time and seq (``seq_arrivals``): what a consumer of the output saw of a failover."""

    def __init__(self, ack: bool = False, tally: Any = None) -> None:
        super().__init__(ack, tally)
        self.seq_arrivals: list[tuple[float, int]] = []

    @classmethod
    async def bind_output(cls, channel: Any, exchange: str) -> TimedCollector:
        return await cls.bind(channel, exchange, queue=f"collect-{exchange}", quorum=True)

    def received(self, at: float, message: aio_pika.abc.AbstractIncomingMessage) -> None:
        self.seq_arrivals.append((at, json.loads(message.body)["seq"]))

    @property
    def unique(self) -> set[int]:
        return {seq for _, seq in self.seq_arrivals}

    async def wait_unique(self, count: int, timeout: float) -> None:
        await wait_for(lambda: len(self.unique) >= count, timeout, f"{count} distinct messages")

    def first_after(self, moment: float) -> float | None:
        return next((at for at, _ in self.seq_arrivals if at > moment), None)

    def stall(self, moment: float, window: float = 30.0) -> float:
        """The longest time the stream stood still from shortly before ``moment`` on: what
        a consumer of the output saw of a failover."""
        end = min(time.monotonic(), moment + window)
        times = [moment - 0.2] + [at for at, _ in self.seq_arrivals if moment - 0.2 <= at <= end]
        if times[-1] <= moment:  # the stream never resumed within the window
            times.append(end)
        return max(b - a for a, b in zip(times, times[1:]))


async def publish_seq(
    channel: Any, exchange: str, start: int, stop: int, rate: float | None = None, batch: int = 100
) -> None:
    """Publish ``{"seq": n}`` with publisher confirms, in confirmed batches, optionally paced.
    Concurrent publishes in a batch may reach the queue in any order: ``batch=1`` keeps it."""
    target = await channel.declare_exchange(exchange, aio_pika.ExchangeType.TOPIC, durable=True)
    began = time.monotonic()
    for first in range(start, stop, batch):
        await asyncio.gather(*(
            target.publish(aio_pika.Message(json.dumps({"seq": n}).encode(), message_id=f"m{n}",
                                            delivery_mode=aio_pika.DeliveryMode.PERSISTENT), "data")
            for n in range(first, min(first + batch, stop))
        ))
        if rate:
            ahead = (first + batch - start) / rate - (time.monotonic() - began)
            if ahead > 0:
                await asyncio.sleep(ahead)  # pacing: the publisher's rate


def kill_engine(engine: EngineProcess) -> float:
    """SIGKILL the engine's whole process group (our own child); returns the moment."""
    os.killpg(engine.process.pid, signal.SIGKILL)
    moment = time.monotonic()
    engine.process.wait()
    return moment


def routes_file(directory: Path, cluster: LocalCluster, body: str, **names: str) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    urls = json.dumps(cluster.urls)
    (directory / "routes.yaml").write_text(
        f"connections:\n  gcs: {{amqp: {{urls: {urls}, queue_type: quorum}}}}\n" + body.format(**names)
    )
    return directory


def start_engines(directory: Path, tmp_path: Path, names: list[str], *extra: str) -> list[EngineProcess]:
    engines = [
        EngineProcess(directory, tmp_path / f"status-{name}.json", {}, "--instance", name, "--no-watch", *extra)
        for name in names
    ]
    for engine in engines:
        engine.wait_started(90)
    return engines


def stop_all(engines: list[EngineProcess]) -> None:
    for engine in engines:
        engine.stop()


def report(title: str, figures: dict[str, Any]) -> None:
    print(f"\n[cluster] {title}: " + json.dumps(figures, default=str))


SHARED_ROUTE = """routes:
  - name: relay-{tag}
    source: {{amqp: {{connection: gcs, exchange: in-{tag}, queue: q-{tag}, prefetch: 200}}}}
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: out-{tag}, routing_key: "relayed"}}}}
"""


@pytest.mark.soak
@pytest.mark.timeout(600)  # its scenario's own bound is 400 s, and the session cluster (three nodes) may start in its setup
def test_two_engines_on_quorum_queues_lose_nothing_when_a_broker_node_is_killed(amqp_cluster, tmp_path):
    """10,000 messages AMQP -> AMQP through two engines; node 0 (the one both engines use,
    and the queue's leader) is killed with -9 mid-stream and restarted afterwards."""
    cluster: LocalCluster = amqp_cluster
    tag = uuid.uuid4().hex[:8]
    total = 10_000
    directory = routes_file(tmp_path / "routes", cluster, SHARED_ROUTE, tag=tag)
    engines = start_engines(directory, tmp_path, ["a", "b"])
    figures: dict[str, Any] = {}

    async def scenario() -> None:
        connection = await aio_pika.connect(cluster.urls[CLIENT_NODE])
        try:
            channel = await connection.channel(publisher_confirms=True)
            collector = await TimedCollector.bind_output(await connection.channel(), f"out-{tag}")
            publishing = asyncio.create_task(publish_seq(channel, f"in-{tag}", 0, total, rate=1500))
            await wait_for(lambda: len(collector.seq_arrivals) >= total // 4, 120, "a quarter of the stream")
            before = {e.status_file.stem: e.current_status()["brokers"]["gcs"] for e in engines}
            killed_at = time.monotonic()
            await asyncio.to_thread(cluster.kill, 0)
            figures["delivered_at_kill"] = len(collector.unique)
            await publishing
            await collector.wait_unique(total, 240)
            resumed = collector.first_after(killed_at)
            figures.update(
                sent=total,
                delivered=len(collector.unique),
                received=len(collector.seq_arrivals),
                duplicates=len(collector.seq_arrivals) - len(collector.unique),
                lost=total - len(collector.unique),
                first_arrival_after_kill_s=round(resumed - killed_at, 3) if resumed else None,
                stall_s=round(collector.stall(killed_at), 3),
                brokers_before=before,
                brokers_after={e.status_file.stem: e.current_status()["brokers"]["gcs"] for e in engines},
                per_engine_delivered={e.status_file.stem: e.current_status()["routes"][f"relay-{tag}"]["delivered"] for e in engines},
            )
        finally:
            await connection.close()

    try:
        asyncio.run(asyncio.wait_for(scenario(), 400))
    finally:
        stop_all(engines)
        cluster.restart(0)
        cluster.wait_running(3)
    report("node killed under two engines", figures)
    assert figures["lost"] == 0
    killed = cluster.nodes[0].url.rsplit(":", 1)[1].rstrip("/")
    assert all(endpoint.endswith(killed) for endpoint in figures["brokers_before"].values())
    assert not any(endpoint.endswith(killed) for endpoint in figures["brokers_after"].values()), figures
    assert all(count > 0 for count in figures["per_engine_delivered"].values()), "both engines carried the route"


ORDERED_ROUTE = """routes:
  - name: ordered-{tag}
    ordered: true
    source: {{amqp: {{connection: gcs, exchange: in-{tag}, queue: q-{tag}, prefetch: {prefetch}}}}}
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: out-{tag}, routing_key: "ordered"}}}}
"""


@pytest.mark.soak
@pytest.mark.timeout(450)  # its scenario's own bound is 300 s, and the session cluster may start in its setup
def test_ordered_route_fails_over_to_the_other_engine_in_order(amqp_cluster, tmp_path):
    cluster: LocalCluster = amqp_cluster
    tag = uuid.uuid4().hex[:8]
    total, prefetch = 3000, 50
    directory = routes_file(tmp_path / "routes", cluster, ORDERED_ROUTE, tag=tag, prefetch=str(prefetch))
    first = start_engines(directory, tmp_path, ["a"])[0]
    second = start_engines(directory, tmp_path, ["b"])[0]
    figures: dict[str, Any] = {}

    async def scenario() -> None:
        connection = await aio_pika.connect(cluster.urls[CLIENT_NODE])
        try:
            channel = await connection.channel(publisher_confirms=True)
            collector = await TimedCollector.bind_output(await connection.channel(), f"out-{tag}")
            publishing = asyncio.create_task(publish_seq(channel, f"in-{tag}", 0, total, rate=500, batch=1))
            await wait_for(lambda: len(collector.seq_arrivals) >= total // 3, 60, "a third of the stream")
            figures["standby_received_before_kill"] = second.current_status()["routes"][f"ordered-{tag}"]["received"]
            killed_at = kill_engine(first)
            seen_at_kill = collector.unique
            in_flight_from = min(set(range(total)) - seen_at_kill)
            await publishing
            await collector.wait_unique(total, 120)
            resumed = collector.first_after(killed_at)
            seen: set[int] = set()
            highest, out_of_order, late = -1, 0, []
            context: list[float] = []
            for index, (_, seq) in enumerate(collector.seq_arrivals):
                if seq < highest and seq not in seen:
                    out_of_order += 1
                    late.append(seq)
                    if not context:
                        context = [round(collector.seq_arrivals[index][0] - killed_at, 3)]
                        context += [s for _, s in collector.seq_arrivals[max(0, index - 40):index + 10]]
                seen.add(seq)
                highest = max(highest, seq)
            figures.update(
                sent=total,
                delivered=len(collector.unique),
                duplicates=len(collector.seq_arrivals) - len(collector.unique),
                out_of_order=out_of_order,
                late_outside_in_flight=[seq for seq in late if not in_flight_from <= seq < in_flight_from + prefetch],
                lost=total - len(collector.unique),
                takeover_s=round(resumed - killed_at, 3) if resumed else None,
                stall_s=round(collector.stall(killed_at), 3),
                survivor_delivered=second.current_status()["routes"][f"ordered-{tag}"]["delivered"],
                first_disorder=context,
            )
        finally:
            await connection.close()

    try:
        asyncio.run(asyncio.wait_for(scenario(), 300))
    finally:
        stop_all([first, second])
    report("ordered route, active engine killed", figures)
    assert figures["standby_received_before_kill"] == 0, "single active consumer: the second engine waits"
    assert figures["lost"] == 0
    # RabbitMQ 3.10's quorum queues may hand the dead consumer's unacknowledged messages to the
    # next one interleaved with newer messages (rabbitmq-server#6804): only those in flight
    # at the kill (at most prefetch) may come late or twice; everything else keeps its order.
    assert figures["late_outside_in_flight"] == [], figures
    assert figures["out_of_order"] <= prefetch
    assert figures["duplicates"] <= prefetch, "only messages in flight at the kill are redelivered"
    assert figures["survivor_delivered"] > 0


STANDBY_ROUTE = """  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
routes:
  - name: telemetry-{tag}
    active_standby: true
    lease: {{heartbeat: {heartbeat}}}
    source: {{ros2: {{connection: ros, topic: /{tag}/telemetry}}}}
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: out-{tag}, routing_key: "telemetry"}}}}
"""
STANDBY_HEARTBEAT = 0.5
TAKEOVER_BOUND_S = 2 * STANDBY_HEARTBEAT + 2.0
"""The stated bound: one heartbeat period for the new holder to hear a beat, one more of
slack, plus 2 s for the broker to drop the dead consumer and for a slow shared machine."""


@pytest.mark.soak
def test_active_standby_ros2_route_standby_takes_over_when_the_active_engine_dies(amqp_cluster, tmp_path):
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import String

    cluster: LocalCluster = amqp_cluster
    tag = "t" + uuid.uuid4().hex[:8]
    domain = ros_domain(2)
    rate = 200.0
    directory = routes_file(tmp_path / "routes", cluster, STANDBY_ROUTE, tag=tag, domain=str(domain),
                            heartbeat=str(STANDBY_HEARTBEAT))
    route = f"telemetry-{tag}"
    active = start_engines(directory, tmp_path, ["a"])[0]
    figures: dict[str, Any] = {}
    context = rclpy.Context()
    rclpy.init(args=[], context=context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(f"robot_{tag}", context=context)
    publisher = node.create_publisher(String, f"/{tag}/telemetry", QoSProfile(depth=10_000, reliability=ReliabilityPolicy.RELIABLE))
    standby: EngineProcess | None = None

    async def scenario() -> None:
        nonlocal standby
        await wait_for(lambda: (active.status() or {}).get("routes", {}).get(route, {}).get("role") == "active", 30, "engine a to hold the lease")
        standby = await asyncio.to_thread(lambda: start_engines(directory, tmp_path, ["b"])[0])
        await wait_for(lambda: node.count_subscribers(f"/{tag}/telemetry") >= 2, 30, "both engines to subscribe")
        connection = await aio_pika.connect(cluster.urls[CLIENT_NODE])
        published: list[float] = []
        stop = asyncio.Event()

        async def robot() -> None:
            began = time.monotonic()
            while not stop.is_set():
                publisher.publish(String(data=json.dumps({"seq": len(published)})))
                published.append(time.monotonic())
                ahead = len(published) / rate - (time.monotonic() - began)
                await asyncio.sleep(max(ahead, 0))  # pacing: the robot's rate

        try:
            collector = await TimedCollector.bind_output(await connection.channel(), f"out-{tag}")
            await asyncio.sleep(0.5)  # settle: as before this change, the cluster's output queue settles before the robot streams (not measured without the cluster)
            robot_task = asyncio.create_task(robot())
            await wait_for(lambda: len(collector.seq_arrivals) >= 400, 30, "the active engine to forward")
            await wait_for(lambda: standby.current_status()["routes"][route]["standby_skipped"] > 0, 10, "the standby to see the stream")
            figures["standby_role_before"] = standby.current_status()["routes"][route]["role"]
            figures["standby_forwarded_before"] = standby.current_status()["routes"][route]["delivered"]
            killed_at = kill_engine(active)
            at_kill = len(published)
            await wait_for(lambda: collector.first_after(killed_at + 0.05) is not None, 30, "the standby to forward")
            resumed = collector.first_after(killed_at + 0.05)
            assert resumed is not None  # waited for just above
            await asyncio.sleep(2.0)  # pacing: the stream goes on 2 s after the takeover (the behaviour under test)
            stop.set()
            await robot_task
            await wait_for(lambda: len(collector.unique) >= len(published) - 2 * rate * (resumed - killed_at + 0.5), 20, "the stream after takeover")
            await asyncio.sleep(1.0)  # quiet window: nothing more may arrive (the behaviour under test; no event says 'nothing')
            received = collector.unique
            missing = sorted(set(range(len(published))) - received)
            # the gap: what the active engine had taken and not forwarded when it died (after the last
            # message that reached the output before the kill; a ROS 2 topic cannot redeliver it), up to
            # the standby's first forward. A fixed window before the kill (0.5 s) missed the active's
            # backlog on a loaded machine: 5 messages fell outside it in a full run.
            last_before_kill = max((seq for at, seq in collector.seq_arrivals if at <= killed_at), default=-1)
            gap = [seq for seq in missing if seq > last_before_kill and published[seq] <= resumed + 0.2]
            outside = sorted(set(missing) - set(gap))
            figures.update(
                published=len(published),
                published_at_kill=at_kill,
                delivered=len(received),
                duplicates=len(collector.seq_arrivals) - len(received),
                lost_in_gap=len(gap),
                lost_outside_gap=len(outside),
                outside_gap_s_from_kill=[round(published[seq] - killed_at, 3) for seq in outside[:10]],
                backlog_at_kill=at_kill - 1 - last_before_kill,
                takeover_s=round(resumed - killed_at, 3),
                stall_s=round(collector.stall(killed_at), 3),
                survivor_role=standby.current_status()["routes"][route]["role"],
                survivor_delivered=standby.current_status()["routes"][route]["delivered"],
            )
        finally:
            stop.set()
            await connection.close()

    try:
        asyncio.run(asyncio.wait_for(scenario(), 240))
    finally:
        stop_all([active] + ([standby] if standby else []))
        node.destroy_node()
        context.try_shutdown()
    report("active/standby ROS 2 -> AMQP, active engine killed", figures)
    assert figures["standby_role_before"] == "standby"
    assert figures["standby_forwarded_before"] == 0
    assert max(figures["takeover_s"], figures["stall_s"]) <= TAKEOVER_BOUND_S, figures
    assert figures["survivor_role"] == "active" and figures["survivor_delivered"] > 0
    assert figures["lost_outside_gap"] == 0, figures
    assert figures["lost_in_gap"] <= rate * (figures["takeover_s"] + 0.7) + 10, figures


def test_check_reports_quorum_and_placement_mistakes_without_passwords(tmp_path):
    from tests.operator.test_cli import cli
    from tests.support.repo import REPO

    (tmp_path / "bad.yaml").write_text("""
connections:
  gcs: {amqp: {urls: ["amqp://farmer:S3cretPass@h1:5672/", "http://farmer:S3cretPass@h2/", "amqp://farmer:S3cretPass@h1:5672/"]}}
routes:
  - name: q
    source: {amqp: {connection: gcs, queue: q, queue_type: quorum, durable: false, queue_arguments: {x-max-priority: 5, x-queue-mode: lazy}}}
    schema: raw_json
    sink: {amqp: {connection: gcs, exchange: out}}
  - name: standby-on-amqp
    active_standby: true
    source: {amqp: {connection: gcs, queue: q2}}
    schema: raw_json
    sink: {amqp: {connection: gcs, exchange: out}}
  - name: ordered-ros
    ordered: true
    source: {ros2: {topic: /x}}
    schema: raw_json
    sink: {amqp: {connection: gcs, exchange: out}}
""")
    result = cli("check", "--routes", str(tmp_path), "--schemas", str(REPO / "schemas"))
    assert result.returncode == 1
    out = result.stderr
    assert "S3cretPass" not in out + result.stdout
    for expected in ("URL 2: not an amqp:// URL: 'http://farmer:***@h2/'", "URL 3:", "same node twice",
                     "quorum queue is always durable", "x-max-priority", "x-queue-mode",
                     "'standby-on-amqp'", "use ordered: true", "'ordered-ros': ordered does not apply to a ros2 source"):
        assert expected in out, (expected, out)
    assert all(line.startswith(str(tmp_path / "bad.yaml") + ":") for line in out.strip().splitlines())


PINNED_ROUTES = """routes:
  - name: here-{tag}
    instances: [gcs-1]
    source: {{amqp: {{connection: gcs, queue: here-{tag}}}}}
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: out-{tag}}}}}
  - name: there-{tag}
    instances: [gcs-2]
    source: {{amqp: {{connection: gcs, queue: there-{tag}}}}}
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: out-{tag}}}}}
"""


def test_routes_pinned_to_an_instance_run_only_there(amqp_cluster, tmp_path, schemas_dir):
    from engine.running.runtime import Engine

    tag = uuid.uuid4().hex[:8]
    directory = routes_file(tmp_path / "routes", amqp_cluster, PINNED_ROUTES, tag=tag)

    async def scenario() -> dict[str, Any]:
        engine = Engine(directory, schemas_dir, instance="gcs-1")
        await engine.start()
        try:
            return engine.status()
        finally:
            await engine.stop()

    status = asyncio.run(scenario())
    assert status["instance"] == "gcs-1"
    assert list(status["routes"]) == [f"here-{tag}"]
    assert status["elsewhere"] == [f"there-{tag}"]
    assert status["brokers"]["gcs"] == amqp_cluster.urls[0].split("@")[1].rstrip("/")


@pytest.mark.soak
def test_cli_local_cluster_runs_routes_on_three_nodes(tmp_path):
    """``--local-broker --cluster 3``: three nodes joined in one cluster, the default AMQP
    connection lists them all and declares quorum queues; stopped with the engine."""
    tag = uuid.uuid4().hex[:8]
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "r.yaml").write_text(f"""routes:
  - name: relay
    source: {{amqp: {{exchange: in-{tag}, queue: q-{tag}}}}}
    schema: raw_json
    sink: {{amqp: {{exchange: out-{tag}, routing_key: relayed}}}}
""")
    urls_file = tmp_path / "urls.txt"
    engine = EngineProcess(routes, tmp_path / "status.json", {}, "--local-broker", "--cluster", "3",
                           "--broker-url-file", str(urls_file), "--no-watch")
    try:
        status = engine.wait_started(180)
        urls = urls_file.read_text().split()
        assert len(urls) == 3 and len(set(urls)) == 3

        async def scenario() -> tuple[list[str], dict[str, Any]]:
            connection = await aio_pika.connect(urls[2])
            try:
                channel = await connection.channel()
                collector = await TimedCollector.bind_output(channel, f"out-{tag}")
                await publish_seq(await connection.channel(publisher_confirms=True), f"in-{tag}", 0, 10)
                await collector.wait_unique(10, 60)
                queue = await channel.declare_queue(f"q-{tag}", passive=True)
                # redeclaring with the other type fails: the engine declared a quorum queue
                other = await connection.channel()
                try:
                    await other.declare_queue(f"q-{tag}", durable=True, arguments={"x-queue-type": "classic"})
                    kind = "classic"
                except aio_pika.exceptions.ChannelPreconditionFailed:
                    kind = "quorum"
                return [kind], {"consumers": queue.declaration_result.consumer_count}
            finally:
                await connection.close()

        kinds, info = asyncio.run(asyncio.wait_for(scenario(), 120))
        assert kinds == ["quorum"] and info["consumers"] == 1
        assert status["brokers"]["default-amqp"] in urls[0]
    finally:
        assert engine.stop(120) == 0
    log = engine.log_file.read_text()
    assert log.count('"nodes"') >= 1 and "rabbitros-" in log
