"""The ros2 endpoint against plain rclpy nodes in the same process (real DDS, no mocks).

Each test runs its own event loop under asyncio.wait_for, so a hang fails the test instead
of the run; the domain id is derived from the pid so parallel runs do not hear each other.
The peer node uses rclpy's EventsExecutor in a thread, so it creates every entity before it
starts spinning (creating one afterwards from another thread deadlocks in rclpy).
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import threading
import time
from typing import Any, Awaitable, Callable

import pytest

import rclpy  # a missing rclpy fails the run

from rclpy.experimental import EventsExecutor  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402

from engine.endpoints.base import EndpointError, Inbound, MessageRejected, Outbound  # noqa: E402
from engine.endpoints.ros2 import TRANSPORT  # noqa: E402
from engine.endpoints.ros2.rosmsg import resolve_type, to_dict  # noqa: E402
from rabbitros_sim.deliver import FunctionDeliver  # noqa: E402
from tests.support.workers import ros_domain
from tests.support.repo import REPO
from tests.support.waiting import wait_for
from tests.support.collecting_deliver import CollectingDeliver

DOMAIN = ros_domain(0)
String = resolve_type("std_msgs/msg/String")
NavSatFix = resolve_type("sensor_msgs/msg/NavSatFix")
PoseArray = resolve_type("geometry_msgs/msg/PoseArray")
DEEP = QoSProfile(depth=10_000, reliability=ReliabilityPolicy.RELIABLE)


class Peer:
    """A plain rclpy node in its own context, standing in for a robot."""

    def __init__(self) -> None:
        self.context = rclpy.Context()
        rclpy.init(args=[], context=self.context, domain_id=DOMAIN,
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("peer", context=self.context)
        self.executor = EventsExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def publisher(self, cls: type, topic: str) -> Any:
        return self.node.create_publisher(cls, topic, DEEP)

    def subscribe(self, cls: type, topic: str) -> list[Any]:
        received: list[Any] = []
        self.node.create_subscription(cls, topic, received.append, DEEP)
        return received

    def start(self) -> None:
        def spin() -> None:
            while not self._stop.is_set():
                self.executor.spin_once(timeout_sec=0.05)
        self._thread = threading.Thread(target=spin, daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
        self.executor.shutdown(timeout_sec=1)
        self.node.destroy_node()
        self.context.try_shutdown()


def run(body: Callable[[], Awaitable[None]], timeout: float = 30.0) -> None:
    asyncio.run(asyncio.wait_for(body(), timeout))


async def subscribed(connection: Any, topic: str) -> None:
    """The engine's node has discovered a subscriber on ``topic`` (then its publisher matches
    at once on creation, and a publisher that exists already matches within moments)."""
    await wait_for(lambda: connection.node.count_subscribers(topic) > 0, what=f"a subscriber on {topic}")


async def open_connection(node: str = "engine_test") -> Any:
    connection = TRANSPORT.connect("ros", {"node": node, "domain_id": DOMAIN})
    await connection.open()
    return connection


def outbound(body: bytes = b"", fields: Any = None, canonical: Any = None) -> Outbound:
    canonical = canonical if canonical is not None else fields
    return Outbound(body=body, canonical=canonical, fields=fields if fields is not None else canonical,
                    message_id="m", meta={})


# ---------------------------------------------------------------- sources

def test_source_receives_string_bytes_exactly():
    texts = ['{"agent_id":"uav1","seq":1}', ' { "spaced" : [1, 2.50, 3e2] }\n', "ção ✓ 🚁", "",
             "\\u00e7 raw\t"]

    async def body() -> None:
        peer = Peer()
        publisher = peer.publisher(String, "/t_exact/json_in")
        connection = await open_connection()
        try:
            got = CollectingDeliver()
            source = connection.source("r-exact", {"topic": "/t_exact/json_in"})
            await source.start(got)
            await wait_for(lambda: publisher.get_subscription_count() > 0, what="discovery")
            for text in texts:
                publisher.publish(String(data=text))
            await wait_for(lambda: len(got.items) == len(texts), what="messages")
            assert [i.body for i in got.items] == [t.encode("utf-8") for t in texts]
            assert all(i.fields is None for i in got.items)
            assert got.items[0].meta == {"topic": "/t_exact/json_in", "type": "std_msgs/msg/String"}
            await source.stop()
        finally:
            await connection.close()
            peer.close()

    run(body)


def test_source_typed_message_gives_fields():
    async def body() -> None:
        peer = Peer()
        publisher = peer.publisher(NavSatFix, "/t_typed/fix")
        connection = await open_connection()
        try:
            got = CollectingDeliver()
            source = connection.source("r-typed", {"topic": "/t_typed/fix", "type": "sensor_msgs/NavSatFix",
                                                   "qos": {"reliability": "reliable", "depth": 50}})
            await source.start(got)
            await wait_for(lambda: publisher.get_subscription_count() > 0, what="discovery")
            fix = NavSatFix(latitude=-22.00123456789, longitude=-47.9, altitude=float("nan"))
            publisher.publish(fix)
            await wait_for(lambda: len(got.items) == 1, what="message")
            fields = got.items[0].fields
            assert got.items[0].body is None
            assert fields is not None, "a ROS 2 message is delivered decoded, as fields"
            assert fields["latitude"] == -22.00123456789 and fields["altitude"] is None
            assert fields == to_dict(fix)
            assert got.items[0].meta["type"] == "sensor_msgs/msg/NavSatFix"
        finally:
            await connection.close()
            peer.close()

    run(body)


def test_source_2000_messages_full_speed_none_lost_in_order():
    async def body() -> None:
        peer = Peer()
        publisher = peer.publisher(String, "/t_flood/in")
        connection = await open_connection()
        try:
            got = CollectingDeliver()
            source = connection.source("r-flood", {"topic": "/t_flood/in"})
            await source.start(got)
            await wait_for(lambda: publisher.get_subscription_count() > 0, what="discovery")
            for i in range(2000):
                publisher.publish(String(data=json.dumps({"seq": i})))
            await wait_for(lambda: len(got.items) == 2000, timeout=20, what="2000 messages")
            assert [json.loads(body)["seq"] for body in got.bodies()] == list(range(2000))
            assert source.dropped == 0
        finally:
            await connection.close()
            peer.close()

    run(body)


def test_source_stop_drains_queue_then_unsubscribes():
    async def body() -> None:
        peer = Peer()
        publisher = peer.publisher(String, "/t_stop/in")
        connection = await open_connection()
        try:
            delivered: list[bytes | None] = []

            async def slow_deliver(inbound: Inbound) -> None:
                await asyncio.sleep(0.002)  # pacing: a slow deliver (the behaviour under test)
                delivered.append(inbound.body)

            source = connection.source("r-stop", {"topic": "/t_stop/in"})
            await source.start(FunctionDeliver(slow_deliver))
            await wait_for(lambda: publisher.get_subscription_count() > 0, what="discovery")
            for i in range(200):
                publisher.publish(String(data=str(i)))
            await wait_for(lambda: source.received == 200, what="all taken")
            assert len(delivered) < 200  # still queued when stop() is called
            await source.stop()
            assert delivered == [str(i).encode() for i in range(200)]
            await wait_for(lambda: publisher.get_subscription_count() == 0, what="unsubscribe")
        finally:
            await connection.close()
            peer.close()

    run(body)


def test_unsettled_messages_are_counted_as_dropped_never_retried_by_the_source():
    """Retrying is the engine's delivery policy, not the source's: a message the route could
    not settle (it was stopping) is counted as dropped, and the next one goes on."""
    async def body() -> None:
        peer = Peer()
        publisher = peer.publisher(String, "/t_retry/in")
        connection = await open_connection()
        try:
            attempts: list[bytes | None] = []

            async def flaky(inbound: Inbound) -> None:
                attempts.append(inbound.body)
                if len(attempts) == 1:
                    raise RuntimeError("not settled")

            deliver = FunctionDeliver(flaky)
            source = connection.source("r-retry", {"topic": "/t_retry/in"})
            await source.start(deliver)
            await wait_for(lambda: publisher.get_subscription_count() > 0, what="discovery")
            publisher.publish(String(data="a"))
            await wait_for(lambda: len(attempts) == 1, what="first delivery")
            publisher.publish(String(data="b"))
            await wait_for(lambda: len(attempts) == 2, what="second delivery")
            assert attempts == [b"a", b"b"] and deliver.drops == 1 and source.dropped == 1
        finally:
            await connection.close()
            peer.close()

    run(body)


def test_overflow_policies_bound_the_queue_and_count_drops():
    """A stalled route: drop_newest keeps the first messages, drop_oldest the last ones,
    block takes no more than the queue holds (DDS history keeps the rest) and loses none."""
    async def body() -> None:
        peer = Peer()
        connection = await open_connection()
        try:
            for policy in ("drop_newest", "drop_oldest", "block"):
                topic = f"/t_overflow_{policy}/in"
                publisher = peer.publisher(String, topic)
                gate = asyncio.Event()
                got: list[bytes | None] = []

                async def stalled(inbound: Inbound, got: list[bytes | None] = got, gate: asyncio.Event = gate) -> None:
                    await gate.wait()
                    got.append(inbound.body)

                deliver = FunctionDeliver(stalled, overflow=policy, queue_limit=20)
                source = connection.source(f"r-{policy}", {"topic": topic})
                await source.start(deliver)
                await wait_for(lambda: publisher.get_subscription_count() > 0, what="discovery")
                publisher.publish(String(data="first"))
                await wait_for(lambda: source.received == 1 and not source._queue, what="first taken")
                for i in range(100):
                    publisher.publish(String(data=str(i)))
                if policy == "block":
                    await wait_for(lambda: source.paused, what="paused")
                    assert source.received <= 1 + 20
                else:
                    await wait_for(lambda: source.received == 101, what="all taken")
                    assert deliver.drops == 80 and source.dropped == 80
                gate.set()
                expected = {"drop_newest": 21, "drop_oldest": 21, "block": 101}[policy]
                await wait_for(lambda: len(got) == expected, what=f"{policy}: delivered")
                if policy == "drop_newest":
                    assert got == [b"first"] + [str(i).encode() for i in range(20)]
                elif policy == "drop_oldest":
                    assert got == [b"first"] + [str(i).encode() for i in range(80, 100)]
                else:
                    assert got == [b"first"] + [str(i).encode() for i in range(100)] and deliver.drops == 0
                await source.stop()
        finally:
            await connection.close()
            peer.close()

    run(body)


def test_idle_connection_does_not_burn_cpu():
    """A polling design costs 40-100 % of a core here; the waiter thread costs ~0."""
    async def body() -> None:
        connection = await open_connection()
        try:
            source = connection.source("r-idle", {"topic": "/t_idle/in"})
            await source.start(CollectingDeliver())
            await asyncio.sleep(0.3)  # settle: the source's start-up work is over before CPU is measured
            cpu, wall = time.process_time(), time.perf_counter()
            await asyncio.sleep(1.5)  # quiet window: the idle interval whose CPU is measured (the behaviour under test)
            assert (time.process_time() - cpu) / (time.perf_counter() - wall) < 0.15
        finally:
            await connection.close()

    run(body)


# ---------------------------------------------------------------- sinks

def test_sink_publishes_string_body_exactly():
    texts = ['{"agent_id":"uav1","seq":1}', "ção ✓ 🚁", ' { "a" : 1.50 }\n']

    async def body() -> None:
        peer = Peer()
        received = peer.subscribe(String, "/t_sink/json_out")
        peer.start()
        connection = await open_connection()
        try:
            sink = connection.sink("r-sink", {"topic": "/t_sink/json_out"})
            await subscribed(connection, "/t_sink/json_out")
            for text in texts:
                await sink.send(outbound(body=text.encode(), canonical={"parsed": True}))
            await wait_for(lambda: len(received) == len(texts), what="messages")
            assert [m.data for m in received] == texts
        finally:
            await connection.close()
            peer.close()

    run(body)


def test_sink_2000_messages_full_speed_none_lost():
    async def body() -> None:
        peer = Peer()
        received = peer.subscribe(String, "/t_sinkflood/out")
        peer.start()
        connection = await open_connection()
        try:
            sink = connection.sink("r-sinkflood", {"topic": "/t_sinkflood/out"})
            await subscribed(connection, "/t_sinkflood/out")
            for i in range(2000):
                await sink.send(outbound(body=b'{"seq":%d}' % i, canonical={"seq": i}))
            await wait_for(lambda: len(received) == 2000, timeout=20, what="2000 messages")
            assert [json.loads(m.data)["seq"] for m in received] == list(range(2000))
        finally:
            await connection.close()
            peer.close()

    run(body)


def test_typed_sink_with_topic_template_created_while_a_source_waits():
    async def body() -> None:
        peer = Peer()
        received = peer.subscribe(PoseArray, "/uav7/weeds")
        peer.start()
        connection = await open_connection()
        try:
            source = connection.source("r-any", {"topic": "/t_tpl/in"})
            await source.start(CollectingDeliver())  # the waiter thread now sits in rcl_wait
            sink = connection.sink("r-weeds", {"topic": "/{agent_id}/weeds",
                                               "type": "geometry_msgs/msg/PoseArray"})
            await subscribed(connection, "/uav7/weeds")
            fields = {"header": {"frame_id": "map"},
                      "poses": [{"position": {"x": 1.5, "y": -2.0}}, {"position": {"x": 3.0}}]}
            # This send creates the publisher for /uav7/weeds from the loop while the waiter thread
            # sits in rcl_wait; its message must still arrive.
            await sink.send(outbound(fields=fields, canonical={"agent_id": "uav7", "weeds": []}))
            await wait_for(lambda: len(received) == 1, what="PoseArray")
            msg = received[0]
            assert msg.header.frame_id == "map" and msg.header.stamp.sec > 0
            assert [(p.position.x, p.position.y) for p in msg.poses] == [(1.5, -2.0), (3.0, 0.0)]
        finally:
            await connection.close()
            peer.close()

    run(body)


def test_sink_is_ready_only_once_a_subscriber_has_matched():
    """A fixed topic's sink is not ready until a subscriber matches (and says why); a
    templated topic's first message refuses (transient) and makes it not ready until that
    topic's subscriber matches; require_subscriber: false is always ready."""
    async def body() -> None:
        connection = await open_connection()
        peer = None
        try:
            fixed = connection.sink("r-fixed", {"topic": "/t_ready/fixed"})
            assert not fixed.ready
            assert fixed.not_ready_reason() == "no subscriber has matched /t_ready/fixed (require_subscriber)"
            anyway = connection.sink("r-anyway", {"topic": "/t_ready/anyway", "require_subscriber": False})
            assert anyway.ready and anyway.not_ready_reason() is None
            templated = connection.sink("r-tpl", {"topic": "/{agent_id}/t_ready"})
            assert templated.ready  # no topic named yet
            with pytest.raises(EndpointError, match="no subscriber has matched /uav3/t_ready yet") as refused:
                await templated.send(outbound(body=b'{"agent_id":"uav3"}', canonical={"agent_id": "uav3"}))
            assert not isinstance(refused.value, MessageRejected)
            assert not templated.ready and "/uav3/t_ready" in templated.not_ready_reason()

            peer = Peer()
            fixed_got = peer.subscribe(String, "/t_ready/fixed")
            templated_got = peer.subscribe(String, "/uav3/t_ready")
            peer.start()
            await wait_for(lambda: fixed.ready and templated.ready, what="both matched")
            assert fixed.not_ready_reason() is None and templated.not_ready_reason() is None
            await fixed.send(outbound(body=b'{"n":1}', canonical={"n": 1}))
            await templated.send(outbound(body=b'{"agent_id":"uav3"}', canonical={"agent_id": "uav3"}))
            await wait_for(lambda: len(fixed_got) == 1 and len(templated_got) == 1, what="both messages")
        finally:
            await connection.close()
            if peer is not None:
                peer.close()

    run(body)


