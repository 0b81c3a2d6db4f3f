"""The Zenoh endpoint against real eclipse-zenoh peers opened by the test in its own process,
with RabbitMQ (tests/conftest.py ``amqp_url``) and rclpy, the engine run in-process
(engine.running.runtime.Engine) as tests/endpoints/mqtt/test_mqtt.py runs it.

Every peer has multicast scouting off and is connected explicitly on tcp/127.0.0.1:PORT, its
port drawn by engine.common.processes.listening_port, so parallel workers never meet. No fixed
sleeps: a put waits until the engine's subscriber matches the test's publisher
(``Publisher.matching_status``), a query until its queryable matches the querier, every
other wait has a deadline.
"""

from __future__ import annotations

import asyncio
import json
import uuid
from pathlib import Path
from typing import Any

import aio_pika
import pytest
import zenoh

from engine.common.processes import listening_port
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector
from tests.support.repo import REPO
from tests.support.waiting import wait_for
from tests.operator.test_cli import cli
from tests.support.workers import ros_domain


def peer_config(listen: list[str] | None = None, connect: list[str] | None = None) -> zenoh.Config:
    config = zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("listen/endpoints", json.dumps(listen or []))
    config.insert_json5("connect/endpoints", json.dumps(connect or []))
    return config


class Peer:
    """A Zenoh peer listening on its own port (the engine's connection connects to it)."""

    def __init__(self) -> None:
        self.port = listening_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.session = zenoh.open(peer_config(listen=[self.endpoint]))
        self.samples: list[tuple[str, bytes]] = []

    def collect(self, key: str) -> Any:
        """Record every sample put on ``key`` (the callback runs on a Zenoh thread)."""
        return self.session.declare_subscriber(key, lambda s: self.samples.append((str(s.key_expr), s.payload.to_bytes())))

    def close(self) -> None:
        self.session.close()


@pytest.fixture
def peer() -> Any:
    opened = Peer()
    try:
        yield opened
    finally:
        opened.close()


def connection_yaml(peer: Peer) -> str:
    return f'{{zenoh: {{connect: ["{peer.endpoint}"], multicast_scouting: false}}}}'


async def until_matched(entity: Any, what: str, timeout: float = 20.0) -> None:
    """Until a publisher has a matching subscriber (a querier a matching queryable)."""
    await wait_for(lambda: entity.matching_status.matching, timeout, what)


async def connection_state(engine: Engine, name: str, state: str, timeout: float = 20.0) -> None:
    await wait_for(lambda: engine.status()["connections"].get(name, {}).get("state") == state, timeout,
                   f"connection {name} {state}: {engine.status()['connections'].get(name)}")


# ------------------------------------------------------------------------------ Zenoh -> AMQP

ZENOH_TO_AMQP = """
connections:
  field: {field}
  bus: {{amqp: "{amqp}"}}
routes:
  - name: weather-{tag}
    source:
      zenoh: {{key: "{tag}/{{robot}}/weather"}}
    mapping: "merge(@, {{robot: meta('robot'), key: meta('key')}})"
    schema: raw_json
    sink:
      amqp: {{exchange: {outbox}, routing_key: "weather.{{robot}}"}}
"""


