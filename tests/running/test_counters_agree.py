"""One set of counters per route: the log's ``route counters`` line, ``status``, ``/metrics``
and the tap agree exactly, and equal the traffic the test sent.

Real parts: the engine as a child process with ``--admin``, two private RabbitMQ nodes (one
is killed with -9 and restarted on its data directory) and a real rclpy peer.

* ``throttled`` (AMQP -> AMQP, ``throttle: {max_rate: 2, per: agent_id}``): 2 agents x 40
  messages at 20 ms intervals and 4 that are not JSON. Each is received once, then
  delivered, conflated or dead-lettered (decode) once; what the sink got is counted by a
  collector. (A parked message used to be converted and counted again when its slot opened:
  received=2x in the log while /metrics said otherwise.)
* ``buffered`` (ROS 2 -> AMQP, the default in-memory buffer): 12 messages while the broker is
  up, 103 while it is down (held, then delivered from the buffer when it is back); 5 of them
  lack the field the sink's routing key needs, so the sink rejects them: dead-lettered at
  stage ``sink``, and their tap lines carry the canonical message. (Messages delivered from
  the buffer used to update the status but not the counters behind /metrics.)
"""

from __future__ import annotations

import asyncio
import json
import threading
import urllib.request
import uuid
from functools import partial
from pathlib import Path
from typing import Any, Callable

import aio_pika
import pytest

from engine.common.processes import listening_port
from engine.endpoints.amqp.broker import LocalBroker
from tests.support.engine_process import EngineProcess
from tests.support.amqp_helpers import Collector
from tests.support.outage_helpers import Tally, robust
from tests.support.workers import ros_domain
from tests.support.waiting import wait_for, wait_for_sync

import rclpy  # noqa: F401,E402  (a missing rclpy fails the run, never skips it)

ROUTES = """
connections:
  steady: {{amqp: "{steady}"}}
  flaky: {{amqp: "{flaky}"}}
  ros: {{ros2: {{domain_id: {domain}, node: counters_{tag}}}}}
dead_letters: {{connection: steady}}
routes:
  - name: throttled
    source: {{amqp: {{connection: steady, exchange: {tag}-in, binding_key: "t.#", queue: {tag}-throttled}}}}
    mapping: "{{agent_id: agent, seq: seq}}"
    schema: raw_json
    throttle: {{max_rate: 2, per: agent_id}}
    sink: {{amqp: {{connection: steady, exchange: {tag}-out, routing_key: "out.{{agent_id}}"}}}}
  - name: buffered
    source: {{ros2: {{topic: /{tag}/up}}}}
    schema: raw_json
    sink: {{amqp: {{connection: flaky, exchange: {tag}-up, routing_key: "up.{{kind}}"}}}}
"""
STAGES = ("decode", "size", "mapping", "schema", "sink mapping", "sink")
AGENTS, PER_AGENT, NOT_JSON = ("uav1", "uav2"), 40, 4
UP_GOOD, UP_BAD, DOWN_GOOD, DOWN_BAD = 10, 2, 100, 3


class TapReader:
    """``GET /tap/{route}`` read in a thread: every JSON line, as it comes."""

    def __init__(self, port: int, route: str) -> None:
        self.lines: list[dict[str, Any]] = []
        self._response = urllib.request.urlopen(f"http://127.0.0.1:{port}/tap/{route}", timeout=300)
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        try:
            for line in self._response:
                self.lines.append(json.loads(line))
        except (OSError, ValueError):
            pass  # the engine stopped

    def counts(self) -> dict[str, Any]:
        lines = list(self.lines)
        outcomes = [line["outcome"] for line in lines]
        stages: dict[str, int] = {}
        for line in lines:
            if line["outcome"] == "dead_lettered":
                stage = next(s for s in sorted(STAGES, key=len, reverse=True) if line["error"].startswith(s + ":"))
                stages[stage] = stages.get(stage, 0) + 1
        settled = ("delivered", "dead_lettered", "conflated")
        return {"received": sum(outcomes.count(o) for o in settled), "delivered": outcomes.count("delivered"),
                "failed": outcomes.count("dead_lettered"), "conflated": outcomes.count("conflated"),
                "retries": outcomes.count("redelivered"), "dead_lettered": stages}