def test_sink_errors_name_route_topic_and_field():
    async def body() -> None:
        connection = await open_connection()
        try:
            sink = connection.sink("r-bad", {"topic": "/t_bad/fix", "type": "sensor_msgs/msg/NavSatFix"})
            with pytest.raises(MessageRejected, match=r"r-bad.*/t_bad/fix.*position_covariance\[1\]"):
                await sink.send(outbound(fields={"position_covariance": [0.0, "x"] + [0.0] * 7}))
            with pytest.raises(MessageRejected, match=r"field status\.colour: unknown field"):
                await sink.send(outbound(fields={"status": {"colour": 1}}))
            templated = connection.sink("r-tpl", {"topic": "/{agent_id}/fix",
                                                  "type": "sensor_msgs/msg/NavSatFix"})
            with pytest.raises(MessageRejected, match="agent_id"):
                await templated.send(outbound(fields={}, canonical={"other": 1}))
            with pytest.raises(MessageRejected, match="r-tpl.*cannot publish on '/uav-1/fix'"):
                await templated.send(outbound(fields={}, canonical={"agent_id": "uav-1"}))
            with pytest.raises(EndpointError, match="is not installed"):
                connection.source("r-missing", {"topic": "/x", "type": "foo_msgs/msg/Bar"})
        finally:
            await connection.close()
        with pytest.raises(EndpointError, match="not open"):
            connection.sink("r-closed", {"topic": "/t_bad/late"})

    run(body)


