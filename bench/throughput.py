"""Throughput of each route kind against its references, interleaved and repeated in one run.

Every bridge (the engine, the reference pass-throughs on the client libraries, the paper's
design) runs in a child process (``bench.systems``) on the same broker and the same load, and
is observed from outside the same way. A sequential search of each system's maximum zero-loss
rate gave the same code ratios from 0.39 to 1.28 for one kind on a quiet 2-core machine
(bench/results/2026-11-23/ratios): the broker, the load generator, the counter and the bridge
share two cores, so a reference measured a minute before the engine saw another machine.
:func:`interleaved` therefore starts every system of a kind once (:class:`Bridge`), drains
the same backlog through each in rounds, A B then B A (``pairs`` rounds, after one warm-up
drain each), and takes the ratio within each round: the median per-round ratio and its spread
(min-max and interquartile range) are what the report gives, next to the absolute rates. Only
the system being measured runs; the others are stopped (SIGSTOP). Each drain also gives the
bridge's CPU time per message (its processes' user + system time over the same window), which
the machine's other load moves much less than the wall-clock rate.

How each source kind is drained (the rate is taken at the sink, from 10 % of the messages to
the last, so the bridge's wake-up is not counted), and why that is the least noisy choice:

* AMQP sources: the bridge's durable queue is filled with ``count`` persistent messages
  (confirmed by the broker) while the bridge is stopped, then it continues and drains them.
  The same N each time, and no publisher runs during the measurement.
* ROS 2 sources: a publisher bursts ``count`` messages as fast as rclpy goes once the bridge's
  subscription matched; reliable, keep-last 10,000 on both sides, so the burst (at most 9,000)
  is held by DDS history and none may be lost. A fixed offered rate above capacity would lose
  messages by design (keep-last history overwrites) and keep the publisher busy for the whole
  measurement, where a burst is published in a fraction of the drain and leaves the bridge
  draining its reader history alone for the rest. The bridge cannot be stopped while its
  history fills: a stopped reliable reader stalls the writer's protocol, whose resends are
  timed.
* MAVLink over UDP: while the bridge is stopped a sender fills its socket's receive buffer
  (4 MiB asked, the engine's own: about 10,000 datagrams of GLOBAL_POSITION_INT) with
  ``count`` frames, none dropped by the kernel (checked), then the bridge continues and drains
  them. A paced ladder of rates decided each step by the longest pause in it (one pause of a
  few hundred ms on a shared machine overflows any UDP buffer) and ran the sender during the
  measurement; the drain measures the same carrying capacity with nothing else running.

Latency p50/p99 at half the measured rate comes from the engine itself (t2 - t1 of every message).
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import signal
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
from engine.common.processes import process_usage

Properties = Basic.Properties

REPO = Path(__file__).resolve().parent.parent
GNSS_MAPPING = "{type: 'position', agent_id: agent, stamp: to_stamp(stamp), lat: lat, lon: lon, alt_msl: alt}"
MAVLINK_POSITION_MAPPING = (
    "{type: 'position', agent_id: 'uav1', stamp: stamp_boot_ms(time_boot_ms), time_boot_ms: time_boot_ms, "
    "lat: deg_e7_to_deg(lat), lon: deg_e7_to_deg(lon), alt_msl: mm_to_m(alt), alt_rel: mm_to_m(relative_alt), "
    "velocity_enu: ned_to_enu([cm_to_m(vx), cm_to_m(vy), cm_to_m(vz)]), heading: heading_cdeg_to_deg(hdg)}"
)
MAX_BURST = 9000
"""Most messages of one drain: a ROS 2 burst must fit DDS history (keep-last 10,000) and a
MAVLink one the UDP socket's receive buffer (about 10,000 datagrams of 8 MiB at Linux's
accounting)."""
STALL_S = 8.0
"""No progress at the sink for this long ends a measurement (the rest counts as lost)."""


def domain_id() -> int:
    return 100 + os.getpid() % 100


class Child:
    """A bench.systems process; ``ready`` once it has printed so, stopped with SIGTERM."""

    def __init__(self, system: str, args: dict[str, Any], env: dict[str, str] | None = None, limit_s: float = 600) -> None:
        """``limit_s``: the child is killed (SIGKILL) after this long whatever happens."""
        self.system = system
        self.stderr = tempfile.TemporaryFile("w+")
        self.process = subprocess.Popen(
            ["timeout", "-s", "KILL", str(int(limit_s)), sys.executable, "-m", "bench.systems", system, json.dumps(args)],
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

    def group_pids(self) -> list[int]:
        """The processes of the child's group besides its leader (``timeout``)."""
        pids = []
        for entry in Path("/proc").iterdir():
            if entry.name.isdigit() and int(entry.name) != self.process.pid:
                try:
                    if int((entry / "stat").read_text().rsplit(")", 1)[1].split()[2]) == self.process.pid:
                        pids.append(int(entry.name))
                except OSError:
                    continue
        return pids

    def pause(self) -> None:
        """Stop the child's processes (SIGSTOP): whatever is sent to it waits in its buffers."""
        os.killpg(self.process.pid, signal.SIGSTOP)

    def resume(self) -> None:
        os.killpg(self.process.pid, signal.SIGCONT)

    async def stop(self, timeout: float = 20.0) -> None:
        if self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGTERM)
            os.killpg(self.process.pid, signal.SIGCONT)  # a paused child must see its SIGTERM
            deadline = time.monotonic() + timeout
            while self.process.poll() is None and time.monotonic() < deadline:
                await asyncio.sleep(0.05)
            if self.process.poll() is None:
                os.killpg(self.process.pid, signal.SIGKILL)
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

    async def prefill_confirmed(self, queue: str, bodies: list[bytes]) -> None:
        """Publish ``bodies`` (persistent) to ``queue`` and return once the broker confirmed
        every one: they are all in the queue or already delivered to its consumer."""
        channel = await self.connection.channel(publisher_confirms=True)
        properties = Properties(delivery_mode=2, content_type="application/json")
        try:
            for begin in range(0, len(bodies), 1000):
                await asyncio.gather(*(channel.basic_publish(body, routing_key=queue, properties=properties)
                                       for body in bodies[begin:begin + 1000]))
        finally:
            await channel.close()

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
    """A port for the engine's (or the reference's) ``udpin`` link, below the ephemeral range."""
    import socket

    from engine.common.processes import listening_port

    return listening_port(kind=socket.SOCK_DGRAM)


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
            args: dict[str, Any] = {"url": broker.url, "domain": domain, "topic": topic, "convert": mapping is not None, **names}
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
            args: dict[str, Any] = {"url": broker.url, "domain": domain, "topic": topic, "convert": True, **names}
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


