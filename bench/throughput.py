"""Maximum zero-loss throughput of each route kind, against its references, in one run.

Every bridge (the engine, the reference pass-throughs on the client libraries, the paper's
design) runs alone in a child process (``bench.systems``) on the same broker and the same
load, and is observed from outside the same way:

* AMQP sources drain a pre-filled durable queue of persistent messages; ROS 2 sources drain a
  burst held by DDS history (depth 10,000); the rate is taken between 10 % and 100 % of the
  messages at the sink, so start-up is not counted;
* MAVLink (UDP) has no buffer to drain: a sender paces GLOBAL_POSITION_INT at rising rates and
  the highest rate at which every message arrived is the zero-loss throughput;
* zero loss is checked by counting at the sink (AMQP: the bound queue's message count; ROS 2:
  a subscriber in this process).

Latency p50/p99 at half the measured rate comes from the engine itself (t2 - t1 of every message).
"""

from __future__ import annotations

import asyncio
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any, AsyncIterator

from pamqp.commands import Basic

from bench.systems import gnss_json

Properties = Basic.Properties

REPO = Path(__file__).resolve().parent.parent
GNSS_MAPPING = "{type: 'position', agent_id: agent, stamp: to_stamp(stamp), lat: lat, lon: lon, alt_msl: alt}"
MAVLINK_POSITION_MAPPING = (
    "{type: 'position', agent_id: 'uav1', stamp: stamp_boot_ms(time_boot_ms), time_boot_ms: time_boot_ms, "
    "lat: deg_e7_to_deg(lat), lon: deg_e7_to_deg(lon), alt_msl: mm_to_m(alt), alt_rel: mm_to_m(relative_alt), "
    "velocity_enu: ned_to_enu([cm_to_m(vx), cm_to_m(vy), cm_to_m(vz)]), heading: heading_cdeg_to_deg(hdg)}"
)
STALL_S = 8.0
"""No progress at the sink for this long ends a measurement (the rest counts as lost)."""


def domain_id() -> int:
    return 100 + os.getpid() % 100


class Child:
    """A bench.systems process; ``ready`` once it has printed so, stopped with SIGTERM."""

    def __init__(self, system: str, args: dict[str, Any], env: dict[str, str] | None = None) -> None:
        self.system = system
        self.stderr = tempfile.TemporaryFile("w+")
        self.process = subprocess.Popen(
            ["timeout", "-s", "KILL", "600", sys.executable, "-m", "bench.systems", system, json.dumps(args)],
            cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO), **(env or {})},
            stdout=subprocess.PIPE, stderr=self.stderr, text=True, start_new_session=True,
        )
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.lines.append(line.strip())

    async def wait_for(self, prefix: str, timeout: float = 60.0) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for line in self.lines:
                if line.startswith(prefix):
                    return line
            if self.process.poll() is not None:
                break
            await asyncio.sleep(0.02)
        raise RuntimeError(f"{self.system}: no {prefix!r} within {timeout:.0f}s (exit {self.process.poll()}): {self.errors()}")

    def errors(self) -> str:
        self.stderr.seek(0)
        return self.stderr.read()[-3000:]

    def cpu_seconds(self) -> float:
        """CPU time (user + system) the child's processes have used so far."""
        total = 0
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit():
                continue
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[2]) == self.process.pid:  # the process group (start_new_session)
                total += int(fields[11]) + int(fields[12])
        return total / os.sysconf("SC_CLK_TCK")

    async def stop(self, timeout: float = 20.0) -> None:
        if self.process.poll() is None:
            os.killpg(self.process.pid, 15)
            deadline = time.monotonic() + timeout
            while self.process.poll() is None and time.monotonic() < deadline:
                await asyncio.sleep(0.05)
            if self.process.poll() is None:
                os.killpg(self.process.pid, 9)
                self.process.wait()


