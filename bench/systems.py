"""The bridges the benchmark compares, each run alone in a child process until SIGTERM.

    python -m bench.systems SYSTEM '{"url": ..., ...}'

* ``engine``: the RabbitROS engine on a routes file (on its default loop, engine/running/loop.py); with
  ``latency_out`` it records every message's reception-to-acceptance time (t2 - t1) and
  writes them there when stopped.
* ``ref-amqp-amqp``: the plain aiormq pass-through of issue 10: consume with prefetch 1,000
  (a 300-frame channel buffer, as the engine's sources), publish each batch of received messages pipelined on a confirm channel (persistent),
  one ``basic_ack(multiple=True)`` per batch.
* ``ref-amqp-ros2``: the same consumer, each batch published as std_msgs/String with rclpy.
* ``ref-ros2-amqp``: an rclpy subscription taken in batches from rcl's wait set in a thread
  -> the batched aiormq publisher.
* ``ref-mavlink-amqp``: UDP datagrams -> pymavlink ``parse_buffer`` -> GLOBAL_POSITION_INT
  converted by hand to the canonical position -> the batched aiormq publisher.
* ``ref-fleet``: bench/fleet.py's whole fleet (100 ROS 2 topics and 7 ``udpin`` links to one
  exchange, a command queue per agent back) in one process on rclpy, pymavlink and aiormq:
  :func:`ref_fleet`.
* ``paper-amqp-ros2`` / ``paper-ros2-amqp``: the paper's own design re-implemented:
  aio-pika, rclpy's default executor spun from the asyncio loop, pure-Python ``jsonschema``
  validation and synchronous logging of every message, publisher confirms off; with
  ``latency_out`` the AMQP -> ROS 2 one records t2 - t1 as the engine does (bench/ct_l1.py);
  with ``minimal`` it neither validates nor logs (the least the design can do per message).

References do no schema validation: they are what the client libraries allow, the bound. They
do the route's conversion written by hand (``convert``: orjson, the mapping as code, sorted-key
orjson), the same work on the body the engine's route does, with the same acknowledgement
and confirm semantics (a source message acknowledged once its batch is published; confirms
awaited per batch).
"""

from __future__ import annotations

import asyncio
import functools
import json
import logging
import os
import signal
import sys
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

from pamqp.commands import Basic

from engine.common.stamps import from_ns, to_stamp

Properties = Basic.Properties

REPO = Path(__file__).resolve().parent.parent


# ---------------------------------------------------------------- shared pieces

async def _until_stopped() -> None:
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    loop.add_signal_handler(signal.SIGINT, stop.set)
    print("ready", flush=True)
    await stop.wait()