# ---------------------------------------------------------------- static checks

def test_check_uninstalled_type_and_bad_options():
    errors = list(TRANSPORT.check_source({"topic": "/a", "type": "foo_msgs/msg/Bar"}, None))
    assert ("type", "type 'foo_msgs/msg/Bar' is not installed") in errors
    assert [k for k, _ in TRANSPORT.check_source({}, None)] == ["topic"]
    bad_topic = list(TRANSPORT.check_source({"topic": "/uav-1/x"}, None))
    assert bad_topic and bad_topic[0][0] == "topic" and "uav-1" in bad_topic[0][1]
    assert list(TRANSPORT.check_source({"topic": "/{agent_id}/x"}, None)) == []  # a pattern: discovery
    partial = list(TRANSPORT.check_source({"topic": "/robot{n}/x"}, None))
    assert partial and partial[0][0] == "topic" and "whole name segment" in partial[0][1]
    assert "meta('topic')" in list(TRANSPORT.check_source({"topic": "/{topic}/x"}, None))[0][1]
    assert [k for k, _ in TRANSPORT.check_source({"topic": "/a/x", "forget_after": 5}, None)] == ["forget_after"]
    assert [k for k, _ in TRANSPORT.check_source({"topic": "/{a}/x", "forget_after": 0}, None)] == ["forget_after"]
    assert [k for k, _ in TRANSPORT.check_source({"service": "/{a}/s", "type": "std_srvs/srv/Trigger"}, None)] == ["service"]
    qos = dict(TRANSPORT.check_sink({"topic": "/a", "qos": {"reliability": "sometimes", "depth": 0,
                                                              "durability": "forever", "histroy": 1}}, None))
    assert set(qos) == {"qos.reliability", "qos.depth", "qos.durability", "qos.histroy"}
    assert [k for k, _ in TRANSPORT.check_sink({"topic": "/a", "typ": "x"}, None)] == ["typ"]
    assert list(TRANSPORT.check_sink({"topic": "/{agent_id}/weeds", "type": "geometry_msgs/PoseArray",
                                      "qos": {"reliability": "best_effort", "durability": "transient_local",
                                              "depth": 5}}, None)) == []
    assert list(TRANSPORT.check_connection({"node": "bad node", "domain_id": 300}))[0][0] == "node"
    assert list(TRANSPORT.check_connection(TRANSPORT.default_settings)) == []