class Broker:
    """Declarations, pre-filling and sink counting on one aiormq connection."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.connection: Any = None
        self.channel: Any = None

    async def open(self) -> None:
        import aiormq

        self.connection = await aiormq.connect(self.url)
        self.channel = await self.connection.channel()

    async def close(self) -> None:
        await self.connection.close()

    async def topology(self, tag: str) -> dict[str, str]:
        """A source queue (durable), an output exchange and a sink queue bound to all of it."""
        names = {"queue": f"bench-in-{tag}", "exchange": f"bench-out-{tag}", "sink": f"bench-sink-{tag}",
                 "routing_key": "canonical.position.uav1"}
        channel = self.channel
        await channel.queue_declare(names["queue"], durable=True)
        await channel.exchange_declare(names["exchange"], exchange_type="topic", durable=True)
        await channel.queue_declare(names["sink"], durable=True)
        await channel.queue_bind(names["sink"], names["exchange"], routing_key="#")
        return names

    async def drop(self, names: dict[str, str]) -> None:
        await self.channel.queue_delete(names["queue"])
        await self.channel.queue_delete(names["sink"])
        await self.channel.exchange_delete(names["exchange"])

    async def count(self, queue: str) -> int:
        return int((await self.channel.queue_declare(queue, passive=True)).message_count)

    async def prefill(self, queue: str, bodies: list[bytes], wait: bool = True) -> None:
        properties = Properties(delivery_mode=2, content_type="application/json")
        for index, body in enumerate(bodies):
            await self.channel.basic_publish(body, routing_key=queue, properties=properties)
            if index % 1000 == 999:
                await asyncio.sleep(0)
        deadline = time.monotonic() + 60
        while wait and await self.count(queue) < len(bodies) and time.monotonic() < deadline:
            await asyncio.sleep(0.05)

    async def publish_paced(self, queue: str, count: int, rate: float) -> None:
        properties = Properties(delivery_mode=2, content_type="application/json")
        began = time.monotonic()
        for index in range(count):
            await self.channel.basic_publish(gnss_json(index), routing_key=queue, properties=properties)
            delay = began + (index + 1) / rate - time.monotonic()
            if delay > 0.0005:
                await asyncio.sleep(delay)


async def observe(counter: Any, total: int, stall: float = STALL_S, first: float = 40.0) -> dict[str, Any]:
    """Poll ``await counter()`` until it reaches ``total`` or stalls; the rate between 10 %
    and the end, with the number that arrived. The first message may take ``first`` seconds
    (DDS discovery on a busy machine)."""
    samples: list[tuple[float, int]] = []
    last_change, last = time.monotonic() + first - stall, 0
    while True:
        now, seen = time.monotonic(), await counter()
        samples.append((now, seen))
        if seen != last:
            last_change, last = now, seen
        if seen >= total or now - last_change > stall:
            break
        await asyncio.sleep(0.02)
    start = next(((t, n) for t, n in samples if n >= total * 0.1), samples[0])
    end = next(((t, n) for t, n in samples if n >= seen), samples[-1])
    rate = (end[1] - start[1]) / (end[0] - start[0]) if end[0] > start[0] else float("nan")
    return {"msg_per_s": rate, "delivered": seen, "sent": total, "lost": max(0, total - seen), "done_at": end[0]}


class RosCounter:
    """Counts what a bridge publishes on a topic (a plain rclpy subscription taken in batches)."""

    def __init__(self, domain: int, topic: str) -> None:
        from std_msgs.msg import String

        from bench.systems import TakeLoop, _qos, _ros_context

        self.count = 0
        self.context, self.node = _ros_context(domain)
        self.subscription = self.node.create_subscription(String, topic, lambda msg: None, _qos(latched=True))
        self.taker = TakeLoop(self.context, self.subscription, String, self._on_batch)

    def _on_batch(self, batch: list[Any]) -> None:
        self.count += len(batch)

    async def value(self) -> int:
        return self.count

    async def matched(self, timeout: float = 40.0) -> None:
        deadline = time.monotonic() + timeout
        while self.subscription.get_publisher_count() < 1 and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        await asyncio.sleep(0.5)

    def close(self) -> None:
        self.taker.stop()
        self.node.destroy_node()
        self.context.try_shutdown()


def routes_file(directory: Path, kind: str, names: dict[str, str], url: str, domain: int, port: int = 0,
                mapping: str | None = GNSS_MAPPING, schema: str = "position", confirms: bool = True) -> Path:
    amqp_source = f"amqp: {{queue: {names['queue']}, prefetch: 1000}}"
    amqp_sink = f"amqp: {{exchange: {names['exchange']}, routing_key: \"canonical.position.{{agent_id}}\"}}"
    if schema == "raw_json":
        amqp_sink = f"amqp: {{exchange: {names['exchange']}, routing_key: {names['routing_key']}}}"
    ros_topic = f"/bench/{names['queue'].replace('-', '_')}"
    source, sink, extra = {
        "amqp-amqp": (amqp_source, amqp_sink, ""),
        "amqp-ros2": (amqp_source, f"ros2: {{topic: {ros_topic}, qos: {{durability: transient_local}}}}", ""),
        "ros2-amqp": (f"ros2: {{topic: {ros_topic}}}", amqp_sink, ""),
        "mavlink-amqp": ("mavlink: {message: GLOBAL_POSITION_INT, system_id: 1}", amqp_sink,
                         f"\n  uav: {{mavlink: \"udpin:127.0.0.1:{port}\", heartbeat: 0}}"),
    }[kind]
    if kind == "mavlink-amqp":
        mapping = MAVLINK_POSITION_MAPPING
    lines = [
        "connections:",
        f"  gcs: {{amqp: {{url: \"{url}\", publisher_confirms: {str(confirms).lower()}}}}}",
        f"  ros: {{ros2: {{domain_id: {domain}, node: bench_engine_{os.getpid()}}}}}{extra}",
        "routes:",
        "  - name: bench",
        f"    source: {{{source}}}",
        *([f"    mapping: \"{mapping}\""] if mapping else []),
        f"    schema: {schema}",
        f"    sink: {{{sink}}}",
    ]
    path = directory / "bench.yaml"
    path.write_text("\n".join(lines) + "\n")
    return path


def free_udp_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@asynccontextmanager
async def child(system: str, args: dict[str, Any]) -> AsyncIterator[Child]:
    process = Child(system, args)
    try:
        await process.wait_for("ready")
        yield process
    finally:
        await process.stop()


async def drain_amqp_source(broker: Broker, kind: str, system: str, count: int, domain: int,  # noqa: PLR0913
                            body: Any = gnss_json, schema: str = "position", mapping: str | None = GNSS_MAPPING) -> dict[str, Any]:
    """AMQP -> AMQP or AMQP -> ROS 2: the bridge drains ``count`` pre-filled messages.

    The rate is read at the source, from the queue's ready count (a message leaves the queue
    when the bridge has it, is acknowledged once the sink accepted it, and the prefetch window
    bounds what is taken but not yet settled): from 85 % left to empty. Loss is checked at the
    sink, which must receive every message."""
    tag = uuid.uuid4().hex[:8]
    names = await broker.topology(tag)
    topic = f"/bench/{names['queue'].replace('-', '_')}"
    counter = RosCounter(domain, topic) if kind == "amqp-ros2" else None
    await broker.prefill(names["queue"], [body(i) for i in range(count)])
    try:
        with tempfile.TemporaryDirectory() as work:
            args: dict[str, Any] = {"url": broker.url, "domain": domain, "topic": topic, **names}
            if system == "engine":
                args["routes"] = str(routes_file(Path(work), kind, names, broker.url, domain, schema=schema, mapping=mapping).parent)
            async with child(system, args) as bridge:
                result = await observe_source(broker, names["queue"], count)
                sink = counter.value if counter else (lambda: broker.count(names["sink"]))
                arrived = await observe(sink, count)
                result.update(delivered=arrived["delivered"], lost=arrived["lost"])
                if result["lost"]:
                    result["errors"] = bridge.errors()[-1000:]
    finally:
        if counter:
            counter.close()
        await broker.drop(names)
    return result


async def observe_source(broker: Broker, queue: str, total: int) -> dict[str, Any]:
    samples: list[tuple[float, int]] = []
    last_change, last = time.monotonic() + 40.0 - STALL_S, total
    while True:
        now, ready = time.monotonic(), await broker.count(queue)
        samples.append((now, ready))
        if ready != last:
            last_change, last = now, ready
        if ready == 0 or now - last_change > STALL_S:
            break
        await asyncio.sleep(0.02)
    start = next(((t, n) for t, n in samples if n <= total * 0.85), samples[-1])
    end = samples[-1]
    rate = (start[1] - end[1]) / (end[0] - start[0]) if end[0] > start[0] else float("nan")
    return {"msg_per_s": rate, "sent": total}


async def drain_ros2_source(broker: Broker, system: str, count: int, domain: int) -> dict[str, Any]:
    """ROS 2 -> AMQP: a publisher bursts ``count`` messages (held by DDS history) into the bridge."""
    tag = uuid.uuid4().hex[:8]
    names = await broker.topology(tag)
    topic = f"/bench/{names['queue'].replace('-', '_')}"
    try:
        with tempfile.TemporaryDirectory() as work:
            args: dict[str, Any] = {"url": broker.url, "domain": domain, "topic": topic, **names}
            if system == "engine":
                args["routes"] = str(routes_file(Path(work), "ros2-amqp", names, broker.url, domain).parent)
            async with child(system, args) as bridge:
                publisher = Child("ros-publisher", {"domain": domain, "topic": topic, "count": count, "rate": 0})
                try:
                    result = await observe(lambda: broker.count(names["sink"]), count)
                    if result["lost"]:
                        result["errors"] = bridge.errors()[-1000:] + publisher.errors()[-1000:]
                finally:
                    await publisher.stop()
    finally:
        await broker.drop(names)
    return result


def udp_drops(port: int) -> int:
    """Datagrams the kernel dropped at the socket bound to ``port`` (its receive buffer was full)."""
    for line in Path("/proc/net/udp").read_text().splitlines()[1:]:
        fields = line.split()
        if int(fields[1].rsplit(":", 1)[1], 16) == port:
            return int(fields[-1])
    return 0


async def mavlink_ladder(broker: Broker, system: str, rates: list[int], seconds: float,
                         attempts: int = 2, refine: int = 2) -> dict[str, Any]:
    """MAVLink (UDP) -> AMQP: the highest paced rate the bridge sustains with zero loss.

    A step passes when every message arrived and the sink kept up: the messages reached it
    at no less than 90 % of the paced rate, from the sender's first frame to the last
    message at the sink (a bridge that only queues what it cannot carry would otherwise pass
    a short step and fall behind for good on a long one). Every system climbs the same
    ladder in the same way: each rate is sent for ``seconds`` by a fresh sender; a step
    that fails (or whose sender fell behind) is tried again, up to
    ``attempts`` times, since on a shared machine one pause of a few hundred ms fills any UDP
    receive buffer; the climb ends at the first rate that fails every attempt, and ``refine``
    bisections between it and the last rate passed sharpen the result (1,000 msg/s steps
    alone would move a ratio by a sixth). Each step
    records the kernel's drops at the bridge's socket (``udp_drops``): loss there means the
    bridge did not read in time, loss elsewhere is the bridge's own."""
    tag = uuid.uuid4().hex[:8]
    names = await broker.topology(tag)
    port = free_udp_port()
    steps = []
    try:
        with tempfile.TemporaryDirectory() as work:
            args: dict[str, Any] = {"url": broker.url, "port": port, **names}
            if system == "engine":
                args["routes"] = str(routes_file(Path(work), "mavlink-amqp", names, broker.url, domain_id(), port=port).parent)
            async with child(system, args):
                delivered = [0]

                async def passes(rate: int) -> bool:
                    for attempt in range(1, attempts + 1):
                        count = int(rate * seconds)
                        drops_before = udp_drops(port)
                        sender = Child("mavlink-sender", {"port": port, "rate": rate, "count": count})
                        await sender.wait_for("sending", timeout=30)
                        began = time.monotonic()
                        sent_line = await sender.wait_for("sent", timeout=seconds * 4 + 30)
                        achieved = count / float(sent_line.split()[-1])
                        result = await observe(lambda: broker.count(names["sink"]), delivered[0] + count,
                                               stall=2.0, first=10.0)
                        arrived = result["delivered"] - delivered[0]
                        delivered[0] = result["delivered"]
                        step = {"rate": rate, "attempt": attempt, "sent_rate": achieved, "sent": count,
                                "delivered": arrived, "lost": count - arrived,
                                "sink_rate": arrived / max(1e-3, result["done_at"] - began),
                                "udp_drops": udp_drops(port) - drops_before}
                        step["passed"] = (not step["lost"] and achieved >= rate * 0.9
                                          and step["sink_rate"] >= rate * 0.9)
                        steps.append(step)
                        if step["passed"]:
                            return True
                    return False

                passed, failed = 0, None
                for rate in rates:
                    if not await passes(rate):
                        failed = rate
                        break
                    passed = rate
                for _ in range(refine if failed is not None else 0):  # between the last rate passed and the first failed
                    middle = (passed + failed) // 2
                    if middle in (passed, failed):
                        break
                    if await passes(middle):
                        passed = middle
                    else:
                        failed = middle
    finally:
        await broker.drop(names)
    zero_loss = [s for s in steps if s["passed"]]
    return {"msg_per_s": max((s["rate"] for s in zero_loss), default=0), "steps": steps,
            "lost": 0 if zero_loss else steps[-1]["lost"]}


