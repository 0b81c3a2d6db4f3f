"""The delivery policy against real parts: a sink that always fails transiently is retried
max_attempts times with backoff, counted across redeliveries, then dead-lettered; a ROS 2
publisher of the wrong type is reported and the route keeps running; a directory without
AMQP keeps its dead letters in a local spool."""

from __future__ import annotations

import asyncio
import logging
import time
import uuid
from pathlib import Path
from typing import Any

import aio_pika
import pytest
import rclpy
import rclpy.executors
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions

from engine.endpoints.ros2.rosmsg import resolve_type
from engine.running.dead_letters import DeadLetterSpool
from engine.running.delivery import BACKOFF_FIRST
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector, header_text

from tests.support.workers import ros_domain
from tests.support.waiting import wait_for

MAX_ATTEMPTS = 3

FAILING_SINK = """
connections:
  gcs: {{amqp: "{url}"}}
routes:
  - name: always-nacked
    max_attempts: {attempts}
    source: {{amqp: {{exchange: {inbox}, binding_key: "#", queue: {inbox}-q}}}}
    schema: raw_json
    sink: {{amqp: {{exchange: "", routing_key: {full}}}}}
"""


def test_transient_sink_failure_is_retried_with_backoff_then_dead_lettered(tmp_path: Path, amqp_url: str, schemas_dir: Path) -> None:
    """The sink's queue rejects every publish (x-max-length 0, reject-publish): the broker
    nacks, which is transient. Each message is tried max_attempts times in all, counting the
    attempts its header says were made before, then dead-lettered with the last error."""
    tag = uuid.uuid4().hex[:8]
    inbox, full = f"dp-in-{tag}", f"dp-full-{tag}"
    (tmp_path / "r.yaml").write_text(FAILING_SINK.format(url=amqp_url, attempts=MAX_ATTEMPTS, inbox=inbox, full=full))

    async def scenario() -> None:
        connection = await aio_pika.connect(amqp_url)
        channel = await connection.channel()
        await channel.declare_queue(full, arguments={"x-max-length": 0, "x-overflow": "reject-publish"}, auto_delete=True)
        dead = await Collector.bind(channel, "rabbitros.dead-letter", "always-nacked")
        engine = Engine(tmp_path, schemas_dir)
        await engine.start()
        try:
            exchange = await channel.declare_exchange(inbox, aio_pika.ExchangeType.TOPIC, durable=True)
            began = time.monotonic()
            for index in range(5):
                await exchange.publish(aio_pika.Message(b'{"n": %d}' % index, message_id=f"fresh{index}"), "x")
            # attempts made before this delivery (by an earlier engine) count too
            await exchange.publish(aio_pika.Message(b'{"n": 5}', message_id="tried2", headers={"x-rabbitros-attempts": 2}), "x")
            await exchange.publish(aio_pika.Message(b'{"n": 6}', message_id="tried3", headers={"x-rabbitros-attempts": 3}), "x")
            letters = await dead.wait_for(7, timeout=60)
            elapsed = time.monotonic() - began
            await wait_for(lambda: engine.status()["routes"]["always-nacked"]["failed"] == 7, 10, "the route to count its 7 failures")
            stats = engine.status()["routes"]["always-nacked"]
        finally:
            await engine.stop()
            await connection.close()

        assert len(dead.messages) == 7
        by_id = {m.headers["x-source-message_id"]: m for m in letters}
        for index in range(5):
            letter = by_id[f"fresh{index}"]
            assert letter.body == b'{"n": %d}' % index
            assert letter.headers["x-rabbitros-stage"] == "sink"
            assert letter.headers["x-rabbitros-attempts"] == MAX_ATTEMPTS
            assert "gave up after 3 attempts" in header_text(letter, "x-rabbitros-error")
            assert "nack" in header_text(letter, "x-rabbitros-error").lower()
            assert letter.headers["x-rabbitros-route"] == "always-nacked"
        assert by_id["tried2"].headers["x-rabbitros-attempts"] == MAX_ATTEMPTS
        assert by_id["tried3"].headers["x-rabbitros-attempts"] == MAX_ATTEMPTS
        # 5 messages x 3 attempts, 1 x 1, 1 x 0: the sink saw each at most max_attempts times
        assert stats["sink_errors"] == 5 * MAX_ATTEMPTS + 1
        assert stats["failed"] == 7 and stats["delivered"] == 0
        assert stats["dead_lettered"] == {"sink": 7}
        # backoff: at least half of 0.1 s then half of 0.2 s (jitter) between the attempts
        assert elapsed >= BACKOFF_FIRST * 0.5 * (1 + 2)

    asyncio.run(scenario())


