"""Fan-out on ROS 2: two routes on one topic each receive every message (real rclpy, real
RabbitMQ). AMQP keeps its own semantics: one queue is competing consumers, which ``check``
warns about (tests/language/test_plan.py)."""

from __future__ import annotations

import asyncio
import json
import uuid
from pathlib import Path

import aio_pika
import pytest

from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector, publish
from tests.support.workers import ros_domain
from tests.support.waiting import probe_until, wait_for

ROUTES = """
connections:
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
routes:
  - name: into-ros
    source: {{amqp: {{exchange: {inbox}, binding_key: "#", queue: {inbox}-q}}}}
    schema: raw_json
    sink: {{ros2: {{topic: /{tag}/shared}}}}
  - name: record
    source: {{ros2: {{topic: /{tag}/shared}}}}
    schema: raw_json
    sink: {{amqp: {{exchange: {outbox}, routing_key: record}}}}
  - name: echo
    source: {{ros2: {{topic: /{tag}/shared}}}}
    schema: raw_json
    sink: {{amqp: {{exchange: {outbox}, routing_key: echo}}}}
"""


def test_two_routes_on_one_ros_topic_each_get_every_message(amqp_url: str, tmp_path: Path, schemas_dir: Path,
                                                           monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setenv("RABBITROS_AMQP_URL", amqp_url)
    tag = "f" + uuid.uuid4().hex[:8]
    n = {"tag": tag, "inbox": f"in-{tag}", "outbox": f"out-{tag}", "domain": str(ros_domain(10))}
    (tmp_path / "fanout.yaml").write_text(ROUTES.format(**n))

    async def scenario() -> dict[str, list[int]]:
        engine = Engine(tmp_path, schemas_dir)
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            record = await Collector.bind(channel, n["outbox"], "record")
            echo = await Collector.bind(channel, n["outbox"], "echo")
            # DDS matching is asynchronous: probe until both readers hear the writer
            await probe_until(lambda: record.messages and echo.messages, lambda: publish(channel, n["inbox"], "x", [b'{"seq": -1}']),
                              20, "a probe through both readers", every=0.1)
            await publish(channel, n["inbox"], "x", [json.dumps({"seq": i}).encode() for i in range(300)])

            def carried(collector: Collector) -> int:  # a probe still in flight may land among them
                return sum(json.loads(m.body)["seq"] >= 0 for m in collector.messages)

            await wait_for(lambda: carried(record) >= 300 and carried(echo) >= 300, 60, "the 300 at both routes",
                           lambda: (carried(record), carried(echo)))
            return {name: [json.loads(m.body)["seq"] for m in c.messages] for name, c in (("record", record), ("echo", echo))}
        finally:
            await connection.close()
            await engine.stop()

    received = asyncio.run(asyncio.wait_for(scenario(), 120))
    for route, seqs in received.items():
        assert sorted(s for s in seqs if s >= 0) == list(range(300)), f"{route} missed messages"
