"""Calling a ROS 2 service from AMQP (issue 19): a real rclpy server, the real broker, the engine.

200 requests published at once over direct reply-to each get the response to their own request
(matched by correlation id); a request without ``reply_to`` is answered by the server and only
counted; a service nobody serves gives one ``error`` reply within the route's timeout.
"""

from __future__ import annotations

import asyncio
import json
import os
import statistics
import threading
import time
import uuid
from pathlib import Path
from typing import Any, Iterator

import aio_pika
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from test_msgs.srv import BasicTypes

from engine.endpoints.ros2_calls import service_qos
from engine.runtime import Engine
from tests.amqp_helpers import Caller
from tests.conftest import REPO

CALLS = 200
MAX_IN_FLIGHT = 64


class BasicTypesServer:
    """``test_msgs/srv/BasicTypes`` in its own context and executor thread: answers
    ``int64_value * 2`` and ``string_value + '!'``; its queue is sized for the route's bound."""

    def __init__(self, domain_id: int, service: str, depth: int) -> None:
        self.context = Context()
        rclpy.init(args=[], context=self.context, domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
        self.node = Node("basic_types_server", context=self.context, start_parameter_services=False)
        self.calls = 0
        self.node.create_service(BasicTypes, service, self._answer, qos_profile=service_qos(depth))
        self.client = self.node.create_client(BasicTypes, service)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass

    def _answer(self, request: Any, response: Any) -> Any:
        self.calls += 1
        response.int64_value = request.int64_value * 2
        response.string_value = request.string_value + "!"
        return response

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2)
        self.thread.join(5)
        self.node.destroy_node()
        self.context.try_shutdown()


@pytest.fixture
def call_routes(tmp_path: Path, amqp_url: str) -> Iterator[tuple[Path, dict[str, Any], BasicTypesServer]]:
    tag = "c" + uuid.uuid4().hex[:8]
    domain = 101 + os.getpid() % 100
    names = {"tag": tag, "domain": domain, "service": f"/{tag}/basic", "missing": f"/{tag}/nobody"}
    (tmp_path / "calls.yaml").write_text(f"""\
connections:
  bus: {{amqp: "{amqp_url}"}}
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
routes:
  - name: call-{tag}
    source: {{amqp: {{connection: bus, queue: call-{tag}, prefetch: 512}}}}
    schema: raw_json
    sink:
      ros2: {{connection: ros, service: {names['service']}, type: test_msgs/srv/BasicTypes, timeout: 10, max_in_flight: {MAX_IN_FLIGHT}}}
      mapping: "{{int64_value: n, string_value: name}}"
    reply: {{mapping: "{{doubled: int64_value, echo: string_value}}"}}
  - name: nobody-{tag}
    source: {{amqp: {{connection: bus, queue: nobody-{tag}}}}}
    schema: raw_json
    sink: {{ros2: {{connection: ros, service: {names['missing']}, type: test_msgs/srv/BasicTypes, timeout: 1.0}}}}
""")
    server = BasicTypesServer(domain, names["service"], MAX_IN_FLIGHT)
    try:
        yield tmp_path, names, server
    finally:
        server.close()


def test_200_concurrent_service_calls_each_get_their_own_response(call_routes: Any, amqp_url: str) -> None:
    directory, names, server = call_routes
    tag = names["tag"]

    async def scenario() -> tuple[Caller, dict[str, int], dict[str, float], dict[str, Any]]:
        engine = Engine(directory, REPO / "schemas")
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            caller = await Caller.open(channel)
            sent: dict[str, int] = {}
            started: dict[str, float] = {}
            for n in range(CALLS):
                started_at = time.monotonic()
                correlation_id = await caller.call("", f"call-{tag}", json.dumps({"n": n, "name": f"r{n}"}).encode())
                sent[correlation_id], started[correlation_id] = n, started_at
            await caller.wait(lambda replies: len(replies) >= CALLS, 40, f"{CALLS} replies")
            await caller.call("", f"call-{tag}", json.dumps({"n": 1, "name": "quiet"}).encode(), reply_to=None)
            route = f"call-{tag}"
            deadline = time.monotonic() + 20
            while engine.status()["routes"][route]["replies"]["unrequested"] < 1:
                assert time.monotonic() < deadline, "the fire-and-forget call was not answered"
                await asyncio.sleep(0.05)
            status = engine.status()["routes"][route]
            for queue in (f"call-{tag}", f"nobody-{tag}"):
                await channel.queue_delete(queue)
        finally:
            await engine.stop()
            await connection.close()
        return caller, sent, started, status

    caller, sent, _, status = asyncio.run(asyncio.wait_for(scenario(), 90))
    assert set(caller.replies) == set(sent)
    for correlation_id, n in sent.items():
        [reply] = caller.replies[correlation_id]
        assert reply.headers["x-rabbitros-reply"] == "result", reply.body
        assert json.loads(reply.body) == {"doubled": 2 * n, "echo": f"r{n}!"}
    assert server.calls == CALLS + 1
    assert status["replies"] == {"sent": CALLS, "errors": 0, "unrequested": 1, "late": 0, "undelivered": 0}, status
    assert (status["delivered"], status["failed"]) == (CALLS + 1, 0), status


def test_a_service_nobody_serves_is_an_error_reply_within_its_timeout(call_routes: Any, amqp_url: str) -> None:
    directory, names, _ = call_routes
    tag = names["tag"]

    async def scenario() -> tuple[list[Any], float]:
        engine = Engine(directory, REPO / "schemas")
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            caller = await Caller.open(channel)
            started = time.monotonic()
            correlation_id = await caller.call("", f"nobody-{tag}", b'{"int64_value": 1}')
            await caller.wait(lambda replies: correlation_id in replies, 10, "the error reply")
            elapsed = time.monotonic() - started
            for queue in (f"call-{tag}", f"nobody-{tag}"):
                await channel.queue_delete(queue)
        finally:
            await engine.stop()
            await connection.close()
        return caller.replies[correlation_id], elapsed

    replies, elapsed = asyncio.run(asyncio.wait_for(scenario(), 60))
    [reply] = replies
    body = json.loads(reply.body)
    assert reply.headers["x-rabbitros-reply"] == "error" and reply.headers["x-rabbitros-route"] == f"nobody-{tag}"
    assert body == {"kind": "error", "stage": "sink", "route": f"nobody-{tag}",
                    "error": f"route 'nobody-{tag}', ros2 service '{names['missing']}': not available (no server within 1 s)"}
    assert 1.0 <= elapsed < 3.0, elapsed


def test_service_sink_options_are_checked() -> None:
    from engine.endpoints.ros2 import TRANSPORT

    check = TRANSPORT.check_sink
    assert list(check({"service": "/a", "type": "test_msgs/srv/BasicTypes"}, None)) == []
    assert list(check({"service": "/a", "type": "test_msgs/srv/BasicType"}, None)) == [
        ("type", "service type 'test_msgs/srv/BasicType' is not installed")]
    assert list(check({"service": "/a", "topic": "/b", "type": "test_msgs/srv/BasicTypes"}, None)) == [
        ("service", "a ros2 sink names a topic or a service, not both")]
    assert list(check({"topic": "/b", "timeout": 3}, None)) == [("timeout", "timeout applies to a sink that calls a service")]
    problems = list(check({"service": "/a", "type": "test_msgs/srv/BasicTypes"}, "{int64_valu: n}"))
    assert problems and "did you mean 'int64_value'" in problems[0][1], problems