def _ros_context(domain: int) -> tuple[Any, Any]:
    import rclpy
    from rclpy.context import Context
    from rclpy.signals import SignalHandlerOptions

    context = Context()
    rclpy.init(args=[], context=context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(f"bench_{os.getpid()}", context=context, start_parameter_services=False)
    return context, node


def _qos(latched: bool = False) -> Any:
    """Reliable, keep-last 10,000 (the engine's default); ``latched`` (transient local) where a
    bridge may publish before the bench's counter has matched."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    durability = DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE
    return QoSProfile(depth=10_000, reliability=ReliabilityPolicy.RELIABLE, durability=durability)


class BatchPublisher:
    """Publishes whatever has been queued, pipelined, confirms awaited together."""

    def __init__(self, channel: Any, exchange: str, routing_key: str) -> None:
        self.channel = channel
        self.exchange = exchange
        self.routing_key = routing_key
        self.properties = Properties(delivery_mode=2, content_type="application/json")
        self.pending: deque[bytes] = deque()
        self.ready = asyncio.Event()

    def put(self, body: bytes) -> None:
        self.pending.append(body)
        self.ready.set()

    async def run(self) -> None:
        publish, exchange, key, properties = self.channel.basic_publish, self.exchange, self.routing_key, self.properties
        while True:
            await self.ready.wait()
            self.ready.clear()
            batch = [self.pending.popleft() for _ in range(len(self.pending))]
            if batch:
                await asyncio.gather(*(publish(b, exchange=exchange, routing_key=key, properties=properties) for b in batch))


def _converter(args: dict[str, Any]) -> Any:
    """What a reference does to each body: the route's GNSS mapping written by hand
    (orjson in, :func:`to_canonical`, sorted-key orjson out: the engine's canonical bytes)
    where the engine's route has that mapping (``args['convert']``), else nothing (an
    identity route). A reference that forwarded the bytes untouched would be measured
    against an engine that parses, maps and serializes every message."""
    if not args.get("convert"):
        return None
    import orjson

    loads, dumps, sort = orjson.loads, orjson.dumps, orjson.OPT_SORT_KEYS

    def convert(body: bytes) -> bytes:
        return dumps(to_canonical(loads(body)), option=sort)

    return convert


def position_from_global_position_int(msg: Any) -> dict[str, Any]:
    """What the engine's uav1-position mapping computes, written by hand."""
    vx, vy, vz = msg.vx / 100, msg.vy / 100, msg.vz / 100
    return {
        "type": "position", "agent_id": "uav1", "stamp": from_ns(time.time_ns()), "time_boot_ms": msg.time_boot_ms,
        "lat": msg.lat / 1e7, "lon": msg.lon / 1e7, "alt_msl": msg.alt / 1000, "alt_rel": msg.relative_alt / 1000,
        "velocity_enu": [vy, vx, -vz], "heading": None if msg.hdg == 65535 else msg.hdg / 100,
    }


def _rss_kib() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


# ---------------------------------------------------------------- the engine

async def engine(args: dict[str, Any]) -> None:
    from bench import probes
    from engine.running.runtime import Engine

    bridge = Engine(Path(args["routes"]), REPO / "schemas")
    began = time.perf_counter()
    await bridge.start()
    print(f"started {time.perf_counter() - began:.4f} {_rss_kib()}", flush=True)
    latency = {name: probes.latency(runner) for name, runner in bridge.runners.items()} if args.get("latency_out") else {}
    # reception to the sink (without the sink's own wait): bench/fleet.py
    handed = {name: probes.handed(runner) for name, runner in bridge.runners.items()} if args.get("handed_out") else {}
    try:
        await _until_stopped()
    finally:
        if args.get("latency_out"):
            Path(args["latency_out"]).write_text(json.dumps({name: probe.samples for name, probe in latency.items()}))
        if args.get("handed_out"):
            Path(args["handed_out"]).write_text(json.dumps({name: probe.samples for name, probe in handed.items()}))
        if args.get("publish_out"):  # each AMQP connection's publishes and the rounds that carried them
            rounds = {connection.name: {key: health[key] for key in ("published", "publish_rounds")}
                      for protocol, connection in bridge.open_connections() if protocol == "amqp"
                      for health in (connection.health(),)}
            Path(args["publish_out"]).write_text(json.dumps(rounds))
        await bridge.stop()


# ---------------------------------------------------------------- references on the client libraries

async def _aiormq_consumer(args: dict[str, Any], handle_batch: Any) -> Any:
    """Consume ``args['queue']``; each batch handed to ``handle_batch(bodies)`` (awaited),
    then acknowledged with one multiple=True ack."""
    import aiormq

    connection = await aiormq.connect(args["url"])
    # the engine's sources buffer 300 frames (engine/endpoints/amqp/source.py FRAME_BUFFER:
    # aiormq's default of 10 let a drain reach the consumer 3 messages at a time); the
    # reference asks the same through aiormq's public argument, so neither is held to the default
    channel = await connection.channel(frame_buffer_size=300)
    await channel.basic_qos(prefetch_count=1000)
    received: list[Any] = []
    ready = asyncio.Event()

    async def on_message(message: Any) -> None:
        received.append(message)
        ready.set()

    async def pump() -> None:
        while True:
            await ready.wait()
            ready.clear()
            batch = received[:]
            del received[: len(batch)]
            if batch:
                await handle_batch([m.body for m in batch])
                await channel.basic_ack(batch[-1].delivery_tag, multiple=True)

    task = asyncio.create_task(pump())
    await channel.basic_consume(args["queue"], on_message, no_ack=False)
    return connection, task


async def ref_amqp_amqp(args: dict[str, Any]) -> None:
    import aiormq

    out = await aiormq.connect(args["url"])
    publish_channel = await out.channel(publisher_confirms=True)
    properties = Properties(delivery_mode=2, content_type="application/json")
    publish, exchange, key = publish_channel.basic_publish, args["exchange"], args["routing_key"]
    convert = _converter(args)

    async def forward(bodies: list[bytes]) -> None:
        if convert:
            bodies = [convert(b) for b in bodies]
        await asyncio.gather(*(publish(b, exchange=exchange, routing_key=key, properties=properties) for b in bodies))

    connection, task = await _aiormq_consumer(args, forward)
    await _until_stopped()
    task.cancel()
    await connection.close()
    await out.close()


async def ref_amqp_ros2(args: dict[str, Any]) -> None:
    from std_msgs.msg import String

    context, node = _ros_context(args["domain"])
    publisher = node.create_publisher(String, args["topic"], _qos(latched=True))
    message = String()
    convert = _converter(args)

    async def forward(bodies: list[bytes]) -> None:
        for body in bodies:
            message.data = (convert(body) if convert else body).decode()
            publisher.publish(message)

    connection, task = await _aiormq_consumer(args, forward)
    await _until_stopped()
    task.cancel()
    await connection.close()
    node.destroy_node()
    context.try_shutdown()


class TakeLoop:
    """A thread that blocks in rcl's wait set on one subscription and takes every ready
    message, handing each batch to ``on_batch`` (in that thread). This is what rclpy's
    executors do inside, without their per-callback machinery; rclpy's EventsExecutor,
    spun in a thread, holds the GIL here and starves the asyncio thread."""

    def __init__(self, context: Any, subscription: Any, cls: type, on_batch: Any) -> None:
        self.context, self.subscription, self.cls, self.on_batch = context, subscription, cls, on_batch
        self.stopped = False
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

        handle, cls = self.subscription.handle, self.cls
        while not self.stopped:
            with handle, self.context.handle:
                wait_set = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, self.context.handle)
                wait_set.clear_entities()
                wait_set.add_subscription(handle)
                wait_set.wait(100_000_000)  # ns: wakes up to notice ``stopped``
                batch = []
                while (taken := handle.take_message(cls, False)) is not None:
                    batch.append(taken[0])
            if batch:
                self.on_batch(batch)

    def stop(self) -> None:
        self.stopped = True
        self.thread.join(5)