def test_check_sink_mapping_keys_against_message_fields():
    options = {"topic": "/uav1/fix", "type": "sensor_msgs/msg/NavSatFix"}
    assert list(TRANSPORT.check_sink(options, "{latitude: lat, longitude: lon, status: {status: fix}}")) == []
    errors = list(TRANSPORT.check_sink(options, "{latitude: lat, lng: lon}"))
    assert len(errors) == 1 and errors[0][0] == "mapping"
    assert "'lng'" in errors[0][1] and "sensor_msgs/msg/NavSatFix" in errors[0][1]
    nested = list(TRANSPORT.check_sink(options, "{status: {state: fix}}"))
    assert len(nested) == 1 and "status.'state'" in nested[0][1] and "NavSatStatus" in nested[0][1]
    assert list(TRANSPORT.check_sink(options, "payload")) == []  # not a multiselect hash: not checkable
    assert list(TRANSPORT.check_sink({"topic": "/s"}, "{anything: x}")) == []  # String publishes the body


def test_nan_survives_typed_sink():
    async def body() -> None:
        peer = Peer()
        received = peer.subscribe(NavSatFix, "/t_nan/fix")
        peer.start()
        connection = await open_connection()
        try:
            sink = connection.sink("r-nan", {"topic": "/t_nan/fix", "type": "sensor_msgs/msg/NavSatFix"})
            await subscribed(connection, "/t_nan/fix")
            await sink.send(outbound(fields={"latitude": 0.1, "altitude": None}))
            await wait_for(lambda: len(received) == 1, what="NavSatFix")
            assert received[0].latitude == 0.1 and math.isnan(received[0].altitude)
        finally:
            await connection.close()
            peer.close()

    run(body)


