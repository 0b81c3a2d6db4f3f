"""``run --workers 2`` on a ROS 2 topic pattern (``/{agent}/fix``, discovered): the route runs
on both workers and each follows its share of the robots (a stable hash of the topic,
engine/common/shares.py), so a fleet's agents spread over the workers, every one on exactly one.

Real parts: a private RabbitMQ node (tests/conftest.py), rclpy publishers in this process (one
node per robot, transient local so nothing published before discovery is lost), the engine as an
operator runs it (the supervisor and its two worker processes) and its admin endpoint."""

from __future__ import annotations

import json
import uuid
from pathlib import Path
from typing import Any

import aio_pika

from engine.common.shares import share_of
from tests.operator.test_workers import admin_status, two_workers
from tests.support.amqp_helpers import Collector
from tests.support.waiting import wait_for
from tests.support.workers import ros_domain

ROUTES = """
connections:
  broker: {{amqp: "{url}"}}
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
routes:
  - name: fixes-{tag}
    source: {{ros2: {{connection: ros, topic: "/{{agent}}/fix_{tag}", type: std_msgs/msg/String}}}}
    schema: raw_json
    mapping: "{{agent: meta('agent'), seq: seq}}"
    sink: {{amqp: {{connection: broker, exchange: {tag}-out, routing_key: "fix.{{agent}}"}}}}
"""
EACH = 30


def robots(tag: str, per_share: int = 3) -> list[str]:
    """Robot names whose topics fall ``per_share`` in each of the two shares (a hash decides, so
    the test picks names that make both workers follow some)."""
    chosen: dict[int, list[str]] = {0: [], 1: []}
    index = 0
    while min(len(names) for names in chosen.values()) < per_share:
        name = f"robot{index}"
        share = share_of(f"/{name}/fix_{tag}", 2)
        if len(chosen[share]) < per_share:
            chosen[share].append(name)
        index += 1
    return sorted(chosen[0] + chosen[1])


def test_a_topic_patterns_robots_are_shared_between_the_workers(tmp_path: Path, amqp_url: str) -> None:
    import rclpy
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions
    from std_msgs.msg import String

    tag = "r" + uuid.uuid4().hex[:6]
    domain = ros_domain(19)
    names = robots(tag)
    context = rclpy.Context()
    rclpy.init(args=[], context=context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(f"fleet_{tag}", context=context)
    qos = QoSProfile(depth=EACH, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    publishers = {name: node.create_publisher(String, f"/{name}/fix_{tag}", qos) for name in names}
    for seq in range(EACH):
        for publisher in publishers.values():
            publisher.publish(String(data=json.dumps({"seq": seq})))  # a String's data is the JSON message
    _, port, engine = two_workers(tmp_path, ROUTES.format(url=amqp_url, domain=domain, tag=tag))

    async def scenario() -> dict[str, Any]:
        connection = await aio_pika.connect(amqp_url)
        out = await Collector.bind(await connection.channel(), f"{tag}-out", "#")
        try:
            placed = await admin_status(port)
            assert placed["placement"] == {f"fixes-{tag}": [0, 1]}, placed["placement"]
            expected = {(name, seq) for name in names for seq in range(EACH)}
            await wait_for(lambda: {(m["agent"], m["seq"]) for m in map(json.loads, (x.body for x in out.messages))} >= expected,
                           90, f"{len(expected)} fixes from {len(names)} robots", lambda: len(out.messages))
            return {"status": await admin_status(port), "arrived": [json.loads(m.body) for m in out.messages]}
        finally:
            await connection.close()

    try:
        result, _ = engine.run(scenario)
    finally:
        node.destroy_node()
        context.try_shutdown()
    following = [set(worker["status"]["routes"][f"fixes-{tag}"]["source"]["following"]) for worker in result["status"]["workers"]]
    print(f"ROS 2 topic pattern over 2 workers: worker 0 follows {sorted(following[0])}, worker 1 {sorted(following[1])}")
    topics = {f"/{name}/fix_{tag}" for name in names}
    assert following[0] | following[1] == topics and not following[0] & following[1], following
    assert all({share_of(topic, 2) for topic in mine} == {index} for index, mine in enumerate(following)), following
    arrivals = [(m["agent"], m["seq"]) for m in result["arrived"]]
    assert len(arrivals) == len(set(arrivals)) == len(names) * EACH, "every fix once: each robot is one worker's"