SPOOL_ROUTES = """
connections:
  ros: {{ros2: {{domain_id: {domain}, node: spool_engine}}}}
dead_letters: {{spool_dir: "{spool}", spool_max_bytes: 65536}}
routes:
  - name: ros-loop
    source: {{ros2: {{topic: /{tag}/in}}}}
    schema: position
    sink: {{ros2: {{topic: /{tag}/out}}}}
  - name: ros-wrong-type
    source: {{ros2: {{topic: /{tag}/typed}}}}
    schema: raw_json
    sink: {{ros2: {{topic: /{tag}/typed_out}}}}
"""


def test_no_amqp_dead_letters_go_to_a_bounded_spool_and_wrong_ros_types_are_reported(
    tmp_path: Path, schemas_dir: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """ROS 2 -> ROS 2 only: bad messages are kept in the JSON-lines spool (rotated within its
    bound); a NavSatFix publisher on a String route's topic is reported (log and status)
    while the route keeps carrying the right type."""
    domain = ros_domain(7)
    tag = "s" + uuid.uuid4().hex[:8]
    spool = tmp_path / "spool"
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "r.yaml").write_text(SPOOL_ROUTES.format(domain=domain, spool=spool, tag=tag))
    String = resolve_type("std_msgs/msg/String")
    NavSatFix = resolve_type("sensor_msgs/msg/NavSatFix")
    caplog.set_level(logging.ERROR, logger="engine.ros2")

    async def scenario() -> None:
        context = rclpy.Context()
        rclpy.init(args=[], context=context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
        node = rclpy.create_node("spool_peer", context=context)
        other = rclpy.Context()  # one DDS participant cannot have two types on a topic
        rclpy.init(args=[], context=other, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
        other_node = rclpy.create_node("wrong_type_peer", context=other)
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        engine = Engine(routes, schemas_dir)
        await engine.start()
        try:
            publisher = node.create_publisher(String, f"/{tag}/in", qos)
            wrong = other_node.create_publisher(NavSatFix, f"/{tag}/typed", qos)
            right = node.create_publisher(String, f"/{tag}/typed", qos)
            received: list[str] = []

            def heard(message: Any) -> None:  # a std_msgs String, its class resolved at run time
                received.append(message.data)

            node.create_subscription(String, f"/{tag}/typed_out", heard, qos)
            await wait_for(lambda: publisher.get_subscription_count() > 0, 30, "discovery")
            bad = [b"{not json", b'{"agent_id": "a", "lat": 91, "lon": 0}'] * 150  # ~300 x 60 B > 65536 / 4
            for body in bad:
                publisher.publish(String(data=body.decode()))
            await wait_for(lambda: engine.status()["routes"]["ros-loop"]["failed"] == len(bad), 30, "dead letters")

            await wait_for(lambda: bool(engine.status()["routes"]["ros-wrong-type"]["source"]["mismatched_publishers"]),
                           30, "the mismatch reported in the status")
            await wait_for(lambda: right.get_subscription_count() > 0, 30, "discovery of the right type")
            wrong.publish(NavSatFix())
            right.publish(String(data='{"ok": true}'))
            executor = rclpy.executors.SingleThreadedExecutor(context=context)
            executor.add_node(node)

            def spun() -> bool:
                executor.spin_once(timeout_sec=0.05)
                return bool(received)

            await wait_for(spun, 30, "the right-typed message at our subscriber")
            assert received == ['{"ok": true}']
            mismatch = engine.status()["routes"]["ros-wrong-type"]["source"]["mismatched_publishers"]
            executor.shutdown()
        finally:
            await engine.stop()
            node.destroy_node()
            other_node.destroy_node()
            context.try_shutdown()
            other.try_shutdown()

        assert any("sensor_msgs/msg/NavSatFix" in entry for entry in mismatch)
        assert any("does not match the route's type" in r.getMessage() for r in caplog.records)
        records = DeadLetterSpool(spool).read()
        files = sorted(p.name for p in spool.iterdir())
        assert len(files) > 1, "the spool rotated"
        assert sum(p.stat().st_size for p in spool.iterdir()) <= 65536 + 65536 // 4
        stages = {r["headers"]["x-rabbitros-stage"] for r in records}
        assert stages == {"decode", "schema"}
        assert all(r["route"] == "ros-loop" for r in records)
        assert records[-1]["body"] in {b.decode() for b in bad}

    asyncio.run(scenario())