def test_zenoh_to_amqp_captures_the_robot_and_dead_letters_a_bad_payload_once(tmp_path: Path, amqp_url: str, peer: Peer) -> None:
    """Samples put on {tag}/r*/weather reach AMQP once each, in order per robot, with the
    ``{robot}`` chunk of their key in ``meta('robot')`` (read by the mapping) and in the sink's
    routing key; a key the pattern does not match does not arrive; a payload that is no JSON is
    dead-lettered once (stage decode) and the messages after it flow."""
    tag = "z" + uuid.uuid4().hex[:8]
    outbox = f"zw-{tag}"
    (tmp_path / "r.yaml").write_text(ZENOH_TO_AMQP.format(field=connection_yaml(peer), amqp=amqp_url, tag=tag, outbox=outbox))
    sent = [(f"{tag}/r{seq % 3}/weather", {"seq": seq, "temp_c": 20 + seq % 7}) for seq in range(60)]

    async def scenario() -> tuple[list[Any], list[Any], dict[str, Any]]:
        engine = Engine(tmp_path, REPO / "schemas")
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        publisher = peer.session.declare_publisher(f"{tag}/r0/weather")
        try:
            channel = await connection.channel()
            out = await Collector.bind(channel, outbox, "#")
            dead = await Collector.bind(channel, "rabbitros.dead-letter", f"weather-{tag}")
            await until_matched(publisher, "the engine's subscriber")
            peer.session.put(f"{tag}/r0/soil", b'{"seq": -1}')
            peer.session.put(f"{tag}/r0/weather", b"not json {")
            for key, body in sent:
                peer.session.put(key, json.dumps(body).encode())
            received = await out.wait_for(len(sent), 30)
            dead_letters = await dead.wait_for(1, 10)
            # the route counts a message once the broker's confirmation is back, which may come
            # after our queue already has it
            route = f"weather-{tag}"
            await wait_for(lambda: engine.status()["routes"][route]["delivered"] == len(sent)
                           and engine.status()["routes"][route]["dead_lettered"], 10,
                           "the route counting what the broker confirmed", lambda: engine.status()["routes"][route])
            return list(received), list(dead_letters), engine.status()
        finally:
            publisher.undeclare()
            await connection.close()
            await engine.stop()

    received, dead_letters, status = asyncio.run(asyncio.wait_for(scenario(), 90))
    bodies = [json.loads(message.body) for message in received]
    assert [body["seq"] for body in bodies if body["robot"] == "r1"] == [seq for seq in range(60) if seq % 3 == 1]
    assert sorted(body["seq"] for body in bodies) == list(range(60))
    assert all(message.routing_key == f"weather.{body['robot']}" for message, body in zip(received, bodies))
    assert all(body["key"] == f"{tag}/{body['robot']}/weather" for body in bodies)
    assert len(dead_letters) == 1 and dead_letters[0].headers["x-rabbitros-stage"] == "decode"
    assert dead_letters[0].body == b"not json {"
    route = status["routes"][f"weather-{tag}"]
    assert route["dead_lettered"] == {"decode": 1} and route["delivered"] == 60, route
    assert status["connections"]["field"]["state"] == "up" and status["connections"]["field"]["transports"] == 1


# ------------------------------------------------------------------------------ ROS 2 -> Zenoh

ROS2_TO_ZENOH = """
connections:
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
  field: {field}
routes:
  - name: status-{tag}
    source:
      ros2: {{topic: "/{tag}/{{agent}}/status"}}
    schema: raw_json
    sink:
      zenoh: {{key: "{tag}/{{agent}}/status/n{{seq:03d}}"}}
"""


def test_ros2_to_zenoh_puts_on_a_key_from_the_topics_capture_and_a_formatted_field(tmp_path: Path, peer: Peer) -> None:
    """A ROS 2 topic pattern /{tag}/{agent}/status (std_msgs/String, JSON) is carried to Zenoh
    keys {tag}/{agent}/status/nNNN: the agent from the topic the engine discovered, the number
    from the message's ``seq`` with a format spec; the payload is the message's bytes."""
    from std_msgs.msg import String

    from tests.support.ros_nodes import SpunNode

    tag = "z" + uuid.uuid4().hex[:8]
    domain = ros_domain(13)
    (tmp_path / "r.yaml").write_text(ROS2_TO_ZENOH.format(domain=domain, tag=tag, field=connection_yaml(peer)))
    subscriber = peer.collect(f"{tag}/**")
    node = SpunNode(domain, f"robot_{tag}")
    publisher = node.node.create_publisher(String, f"/{tag}/a7/status", 100)
    bodies = [json.dumps({"seq": seq, "battery": 90 - seq}) for seq in range(30)]

    async def scenario() -> dict[str, Any]:
        engine = Engine(tmp_path, REPO / "schemas")
        await engine.start()
        try:
            await connection_state(engine, "field", "up")
            await wait_for(lambda: publisher.get_subscription_count() > 0, 30, "the engine's subscription to the topic")
            for body in bodies:
                publisher.publish(String(data=body))
            await wait_for(lambda: len(peer.samples) >= len(bodies), 30, f"{len(bodies)} Zenoh samples")
            return engine.status()
        finally:
            await engine.stop()

    try:
        status = asyncio.run(asyncio.wait_for(scenario(), 90))
    finally:
        subscriber.undeclare()
        node.close()
    assert peer.samples == [(f"{tag}/a7/status/n{seq:03d}", body.encode()) for seq, body in enumerate(bodies)]
    assert status["routes"][f"status-{tag}"]["delivered"] == len(bodies)


# ------------------------------------------------------------------------------ a query answered

QUERY = """
connections:
  field: {field}
  bus: {{amqp: "{amqp}"}}
routes:
  - name: plan-{tag}
    source:
      zenoh: {{key: "{tag}/{{robot}}/plan", queryable: true}}
    mapping: "merge(@, {{robot: meta('robot')}})"
    schema: raw_json
    sink:
      amqp: {{connection: bus, routing_key: work-{tag}, timeout: 5}}
    reply: {{mapping: "{{plan: steps, robot: robot}}"}}
"""


