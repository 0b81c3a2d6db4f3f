"""Scale-out on a private three-node RabbitMQ cluster: throughput of one vs two engine
instances sharing an AMQP -> AMQP route on quorum queues, against a relay written directly
on aiormq in the same run, and repeated failovers (median and max).

    .venv/bin/python -m bench.bench_scale [--count 20000] [--repeat 3] [--rounds 5] [--skip-ros] [--throughput-only]

Throughput: the source queue is filled first, then the engines (separate processes, as in
production) are started together; the rate is measured from the first message in the sink
queue to the last, so start-up is not counted. Failovers: a steady stream runs while
(a) the broker node the engines use is killed with -9 (then restarted), (b) the active
engine of an ``ordered: true`` route is killed with -9 (then started again, as standby),
(c) the active engine of an ``active_standby`` ROS 2 -> AMQP route is killed with -9; the
figure is the longest time the output stream stood still around the kill.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import statistics
import tempfile
import time
import uuid
from pathlib import Path

import aio_pika
import aiormq
from pamqp.common import FieldTable

from engine.endpoints.amqp.broker import LocalCluster
from tests.support.engine_process import EngineProcess
from tests.faults.test_cluster import TimedCollector, publish_seq

QUORUM: FieldTable = {"x-queue-type": "quorum"}
RELAY_ROUTE = """connections:
  gcs: {{amqp: {{urls: {urls}, queue_type: quorum}}}}
routes:
  - name: relay
    {ordered}source: {{amqp: {{connection: gcs, exchange: in-{tag}, queue: q-{tag}, prefetch: {prefetch}}}}}
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: out-{tag}, routing_key: "relayed"}}}}
"""
STANDBY_ROUTE = """connections:
  gcs: {{amqp: {{urls: {urls}, queue_type: quorum}}}}
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
routes:
  - name: telemetry
    active_standby: true
    lease: {{heartbeat: 0.5}}
    source: {{ros2: {{connection: ros, topic: /{tag}/telemetry}}}}
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: out-{tag}, routing_key: "telemetry"}}}}
"""


def engines(directory: Path, work: Path, names: list[str]) -> list[EngineProcess]:
    return [EngineProcess(directory, work / f"status-{name}-{uuid.uuid4().hex[:4]}.json", {},
                          "--instance", name, "--no-watch") for name in names]


def kill(engine: EngineProcess) -> float:
    os.killpg(engine.process.pid, signal.SIGKILL)
    moment = time.monotonic()
    engine.process.wait()
    return moment


async def fill(url: str, tag: str, count: int) -> None:
    connection = await aio_pika.connect(url)
    channel = await connection.channel(publisher_confirms=True)
    exchange = await channel.declare_exchange(f"in-{tag}", aio_pika.ExchangeType.TOPIC, durable=True)
    queue = await channel.declare_queue(f"q-{tag}", durable=True, arguments=QUORUM)
    await queue.bind(exchange, "#")
    out = await channel.declare_exchange(f"out-{tag}", aio_pika.ExchangeType.TOPIC, durable=True)
    sink = await channel.declare_queue(f"sink-{tag}", durable=True, arguments=QUORUM)
    await sink.bind(out, "#")
    await publish_seq(channel, f"in-{tag}", 0, count, batch=500)
    await connection.close()


def cpu_seconds(engines: list[EngineProcess]) -> float:
    """CPU time (user + system) of the engines' Python processes (children of ``timeout``)."""
    total = 0.0
    for engine in engines:
        try:
            children = Path(f"/proc/{engine.process.pid}/task/{engine.process.pid}/children").read_text().split()
            for pid in children:
                fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
                total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        except OSError:
            pass
    return total