async def ref_ros2_amqp(args: dict[str, Any]) -> None:
    import aiormq
    from std_msgs.msg import String

    connection = await aiormq.connect(args["url"])
    channel = await connection.channel(publisher_confirms=True)
    batcher = BatchPublisher(channel, args["exchange"], args["routing_key"])
    loop = asyncio.get_running_loop()
    context, node = _ros_context(args["domain"])

    def put_all(bodies: list[bytes]) -> None:
        for body in bodies:
            batcher.put(body)

    convert = _converter(args)

    def on_batch(batch: list[Any]) -> None:  # the take thread
        bodies = [msg.data.encode() for msg in batch]
        loop.call_soon_threadsafe(put_all, [convert(b) for b in bodies] if convert else bodies)

    subscription = node.create_subscription(String, args["topic"], lambda msg: None, _qos())
    taker = TakeLoop(context, subscription, String, on_batch)
    task = asyncio.create_task(batcher.run())
    await _until_stopped()
    taker.stop()
    task.cancel()
    await connection.close()
    node.destroy_node()
    context.try_shutdown()


async def ref_mavlink_amqp(args: dict[str, Any]) -> None:
    os.environ["MAVLINK20"] = "1"
    import socket

    import aiormq
    import orjson

    from engine.endpoints.mavlink.links import UDP_RECEIVE_BUFFER
    from pymavlink.dialects.v20 import common as mavlink2

    connection = await aiormq.connect(args["url"])
    channel = await connection.channel(publisher_confirms=True)
    batcher = BatchPublisher(channel, args["exchange"], args["routing_key"])
    parser = mavlink2.MAVLink(None)
    parser.robust_parsing = True
    wanted = mavlink2.MAVLINK_MSG_ID_GLOBAL_POSITION_INT

    class Datagrams(asyncio.DatagramProtocol):
        def datagram_received(self, data: bytes, addr: Any) -> None:
            for msg in parser.parse_buffer(data) or ():
                if msg.get_msgId() == wanted:
                    batcher.put(orjson.dumps(position_from_global_position_int(msg), option=orjson.OPT_SORT_KEYS))

    loop = asyncio.get_running_loop()
    transport, _ = await loop.create_datagram_endpoint(Datagrams, local_addr=("127.0.0.1", args["port"]))
    # the same kernel receive buffer as the engine's UDP link asks for
    transport.get_extra_info("socket").setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RECEIVE_BUFFER)
    task = asyncio.create_task(batcher.run())
    await _until_stopped()
    task.cancel()
    transport.close()
    await connection.close()


# ---------------------------------------------------------------- the fleet's reference (bench/fleet.py)

