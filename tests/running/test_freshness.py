"""Freshness after an outage (issue 22): ``max_age`` expires what is too old to be worth
sending, ``buffer: {latest_only: {per: ...}}`` replays only the newest held message per key.

Real parts: the engine as a child process with ``--admin``, a private RabbitMQ node killed
with -9 and restarted on its data directory, a real rclpy publisher. Two buffered routes
read the same ROS 2 topic and publish to the same broker:

* ``aged`` (``max_age: 1``): what is held during the outage is older than a second when the
  broker is back, so none of it is delivered; each is counted ``expired`` once, and the
  status, ``/metrics`` (``outcome="expired"``), the tap and the log's counter line say so.
  Messages published once the broker is back are delivered.
* ``latest`` (``latest_only: {per: id}``): of the held messages only the newest per ``id``
  is delivered, the rest are counted ``conflated``.

The other two places a message waits, a throttle slot and a retry, are tested in the engine
itself against the shared broker (``test_max_age_expires_what_waited_in_a_throttle_slot_or_for_a_retry``).
"""

from __future__ import annotations

import asyncio
import json
import time
import urllib.request
import uuid
from pathlib import Path
from typing import Any

from engine.common.processes import listening_port
from engine.endpoints.amqp.broker import LocalBroker
from tests.support.engine_process import EngineProcess
from tests.support.amqp_helpers import Collector
from tests.support.outage_helpers import Tally, robust
from tests.running.test_counters_agree import TapReader
from tests.support.workers import ros_domain
from tests.support.waiting import wait_for, wait_for_sync

import rclpy  # noqa: F401,E402  (a missing rclpy fails the run, never skips it)

ROUTES = """
connections:
  flaky: {{amqp: "{flaky}"}}
  ros: {{ros2: {{domain_id: {domain}, node: fresh_{tag}}}}}
routes:
  - name: aged
    source: {{ros2: {{topic: /{tag}/pos}}}}
    schema: raw_json
    max_age: 1
    sink: {{amqp: {{connection: flaky, exchange: {tag}-out, routing_key: "aged"}}}}
  - name: latest
    source: {{ros2: {{topic: /{tag}/pos}}}}
    schema: raw_json
    buffer: {{latest_only: {{per: id}}}}
    sink: {{amqp: {{connection: flaky, exchange: {tag}-out, routing_key: "latest"}}}}
"""
KEYS = ("a", "b", "c")
BEFORE, DURING, AFTER = 4, 30, 5
"""Messages published while the broker is up, while it is down (10 per key), once it is back."""
MAX_AGE = 1.0


def test_max_age_expires_stale_held_messages_and_latest_only_replays_one_per_key(tmp_path: Path) -> None:
    tag = "f" + uuid.uuid4().hex[:8]
    domain = ros_domain(3)
    flaky = LocalBroker()
    flaky.start()
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "fresh.yaml").write_text(ROUTES.format(flaky=flaky.url, domain=domain, tag=tag))
    port = listening_port()
    engine = EngineProcess(routes, tmp_path / "status.json", {}, "--admin", str(port))
    aged, latest = Tally("aged"), Tally("latest")
    try:
        engine.wait_started()
        tap = TapReader(port, "aged")
        asyncio.run(traffic(flaky, engine, tag, domain, aged, latest))
        during = range(1000, 1000 + DURING)
        assert not [seq for seq in during if seq in aged.copies], "a stale message was delivered"
        assert sorted(aged.copies) == [*range(BEFORE), *range(2000, 2000 + AFTER)], sorted(aged.copies)
        newest = {1000 + DURING - len(KEYS) + i for i in range(len(KEYS))}  # the last of each key
        assert sorted(seq for seq in latest.copies if seq in during) == sorted(newest), sorted(latest.copies)

        want_aged = {"received": BEFORE + DURING + AFTER, "delivered": BEFORE + AFTER, "expired": DURING, "conflated": 0}
        want_latest = {"received": BEFORE + DURING + AFTER, "delivered": BEFORE + len(KEYS) + AFTER,
                       "expired": 0, "conflated": DURING - len(KEYS)}
        for route, want in (("aged", want_aged), ("latest", want_latest)):
            document = route_status(port, route)
            assert {k: document[k] for k in want} == want, document
            assert document["messages"]["expired"] == want["expired"], document
            assert metric(port, route, "expired") == want["expired"]
            assert metric(port, route, "conflated") == want["conflated"]
            assert document["buffer"]["expired"] == want["expired"] and document["buffer"]["conflated"] == want["conflated"]

            def log_counts_expired(route: str = route, want: dict[str, int] = want) -> bool:
                return logged(engine.log_file, route) == want["expired"]

            def log_detail(route: str = route, want: dict[str, int] = want) -> str:
                return f"{logged(engine.log_file, route)} != {want['expired']}"

            wait_for_sync(log_counts_expired, 15, "the log's counter line", detail=log_detail)
        wait_for_sync(lambda: sum(line["outcome"] == "expired" for line in tap.lines) == DURING, 15, "the tap's expired lines",
                      detail=lambda: sum(line["outcome"] == "expired" for line in tap.lines))
        expired_lines = [line for line in tap.lines if line["outcome"] == "expired"]
        assert sorted(line["canonical"]["seq"] for line in expired_lines) == list(during)
        print(f"\naged: {want_aged}\nlatest: {want_latest}")
    finally:
        assert engine.stop() == 0, engine.log()
        flaky.stop()