async def drain_rate(url: str, tag: str, count: int, engines: list[EngineProcess], timeout: float = 600) -> tuple[float, float]:
    """msg/s from the first message in the sink queue to the last, and the engines' CPU
    microseconds per message over the same span."""
    connection = await aio_pika.connect(url)
    channel = await connection.channel()
    first_at = None
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        queue = await channel.declare_queue(f"sink-{tag}", passive=True)
        have = queue.declaration_result.message_count
        assert have is not None, "a passive Queue.Declare's DeclareOk carries the message count"
        now = time.monotonic()
        if have and first_at is None:
            first_at, first_count, first_cpu = now, have, cpu_seconds(engines)
        if have >= count:
            await connection.close()
            assert first_at is not None
            moved = max(count - first_count, 1)
            return moved / max(now - first_at, 1e-3), (cpu_seconds(engines) - first_cpu) / moved * 1e6
        await asyncio.sleep(0.05)
    raise TimeoutError(f"sink-{tag} did not reach {count}")


async def reference_relay(url: str, tag: str, count: int, prefetch: int) -> None:
    """What the engine does, written directly on aiormq: consume, publish with confirms in
    batches, one multiple ack per batch."""
    connection = await aiormq.connect(url)
    consume = await connection.channel()
    publish = await connection.channel(publisher_confirms=True)
    await consume.basic_qos(prefetch_count=prefetch)
    pending: list[aiormq.abc.DeliveredMessage] = []
    arrived = asyncio.Event()

    async def on_message(message: aiormq.abc.DeliveredMessage) -> None:
        pending.append(message)
        arrived.set()

    await consume.basic_consume(f"q-{tag}", on_message)
    done = 0
    while done < count:
        await arrived.wait()
        arrived.clear()
        batch, pending[:] = list(pending[: prefetch // 2]), pending[prefetch // 2:]
        if pending:
            arrived.set()
        if not batch:
            continue
        await asyncio.gather(*(publish.basic_publish(m.body, exchange=f"out-{tag}", routing_key="relayed",
                                                     properties=aiormq.spec.Basic.Properties(delivery_mode=2))
                               for m in batch))
        last = batch[-1].delivery_tag
        assert last is not None, "a Basic.Deliver always carries its delivery tag"
        await consume.basic_ack(last, multiple=True)
        done += len(batch)
    await connection.close()


async def throughput(cluster: LocalCluster, work: Path, count: int, repeat: int, prefetch: int = 400) -> dict[str, float]:
    """Medians over ``repeat`` interleaved passes: the machine is shared, and a neighbour's
    load during one measurement would otherwise decide the ratio."""
    passes = [await throughput_pass(cluster, work, count, prefetch) for _ in range(repeat)]
    medians = {label: statistics.median(p[label] for p in passes) for label in passes[0]}
    ratios = [p["2 instances"] / p["1 instance"] for p in passes]
    print("  medians: " + ", ".join(f"{label} {rate:.0f} msg/s" for label, rate in medians.items())
          + f"; 2/1 per pass: {', '.join(f'{r:.2f}' for r in ratios)}")
    return medians


async def throughput_pass(cluster: LocalCluster, work: Path, count: int, prefetch: int) -> dict[str, float]:
    client = cluster.urls[2]
    results: dict[str, float] = {}
    for label, instances in (("reference", 0), ("1 instance", 1), ("2 instances", 2)):
        tag = uuid.uuid4().hex[:8]
        await fill(client, tag, count)
        started: list[EngineProcess] = []
        relay = None
        if instances:
            directory = work / f"routes-{tag}"
            directory.mkdir()
            (directory / "r.yaml").write_text(RELAY_ROUTE.format(urls=json.dumps(cluster.urls[:2]), tag=tag, prefetch=prefetch, ordered=""))
            started = engines(directory, work, [f"e{i}" for i in range(instances)])
        else:
            relay = asyncio.create_task(reference_relay(cluster.urls[0], tag, count, prefetch))
        try:
            results[label], cpu_us = await drain_rate(client, tag, count, started)
        finally:
            for engine in started:
                engine.stop()
            if relay:
                await relay
        cpu = f"   engines' CPU {cpu_us:5.0f} us/msg" if instances else ""
        print(f"  {label:12} {results[label]:8.0f} msg/s{cpu}", flush=True)
    return results


async def node_failovers(cluster: LocalCluster, work: Path, rounds: int) -> list[float]:
    tag = uuid.uuid4().hex[:8]
    directory = work / f"routes-{tag}"
    directory.mkdir()
    (directory / "r.yaml").write_text(RELAY_ROUTE.format(urls=json.dumps(cluster.urls[:2]), tag=tag, prefetch=200, ordered=""))
    pair = engines(directory, work, ["a", "b"])
    for engine in pair:
        engine.wait_started(90)
    connection = await aio_pika.connect(cluster.urls[2])
    stalls = []
    try:
        channel = await connection.channel(publisher_confirms=True)
        collector = await TimedCollector.bind_output(await connection.channel(), f"out-{tag}")
        total = 0
        for _ in range(rounds):
            stream = asyncio.create_task(publish_seq(channel, f"in-{tag}", total, total + 6000, rate=1000))
            total += 6000
            await asyncio.sleep(2.0)
            in_use = pair[0].current_status()["brokers"]["gcs"]
            index = next(i for i, url in enumerate(cluster.urls) if in_use in url)
            killed_at = time.monotonic()
            await asyncio.to_thread(cluster.kill, index)
            await stream
            await collector.wait_unique(total, 120)
            stalls.append(collector.stall(killed_at))
            print(f"  node {index + 1} killed: stream stood still {stalls[-1]:.2f} s; "
                  f"{len(collector.seq_arrivals) - len(collector.unique)} duplicates so far, 0 lost", flush=True)
            await asyncio.to_thread(cluster.restart, index)
            await asyncio.to_thread(cluster.wait_running, 3)
    finally:
        await connection.close()
        for engine in pair:
            engine.stop()
    return stalls


async def ordered_failovers(cluster: LocalCluster, work: Path, rounds: int) -> list[float]:
    tag = uuid.uuid4().hex[:8]
    directory = work / f"routes-{tag}"
    directory.mkdir()
    (directory / "r.yaml").write_text(RELAY_ROUTE.format(urls=json.dumps(cluster.urls), tag=tag, prefetch=50, ordered="ordered: true\n    "))
    live = {name: engines(directory, work, [name])[0] for name in ("a", "b")}
    for engine in live.values():
        engine.wait_started(90)
    connection = await aio_pika.connect(cluster.urls[2])
    stalls = []
    try:
        channel = await connection.channel(publisher_confirms=True)
        collector = await TimedCollector.bind_output(await connection.channel(), f"out-{tag}")
        total = 0
        for _ in range(rounds):
            stream = asyncio.create_task(publish_seq(channel, f"in-{tag}", total, total + 2000, rate=500, batch=1))
            total += 2000
            await asyncio.sleep(1.5)
            before = {name: e.current_status()["routes"]["relay"]["received"] for name, e in live.items()}
            await asyncio.sleep(0.6)
            active = max(live, key=lambda name: live[name].current_status()["routes"]["relay"]["received"] - before[name])
            killed_at = kill(live[active])
            await stream
            await collector.wait_unique(total, 120)
            stalls.append(collector.stall(killed_at))
            print(f"  active engine {active} killed: stream stood still {stalls[-1]:.2f} s", flush=True)
            live[active] = engines(directory, work, [active])[0]
            live[active].wait_started(90)
    finally:
        await connection.close()
        for engine in live.values():
            engine.stop()
    return stalls


async def standby_failovers(cluster: LocalCluster, work: Path, rounds: int) -> list[float]:
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import String

    tag = "b" + uuid.uuid4().hex[:8]
    domain = 1 + (os.getpid() + 53) % 100
    directory = work / f"routes-{tag}"
    directory.mkdir()
    (directory / "r.yaml").write_text(STANDBY_ROUTE.format(urls=json.dumps(cluster.urls), tag=tag, domain=domain))
    context = rclpy.Context()
    rclpy.init(args=[], context=context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(f"robot_{tag}", context=context)
    publisher = node.create_publisher(String, f"/{tag}/telemetry", QoSProfile(depth=10_000, reliability=ReliabilityPolicy.RELIABLE))
    live = {name: engines(directory, work, [name])[0] for name in ("a", "b")}
    for engine in live.values():
        engine.wait_started(90)
    connection = await aio_pika.connect(cluster.urls[2])
    stalls: list[float] = []
    ready: list[float] = []
    stop = asyncio.Event()
    published: list[float] = []

    async def robot() -> None:
        began = time.monotonic()
        while not stop.is_set():
            publisher.publish(String(data=json.dumps({"seq": len(published)})))
            published.append(time.monotonic())
            await asyncio.sleep(max(len(published) / 200 - (time.monotonic() - began), 0))

    try:
        collector = await TimedCollector.bind_output(await connection.channel(), f"out-{tag}")
        task = asyncio.create_task(robot())
        for _ in range(rounds):
            await asyncio.sleep(2.0)
            active = next(n for n, e in live.items() if e.current_status()["routes"]["telemetry"]["role"] == "active")
            killed_at = kill(live[active])
            await asyncio.sleep(4.0)
            around = [seq for seq, at in enumerate(published) if killed_at - 1.0 <= at <= killed_at + 3.0]
            lost = len(set(around) - collector.unique)
            stalls.append(collector.stall(killed_at, 4.0))
            survivor = next(e for n, e in live.items() if n != active).current_status()["routes"]["telemetry"]
            print(f"  active engine {active} killed: stream stood still {stalls[-1]:.2f} s "
                  f"({lost} robot messages lost in the gap; survivor {survivor['role']}, "
                  f"forwarded {survivor['delivered']}, skipped {survivor['standby_skipped']})", flush=True)
            live[active] = engines(directory, work, [active])[0]
            live[active].wait_started(90)
            restarted = time.monotonic()
            while live[active].current_status()["routes"]["telemetry"]["standby_skipped"] == 0:
                if time.monotonic() - restarted > 120:
                    raise TimeoutError("the restarted engine never saw the robot's messages")
                await asyncio.sleep(0.1)
            ready.append(time.monotonic() - restarted)
            print(f"  restarted engine {active} sees the stream (ready as standby) after {ready[-1]:.1f} s", flush=True)
        stop.set()
        await task
        print(summary("restarted standby ready", ready))
    finally:
        stop.set()
        await connection.close()
        for engine in live.values():
            engine.stop()
        node.destroy_node()
        context.try_shutdown()
    return stalls


def summary(name: str, values: list[float]) -> str:
    return f"{name}: median {statistics.median(values):.2f} s, max {max(values):.2f} s over {len(values)} samples"


async def main(args: argparse.Namespace) -> None:
    cluster = LocalCluster(3)
    began = time.monotonic()
    await asyncio.to_thread(cluster.start)
    print(f"three-node cluster up in {time.monotonic() - began:.1f} s", flush=True)
    try:
        with tempfile.TemporaryDirectory(prefix="bench-scale-") as tmp:
            work = Path(tmp)
            print(f"throughput, AMQP -> AMQP on quorum queues, {args.count} messages:")
            rates = await throughput(cluster, work, args.count, args.repeat)
            print(f"  medians, engine/reference: 1 instance {rates['1 instance'] / rates['reference']:.2f}, "
                  f"2 instances {rates['2 instances'] / rates['reference']:.2f}; "
                  f"2 instances / 1 instance: {rates['2 instances'] / rates['1 instance']:.2f}")
            if args.throughput_only:
                return
            print("broker node killed under two engines:")
            lines = [summary("node failover (stream stall)", await node_failovers(cluster, work, args.rounds))]
            print("ordered route, active engine killed:")
            lines.append(summary("ordered takeover (stream stall)", await ordered_failovers(cluster, work, args.rounds)))
            if not args.skip_ros:
                print("active/standby ROS 2 -> AMQP, active engine killed:")
                lines.append(summary("standby takeover (stream stall)", await standby_failovers(cluster, work, args.rounds)))
            print("\n".join(lines))
    finally:
        await asyncio.to_thread(cluster.stop)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--count", type=int, default=20000)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--skip-ros", action="store_true")
    parser.add_argument("--throughput-only", action="store_true")
    parser.add_argument("--repeat", type=int, default=3, help="throughput passes (medians are reported)")
    asyncio.run(main(parser.parse_args()))