class Bridge:
    """One system of a route kind (``engine``, a reference or the paper's design), started once
    for all its drains on its own topology, and stopped (SIGSTOP) whenever it is not the one
    being measured: the paper's design spins its executor every 0.5 ms even when idle, and only
    the system under measurement may use the machine. A pause lasts a few seconds, well within
    DDS's participant lease (Fast DDS: 20 s), so ROS 2 matches survive it."""

    def __init__(self, broker: Broker, kind: str, system: str, domain: int, work: Path) -> None:
        self.broker, self.kind, self.system, self.domain, self.work = broker, kind, system, domain, work
        self.names: dict[str, str] = {}
        self.port = free_udp_port()
        self.counter: RosCounter | None = None
        self.child: Child | None = None
        self.pids: list[int] = []

    @property
    def topic(self) -> str:
        return f"/bench/{self.names['queue'].replace('-', '_')}"

    async def start(self) -> None:
        self.names = await self.broker.topology(uuid.uuid4().hex[:8])
        if self.kind == "amqp-ros2":
            self.counter = RosCounter(self.domain, self.topic)
        args: dict[str, Any] = {"url": self.broker.url, "domain": self.domain, "topic": self.topic, "port": self.port,
                                "convert": True, **self.names}
        if self.system == "engine":
            directory = self.work / self.names["queue"]
            directory.mkdir()
            args["routes"] = str(routes_file(directory, self.kind, self.names, self.broker.url, self.domain, port=self.port).parent)
        self.child = Child(self.system, args)
        await self.child.wait_for("ready")
        self.pids = [self.child.process.pid, *self.child.group_pids()]
        if self.counter is not None:
            await self.counter.matched()
        self.child.pause()

    async def sunk(self) -> int:
        """Messages at the sink so far."""
        if self.counter is not None:
            return self.counter.count
        return await self.broker.count(self.names["sink"])

    def cpu_seconds(self) -> float:
        return sum(process_cpu_seconds(pid) for pid in self.pids)

    async def drain(self, count: int) -> dict[str, Any]:
        """One drain of ``count`` messages (the module's docstring says how, per source kind);
        the bridge runs only during it."""
        assert self.child is not None
        if self.counter is None:
            await self.broker.channel.queue_purge(self.names["sink"])
        base, extra = await self.sunk(), {}
        if self.kind == "ros2-amqp":
            self.child.resume()
            publisher = Child("ros-publisher", {"domain": self.domain, "topic": self.topic, "count": count, "rate": 0})
            try:
                result = await observe_drain(self.sunk, base, count, self.cpu_seconds)
            finally:
                await publisher.stop()
        else:
            if self.kind == "mavlink-amqp":
                drops_before = udp_drops(self.port)
                sender = Child("mavlink-sender", {"port": self.port, "rate": 0, "count": count})
                await sender.wait_for("sent", timeout=60)
                extra["kernel_drops"] = udp_drops(self.port) - drops_before
            else:
                await self.broker.prefill_confirmed(self.names["queue"], [gnss_json(i) for i in range(count)])
            self.child.resume()
            result = await observe_drain(self.sunk, base, count - extra.get("kernel_drops", 0), self.cpu_seconds)
        self.child.pause()
        result.update(extra, sent=count, lost=count - result["delivered"])
        if result["lost"]:
            result["errors"] = self.child.errors()[-1000:]
        return result

    async def stop(self) -> None:
        if self.child is not None:
            await self.child.stop()
        if self.counter is not None:
            self.counter.close()
        if self.names:
            await self.broker.drop(self.names)


