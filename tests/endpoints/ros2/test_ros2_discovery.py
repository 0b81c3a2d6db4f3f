"""Discovery (issue 20): a ROS 2 source topic with ``{var}`` segments follows every matching
topic as it appears in the graph, each message carrying the captured value as ``meta('agent')``
and in the sink's templates; a topic without a publisher is let go after ``forget_after``; a
matching topic of another type is reported, never subscribed.

Real parts: the engine in process with a real RabbitMQ, robots as real rclpy publishers (a node
of their own context) created after the engine has started.
"""

from __future__ import annotations

import asyncio
import json
import time
import uuid
from pathlib import Path
from typing import Any

import aio_pika
import pytest

import rclpy  # noqa: F401  (a missing rclpy fails the run, never skips it)
from rclpy.qos import QoSProfile, ReliabilityPolicy

from engine.common.schemas import SchemaRegistry
from engine.endpoints.base import Outbound
from engine.endpoints.ros2.discovery import compile_pattern
from engine.language.routes import RoutesInvalid, load_routes
from engine.ops.route_tests import load_checked, run_tests
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector
from tests.support.repo import REPO
from tests.endpoints.ros2.test_ros2_endpoint import DOMAIN, NavSatFix, Peer, String
from tests.support.waiting import wait_for

ROBOTS = 20
MESSAGES = 10
"""Per robot, after its topic is followed."""
FORGET_AFTER = 1.0
BEST_EFFORT = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)

FLEET = """
connections:
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
routes:
  - name: fleet-fix
    source:
      ros2: {{topic: "/{{agent}}/fix_{tag}", type: sensor_msgs/msg/NavSatFix, forget_after: {forget_after},
             qos: {{reliability: reliable}}}}
    mapping: "{{agent_id: meta('agent'), lat: latitude, lon: longitude, alt_msl: altitude}}"
    schema: position
    sink:
      amqp: {{exchange: {outbox}, routing_key: "farm.{{agent}}.fix"}}
"""


def _fix(robot: int, seq: int) -> Any:
    return NavSatFix(latitude=float(robot), longitude=seq / 100, altitude=float(seq))