FLEET_COMMAND = 31010
"""MAV_CMD_USER_1, as bench/fleet.py's command routes send it."""
FLEET_PUBLISH_CHANNELS = 8
"""Confirm channels the fleet's reference publishes on, each stream always on the same one (its
order kept). aiormq's ``basic_publish`` holds its channel's lock while its frame waits for room
in the connection's 10-frame write queue, and asyncio hands a lock over one loop turn at a
time: past ten publishes in one turn, one channel publishes ONE message per loop turn, and a
burst (a stall of the process on a loaded machine) drains no faster than the load arrives.
On one channel the full fleet (2,000 msg/s) took p50 246 ms from reception to confirm while
handing its messages over within 3 ms, end to end p99 2.4 s (bench/fleet.py, load 2-4). In one
run, 35 robots and 35 vehicles for 20 s, load 2.0-2.5: one channel p99 119 ms end to end
(reception to confirm 117 ms), eight channels 39 ms (42 ms)."""
FLEET_PEER_TTL = 30.0
"""Seconds a vehicle's address is kept after its last datagram: the engine's ``udpin`` link's
PEER_TTL (engine/endpoints/mavlink/links.py), for our HEARTBEAT."""


class FleetTakeThread:
    """:class:`TakeLoop` for many subscriptions: one thread blocks in rcl's wait set on all of
    them (GIL released) and takes every ready message, handing each wake-up's batch to
    ``on_batch([(subscription index, body, reception ns), ...])`` in that thread. The wait set
    and the hold on the handles are made once: rebuilding them at every wake-up enters each of
    the 100 handles with the GIL held (the engine's waiter learned that on this bench)."""

    def __init__(self, context: Any, subscriptions: list[Any], cls: type, on_batch: Any) -> None:
        self.context, self.subscriptions, self.cls, self.on_batch = context, subscriptions, cls, on_batch
        self.stopped = False
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        from contextlib import ExitStack

        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

        handles = [sub.handle for sub in self.subscriptions]
        index = {handle.pointer: slot for slot, handle in enumerate(handles)}
        cls, on_batch, monotonic_ns = self.cls, self.on_batch, time.monotonic_ns
        with ExitStack() as held:
            for handle in handles:
                held.enter_context(handle)
            held.enter_context(self.context.handle)
            wait_set = _rclpy.WaitSet(len(handles), 0, 0, 0, 0, 0, self.context.handle)
            while not self.stopped:
                wait_set.clear_entities()
                for handle in handles:
                    wait_set.add_subscription(handle)
                wait_set.wait(100_000_000)  # ns: wakes up to notice ``stopped``
                now = monotonic_ns()
                batch = []
                for pointer in wait_set.get_ready_entities("subscription"):
                    slot = index[pointer]
                    handle = handles[slot]
                    while (taken := handle.take_message(cls, False)) is not None:
                        batch.append((slot, taken[0].data.encode(), now))
                if batch:
                    on_batch(batch)

    def stop(self) -> None:
        self.stopped = True
        self.thread.join(5)


