"""Calling a ROS 2 service from AMQP (issue 19): a real rclpy server, the real broker, the engine.

200 requests published at once over direct reply-to each get the response to their own request
(matched by correlation id); a request without ``reply_to`` is answered by the server and only
counted; a service nobody serves gives one ``error`` reply within the route's timeout.
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
import uuid
from pathlib import Path
from typing import Any, Iterator

import aio_pika
import pytest
from test_msgs.srv import BasicTypes

from engine.endpoints.ros2.calls import service_qos
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Caller
from tests.support.repo import REPO
from tests.support.ros_nodes import SpunNode
from tests.support.workers import ros_domain
from tests.support.waiting import wait_for

CALLS = 200
MAX_IN_FLIGHT = 64


class BasicTypesServer:
    """``test_msgs/srv/BasicTypes`` in its own context and executor thread: answers
    ``int64_value * 2`` and ``string_value + '!'``; its queue is sized for the route's bound."""

    def __init__(self, domain_id: int, service: str, depth: int) -> None:
        self.ros = SpunNode(domain_id, "basic_types_server")
        self.calls = 0
        self.ros.node.create_service(BasicTypes, service, self._answer, qos_profile=service_qos(depth))

    def _answer(self, request: Any, response: Any) -> Any:
        self.calls += 1
        response.int64_value = request.int64_value * 2
        response.string_value = request.string_value + "!"
        return response

    def close(self) -> None:
        self.ros.close()


@pytest.fixture
def call_routes(tmp_path: Path, amqp_url: str) -> Iterator[tuple[Path, dict[str, Any], BasicTypesServer]]:
    tag = "c" + uuid.uuid4().hex[:8]
    domain = ros_domain(4)
    names: dict[str, Any] = {"tag": tag, "domain": domain, "service": f"/{tag}/basic", "missing": f"/{tag}/nobody"}
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
            await wait_for(lambda: engine.status()["routes"][route]["replies"]["unrequested"] >= 1, 20,
                           "the fire-and-forget call answered (an unrequested reply)")
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
        ("service", "a ros2 sink names one of topic, service or action")]
    assert list(check({"topic": "/b", "timeout": 3}, None)) == [("timeout", "timeout applies to a sink that calls a service")]
    problems = list(check({"service": "/a", "type": "test_msgs/srv/BasicTypes"}, "{int64_valu: n}"))
    assert problems and "did you mean 'int64_value'" in problems[0][1], problems
    assert list(check({"action": "/f", "type": "test_msgs/action/Fibonaci"}, None)) == [
        ("type", "action type 'test_msgs/action/Fibonaci' is not installed")]
    problems = list(check({"action": "/f", "type": "test_msgs/action/Fibonacci"}, "{ordr: n}"))
    assert problems and "did you mean 'order'" in problems[0][1], problems


class FibonacciServer:
    """``test_msgs/action/Fibonacci`` on a MultiThreadedExecutor: one feedback per step
    (``step_s`` apart), cancelable between steps; refuses an order above 100. Records the
    feedback it published per order."""

    def __init__(self, domain_id: int, action: str, step_s: float) -> None:
        from rclpy.action import ActionServer, CancelResponse, GoalResponse
        from rclpy.callback_groups import ReentrantCallbackGroup
        from rclpy.executors import MultiThreadedExecutor
        from test_msgs.action import Fibonacci

        self.Fibonacci, self.step_s = Fibonacci, step_s
        self.feedback_sent: dict[int, int] = {}
        self.ros = SpunNode(domain_id, "fibonacci_server",
                            executor=lambda context: MultiThreadedExecutor(num_threads=4, context=context))
        self.ros.destroy_on_close(ActionServer(
            self.ros.node, Fibonacci, action, self._execute, callback_group=ReentrantCallbackGroup(),
            goal_callback=lambda goal: GoalResponse.REJECT if goal.order > 100 else GoalResponse.ACCEPT,
            cancel_callback=lambda _: CancelResponse.ACCEPT))

    def _execute(self, goal_handle: Any) -> Any:
        order = goal_handle.request.order
        sequence = [0, 1]
        for _ in range(1, order):
            if goal_handle.is_cancel_requested:
                goal_handle.canceled()
                return self.Fibonacci.Result(sequence=sequence)
            sequence.append(sequence[-1] + sequence[-2])
            goal_handle.publish_feedback(self.Fibonacci.Feedback(sequence=sequence))
            self.feedback_sent[order] = self.feedback_sent.get(order, 0) + 1
            time.sleep(self.step_s)  # pacing: the action server's work per step
        goal_handle.succeed()
        return self.Fibonacci.Result(sequence=sequence)

    def close(self) -> None:
        self.ros.close()