def test_twenty_robots_appearing_after_the_engine_starts_are_followed_each_message_with_its_agent(
        tmp_path: Path, amqp_url: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The engine starts first; then 20 robots' topics appear (and one of another type, and one
    whose QoS the route's stated reliable reader cannot match). Every
    robot's topic is followed, every message reaches RabbitMQ under its robot's routing key with
    its agent, in order; a robot that leaves is let go after forget_after (not before), and
    followed again when it comes back. The topics carry the test's tag (``/robot3/fix_<tag>``)
    so that no other test's topics in the same DDS domain match."""
    monkeypatch.setenv("RABBITROS_AMQP_URL", amqp_url)
    tag = "d" + uuid.uuid4().hex[:8]
    outbox = f"out-{tag}"
    topic = "/{}/fix_" + tag
    (tmp_path / "fleet.yaml").write_text(FLEET.format(domain=DOMAIN, tag=tag, outbox=outbox, forget_after=FORGET_AFTER))

    async def scenario() -> dict[str, Any]:
        engine = Engine(tmp_path, REPO / "schemas")
        await engine.start()
        robots = Peer()
        connection = await aio_pika.connect(amqp_url)

        def source() -> dict[str, Any]:
            return engine.status()["routes"]["fleet-fix"]["source"]

        try:
            channel = await connection.channel()
            output = await Collector.bind(channel, outbox, "farm.#")
            assert source()["following"] == {}
            stranger = robots.node.create_publisher(String, topic.format("rover"), 10)
            shy = robots.node.create_publisher(NavSatFix, topic.format("shy"), BEST_EFFORT)  # the route's reader is reliable
            publishers = {f"robot{i}": robots.publisher(NavSatFix, topic.format(f"robot{i}")) for i in range(ROBOTS)}
            await wait_for(lambda: all(p.get_subscription_count() > 0 for p in publishers.values()), 15,
                             "the engine's subscription on every robot's topic")
            for seq in range(MESSAGES):
                for robot, publisher in enumerate(publishers.values()):
                    publisher.publish(_fix(robot, seq))
            received = await output.wait_for(ROBOTS * MESSAGES, timeout=15)
            await wait_for(lambda: topic.format("rover") in source()["mismatched_topics"], 5, "the other type reported")
            results: dict[str, Any] = {
                "messages": [(m.routing_key, json.loads(m.body)) for m in received],
                "following": {t: v for t, v in source()["following"].items() if t != topic.format("shy")},
                "mismatched": source()["mismatched_topics"],
                "rover_subscribers": robots.node.count_subscribers(topic.format("rover")),
            }
            # robot0 leaves: its topic is let go after forget_after, not before
            left = time.monotonic()
            robots.node.destroy_publisher(publishers.pop("robot0"))
            gone = topic.format("robot0")
            await wait_for(lambda: gone not in source()["following"], 10, "robot0's topic let go")
            results["let_go_after"] = time.monotonic() - left
            await wait_for(lambda: robots.node.count_subscribers(gone) == 0, 5, "the engine's subscription on robot0 gone")
            results["after_leaving"] = dict(source())
            await wait_for(lambda: topic.format("shy") in source()["unmatched_topics"], 5, "the unmatched QoS reported")
            results["shy_subscribers"] = robots.node.count_subscribers(topic.format("shy"))
            # and comes back: followed again
            back = robots.publisher(NavSatFix, gone)
            await wait_for(lambda: back.get_subscription_count() > 0, 10, "robot0's topic followed again")
            back.publish(_fix(0, MESSAGES))
            await output.wait_for(ROBOTS * MESSAGES + 1, timeout=10)
            results["returned"] = [(m.routing_key, json.loads(m.body)) for m in output.messages[ROBOTS * MESSAGES:]]
            results["final"] = source()
            robots.node.destroy_publisher(stranger)
            robots.node.destroy_publisher(shy)
            return results
        finally:
            await connection.close()
            robots.close()
            await engine.stop()

    results = asyncio.run(asyncio.wait_for(scenario(), 60))
    by_agent: dict[str, list[dict[str, Any]]] = {}
    for routing_key, body in results["messages"]:
        assert routing_key == f"farm.{body['agent_id']}.fix"
        by_agent.setdefault(body["agent_id"], []).append(body)
    assert sorted(by_agent) == sorted(f"robot{i}" for i in range(ROBOTS))
    for agent, bodies in by_agent.items():  # every message, in its topic's order, none of another robot's
        robot = int(agent.removeprefix("robot"))
        assert [(b["lat"], b["alt_msl"]) for b in bodies] == [(robot, seq) for seq in range(MESSAGES)], agent
    assert results["following"] == {topic.format(f"robot{i}"): {"agent": f"robot{i}", "received": MESSAGES, "qos": "reliable volatile"}
                                    for i in range(ROBOTS)}
    assert results["mismatched"] == {topic.format("rover"): ["std_msgs/msg/String"]}
    assert results["rover_subscribers"] == 0  # reported, never subscribed
    assert FORGET_AFTER <= results["let_go_after"] < FORGET_AFTER + 8
    leaving = results["after_leaving"]
    assert (leaving["forgotten"], leaving["discovered"], len(leaving["following"])) == (1, ROBOTS + 1, ROBOTS)
    assert results["shy_subscribers"] == 1  # published yet never matched (QoS): reported, kept, not let go
    assert [entry for entry in leaving["mismatched_publishers"] if "shy" in entry] == [
        f"/peer on {topic.format('shy')} offers best_effort volatile, the route requests reliable volatile "
        "(Best effort publisher and reliable subscription)"]
    assert results["returned"] == [("farm.robot0.fix", {"agent_id": "robot0", "lat": 0.0, "lon": MESSAGES / 100,
                                                          "alt_msl": float(MESSAGES)})]
    assert results["final"]["discovered"] == ROBOTS + 2
    assert results["final"]["received"] == ROBOTS * MESSAGES + 1


def test_a_reloaded_discovering_route_follows_the_same_topics_and_leaves_no_subscription_behind(
        tmp_path: Path, amqp_url: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """A route whose source changed gets a new source: it follows every robot's topic at once,
    and the old source's subscriptions are all destroyed (one subscriber per topic)."""
    monkeypatch.setenv("RABBITROS_AMQP_URL", amqp_url)
    tag = "r" + uuid.uuid4().hex[:8]
    outbox, topic = f"out-{tag}", "/{}/fix_" + tag
    routes = tmp_path / "fleet.yaml"
    routes.write_text(FLEET.format(domain=DOMAIN, tag=tag, outbox=outbox, forget_after=30))

    async def scenario() -> tuple[list[Any], dict[str, Any], list[int]]:
        engine = Engine(tmp_path, REPO / "schemas")
        await engine.start()
        robots = Peer()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            output = await Collector.bind(channel, outbox, "farm.#")
            publishers = [robots.publisher(NavSatFix, topic.format(f"robot{i}")) for i in range(3)]
            await wait_for(lambda: all(p.get_subscription_count() > 0 for p in publishers), 15, "every robot followed")
            routes.write_text(routes.read_text().replace("alt_msl: altitude", "alt_msl: altitude, alt_rel: altitude")
                              .replace("forget_after: 30", "forget_after: 20"))  # a new source, not only a new mapping
            assert await engine.reload(), engine.reloads.last_error
            await wait_for(lambda: all(robots.node.count_subscribers(topic.format(f"robot{i}")) == 1 for i in range(3)),
                             10, "one subscription per topic after the reload")
            await wait_for(lambda: all(p.get_subscription_count() == 1 for p in publishers), 10, "the new subscriptions matched")
            for robot, publisher in enumerate(publishers):
                publisher.publish(_fix(robot, 0))
            received = await output.wait_for(3, timeout=10)
            return ([(m.routing_key, json.loads(m.body)) for m in received], engine.status()["routes"]["fleet-fix"]["source"],
                    [robots.node.count_subscribers(topic.format(f"robot{i}")) for i in range(3)])
        finally:
            await connection.close()
            robots.close()
            await engine.stop()

    received, source, subscribers = asyncio.run(asyncio.wait_for(scenario(), 60))
    assert sorted(received, key=lambda r: r[0]) == [
        (f"farm.robot{i}.fix", {"agent_id": f"robot{i}", "lat": float(i), "lon": 0.0, "alt_msl": 0.0, "alt_rel": 0.0})
        for i in range(3)]
    assert sorted(source["following"]) == [topic.format(f"robot{i}") for i in range(3)]
    assert subscribers == [1, 1, 1]


def test_a_pattern_captures_exactly_one_segment_expanded_as_rcl_expands_the_topic() -> None:
    fix = compile_pattern("/{agent}/fix", "engine", "/")
    assert fix.match("/robot3/fix") == {"agent": "robot3"}
    assert fix.match("/farm/robot3/fix") is None and fix.match("/robot3/fix/raw") is None and fix.match("/fix") is None
    relative = compile_pattern("{farm}/{agent}/fix", "engine", "/fleet")
    assert relative.match("/fleet/north/uav2/fix") == {"farm": "north", "agent": "uav2"}
    assert relative.match("/north/uav2/fix") is None
    twice = compile_pattern("/{a}/x/{a}", "engine", "/")
    assert twice.match("/r1/x/r1") == {"a": "r1"} and twice.match("/r1/x/r2") is None
    assert compile_pattern("~/{a}", "engine", "/ns").match("/ns/engine/r1") == {"a": "r1"}


ROUTES = """
connections:
  ros: {ros2: {node: discovery_check}}
routes:
  - name: fleet-fix
    source:
      ros2: {topic: "/{agent}/fix", type: sensor_msgs/msg/NavSatFix}
    mapping: "{agent_id: meta('agent'), lat: latitude, lon: longitude, alt_msl: altitude}"
    schema: position
    sink:
      amqp: {exchange: farm, routing_key: "farm.{agent}.fix"}
"""

TESTS = """
tests:
  - route: fleet-fix
    input: {latitude: 1.5, longitude: 2.5, altitude: 3.0}
    meta: {topic: /robot7/fix, agent: robot7}
    expect: {agent_id: robot7, lat: 1.5, lon: 2.5, alt_msl: 3.0}
    expect_routing_key: farm.robot7.fix
"""


def _write(directory: Path, routes: str, tests: str | None = None) -> Path:
    directory.mkdir()
    (directory / "routes.yaml").write_text(routes)
    if tests is not None:
        (directory / "routes.test.yaml").write_text(tests)
    return directory


def test_check_and_route_tests_know_a_discovery_variable(tmp_path: Path, schemas_dir: Path) -> None:
    """``meta('agent')`` and the sink's ``{agent}`` pass check (no undeclared-field warning); a
    route test gives the agent as meta and sees it in the routing key; a variable of the source
    named like a declared canonical field is said to win; meta names the source lacks fail."""
    schemas = SchemaRegistry(schemas_dir)
    config, cases, problems, warnings = load_checked(_write(tmp_path / "ok", ROUTES, TESTS), schemas)
    assert config is not None and not problems and not warnings, (problems, warnings)
    results = list(run_tests(cases, config, schemas))
    assert [(r.passed, r.reason) for r in results] == [(True, "")]

    missing = TESTS.replace("agent: robot7}", "}")
    _, cases, _, _ = load_checked(_write(tmp_path / "missing", ROUTES, missing), schemas)
    assert [r.passed for r in run_tests(cases, config, schemas)] == [False]  # no agent: the routing key cannot be rendered

    shadow = ROUTES.replace("{agent}", "{agent_id}").replace("meta('agent')", "meta('agent_id')")
    _, _, problems, warnings = load_checked(_write(tmp_path / "shadow", shadow), schemas)
    assert not problems, problems
    assert [w.message for w in warnings] == [
        "route 'fleet-fix': {agent_id} in sink routing_key is the value the source captures from each topic, not the "
        "canonical field 'agent_id' of position: the captured value wins (rename the topic's variable to read the field "
        "at send time)"]

    with pytest.raises(RoutesInvalid) as caught:
        load_routes(_write(tmp_path / "bad", ROUTES.replace("meta('agent')", "meta('agnet')")), schemas)
    assert ["meta('agnet'): the ros2 source gives no 'agnet'; did you mean 'agent'?" in p.message
            for p in caught.value.problems] == [True]


TEMPLATED = """
connections:
  ros: {ros2: {node: discovery_check}}
routes:
  - name: "{farm}-fix"
    for_each: [{farm: north}, {farm: south}]
    source:
      ros2: {topic: "/{farm}/{agnt}/fix", type: sensor_msgs/msg/NavSatFix}
    mapping: "{agent_id: meta('agnt'), lat: latitude, lon: longitude, alt_msl: altitude}"
    schema: position
    sink:
      amqp: {exchange: farm, routing_key: "{farm}.{agnt}.fix"}
"""


def test_check_says_which_source_variables_are_discovered_in_a_for_each_route(tmp_path: Path, schemas_dir: Path) -> None:
    """for_each variables are filled in at load; what is left in the topic is discovered, and
    check says so (a misspelt item variable would silently become one)."""
    config, _, problems, warnings = load_checked(_write(tmp_path / "r", TEMPLATED), SchemaRegistry(schemas_dir))
    assert config is not None and not problems, problems
    assert config.routes["north-fix"].source.options.topic == "/north/{agnt}/fix"
    assert sorted(w.message for w in warnings) == [
        f"route '{farm}-fix': {{agnt}} in the source is no for_each variable (variables: farm): it is captured from each "
        "message (every matching topic, meta('agnt'))" for farm in ("north", "south")]


def test_a_sink_template_reads_the_captured_value_before_a_canonical_field() -> None:
    canonical = {"agent": "from-body", "lat": 1}
    plain = Outbound(b"{}", canonical, canonical, "id", {})
    assert plain.template_data is canonical
    captured = Outbound(b"{}", canonical, canonical, "id", {}, captured={"agent": "robot3"})
    assert captured.template_data == {"agent": "robot3", "lat": 1}
    assert canonical == {"agent": "from-body", "lat": 1}  # the message itself is untouched


def test_a_held_message_keeps_its_captured_values_on_disk() -> None:
    """A route's buffer spills held messages to disk: the captured values go with them, so the
    routing key rendered when the sink is back is the robot's."""
    from engine.running.buffer_stores import decode, encode

    canonical = {"agent_id": "robot3", "lat": 1}
    held = decode(encode(Outbound(b'{"lat":1}', canonical, canonical, "id", {"topic": "/robot3/fix"}, captured={"agent": "robot3"})))
    assert held.captured == {"agent": "robot3"} and held.template_data["agent"] == "robot3"
    assert decode(encode(Outbound(b"{}", {}, {}, "id", {}))).captured is None