def test_a_zenoh_query_is_answered_by_an_amqp_worker(tmp_path: Path, amqp_url: str, peer: Peer) -> None:
    """A ``get`` on {tag}/r1/plan is a call: the engine's queryable hands the query (its payload,
    or its parameters when it has none) to an AMQP worker, whose answer, through the route's
    reply mapping, is the query's one reply (attachment ``result``); a query whose payload is no
    JSON gets an error reply at once naming the stage, not a querier's timeout."""
    tag = "z" + uuid.uuid4().hex[:8]
    (tmp_path / "r.yaml").write_text(QUERY.format(field=connection_yaml(peer), amqp=amqp_url, tag=tag))
    querier = peer.session.declare_querier(f"{tag}/*/plan", timeout=20)

    def ask(selector: str, payload: bytes | None) -> list[tuple[str, Any, bytes | None]]:
        out = []
        for reply in peer.session.get(selector, payload=payload, timeout=20):
            if reply.ok is not None:
                attachment = reply.ok.attachment
                out.append(("ok", json.loads(reply.ok.payload.to_bytes()), attachment.to_bytes() if attachment else None))
            else:
                assert reply.err is not None, "a reply is either ok or an error"
                out.append(("error", json.loads(reply.err.payload.to_bytes()), None))
        return out

    async def scenario() -> tuple[list[Any], list[Any], list[Any], dict[str, Any]]:
        engine = Engine(tmp_path, REPO / "schemas")
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            work = await channel.declare_queue(f"work-{tag}", exclusive=True)

            async def worker(message: aio_pika.abc.AbstractIncomingMessage) -> None:
                request = json.loads(message.body)
                steps = [f"{request['robot']}:{request.get('goal', 'depth ' + str(request.get('depth')))}"]
                assert message.reply_to is not None, "the engine's call names its reply queue"
                await channel.default_exchange.publish(aio_pika.Message(
                    json.dumps({"steps": steps, "robot": request["robot"]}).encode(),
                    correlation_id=message.correlation_id), message.reply_to)

            await work.consume(worker, no_ack=True)
            await until_matched(querier, "the engine's queryable")
            answered = await asyncio.to_thread(ask, f"{tag}/r1/plan", b'{"goal": "spray"}')
            by_parameters = await asyncio.to_thread(ask, f"{tag}/r2/plan?depth=3", None)
            refused = await asyncio.to_thread(ask, f"{tag}/r1/plan", b"{oops")
            return answered, by_parameters, refused, engine.status()["routes"][f"plan-{tag}"]
        finally:
            querier.undeclare()
            await connection.close()
            await engine.stop()

    answered, by_parameters, refused, route = asyncio.run(asyncio.wait_for(scenario(), 90))
    assert answered == [("ok", {"plan": ["r1:spray"], "robot": "r1"}, b"result")]
    assert by_parameters == [("ok", {"plan": ["r2:depth 3"], "robot": "r2"}, b"result")]
    assert len(refused) == 1 and refused[0][0] == "error" and refused[0][1]["stage"] == "decode", refused
    assert route["source"] == {"queryable": f"{tag}/*/plan", "pending": 0, "queries": 3, "answered": 2, "failed": 1}, route
    assert route["replies"]["sent"] == 3 and route["replies"]["errors"] == 1, route


# ------------------------------------------------------------------------------ health

HEALTH = """
connections:
  field: {{zenoh: {{connect: ["tcp/127.0.0.1:{port}"], multicast_scouting: false}}}}
routes:
  - name: echo-{tag}
    source: {{zenoh: {{key: "{tag}/in"}}}}
    schema: raw_json
    sink: {{zenoh: {{key: "{tag}/out"}}}}
"""