async def ref_fleet(args: dict[str, Any]) -> None:
    """bench/fleet.py's fleet bridged without the engine, on the client libraries: rclpy
    (subscriptions taken by :class:`FleetTakeThread`, publishers for the commands), asyncio
    datagram endpoints on the ``udpin`` ports the engine would bind, pymavlink to parse and
    encode, aiormq to publish (persistent, confirm channel) and consume (one channel, each
    agent's queue declared and bound as the engine's route does, prefetch 256 per consumer as
    the engine's source asks). Telemetry bodies: a robot's unchanged, a vehicle's the JSON its
    route's mapping makes (sorted-key orjson, the engine's canonical bytes). Publishes are
    pipelined, each loop turn's messages together (``wait=False``: aiormq would otherwise hold
    its channel lock until the writer task has written each frame, one loop round trip per
    message), their confirms awaited in a task of their own while the next turn publishes, on
    :data:`FLEET_PUBLISH_CHANNELS` confirm channels (one channel serializes a burst). A
    command is acknowledged once sent. Like the engine's links, each link sends our HEARTBEAT
    at 1 Hz to the vehicles heard on it.

    ``args``: url, out / cmd (exchanges), domain, robots (names), links ([[port, [system ids]]]),
    optional publish_channels (:data:`FLEET_PUBLISH_CHANNELS`),
    optional latency_out / handed_out: per stream kind, reception to confirm (or to the
    command's send) and reception to publish, in ns, written when stopped (as the engine's
    runners record them for bench/fleet.py)."""
    os.environ["MAVLINK20"] = "1"
    import socket

    import aiormq
    import orjson
    from pymavlink.dialects.v20 import common as mavlink2
    from std_msgs.msg import String

    from engine.endpoints.mavlink.links import UDP_RECEIVE_BUFFER

    began = time.perf_counter()
    loop = asyncio.get_running_loop()
    out, cmd = args["out"], args["cmd"]
    robots: list[str] = args["robots"]
    links: list[tuple[int, list[int]]] = [(int(port), [int(sid) for sid in ids]) for port, ids in args["links"]]
    record = bool(args.get("latency_out") or args.get("handed_out"))
    kinds = ("robots-fix", "robots-battery", "uavs-position", "uavs-attitude", "robots-cmd", "uavs-cmd")
    accepted: dict[str, list[int]] = {kind: [] for kind in kinds}  # names bench/fleet.py's _route_kind reads
    handed: dict[str, list[int]] = {kind: [] for kind in kinds}
    failures = [0]

    connection = await aiormq.connect(args["url"])
    channels = int(args.get("publish_channels", FLEET_PUBLISH_CHANNELS))
    publish_channels = [await connection.channel(publisher_confirms=True) for _ in range(channels)]
    publishes = [channel.basic_publish for channel in publish_channels]
    properties = Properties(delivery_mode=2, content_type="application/json")

    # -- telemetry -> the out exchange: each loop turn's messages published together
    pending: list[tuple[Any, str, bytes, int, str]] = []  # (its channel's publish, routing key, body, reception ns, kind)
    flushing: set[asyncio.Task[None]] = set()

    async def confirm(batch: list[tuple[Any, str, bytes, int, str]]) -> None:
        if record:
            now = time.monotonic_ns()
            for _, _, _, received, kind in batch:
                handed[kind].append(now - received)
        results = await asyncio.gather(*(publish(body, exchange=out, routing_key=key, properties=properties, wait=False)
                                         for publish, key, body, _, _ in batch), return_exceptions=True)
        now = time.monotonic_ns()
        for (_, _, _, received, kind), result in zip(batch, results):
            if isinstance(result, BaseException) or not isinstance(result, Basic.Ack):
                failures[0] += 1
            elif record:
                accepted[kind].append(now - received)

    def flush() -> None:
        batch = pending[:]
        pending.clear()
        task = asyncio.create_task(confirm(batch))
        flushing.add(task)
        task.add_done_callback(flushing.discard)

    def put(items: list[tuple[Any, str, bytes, int, str]]) -> None:
        if not pending:
            loop.call_soon(flush)
        pending.extend(items)

    # -- ROS 2: the robots' topics in, their command topics out
    context, node = _ros_context(int(args["domain"]))
    streams = [(publishes[number % channels], f"{agent}.{stream}", f"robots-{stream}")
               for number, agent in enumerate(robots) for stream in ("fix", "battery")]
    subscriptions = [node.create_subscription(String, f"/{agent}/{stream}", lambda msg: None, _qos())
                     for agent in robots for stream in ("fix", "battery")]

    def on_ros_batch(batch: list[tuple[int, bytes, int]]) -> None:  # the take thread
        loop.call_soon_threadsafe(put, [(streams[slot][0], streams[slot][1], body, received, streams[slot][2])
                                        for slot, body, received in batch])

    command_publishers = {agent: node.create_publisher(String, f"/{agent}/cmd", _qos()) for agent in robots}

    # -- MAVLink: one datagram endpoint per link, a parser per vehicle address
    heard: dict[int, tuple[asyncio.DatagramTransport, Any]] = {}  # system id -> (its link, its address)
    heard_event = {sid: asyncio.Event() for _, ids in links for sid in ids}
    senders: list[tuple[asyncio.DatagramTransport, Any, dict[Any, float]]] = []  # (transport, MAVLink, peers)
    GPI, ATT, HB = (mavlink2.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, mavlink2.MAVLINK_MSG_ID_ATTITUDE,
                    mavlink2.MAVLINK_MSG_ID_HEARTBEAT)
    dumps, sort = orjson.dumps, orjson.OPT_SORT_KEYS

    class Link(asyncio.DatagramProtocol):
        def __init__(self, ids: list[int]) -> None:
            self.agents = {sid: (f"uav{sid}", f"uav{sid}.position", f"uav{sid}.attitude",
                                 publishes[sid % channels]) for sid in ids}
            self.parsers: dict[Any, Any] = {}
            self.peers: dict[Any, float] = {}
            self.transport: asyncio.DatagramTransport | None = None

        def connection_made(self, transport: Any) -> None:
            self.transport = transport

        def datagram_received(self, data: bytes, addr: Any) -> None:
            received = time.monotonic_ns()
            self.peers[addr] = time.monotonic()
            parser = self.parsers.get(addr)
            if parser is None:
                parser = self.parsers[addr] = mavlink2.MAVLink(None)
                parser.robust_parsing = True
            items = []
            for msg in parser.parse_buffer(data) or ():
                msg_id = msg.get_msgId()
                names = self.agents.get(msg.get_srcSystem())
                if names is None:
                    continue
                if msg_id == GPI:  # the position route's mapping: lat as seq, mm_to_m, heading_cdeg_to_deg
                    body = dumps({"agent": names[0], "seq": msg.lat, "time_boot_ms": msg.time_boot_ms,
                                  "alt_msl": msg.alt / 1e3, "heading": None if msg.hdg == 65535 else msg.hdg / 1e2},
                                 option=sort)
                    items.append((names[3], names[1], body, received, "uavs-position"))
                elif msg_id == ATT:  # the attitude route's mapping: roll as seq
                    body = dumps({"agent": names[0], "seq": msg.roll, "time_boot_ms": msg.time_boot_ms,
                                  "pitch": msg.pitch, "yaw": msg.yaw}, option=sort)
                    items.append((names[3], names[2], body, received, "uavs-attitude"))
                elif msg_id == HB:
                    sid = msg.get_srcSystem()
                    assert self.transport is not None
                    heard[sid] = (self.transport, addr)
                    heard_event[sid].set()
            if items:
                put(items)

    endpoints = []
    for port, ids in links:
        transport, protocol = await loop.create_datagram_endpoint(functools.partial(Link, ids), local_addr=("127.0.0.1", port))
        transport.get_extra_info("socket").setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RECEIVE_BUFFER)
        endpoints.append(transport)
        senders.append((transport, mavlink2.MAVLink(None, srcSystem=255, srcComponent=190), protocol.peers))

    def frame(mav: Any, msg: Any) -> bytes:
        data = msg.pack(mav)
        mav.seq = (mav.seq + 1) % 256  # what MAVLink.send does after packing
        return bytes(data)

    async def heartbeats() -> None:
        while True:
            now = time.monotonic()
            for transport, mav, peers in senders:
                beat = frame(mav, mav.heartbeat_encode(mavlink2.MAV_TYPE_GCS, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0,
                                                       mavlink2.MAV_STATE_ACTIVE))
                for addr, seen in list(peers.items()):
                    if now - seen < FLEET_PEER_TTL:
                        transport.sendto(beat, addr)
            await asyncio.sleep(1.0)

    link_of = {sid: index for index, (_, ids) in enumerate(links) for sid in ids}

    # -- commands: each agent's queue, as the engine's command routes declare it
    command_channel = await connection.channel(frame_buffer_size=300)  # as the engine's sources
    await command_channel.basic_qos(prefetch_count=256)
    await command_channel.exchange_declare(cmd, exchange_type="topic", durable=True)
    await publish_channels[0].exchange_declare(out, exchange_type="topic", durable=True)
    message = String()

    async def to_robot(agent: str, delivery: Any) -> None:
        received = time.monotonic_ns()
        message.data = delivery.body.decode()
        if record:
            handed["robots-cmd"].append(time.monotonic_ns() - received)
        command_publishers[agent].publish(message)
        if record:
            accepted["robots-cmd"].append(time.monotonic_ns() - received)
        await command_channel.basic_ack(delivery.delivery_tag)

    async def to_vehicle(sid: int, delivery: Any) -> None:
        received = time.monotonic_ns()
        body = orjson.loads(delivery.body)
        if sid not in heard:  # nothing that reaches a vehicle is guessed: wait for its HEARTBEAT
            try:
                await asyncio.wait_for(heard_event[sid].wait(), 5.0)
            except TimeoutError:
                failures[0] += 1
                await command_channel.basic_nack(delivery.delivery_tag, requeue=True)
                return
        transport, addr = heard[sid]
        mav = senders[link_of[sid]][1]
        if record:
            handed["uavs-cmd"].append(time.monotonic_ns() - received)
        transport.sendto(frame(mav, mav.command_long_encode(sid, 1, FLEET_COMMAND, 0, float(body["t_ms"]),
                                                            float(body["seq"]), 0, 0, 0, 0, 0)), addr)
        if record:
            accepted["uavs-cmd"].append(time.monotonic_ns() - received)
        await command_channel.basic_ack(delivery.delivery_tag)

    consumers: list[tuple[str, Any]] = [(agent, lambda d, a=agent: to_robot(a, d)) for agent in robots]
    consumers += [(f"uav{sid}", lambda d, s=sid: to_vehicle(s, d)) for _, ids in links for sid in ids]
    for agent, on_message in consumers:
        queue = f"{cmd}-{agent}"
        await command_channel.queue_declare(queue, durable=True)
        await command_channel.queue_bind(queue, cmd, routing_key=agent)
        await command_channel.basic_consume(queue, on_message, no_ack=False)

    taker = FleetTakeThread(context, subscriptions, String, on_ros_batch)
    beating = asyncio.create_task(heartbeats())
    print(f"started {time.perf_counter() - began:.4f} {_rss_kib()}", flush=True)
    try:
        await _until_stopped()
    finally:
        if args.get("latency_out"):
            Path(args["latency_out"]).write_text(json.dumps(accepted))
        if args.get("handed_out"):
            Path(args["handed_out"]).write_text(json.dumps(handed))
        if failures[0]:
            print(f"fleet reference: {failures[0]} publishes or commands failed", file=sys.stderr, flush=True)
        taker.stop()
        beating.cancel()
        for transport in endpoints:
            transport.close()
        await connection.close()
        node.destroy_node()
        context.try_shutdown()