def process_cpu_seconds(pid: int) -> float:
    """CPU time (user + system, all threads) process ``pid`` has used, 0 once it is gone."""
    usage = process_usage(pid)
    return usage.cpu_s if usage is not None else 0.0


async def observe_drain(sunk: Any, base: int, total: int, cpu: Any, stall: float = STALL_S) -> dict[str, Any]:
    """Poll the sink until ``total`` messages arrived past ``base`` or it stalls; the rate and
    the bridge's CPU time per message between 10 % of them and the last (start-up, the first
    batches and, for ROS 2, the publisher's start are not counted)."""
    samples: list[tuple[float, int, float]] = []
    last_change, last = time.monotonic() + 40.0 - stall, 0
    while True:
        now, seen = time.monotonic(), await sunk() - base
        samples.append((now, seen, cpu()))
        if seen != last:
            last_change, last = now, seen
        if seen >= total or now - last_change > stall:
            break
        await asyncio.sleep(0.02)
    start = next((sample for sample in samples if sample[1] >= total * 0.1), samples[0])
    end = next(sample for sample in samples if sample[1] >= seen)
    carried = end[1] - start[1]
    rate = carried / (end[0] - start[0]) if end[0] > start[0] else float("nan")
    cpu_s = end[2] - start[2]  # clock ticks (10 ms): a drain shorter than a few of them has no figure
    cpu_us = cpu_s * 1e6 / carried if carried > 0 and cpu_s > 0 else float("nan")
    return {"msg_per_s": rate, "cpu_us_per_msg": cpu_us, "delivered": seen}