def test_health_follows_the_session(tmp_path: Path) -> None:
    """A peer whose only connect endpoint is down is ``reconnecting`` (unhealthy: its sinks
    hold their messages), ``up`` once a peer listens there (Zenoh retries by itself), and
    ``reconnecting`` again when that peer goes; messages carried meanwhile go through."""
    tag = "z" + uuid.uuid4().hex[:8]
    port = listening_port()
    (tmp_path / "r.yaml").write_text(HEALTH.format(port=port, tag=tag))

    async def scenario() -> list[str]:
        engine = Engine(tmp_path, REPO / "schemas")
        await engine.start()
        seen = []
        try:
            await connection_state(engine, "field", "reconnecting")
            seen.append(engine.status()["connections"]["field"]["last_error"])
            other = Peer.__new__(Peer)
            other.port, other.endpoint, other.samples = port, f"tcp/127.0.0.1:{port}", []
            other.session = await asyncio.to_thread(zenoh.open, peer_config(listen=[other.endpoint]))
            try:
                await connection_state(engine, "field", "up", timeout=30)
                assert engine.status()["connections"]["field"]["healthy"] is True
                subscriber = other.collect(f"{tag}/out")
                publisher = other.session.declare_publisher(f"{tag}/in")
                await until_matched(publisher, "the engine's subscriber")
                publisher.put(b'{"n": 1}')
                await wait_for(lambda: other.samples == [(f"{tag}/out", b'{"n": 1}')], 20, "the echo")
                subscriber.undeclare()
                publisher.undeclare()
            finally:
                await asyncio.to_thread(other.close)
            await connection_state(engine, "field", "reconnecting")
            seen.append(engine.status()["connections"]["field"]["state"])
        finally:
            await engine.stop()
        return seen

    seen = asyncio.run(asyncio.wait_for(scenario(), 90))
    assert seen == [f"no open transport to any of tcp/127.0.0.1:{port}", "reconnecting"]


# ------------------------------------------------------------------------------ check and test

@pytest.mark.fast
def test_check_refuses_what_the_run_could_not_do_and_test_renders_the_key(tmp_path: Path) -> None:
    """``{id:03d}`` in a source key is refused by ``check`` (a received key is read, not
    formatted), as a capture inside a chunk, between two ``**``, or over a meta name; in a sink
    key a format spec is honoured, and ``rabbitros-engine test`` shows the key the run puts on."""
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "r.yaml").write_text("""
connections:
  field: {zenoh: {connect: ["tcp/127.0.0.1:7447", "bogus:1"], multicast_scouting: false}}
routes:
  - {name: a, source: {zenoh: {key: "farm/{id:03d}/x"}}, schema: raw_json, sink: {zenoh: {key: "out/a"}}}
  - {name: b, source: {zenoh: {key: "farm/r{id}/x"}}, schema: raw_json, sink: {zenoh: {key: "out/b"}}}
  - {name: c, source: {zenoh: {key: "{a}/**/{b}/**"}}, schema: raw_json, sink: {zenoh: {key: "out/c"}}}
  - {name: d, source: {zenoh: {key: "farm/{key}/x"}}, schema: raw_json, sink: {zenoh: {key: "out//d"}}}
""")
    result = cli("check", "--routes", str(bad), "--schemas", str(REPO / "schemas"))
    assert result.returncode != 0
    out = result.stdout + result.stderr
    for expected in ("{id:03d} has a format spec, which a source cannot match", "{id} must be a whole chunk",
                     "{b} sits between two **", "{key} would overwrite the message's meta('key')",
                     "'out//d' is no Zenoh key expression", "'bogus:1' is not a Zenoh endpoint"):
        assert expected in out, (expected, out)

    good = tmp_path / "good"
    good.mkdir()
    (good / "r.yaml").write_text("""
connections:
  field: {zenoh: {mode: client, connect: ["tcp/127.0.0.1:7447"]}}
routes:
  - name: cmd
    source: {zenoh: {key: "farm/{robot}/**/goal"}}
    mapping: "merge(@, {robot: meta('robot'), key: meta('key')})"
    schema: raw_json
    sink: {zenoh: {key: "robot_{n:03d}/{robot}/cmd"}}
""")
    (good / "r.test.yaml").write_text("""
tests:
  - name: the key is rendered from the capture and a formatted field
    route: cmd
    input: {n: 7}
    meta: {robot: r1, key: farm/r1/x/goal}
    expect: {n: 7, robot: r1, key: farm/r1/x/goal}
    expect_routing_key: robot_007/r1/cmd
""")
    checked = cli("check", "--routes", str(good), "--schemas", str(REPO / "schemas"))
    assert checked.returncode == 0, checked.stdout + checked.stderr
    tested = cli("test", "--routes", str(good), "--schemas", str(REPO / "schemas"))
    assert tested.returncode == 0, tested.stdout + tested.stderr
    assert tested.stdout.splitlines()[-1] == "1 passed, 0 failed"


@pytest.mark.fast
def test_captures_are_read_from_their_place_in_the_key() -> None:
    """Before a ``**`` a capture counts from the start, after it from the end."""
    from engine.endpoints.zenoh.keys import parse_pattern

    pattern = parse_pattern("farm/{robot}/**/{sensor}")
    assert pattern.subscription == "farm/*/*/**"  # Zenoh's canon form of farm/*/**/*
    assert pattern.captured("farm/r1/a/b/lidar") == {"robot": "r1", "sensor": "lidar"}
    assert parse_pattern("**/{robot}/weather").captured("x/y/r2/weather") == {"robot": "r2"}