# ---------------------------------------------------------------- the paper's design

def to_canonical(data: dict[str, Any]) -> dict[str, Any]:
    """The GNSS route's mapping, written by hand (the paper's converters are code, not routes)."""
    return {"type": "position", "agent_id": data["agent"], "stamp": to_stamp(data["stamp"]),
            "lat": data["lat"], "lon": data["lon"], "alt_msl": data["alt"]}


def _paper_logging() -> logging.Logger:
    log = logging.getLogger("rabbitros.paper")
    handler = logging.FileHandler(os.devnull)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s %(message)s"))
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    return log


def _paper_validator() -> Any:
    import jsonschema

    schemas = {p.name: json.loads(p.read_text()) for p in (REPO / "schemas").glob("*.json")}
    from referencing import Registry, Resource

    registry = Registry().with_resources(
        (doc.get("$id", name), Resource.from_contents(doc)) for name, doc in schemas.items())
    schema = schemas["position.v1.json"]
    return jsonschema.Draft202012Validator(schema, registry=registry)


async def _spin_default_executor(node: Any) -> None:
    """The paper: ROS 2 callbacks run in the asyncio loop that runs the AMQP client."""
    import rclpy.executors

    executor = rclpy.executors.SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    while True:
        executor.spin_once(timeout_sec=0)
        await asyncio.sleep(0.0005)