def test_fibonacci_goals_accepted_feedback_result_rejected_and_canceled(tmp_path: Path, amqp_url: str) -> None:
    """A goal gets ``accepted``, every feedback the server published (in order) and the right
    ``result`` with SUCCEEDED; a goal the server refuses gets one ``rejected``; a message with
    ``x-rabbitros-cancel: <its correlation id>`` (no reply_to, body ignored) cancels a goal
    mid-way, whose own caller gets ``result`` with CANCELED."""
    tag = "a" + uuid.uuid4().hex[:8]
    domain = ros_domain(4)
    action = f"/{tag}/fibonacci"
    (tmp_path / "actions.yaml").write_text(f"""\
connections:
  bus: {{amqp: "{amqp_url}"}}
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
routes:
  - name: fib-{tag}
    source: {{amqp: {{connection: bus, queue: fib-{tag}}}}}
    schema: raw_json
    sink:
      ros2: {{connection: ros, action: {action}, type: test_msgs/action/Fibonacci, timeout: 30}}
      mapping: "{{order: order}}"
""")
    server = FibonacciServer(domain, action, step_s=0.1)

    def kinds(replies: list[Any]) -> list[str]:
        return [m.headers["x-rabbitros-reply"] for m in replies]

    async def scenario() -> tuple[Caller, str, str, str]:
        engine = Engine(tmp_path, REPO / "schemas")
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            caller = await Caller.open(channel)
            done = await caller.call("", f"fib-{tag}", b'{"order": 6}')
            refused = await caller.call("", f"fib-{tag}", b'{"order": 500}')
            long = await caller.call("", f"fib-{tag}", b'{"order": 60}')
            await caller.wait(lambda r: len(r.get(long, [])) >= 3, 20, "the long goal's feedback")
            await caller.call("", f"fib-{tag}", b"{}", reply_to=None, headers={"x-rabbitros-cancel": long})
            await caller.wait(lambda r: "result" in kinds(r.get(done, [])) and refused in r
                              and "result" in kinds(r.get(long, [])), 30, "every goal's end")
            await channel.queue_delete(f"fib-{tag}")
        finally:
            await engine.stop()
            await connection.close()
        return caller, done, refused, long

    try:
        caller, done, refused, long = asyncio.run(asyncio.wait_for(scenario(), 90))
    finally:
        server.close()
    replies = [(m.headers["x-rabbitros-reply"], json.loads(m.body)) for m in caller.replies[done]]
    assert replies[0] == ("accepted", {"kind": "accepted"})
    feedback = [body["feedback"]["sequence"] for kind, body in replies if kind == "feedback"]
    expected = [0, 1, 1, 2, 3, 5, 8]
    assert feedback == [expected[:n] for n in range(3, 8)] and len(feedback) == server.feedback_sent[6]
    assert replies[-1] == ("result", {"kind": "result", "status": "SUCCEEDED", "result": {"sequence": expected}})
    assert [(m.headers["x-rabbitros-reply"], json.loads(m.body)) for m in caller.replies[refused]] == [
        ("rejected", {"kind": "rejected"})]
    long_replies = [(m.headers["x-rabbitros-reply"], json.loads(m.body)) for m in caller.replies[long]]
    kind, end = long_replies[-1]
    assert kind == "result" and end["status"] == "CANCELED" and len(end["result"]["sequence"]) < 61, end
    assert kinds(caller.replies[long]).count("accepted") == 1


def test_a_ros2_client_calls_the_engines_service_and_gets_the_amqp_workers_answer(tmp_path: Path, amqp_url: str) -> None:
    """The engine offers ``test_msgs/srv/BasicTypes``; each call is an AMQP request (direct
    reply-to) on the worker's queue, and the worker's answer, through ``reply.mapping``, is the
    response the rclpy client gets. A call the worker leaves unanswered gets no response (ROS 2
    has no error response: the client's own wait ends it) and is counted as failed."""
    tag = "o" + uuid.uuid4().hex[:8]
    domain = ros_domain(4)
    service = f"/{tag}/offered"
    (tmp_path / "offered.yaml").write_text(f"""\
connections:
  bus: {{amqp: "{amqp_url}"}}
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
routes:
  - name: offer-{tag}
    source: {{ros2: {{connection: ros, service: {service}, type: test_msgs/srv/BasicTypes}}}}
    mapping: "{{n: int64_value, ask: string_value}}"
    schema: raw_json
    sink: {{amqp: {{connection: bus, routing_key: work-{tag}, timeout: 2}}}}
    reply: {{mapping: "{{int64_value: answer, string_value: note}}"}}
""")
    client_node = SpunNode(domain, "offered_client")
    client = client_node.node.create_client(BasicTypes, service)

    def call(n: int, ask: str, wait: float) -> Any:
        done = threading.Event()
        future = client.call_async(BasicTypes.Request(int64_value=n, string_value=ask))
        future.add_done_callback(lambda _: done.set())
        answered = done.wait(wait)
        if not answered:
            client.remove_pending_request(future)
        return future.result() if answered else None

    async def scenario() -> tuple[list[Any], Any, dict[str, Any]]:
        engine = Engine(tmp_path, REPO / "schemas")
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            work = await channel.declare_queue(f"work-{tag}", exclusive=True)

            async def worker(message: aio_pika.abc.AbstractIncomingMessage) -> None:
                request = json.loads(message.body)
                if request["ask"] == "ignore me":
                    return
                assert message.reply_to is not None, "the engine's call names its reply queue"
                await channel.default_exchange.publish(aio_pika.Message(
                    json.dumps({"answer": request["n"] * 3, "note": f"{request['ask']} done"}).encode(),
                    correlation_id=message.correlation_id), message.reply_to)

            await work.consume(worker, no_ack=True)
            ready = await asyncio.to_thread(client.wait_for_service, timeout_sec=10)
            assert ready, "the engine does not offer the service"
            answers = await asyncio.gather(*(asyncio.to_thread(call, n, f"task{n}", 10) for n in range(5)))
            ignored = await asyncio.to_thread(call, 7, "ignore me", 4)
            status = engine.status()["routes"][f"offer-{tag}"]
        finally:
            await engine.stop()
            await connection.close()
        return answers, ignored, status

    try:
        answers, ignored, status = asyncio.run(asyncio.wait_for(scenario(), 60))
    finally:
        client_node.close()
    assert None not in answers, (answers, {k: status[k] for k in ("received", "delivered", "failed", "dead_lettered", "replies", "source")})
    assert [(a.int64_value, a.string_value) for a in answers] == [(3 * n, f"task{n} done") for n in range(5)]
    assert ignored is None
    assert status["source"] == {"calls": 6, "answered": 5, "failed": 1}, status
    assert status["replies"]["sent"] == 6 and status["replies"]["errors"] == 1, status