async def engine_latency_at_rate(broker: Broker, kind: str, rate: float, seconds: float, domain: int) -> dict[str, Any]:
    """The engine's own t2 - t1 for every message while the source runs at ``rate``."""
    tag = uuid.uuid4().hex[:8]
    names = await broker.topology(tag)
    port = free_udp_port()
    topic = f"/bench/{names['queue'].replace('-', '_')}"
    count = max(50, int(rate * seconds))
    counter = RosCounter(domain, topic) if kind == "amqp-ros2" else None
    try:
        with tempfile.TemporaryDirectory() as work:
            latency_file = Path(work) / "latency.json"
            routes = routes_file(Path(work), kind, names, broker.url, domain, port=port).parent
            async with child("engine", {"routes": str(routes), "latency_out": str(latency_file)}) as engine:
                if kind in ("amqp-amqp", "amqp-ros2"):
                    await broker.publish_paced(names["queue"], count, rate)
                elif kind == "ros2-amqp":
                    publisher = Child("ros-publisher", {"domain": domain, "topic": topic, "count": count, "rate": rate})
                    await publisher.wait_for("published", timeout=seconds * 3 + 60)
                else:
                    sender = Child("mavlink-sender", {"port": port, "rate": rate, "count": count})
                    await sender.wait_for("sent", timeout=seconds * 3 + 30)
                sink = counter.value if counter else (lambda: broker.count(names["sink"]))
                arrived = await observe(sink, count, stall=3.0)
                await engine.stop()
            samples = json.loads(latency_file.read_text()).get("bench", [])
    finally:
        if counter:
            counter.close()
        await broker.drop(names)
    ms = sorted(ns / 1e6 for ns in samples)
    return {"rate": rate, "count": count, "delivered": arrived["delivered"], **summary(ms)}


def summary(ms: list[float]) -> dict[str, float]:
    if not ms:
        return {"n": 0}
    ms = sorted(ms)
    return {
        "n": len(ms), "mean": statistics.fmean(ms), "std": statistics.pstdev(ms), "min": ms[0], "max": ms[-1],
        "p50": ms[len(ms) // 2], "p99": ms[min(len(ms) - 1, int(len(ms) * 0.99))],
    }