async def paper_amqp_ros2(args: dict[str, Any]) -> None:
    import aio_pika
    from std_msgs.msg import String

    log, validator = _paper_logging(), _paper_validator()
    context, node = _ros_context(args["domain"])
    publisher = node.create_publisher(String, args["topic"], _qos(latched=True))
    connection = await aio_pika.connect_robust(args["url"])
    channel = await connection.channel(publisher_confirms=False)
    await channel.set_qos(prefetch_count=256)
    queue = await channel.get_queue(args["queue"])

    latency_ns: list[int] | None = [] if args.get("latency_out") else None
    validate = not args.get("minimal")

    async def on_message(message: aio_pika.abc.AbstractIncomingMessage) -> None:
        received_ns = time.monotonic_ns()  # t1: aio-pika hands the message over
        async with message.process():
            canonical = to_canonical(json.loads(message.body))
            if validate:
                validator.validate(canonical)
            publisher.publish(String(data=json.dumps(canonical)))
            if latency_ns is not None:  # t2: ROS 2 took it
                latency_ns.append(time.monotonic_ns() - received_ns)
            if validate:
                log.info("AMQP -> ROS 2 %s: %s", args["topic"], canonical)

    spinner = asyncio.create_task(_spin_default_executor(node))
    await queue.consume(on_message)
    await _until_stopped()
    if latency_ns is not None:
        Path(args["latency_out"]).write_text(json.dumps(latency_ns))
    spinner.cancel()
    await connection.close()
    node.destroy_node()
    context.try_shutdown()


async def paper_ros2_amqp(args: dict[str, Any]) -> None:
    import aio_pika
    from std_msgs.msg import String

    log, validator = _paper_logging(), _paper_validator()
    context, node = _ros_context(args["domain"])
    connection = await aio_pika.connect_robust(args["url"])
    channel = await connection.channel(publisher_confirms=False)
    exchange = await channel.get_exchange(args["exchange"])
    pending: set[asyncio.Task[Any]] = set()

    def on_message(msg: Any) -> None:
        data = to_canonical(json.loads(msg.data))
        validator.validate(data)
        task = asyncio.ensure_future(exchange.publish(
            aio_pika.Message(json.dumps(data).encode(), delivery_mode=aio_pika.DeliveryMode.PERSISTENT), args["routing_key"]))
        pending.add(task)
        task.add_done_callback(pending.discard)
        log.info("ROS 2 -> AMQP %s: %s", args["routing_key"], data)

    node.create_subscription(String, args["topic"], on_message, _qos())
    spinner = asyncio.create_task(_spin_default_executor(node))
    await _until_stopped()
    spinner.cancel()
    await connection.close()
    node.destroy_node()
    context.try_shutdown()