def spread(values: list[float]) -> dict[str, float]:
    """Median, min-max and interquartile range of ``values`` (at least one)."""
    ordered = sorted(values)
    quartiles = statistics.quantiles(ordered, n=4, method="inclusive") if len(ordered) > 1 else [ordered[0]] * 3
    return {"median": statistics.median(ordered), "min": ordered[0], "max": ordered[-1],
            "q1": quartiles[0], "q3": quartiles[2], "n": len(ordered)}


async def interleaved(broker: Broker, kind: str, systems: dict[str, str], pairs: int, count: int,
                      domain: int, counts: dict[str, int] | None = None) -> dict[str, Any]:
    """``pairs`` rounds of one drain per system (``systems``: role -> system, ``engine`` among
    them), in alternating order (A B, B A, ...), after one warm-up drain each; the engine's
    ratio to every other role taken within each round, for the rate and (inverted, so that
    above 1 is better for the engine too) for CPU time per message. A failed drain (an error,
    or messages lost) gives its round no ratio. ``counts`` gives a role a smaller drain (the
    paper's design carries a few hundred msg/s: ``count`` messages would take it half a
    minute a round)."""
    roles = list(systems)
    counts = {role: count for role in roles} | (counts or {})
    rounds: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as work:
        # one ROS 2 domain per bridge: a stopped participant on the measured one's domain slowed its drains 5-10x
        bridges = {role: Bridge(broker, kind, systems[role], 100 + (domain - 100 + 33 * index) % 100, Path(work))
                   for index, role in enumerate(roles)}
        try:
            for role, bridge in bridges.items():
                await bridge.start()
                await bridge.drain(max(500, counts[role] // 5))  # warm-up, not counted
            for index in range(pairs):
                trial: dict[str, Any] = {"load": os.getloadavg()[0]}
                for role in (roles if index % 2 == 0 else roles[::-1]):
                    print(f"  {kind} round {index + 1}/{pairs}: {systems[role]}", flush=True)
                    try:
                        trial[role] = await bridges[role].drain(counts[role])
                    except Exception as exc:
                        trial[role] = {"error": f"{type(exc).__name__}: {exc}"[:2000], "msg_per_s": float("nan")}
                rounds.append(trial)
        finally:
            for bridge in bridges.values():
                await bridge.stop()
    return summarize(rounds, roles, pairs, counts)


def summarize(rounds: list[dict[str, Any]], roles: list[str], pairs: int, counts: dict[str, int]) -> dict[str, Any]:
    row: dict[str, Any] = {"rounds": rounds, "pairs": pairs, "counts": counts}
    for role in roles:
        good = [r[role] for r in rounds if _good(r[role])]
        row[role] = {**spread([g["msg_per_s"] for g in good]), "msg_per_s": statistics.median(g["msg_per_s"] for g in good),
                     "cpu_us_per_msg": _median_finite(g["cpu_us_per_msg"] for g in good)} if good else {
            "msg_per_s": float("nan"), "error": next((r[role]["error"] for r in rounds if "error" in r[role]), "lost")}
        row[role]["lost"] = sum(r[role].get("lost", 0) for r in rounds)
    for role in roles:
        if role == "engine":
            continue
        pairs_good = [(r["engine"], r[role]) for r in rounds if _good(r["engine"]) and _good(r[role])]
        if pairs_good:
            ratios = [engine["msg_per_s"] / other["msg_per_s"] for engine, other in pairs_good]
            row[f"vs_{role}"] = statistics.median(ratios)
            row[f"vs_{role}_spread"] = spread(ratios)
            cpu = [other["cpu_us_per_msg"] / engine["cpu_us_per_msg"] for engine, other in pairs_good
                   if math.isfinite(engine["cpu_us_per_msg"]) and math.isfinite(other["cpu_us_per_msg"])]
            if cpu:
                row[f"cpu_vs_{role}_spread"] = spread(cpu)
    return row


def _median_finite(values: Any) -> float:
    finite = [value for value in values if math.isfinite(value)]
    return statistics.median(finite) if finite else float("nan")


def _good(result: dict[str, Any]) -> bool:
    rate = result.get("msg_per_s", float("nan"))
    return "error" not in result and not result.get("lost") and math.isfinite(rate) and rate > 0


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