def metrics(port: int, route: str) -> dict[str, Any]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as response:
        text = response.read().decode()
    outcomes: dict[str, int] = {}
    stages: dict[str, int] = {}
    for line in text.splitlines():
        if f'route="{route}"' not in line:
            continue
        labels, value = line.rsplit(" ", 1)
        if line.startswith("rabbitros_messages_total{"):
            outcomes[labels.split('outcome="')[1].split('"')[0]] = int(float(value))
        elif line.startswith("rabbitros_dead_letters_total{"):
            stages[labels.split('stage="')[1].split('"')[0]] = int(float(value))
    return {"received": outcomes["received"], "delivered": outcomes["delivered"], "failed": outcomes["dead_lettered"],
            "conflated": outcomes["conflated"], "retries": outcomes["redelivered"], "dropped": outcomes["dropped"],
            "dead_lettered": stages}


def status(port: int, route: str) -> dict[str, Any]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=10) as response:
        document = json.loads(response.read())["routes"][route]
    by_outcome = document["messages"]
    assert by_outcome == {"received": document["received"], "delivered": document["delivered"],
                          "refused": document["refused"], "dead_lettered": document["failed"], "redelivered": document["retries"],
                          "conflated": document["conflated"], "expired": document["expired"],
                          "dropped": document["dropped"], "filtered": document["filtered"],
                          "duplicates": document["duplicates"], "windowed": document["windowed"]}, document
    assert document["dead_letters"] == document["dead_lettered"], document
    return {key: document[key] for key in ("received", "delivered", "failed", "conflated", "retries", "dropped", "dead_lettered")}


def logged(log_file: Path, route: str) -> dict[str, Any] | None:
    """The last ``route counters`` line the engine logged for ``route``."""
    last = None
    for line in log_file.read_text().splitlines():
        if '"route counters"' in line:
            record = json.loads(line)
            if record.get("route") == route:
                last = record
    if last is None:
        return None
    return {key: last[key] for key in ("received", "delivered", "failed", "conflated", "retries", "dropped", "dead_lettered")}


def agreed(views: dict[str, Callable[[], dict[str, Any] | None]], timeout: float = 30.0) -> dict[str, Any]:
    """Read every view until they agree (each is read at its own moment, and the log is
    written every 0.5 s); the agreed counters, or an AssertionError showing each view."""
    seen: dict[str, Any] = {}

    def agree() -> bool:
        seen.update({name: read() for name, read in views.items()})
        shared = [{k: v for k, v in (value or {}).items() if k != "dropped"} for value in seen.values()]
        return all(value == shared[0] for value in shared) and all(value is not None for value in seen.values())

    wait_for_sync(agree, timeout, "the views of one route's counters to agree", lambda: "\n" + json.dumps(seen, indent=1),
                  every=0.3)  # each poll asks two HTTP endpoints and reads the log
    return seen["status"]


@pytest.mark.soak
def test_log_status_metrics_and_tap_count_the_same_known_traffic(tmp_path: Path, amqp_url: str) -> None:
    tag = "c" + uuid.uuid4().hex[:8]
    domain = ros_domain(6)
    flaky = LocalBroker()
    flaky.start()
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "counters.yaml").write_text(ROUTES.format(steady=amqp_url, flaky=flaky.url, domain=domain, tag=tag))
    port = listening_port()
    engine = EngineProcess(routes, tmp_path / "status.json", {}, "--admin", str(port))
    arrived = Tally("buffered")
    try:
        engine.wait_started()
        taps = {route: TapReader(port, route) for route in ("throttled", "buffered")}
        wait_until_attached(port)
        throttled_sent = asyncio.run(throttled_traffic(amqp_url, tag))
        asyncio.run(buffered_traffic(flaky, engine, tag, domain, arrived))
        for route, known in (("throttled", throttled_known(throttled_sent)), ("buffered", buffered_known())):
            views: dict[str, Callable[[], dict[str, Any] | None]] = {
                "status": partial(status, port, route),
                "metrics": partial(metrics, port, route),
                "log": partial(logged, engine.log_file, route),
                "tap": taps[route].counts,
            }
            counters = agreed(views)
            print(f"\n{route}: {counters}")
            assert {k: counters[k] for k in known} == known, (route, counters)
            assert counters["retries"] == 0 and counters["dropped"] == 0, counters
        rejected = [line for line in taps["buffered"].lines if line["outcome"] == "dead_lettered"]
        assert len(rejected) == UP_BAD + DOWN_BAD
        assert all(line["canonical"] is not None and "kind" not in line["canonical"] for line in rejected), rejected
    finally:
        assert engine.stop() == 0, engine.log()
        flaky.stop()