# ---------------------------------------------------------------- load generators

async def ros_publisher(args: dict[str, Any]) -> None:
    """Publish ``count`` GNSS fixes as std_msgs/String on ``topic`` once a subscriber has
    matched: as fast as rclpy goes (``rate`` 0, a burst held by DDS history) or paced."""
    from std_msgs.msg import String

    context, node = _ros_context(args["domain"])
    publisher = node.create_publisher(String, args["topic"], _qos())
    deadline = time.monotonic() + 30
    while publisher.get_subscription_count() < 1 and time.monotonic() < deadline:
        await asyncio.sleep(0.02)
    await asyncio.sleep(0.5)
    rate, count = float(args.get("rate", 0)), int(args["count"])
    message = String()
    began = time.monotonic()
    for index in range(count):
        message.data = gnss_json(index).decode()
        publisher.publish(message)
        if rate:
            delay = began + (index + 1) / rate - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
        elif index % 500 == 499:
            await asyncio.sleep(0)
    publisher.wait_for_all_acked()
    print(f"published {count}", flush=True)
    await asyncio.sleep(float(args.get("linger", 2.0)))
    node.destroy_node()
    context.try_shutdown()


async def mavlink_sender(args: dict[str, Any]) -> None:
    """Send ``count`` GLOBAL_POSITION_INT frames (system 1) over UDP at ``rate`` per second
    (0: as fast as the socket takes them)."""
    import socket

    os.environ["MAVLINK20"] = "1"
    from pymavlink.dialects.v20 import common as mavlink2

    mav = mavlink2.MAVLink(None, 1, 1)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    target = ("127.0.0.1", int(args["port"]))
    rate, count = float(args["rate"]), int(args["count"])
    frames = [mav.global_position_int_encode(i, -224123456 + i, -475654321, 612340, 35000, 120, -35, 4, 27000).pack(mav)
              for i in range(min(count, 1000))]
    print("sending", flush=True)
    began = time.monotonic()
    for index in range(count):
        sock.sendto(frames[index % len(frames)], target)
        delay = began + (index + 1) / rate - time.monotonic() if rate else 0.0
        if delay > 0.001:
            await asyncio.sleep(delay)
    print(f"sent {count} in {time.monotonic() - began:.3f}", flush=True)


def gnss_json(index: int, pad: int = 0) -> bytes:
    """A GNSS fix as the AMQP and ROS 2 sources receive it (about 100 bytes)."""
    return (b'{"agent":"uav1","lat":%.7f,"lon":-47.5654321,"alt":612.34,"stamp":%.6f,"seq":%d%s}'
            % (-22.4123456 + index * 1e-7, time.time(), index, (b',"pad":"' + b"x" * pad + b'"') if pad else b""))


SYSTEMS = {
    "engine": engine,
    "ref-amqp-amqp": ref_amqp_amqp,
    "ref-amqp-ros2": ref_amqp_ros2,
    "ref-ros2-amqp": ref_ros2_amqp,
    "ref-mavlink-amqp": ref_mavlink_amqp,
    "ref-fleet": ref_fleet,
    "paper-amqp-ros2": paper_amqp_ros2,
    "paper-ros2-amqp": paper_ros2_amqp,
    "ros-publisher": ros_publisher,
    "mavlink-sender": mavlink_sender,
}


def main() -> None:
    from engine.running.loop import run

    system, args = sys.argv[1], json.loads(sys.argv[2])
    if system.startswith("fleet-"):  # bench/fleet.py's load generators: plain threads, no loop
        from bench import fleet

        getattr(fleet, system.removeprefix("fleet-"))(args)
        return
    if system.startswith("paper-") or system in ("ros-publisher", "mavlink-sender"):
        asyncio.run(SYSTEMS[system](args))  # the paper ran on asyncio's own loop
    else:
        run(SYSTEMS[system](args))


if __name__ == "__main__":
    main()


__all__ = ["SYSTEMS", "gnss_json", "position_from_global_position_int"]