# ------------------------------------------------------------------------------ as an operator runs it

def test_an_engine_process_carries_zenoh_and_stops_cleanly(tmp_path: Path, peer: Peer) -> None:
    """``rabbitros-engine`` as a child process (tests/support/engine_process.py): samples put on
    {tag}/in come back on {tag}/out through the engine's own session, its status file shows
    the connection up, and SIGTERM ends it with status 0 (Zenoh's runtime threads do not hold
    the exit)."""
    from tests.support.engine_process import EngineProcess

    tag = "z" + uuid.uuid4().hex[:8]
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "r.yaml").write_text(f"""
connections:
  field: {connection_yaml(peer)}
routes:
  - name: echo-{tag}
    source: {{zenoh: {{key: "{tag}/in"}}}}
    schema: raw_json
    sink: {{zenoh: {{key: "{tag}/out"}}}}
""")
    subscriber = peer.collect(f"{tag}/out")
    publisher = peer.session.declare_publisher(f"{tag}/in")
    engine = EngineProcess(routes, tmp_path / "status.json", {})

    async def scenario() -> None:
        await until_matched(publisher, "the engine's subscriber", timeout=60)
        for n in range(20):
            publisher.put(json.dumps({"n": n}).encode())
        await wait_for(lambda: len(peer.samples) >= 20, 30, "20 echoed samples")
        await wait_for(lambda: ((engine.status() or {}).get("routes", {}).get(f"echo-{tag}", {}).get("delivered") == 20), 10,
                       "the status file's count")

    try:
        _, status = engine.run(scenario)
    finally:
        subscriber.undeclare()
        publisher.undeclare()
    assert [json.loads(body)["n"] for _, body in peer.samples] == list(range(20))
    assert status["connections"]["field"]["state"] == "up", status["connections"]


def test_a_client_goes_through_a_router_and_follows_it(tmp_path: Path) -> None:
    """``mode: client`` reaches the other peers through a router: samples from a peer of the
    router come back through the engine; the router gone, the connection is ``reconnecting``;
    a router back on the same port, Zenoh reconnects the client, the engine's subscriber is
    declared again, and samples flow again without the route restarting."""
    tag = "z" + uuid.uuid4().hex[:8]
    port = listening_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    (tmp_path / "r.yaml").write_text(f"""
connections:
  field: {{zenoh: {{mode: client, connect: ["{endpoint}"], multicast_scouting: false}}}}
routes:
  - name: echo-{tag}
    source: {{zenoh: {{key: "{tag}/in"}}}}
    schema: raw_json
    sink: {{zenoh: {{key: "{tag}/out"}}}}
""")

    def router() -> zenoh.Session:
        config = peer_config(listen=[endpoint])
        config.insert_json5("mode", '"router"')
        return zenoh.open(config)

    async def echo_once(n: int) -> None:
        client = await asyncio.to_thread(zenoh.open, peer_config(connect=[endpoint]))
        got: list[bytes] = []
        subscriber = client.declare_subscriber(f"{tag}/out", lambda s: got.append(s.payload.to_bytes()))
        publisher = client.declare_publisher(f"{tag}/in")
        try:
            await until_matched(publisher, "the engine's subscriber through the router", timeout=30)
            publisher.put(json.dumps({"n": n}).encode())
            await wait_for(lambda: got == [json.dumps({"n": n}).encode()], 20, f"echo {n}")
        finally:
            subscriber.undeclare()
            publisher.undeclare()
            await asyncio.to_thread(client.close)

    async def scenario() -> dict[str, Any]:
        first = await asyncio.to_thread(router)
        engine = Engine(tmp_path, REPO / "schemas")
        await engine.start()
        try:
            await connection_state(engine, "field", "up")
            await echo_once(1)
            await asyncio.to_thread(first.close)
            await connection_state(engine, "field", "reconnecting")
            second = await asyncio.to_thread(router)
            try:
                await connection_state(engine, "field", "up", timeout=30)
                await echo_once(2)
            finally:
                await asyncio.to_thread(second.close)
            return engine.status()["routes"][f"echo-{tag}"]
        finally:
            await engine.stop()

    route = asyncio.run(asyncio.wait_for(scenario(), 120))
    assert route["delivered"] == 2 and route["generation"] == 1, route