# ---------------------------------------------------------------- the robot agent example

def test_round_trip_through_robot_echo_example(tmp_path):
    """Engine sink -> examples/robot_echo.py (own process) -> engine source, byte for byte."""
    import sys

    script = REPO / "examples" / "robot_echo.py"
    store = tmp_path / "robot.jsonl"
    texts = [json.dumps({"agent_id": "uav1", "seq": i, "note": "ção"}, ensure_ascii=False)
             for i in range(300)]

    async def body() -> None:
        robot = await asyncio.create_subprocess_exec(
            sys.executable, str(script), "--in", "/t_robot/json_in", "--out", "/t_robot/json_out",
            "--file", str(store), stdout=asyncio.subprocess.PIPE,
            env={**os.environ, "ROS_DOMAIN_ID": str(DOMAIN)},
        )
        connection = await open_connection()
        try:
            assert robot.stdout is not None, "the robot's stdout is a pipe"
            assert (await asyncio.wait_for(robot.stdout.readline(), 15)).strip() == b"ready"
            got = CollectingDeliver()
            source = connection.source("r-echo-in", {"topic": "/t_robot/json_out"})
            await source.start(got)
            sink = connection.sink("r-echo-out", {"topic": "/t_robot/json_in"})
            await subscribed(connection, "/t_robot/json_in")
            await wait_for(lambda: connection.node.count_publishers("/t_robot/json_out") > 0,
                             what="robot publisher")
            await asyncio.sleep(0.3)  # settle: the robot's reader matching our writer is not observable from here (graph and our side are, above)
            for text in texts:
                await sink.send(outbound(body=text.encode(), canonical=json.loads(text)))
            await wait_for(lambda: len(got.items) == len(texts), timeout=15, what="echoes")
            assert [i.body for i in got.items] == [t.encode() for t in texts]
            robot.terminate()
            assert await asyncio.wait_for(robot.wait(), 10) == 0
            assert store.read_text(encoding="utf-8").splitlines() == texts
        finally:
            if robot.returncode is None:
                robot.kill()
                await robot.wait()
            await connection.close()

    run(body, timeout=45)