async def traffic(flaky: LocalBroker, engine: EngineProcess, tag: str, domain: int, aged: Tally, latest: Tally) -> None:
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import String

    context = rclpy.Context()
    rclpy.init(args=[], context=context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(f"peer_{tag}", context=context)
    publisher = node.create_publisher(String, f"/{tag}/pos", QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    connection = await robust(flaky.url)

    def publish(seqs: range) -> None:
        for seq in seqs:
            publisher.publish(String(data=json.dumps({"seq": seq, "id": KEYS[seq % len(KEYS)]})))

    def route(name: str) -> dict[str, Any]:
        return (engine.status() or {}).get("routes", {}).get(name, {})

    try:
        await Collector.bind(await connection.channel(), f"{tag}-out", "aged", queue=f"aged-{tag}", ack=True, tally=aged, prefetch=500)
        await Collector.bind(await connection.channel(), f"{tag}-out", "latest", queue=f"latest-{tag}", ack=True, tally=latest, prefetch=500)
        await wait_for(lambda: publisher.get_subscription_count() >= 2, 30, "the engine's ROS subscriptions")
        await wait_for(lambda: all(route(name).get("source", {}).get("matched_publishers", 0) > 0 for name in ("aged", "latest")), 30,
                       "the engine's readers to match our writer")
        publish(range(BEFORE))
        await wait_for(lambda: aged.delivered == BEFORE and latest.delivered == BEFORE, 30, "the first messages")
        flaky.kill()
        await wait_for(lambda: not (engine.status() or {})["connections"]["flaky"]["healthy"], 30, "the broker seen down")
        held_since = time.monotonic()
        publish(range(1000, 1000 + DURING))
        await wait_for(lambda: all((route(name).get("buffer") or {}).get("held") == DURING for name in ("aged", "latest")),
                       30, "the messages held")
        await wait_for(lambda: time.monotonic() - held_since > MAX_AGE + 0.2, 5, "the held messages to be stale")
        await asyncio.to_thread(flaky.start)
        await wait_for(lambda: all((route(name).get("buffer") or {}).get("held") == 0 for name in ("aged", "latest")),
                       60, "the buffers emptied")
        await wait_for(lambda: latest.delivered == BEFORE + len(KEYS), 30, "the newest held message per key")
        publish(range(2000, 2000 + AFTER))
        await wait_for(lambda: aged.delivered == BEFORE + AFTER and latest.delivered == BEFORE + len(KEYS) + AFTER,
                       30, "the messages published after the outage")
    finally:
        await connection.close()
        node.destroy_node()
        context.try_shutdown()


def route_status(port: int, route: str) -> dict[str, Any]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=10) as response:
        return json.loads(response.read())["routes"][route]


def metric(port: int, route: str, outcome: str) -> int:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as response:
        text = response.read().decode()
    wanted = f'rabbitros_messages_total{{outcome="{outcome}",route="{route}"}}'
    lines = [line for line in text.splitlines() if line.startswith("rabbitros_messages_total{")
             and f'route="{route}"' in line and f'outcome="{outcome}"' in line]
    assert len(lines) == 1, (wanted, text)
    return int(float(lines[0].rsplit(" ", 1)[1]))


def logged(log_file: Path, route: str) -> int | None:
    """``expired`` in the last ``route counters`` line the engine logged for ``route``."""
    last = None
    for line in log_file.read_text().splitlines():
        if '"route counters"' in line:
            record = json.loads(line)
            if record.get("route") == route:
                last = record.get("expired")
    return last


def test_check_warns_when_latest_only_reads_a_field_the_schema_lacks(tmp_path: Path) -> None:
    from engine.common.schemas import SchemaRegistry
    from engine.language.routes import load_routes
    from tests.support.repo import REPO

    (tmp_path / "r.yaml").write_text("""
routes:
  - name: pos
    source: {amqp: {queue: a}}
    schema: position
    max_age: 5
    buffer: {latest_only: {per: agentid}}
    sink: {amqp: {exchange: farm}}
""")
    config = load_routes(tmp_path, SchemaRegistry(REPO / "schemas"))
    assert config.routes["pos"].delivery.max_age_ns == 5_000_000_000
    assert config.routes["pos"].buffer is not None and config.routes["pos"].buffer.latest_per == ("agentid",)
    assert [str(w).removeprefix(f"{tmp_path}/") for w in config.warnings] == [
        "r.yaml:7: route 'pos': buffer latest_only per reads 'agentid', which schema 'position' does not declare; "
        "did you mean 'agent_id'?"]


THROTTLE_AND_RETRY = """
connections:
  gcs: {{amqp: "{url}"}}
routes:
  - name: slotted
    source: {{amqp: {{exchange: {tag}-in, binding_key: "slot", queue: {tag}-slot}}}}
    schema: raw_json
    throttle: {{max_rate: 0.5}}
    max_age: 0.5
    sink: {{amqp: {{exchange: {tag}-out, routing_key: slotted}}}}
  - name: retried
    source: {{amqp: {{exchange: {tag}-in, binding_key: "retry", queue: {tag}-retry}}}}
    schema: raw_json
    max_attempts: 50
    max_age: 0.4
    sink: {{amqp: {{exchange: "", routing_key: {tag}-full}}}}
"""


def test_max_age_expires_what_waited_in_a_throttle_slot_or_for_a_retry(tmp_path: Path, amqp_url: str,
                                                                      schemas_dir: Path) -> None:
    """In the engine itself: ``slotted`` lets one message through every 2 s; of three sent at
    once the first goes, the second is parked and replaced by the third (conflated), which
    is 2 s old when its slot opens: expired. ``retried``'s sink refuses every publish (a queue
    of length 0 that rejects: transient), so the message is tried with backoff until it is
    older than 0.4 s: expired, neither dead-lettered nor tried 50 times."""
    import aio_pika

    from engine.running.runtime import Engine

    tag = "ft" + uuid.uuid4().hex[:8]
    (tmp_path / "r.yaml").write_text(THROTTLE_AND_RETRY.format(url=amqp_url, tag=tag))

    async def scenario() -> dict[str, Any]:
        connection = await aio_pika.connect(amqp_url)
        channel = await connection.channel()
        await channel.declare_queue(f"{tag}-full", arguments={"x-max-length": 0, "x-overflow": "reject-publish"},
                                    auto_delete=True)
        out = await Collector.bind(channel, f"{tag}-out", "#")
        dead = await Collector.bind(channel, "rabbitros.dead-letter", "retried")
        engine = Engine(tmp_path, schemas_dir)
        await engine.start()
        try:
            inbox = await channel.declare_exchange(f"{tag}-in", aio_pika.ExchangeType.TOPIC, durable=True)
            for n in range(3):
                await inbox.publish(aio_pika.Message(b'{"n": %d}' % n), "slot")
            await inbox.publish(aio_pika.Message(b'{"n": 9}'), "retry")

            def routes() -> dict[str, Any]:
                return engine.status()["routes"]

            await wait_for(lambda: routes()["slotted"]["expired"] >= 1 and routes()["retried"]["expired"] >= 1, 20,
                           "a message expired on each route", routes)
            await asyncio.sleep(0.3)  # quiet window: nothing else arrives
            return {"out": [m.body for m in out.messages], "dead": len(dead.messages), **routes()}
        finally:
            await engine.stop()
            await connection.close()

    seen = asyncio.run(scenario())
    assert seen["out"] == [b'{"n": 0}'], seen["out"]
    slotted, retried = seen["slotted"], seen["retried"]
    assert (slotted["received"], slotted["delivered"], slotted["conflated"], slotted["expired"]) == (3, 1, 1, 1), slotted
    assert (retried["received"], retried["delivered"], retried["failed"], retried["expired"]) == (1, 0, 0, 1), retried
    assert 1 <= retried["retries"] < 10 and seen["dead"] == 0, retried