def wait_until_attached(port: int) -> None:
    def attached() -> bool:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=10) as response:
            routes = json.loads(response.read())["routes"]
        return all(routes[name]["taps"] == 1 for name in ("throttled", "buffered"))

    wait_for_sync(attached, 20, "the taps to attach")


async def throttled_traffic(url: str, tag: str) -> int:
    """Publish the throttled route's traffic; returns how many messages its sink got."""
    connection = await aio_pika.connect(url)
    try:
        channel = await connection.channel()
        got = (await Collector.bind(channel, f"{tag}-out", "out.#")).messages
        inbox = await channel.declare_exchange(f"{tag}-in", aio_pika.ExchangeType.TOPIC, durable=True)
        for index in range(NOT_JSON):
            await inbox.publish(aio_pika.Message(b"{not json %d" % index), "t.bad")
        for seq in range(PER_AGENT):  # 20 msg/s per agent for 0.8 s, against max_rate 2
            for agent in AGENTS:
                await inbox.publish(aio_pika.Message(json.dumps({"agent": agent, "seq": seq}).encode()), f"t.{agent}")
            await asyncio.sleep(0.02)  # pacing: 20 msg/s per agent
        await wait_for(lambda: sorted(json.loads(m.body)["seq"] for m in got)[-2:] == [PER_AGENT - 1] * 2, 30,
                       "the last message of each agent (kept by the throttle, sent when its slot opens)")
        await asyncio.sleep(1.0)  # quiet window: nothing else is parked: the latest was sent
        return len(got)
    finally:
        await connection.close()


def throttled_known(sent: int) -> dict[str, Any]:
    total = len(AGENTS) * PER_AGENT
    return {"received": total + NOT_JSON, "delivered": sent, "conflated": total - sent, "failed": NOT_JSON,
            "dead_lettered": {"decode": NOT_JSON}}


def buffered_known() -> dict[str, Any]:
    good, bad = UP_GOOD + DOWN_GOOD, UP_BAD + DOWN_BAD
    return {"received": good + bad, "delivered": good, "conflated": 0, "failed": bad, "dead_lettered": {"sink": bad}}


async def buffered_traffic(flaky: LocalBroker, engine: EngineProcess, tag: str, domain: int, arrived: Tally) -> None:
    """Traffic through the buffered route: some while its sink's broker is up, more while it
    is down (held), all delivered once it is back."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import String

    context = rclpy.Context()
    rclpy.init(args=[], context=context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(f"peer_{tag}", context=context)
    publisher = node.create_publisher(String, f"/{tag}/up", QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    connection = await robust(flaky.url)

    def publish(first: int, good: int, bad: int) -> None:
        for seq in range(first, first + good):
            publisher.publish(String(data=json.dumps({"seq": seq, "kind": "pos"})))
        for seq in range(first + good, first + good + bad):  # no "kind": the routing key cannot be made
            publisher.publish(String(data=json.dumps({"seq": seq})))

    def route() -> dict[str, Any]:
        return (engine.status() or {}).get("routes", {}).get("buffered", {})

    try:
        await Collector.bind(await connection.channel(), f"{tag}-up", "up.#", queue=f"collect-{tag}", ack=True, tally=arrived, prefetch=500)
        await wait_for(lambda: publisher.get_subscription_count() > 0, 30, "the engine's ROS subscription")
        await wait_for(lambda: route().get("source", {}).get("matched_publishers", 0) > 0, 30, "the engine's reader to match our writer")
        publish(0, UP_GOOD, UP_BAD)
        await wait_for(lambda: arrived.delivered == UP_GOOD and route().get("failed") == UP_BAD, 30, "the first messages")
        flaky.kill()
        await wait_for(lambda: not (engine.status() or {})["connections"]["flaky"]["healthy"], 30, "the engine to see the broker down")
        publish(1000, DOWN_GOOD, DOWN_BAD)
        await wait_for(lambda: (route().get("buffer") or {}).get("held", 0) == DOWN_GOOD + DOWN_BAD, 30, "the messages held")
        await asyncio.to_thread(flaky.start)
        await wait_for(lambda: arrived.delivered == UP_GOOD + DOWN_GOOD and route().get("failed") == UP_BAD + DOWN_BAD,
                       60, "the held messages delivered or dead-lettered")
    finally:
        await connection.close()
        node.destroy_node()
        context.try_shutdown()
