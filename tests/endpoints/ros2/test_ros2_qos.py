"""ROS 2 sources that meet the robot's QoS (issue 31): a route without ``qos`` subscribes with
what its publishers offer, as rosbag2's adaptive QoS does, and a stated ``qos`` that a
publisher cannot match names it (topic, node, offered against requested) in the status and
once in the log.

Real parts: the engine in process with a real RabbitMQ, robots as real rclpy publishers (a
node of their own context in the test process) on fixed topics. Before this, a best-effort
publisher (the ``sensor_data`` QoS of most drivers) reached a route without ``qos`` 0 times
in 50 (the route asked for reliable, which DDS never matches with best-effort), a
transient_local publisher's kept messages never reached it (volatile), and the status said
``mismatched_publishers: []``.
"""

from __future__ import annotations

import asyncio
import json
import logging
import uuid
from pathlib import Path
from typing import Any

import aio_pika
import pytest

import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.signals import SignalHandlerOptions

from engine.endpoints.ros2 import offers
from engine.endpoints.ros2.rosmsg import resolve_type
from engine.endpoints.ros2.source import Ros2Source
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector
from tests.support.repo import REPO
from tests.support.waiting import wait_for
from tests.support.workers import ros_domain

DOMAIN = ros_domain(15)
MESSAGES = 50
String = resolve_type("std_msgs/msg/String")
NavSatFix = resolve_type("sensor_msgs/msg/NavSatFix")
LATCHED = QoSProfile(depth=MESSAGES, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""A map server's or robot_description's QoS: what joins later gets the kept messages."""

ROUTES = """
connections:
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
routes:
  - name: fix-early
    source: {{ros2: {{topic: /robot9/fix_{tag}, type: sensor_msgs/msg/NavSatFix}}}}
    mapping: "{{seq: altitude}}"
    schema: raw_json
    sink: {{amqp: {{exchange: {outbox}, routing_key: fix-early}}}}
  - name: fix-late
    source: {{ros2: {{topic: /robot7/fix_{tag}, type: sensor_msgs/msg/NavSatFix}}}}
    mapping: "{{seq: altitude}}"
    schema: raw_json
    sink: {{amqp: {{exchange: {outbox}, routing_key: fix-late}}}}
  - name: map-early
    source: {{ros2: {{topic: /map_{tag}}}}}
    schema: raw_json
    sink: {{amqp: {{exchange: {outbox}, routing_key: map-early}}}}
  - name: map-late
    source: {{ros2: {{topic: /map2_{tag}}}}}
    schema: raw_json
    sink: {{amqp: {{exchange: {outbox}, routing_key: map-late}}}}
  - name: fix-fleet
    source: {{ros2: {{topic: "/{{agent}}/gps_{tag}", type: sensor_msgs/msg/NavSatFix}}}}
    mapping: "{{seq: altitude, agent: meta('agent')}}"
    schema: raw_json
    sink: {{amqp: {{exchange: {outbox}, routing_key: fix-fleet}}}}
  - name: fix-mixed
    source: {{ros2: {{topic: /robot6/fix_{tag}, type: sensor_msgs/msg/NavSatFix}}}}
    mapping: "{{seq: altitude, who: latitude}}"
    schema: raw_json
    sink: {{amqp: {{exchange: {outbox}, routing_key: fix-mixed}}}}
  - name: fix-stated
    source: {{ros2: {{topic: /robot8/fix_{tag}, type: sensor_msgs/msg/NavSatFix, qos: {{reliability: reliable}}}}}}
    mapping: "{{seq: altitude}}"
    schema: raw_json
    sink: {{amqp: {{exchange: {outbox}, routing_key: fix-stated}}}}
"""


class Robot:
    """A robot's node in its own context: publishers need no spinning."""

    def __init__(self, name: str) -> None:
        self.context = rclpy.Context()
        rclpy.init(args=[], context=self.context, domain_id=DOMAIN, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(name, context=self.context)

    def close(self) -> None:
        self.node.destroy_node()
        self.context.try_shutdown()


def _fix(seq: int) -> Any:
    return NavSatFix(latitude=1.0, longitude=2.0, altitude=float(seq))


def _seqs(messages: list[Any], key: str) -> list[int]:
    return [int(json.loads(m.body)["seq"]) for m in messages if m.routing_key == key]


@pytest.fixture
def routes(tmp_path: Path, amqp_url: str, monkeypatch: pytest.MonkeyPatch) -> dict[str, str]:
    monkeypatch.setenv("RABBITROS_AMQP_URL", amqp_url)
    tag = "q" + uuid.uuid4().hex[:8]
    names = {"tag": tag, "outbox": f"out-{tag}", "domain": str(DOMAIN)}
    (tmp_path / "qos.yaml").write_text(ROUTES.format(**names))
    return names


def test_best_effort_and_transient_local_publishers_reach_routes_without_qos(
        tmp_path: Path, amqp_url: str, routes: dict[str, str]) -> None:
    """Five routes without ``qos``. A best-effort robot publishing before the engine starts,
    another appearing after it (the subscription is re-created to match it), a third on a
    discovering route's pattern, each 50 fixes once they matched: 50/50 each, in order. A transient_local publisher that published its
    50 before the engine started: all 50 kept messages received; one appearing after the
    engine (first matched by the default volatile reader, then re-matched as
    transient_local, whose kept history arrives again): 50, none twice."""
    tag = routes["tag"]
    robot = Robot(f"robot_{tag}")
    early_fix = robot.node.create_publisher(NavSatFix, f"/robot9/fix_{tag}", qos_profile_sensor_data)
    early_map = robot.node.create_publisher(String, f"/map_{tag}", LATCHED)
    for seq in range(MESSAGES):
        early_map.publish(String(data=json.dumps({"seq": seq})))

    async def scenario() -> dict[str, Any]:
        engine = Engine(tmp_path, REPO / "schemas")
        connection = await aio_pika.connect(amqp_url)
        output = await Collector.bind(await connection.channel(), routes["outbox"], "#")
        await engine.start()
        try:
            await wait_for(lambda: early_fix.get_subscription_count() > 0, 15,
                           "the route's subscription matching the best-effort robot that was there first")
            for seq in range(MESSAGES):
                early_fix.publish(_fix(seq))
            late_fix = robot.node.create_publisher(NavSatFix, f"/robot7/fix_{tag}", qos_profile_sensor_data)
            await wait_for(lambda: late_fix.get_subscription_count() > 0, 15,
                           "the route's subscription re-matched to the best-effort robot that came later")
            for seq in range(MESSAGES):
                late_fix.publish(_fix(seq))
            fleet_fix = robot.node.create_publisher(NavSatFix, f"/robot5/gps_{tag}", qos_profile_sensor_data)
            await wait_for(lambda: fleet_fix.get_subscription_count() > 0, 15,
                           "the discovering route's subscription matching the best-effort robot")
            for seq in range(MESSAGES):
                fleet_fix.publish(_fix(seq))
            late_map = robot.node.create_publisher(String, f"/map2_{tag}", LATCHED)
            await wait_for(lambda: late_map.get_subscription_count() > 0, 15, "the late map's first match")
            for seq in range(MESSAGES):
                late_map.publish(String(data=json.dumps({"seq": seq})))

            def late_map_transient() -> bool:
                return engine.status()["routes"]["map-late"]["source"].get("qos") == "reliable transient_local"

            await wait_for(late_map_transient, 15, "the late map's route re-matched as transient_local",
                           detail=lambda: engine.status()["routes"]["map-late"]["source"])
            await output.wait_for(5 * MESSAGES, timeout=15)
            # the re-created subscription has taken the kept history again by now (it arrives on
            # matching, before the switch): a duplicate would be counted as received
            sources = {name: engine.status()["routes"][name]["source"] for name in ("fix-early", "fix-late", "fix-fleet", "map-early", "map-late")}
            return {"messages": list(output.messages), "sources": sources}
        finally:
            await engine.stop()
            await connection.close()

    try:
        result = asyncio.run(asyncio.wait_for(scenario(), 90))
    finally:
        robot.close()
    expected = list(range(MESSAGES))
    messages = result["messages"]
    assert _seqs(messages, "fix-early") == expected
    assert _seqs(messages, "fix-late") == expected
    assert _seqs(messages, "fix-fleet") == expected
    assert {json.loads(m.body)["agent"] for m in messages if m.routing_key == "fix-fleet"} == {"robot5"}
    assert result["sources"]["fix-fleet"]["following"][f"/robot5/gps_{tag}"]["qos"] == "best_effort volatile"
    assert _seqs(messages, "map-early") == expected
    assert _seqs(messages, "map-late") == expected
    assert result["sources"]["fix-early"]["qos"] == "best_effort volatile"
    assert result["sources"]["fix-late"]["qos"] == "best_effort volatile"
    assert result["sources"]["map-early"]["qos"] == "reliable transient_local"
    assert all(source["mismatched_publishers"] == [] for source in result["sources"].values())
    assert {name: source["received"] for name, source in result["sources"].items()} == dict.fromkeys(result["sources"], MESSAGES)


def test_a_best_effort_robot_joining_a_reliable_one_mid_stream_loses_and_repeats_nothing(
        tmp_path: Path, amqp_url: str, routes: dict[str, str]) -> None:
    """A reliable publisher streams 400 fixes at about 200 Hz; midway a best-effort one
    appears on the same topic: the route's subscription is re-created best-effort (make before
    break) while the stream flows. The reliable stream arrives whole and once (400/400, in
    order), the best-effort robot's 50 too."""
    tag = routes["tag"]
    topic = f"/robot6/fix_{tag}"
    robot = Robot(f"mixed_{tag}")
    steady = robot.node.create_publisher(NavSatFix, topic, QoSProfile(depth=1000))
    stream = 400

    async def scenario() -> dict[str, Any]:
        engine = Engine(tmp_path, REPO / "schemas")
        connection = await aio_pika.connect(amqp_url)
        output = await Collector.bind(await connection.channel(), routes["outbox"], "fix-mixed")
        await engine.start()
        try:
            await wait_for(lambda: steady.get_subscription_count() > 0, 15, "the reliable publisher matched")

            async def publish_stream() -> None:
                for seq in range(stream):
                    steady.publish(NavSatFix(latitude=1.0, altitude=float(seq)))
                    await asyncio.sleep(0.005)  # pacing: the stream's rate

            streaming = asyncio.create_task(publish_stream())
            await wait_for(lambda: len(output.messages) >= 50, 15, "the stream under way")
            joiner = robot.node.create_publisher(NavSatFix, topic, qos_profile_sensor_data)
            await wait_for(lambda: joiner.get_subscription_count() > 0, 15, "the best-effort robot matched")
            still_streaming = not streaming.done()
            for seq in range(MESSAGES):
                joiner.publish(NavSatFix(latitude=2.0, altitude=float(seq)))
            await streaming
            await output.wait_for(stream + MESSAGES, timeout=15)
            return {"messages": list(output.messages), "source": engine.status()["routes"]["fix-mixed"]["source"],
                    "still_streaming": still_streaming}
        finally:
            await engine.stop()
            await connection.close()

    try:
        result = asyncio.run(asyncio.wait_for(scenario(), 90))
    finally:
        robot.close()
    bodies = [json.loads(m.body) for m in result["messages"]]
    assert [int(b["seq"]) for b in bodies if b["who"] == 1.0] == list(range(stream))
    assert [int(b["seq"]) for b in bodies if b["who"] == 2.0] == list(range(MESSAGES))
    assert result["still_streaming"], "the subscription was re-created while the reliable stream flowed"
    assert result["source"]["qos"] == "best_effort volatile"
    assert result["source"]["received"] == stream + MESSAGES


def test_a_stated_qos_that_cannot_match_names_the_publisher_in_status_and_once_in_the_log(
        tmp_path: Path, routes: dict[str, str], caplog: pytest.LogCaptureFixture) -> None:
    """The route states ``reliability: reliable``; the robot publishes best-effort: nothing can
    match (DDS), and the status names the topic, the node and what it offers against what the
    route requests; the log says it once, however many times the publishers are read."""
    caplog.set_level(logging.INFO, logger="engine.ros2")
    tag = routes["tag"]
    topic = f"/robot8/fix_{tag}"
    robot = Robot(f"gps_{tag}")
    publisher = robot.node.create_publisher(NavSatFix, topic, qos_profile_sensor_data)

    async def scenario() -> tuple[list[str], list[str], dict[str, Any]]:
        engine = Engine(tmp_path, REPO / "schemas")
        await engine.start()
        try:
            def mismatched() -> list[str]:
                return engine.status()["routes"]["fix-stated"]["source"]["mismatched_publishers"]

            named = await wait_for(mismatched, 15, "the mismatched publisher named in the status",
                                   detail=lambda: engine.status()["routes"]["fix-stated"]["source"])
            source = engine.runners["fix-stated"].source
            assert isinstance(source, Ros2Source), "fix-stated reads a ROS 2 topic"
            looks = source._looked[topic][1]
            # several more full reads of the publishers (every 2 s while one stays unmatched)
            await wait_for(lambda: source._looked[topic][1] > looks, 10, "another read of the publishers")
            again = mismatched()
            return named, again, dict(engine.status()["routes"]["fix-stated"]["source"])
        finally:
            await engine.stop()

    try:
        named, again, status = asyncio.run(asyncio.wait_for(scenario(), 60))
    finally:
        publisher.destroy()
        robot.close()
    assert named == again
    assert len(named) == 1
    assert named[0].startswith(f"/gps_{tag} on {topic} offers best_effort volatile, the route requests reliable volatile")
    assert status["received"] == 0
    logged = [r.getMessage() for r in caplog.records if f"/gps_{tag} on {topic}" in r.getMessage()]
    assert len(logged) == 1 and "offers best_effort volatile" in logged[0], logged


def test_the_request_follows_rosbag2s_rules_for_mixed_offers() -> None:
    """rosbag2's adapt_request_to_offers: reliable only if every publisher offers it,
    transient_local only if every publisher offers it; a policy the route states is kept; no
    publisher, the route's default. (The profiles are rclpy's, as get_publishers_info_by_topic
    gives them.)"""
    default = QoSProfile(depth=10)
    reliable_latched = offers.Offer("/map", "/map_server", LATCHED)
    sensor = offers.Offer("/fix", "/gps", qos_profile_sensor_data)
    reliable = offers.Offer("/fix", "/fusion", QoSProfile(depth=5))

    def request(stated: set[str], *offered: offers.Offer) -> str:
        return offers.describe(offers.adapted(default, frozenset(stated), offered))

    assert request(set()) == "reliable volatile"
    assert request(set(), sensor) == "best_effort volatile"
    assert request(set(), reliable, sensor) == "best_effort volatile"
    assert request(set(), reliable_latched) == "reliable transient_local"
    assert request(set(), reliable_latched, reliable) == "reliable volatile"
    assert request({"reliability"}, sensor) == "reliable volatile"
    assert request({"reliability", "durability"}, reliable_latched) == "reliable volatile"
    assert offers.refusals(offers.adapted(default, frozenset({"reliability"}), [sensor, reliable]), [sensor, reliable]) == [
        "/gps on /fix offers best_effort volatile, the route requests reliable volatile "
        "(Best effort publisher and reliable subscription)"]
