"""The MQTT endpoint against a private mosquitto 2.0 (tests/conftest.py ``mosquitto``), with
RabbitMQ, rclpy and engines run as operators run them (tests/support/engine_process.py).

Peers are plain aiomqtt clients; every wait has a deadline. What each test shows is in its
docstring; the at-least-once tests print their figures (sent, delivered, duplicates, lost).
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import time
import uuid
from collections import Counter
from pathlib import Path
from typing import Any, Callable, Iterable

import aio_pika
import aiomqtt
import pytest

from engine.common.processes import listening_port
from engine.endpoints.mqtt.broker import LocalMosquitto
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector
from tests.support.repo import REPO
from tests.support.engine_process import EngineProcess

from tests.operator.test_admin import get
from tests.operator.test_cli import cli


def routes_dir(tmp_path: Path, text: str) -> Path:
    routes = tmp_path / "routes"
    routes.mkdir(exist_ok=True)
    (routes / "r.yaml").write_text(text)
    return routes


def mqtt_client(broker: LocalMosquitto, **kwargs: Any) -> aiomqtt.Client:
    client = aiomqtt.Client("127.0.0.1", broker.port, protocol=aiomqtt.ProtocolVersion.V5, timeout=30, **kwargs)
    client.pending_calls_threshold = 1 << 16  # publish() pipelines a window on purpose
    return client


async def publish(broker: LocalMosquitto, messages: Iterable[tuple[str, Any]], qos: int = 1, window: int = 16,
                  pause: float = 0.0) -> int:
    """Publish ``(topic, body)`` (a dict is sent as JSON), ``window`` at a time awaiting their
    PUBACKs; returns how many."""
    sent = 0
    async with mqtt_client(broker) as client:
        batch: list[Any] = []
        for topic, body in messages:
            payload = json.dumps(body).encode() if isinstance(body, dict) else body
            batch.append(client.publish(topic, payload, qos=qos))
            if len(batch) == window:
                await asyncio.gather(*batch)
                sent += len(batch)
                batch = []
                if pause:
                    await asyncio.sleep(pause)  # pacing: the caller's pause between windows
        await asyncio.gather(*batch)
        sent += len(batch)
    return sent


class Subscriber:
    """An aiomqtt client subscribed to one filter, recording every message it gets: the MQTT side
    of tests/support/amqp_helpers.py ``Collector`` (the one the other tests import)."""

    def __init__(self, broker: LocalMosquitto, topic: str) -> None:
        self.client = mqtt_client(broker)
        self.topic = topic
        self.messages: list[aiomqtt.Message] = []
        self._task: asyncio.Task[None] | None = None

    async def __aenter__(self) -> Subscriber:
        await self.client.__aenter__()
        await self.client.subscribe(self.topic, qos=1)
        self._task = asyncio.create_task(self._collect())
        return self

    async def _collect(self) -> None:
        async for message in self.client.messages:
            self.messages.append(message)

    async def wait_for(self, count: int, timeout: float = 30.0) -> list[aiomqtt.Message]:
        await wait_for(lambda: len(self.messages) >= count, timeout, f"{count} MQTT messages on {self.topic}")
        return self.messages

    async def __aexit__(self, *exc: object) -> None:
        assert self._task is not None
        self._task.cancel()
        await asyncio.gather(self._task, return_exceptions=True)
        await self.client.__aexit__(None, None, None)


def weather(agent: str, seq: int) -> tuple[str, dict[str, Any]]:
    return f"farm/{agent}/weather", {"agent_id": agent, "seq": seq, "temp_c": 20 + seq % 7}


# ------------------------------------------------------------------------------ MQTT -> AMQP

TO_AMQP = """
connections:
  field: {{mqtt: {{url: "{mqtt}", client_id: {client_id}}}}}
  gcs: {{amqp: "{amqp}"}}
routes:
  - name: weather-in
    source:
      mqtt: {{topic: "farm/+/weather", qos: 1}}
    schema: raw_json
    sink:
      amqp: {{exchange: {outbox}, routing_key: "weather.{{agent_id}}"}}
"""


@pytest.mark.parametrize("qos, protocol", [(1, "5"), (0, "5"), (1, "'3.1.1'")])
def test_mqtt_to_amqp_with_a_wildcard(tmp_path: Path, mosquitto: LocalMosquitto, amqp_url: str,
                                      qos: int, protocol: str) -> None:
    """Every message on farm/+/weather reaches AMQP once, in order per agent; a topic the
    filter does not match (farm/a/soil, farm/a/b/weather) does not. MQTT 5 routes by
    subscription identifier, 3.1.1 by matching the topic."""
    outbox = f"w-{uuid.uuid4().hex[:8]}"
    text = TO_AMQP.format(mqtt=mosquitto.url, amqp=amqp_url, outbox=outbox, client_id=f"wx-1, protocol: {protocol}")
    routes = routes_dir(tmp_path, text.replace("qos: 1", f"qos: {qos}"))

    async def scenario() -> tuple[list[Any], dict[str, Any]]:
        engine = Engine(routes, REPO / "schemas")
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            out = await Collector.bind(await connection.channel(), outbox, "#")
            sent = [weather(f"a{seq % 3}", seq) for seq in range(300)]
            await publish(mosquitto, [("farm/a0/soil", {"seq": -1}), ("farm/a0/b/weather", {"seq": -2}), *sent])
            received = await out.wait_for(300, 30)
            await asyncio.sleep(0.5)  # quiet window: anything unexpected arrives meanwhile
            return list(received), engine.status()
        finally:
            await connection.close()
            await engine.stop()

    received, status = asyncio.run(asyncio.wait_for(scenario(), 120))
    bodies = [json.loads(m.body) for m in received]
    assert sorted(b["seq"] for b in bodies) == list(range(300))
    for agent in ("a0", "a1", "a2"):
        seqs = [b["seq"] for b in bodies if b["agent_id"] == agent]
        assert seqs == sorted(seqs)
    assert {m.routing_key for m in received} == {"weather.a0", "weather.a1", "weather.a2"}
    health = status["connections"]["field"]
    assert health["state"] == "up" and health["session"] == "persistent" and "held" not in health


def test_reload_to_another_topic_unsubscribes_the_old_one_from_the_session(
        tmp_path: Path, mosquitto: LocalMosquitto, amqp_url: str) -> None:
    """A reload that changes the route's filter subscribes the new one before the old source
    stops, and once the old source is retired removes its filter from the persistent
    session: a message on the old topic is then not sent to the engine at all (none held)."""
    outbox = f"r-{uuid.uuid4().hex[:8]}"
    text = TO_AMQP.format(mqtt=mosquitto.url, amqp=amqp_url, outbox=outbox, client_id="reload-1")
    routes = routes_dir(tmp_path, text)

    async def scenario() -> tuple[list[int], dict[str, Any]]:
        engine = Engine(routes, REPO / "schemas")
        engine.retire_after_s = 0.1
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            out = await Collector.bind(await connection.channel(), outbox, "#")
            await publish(mosquitto, [weather("a1", 1)])
            await out.wait_for(1, 20)
            (routes / "r.yaml").write_text(text.replace("farm/+/weather", "farm/+/wind"))
            assert await engine.reload()
            await engine.topology_settled()
            await publish(mosquitto, [weather("a1", 2), ("farm/a1/wind", {"agent_id": "a1", "seq": 3})])
            await out.wait_for(2, 20)
            await asyncio.sleep(0.5)  # quiet window: the old topic's message would be here by now
            return [json.loads(m.body)["seq"] for m in out.messages], engine.status()["connections"]["field"]
        finally:
            await connection.close()
            await engine.stop()

    seqs, health = asyncio.run(asyncio.wait_for(scenario(), 90))
    assert seqs == [1, 3]
    assert "held" not in health and "unrouted" not in health, health


# ------------------------------------------------------------ a schema failure, dead-lettered

DEAD_LETTERS = """
connections:
  field: {{mqtt: {{url: "{mqtt}", client_id: dl-1}}}}
  gcs: {{amqp: "{amqp}"}}
routes:
  - name: position-in
    source:
      mqtt: {{topic: "farm/+/position"}}
    schema: position
    sink:
      amqp: {{exchange: {outbox}, routing_key: "position.{{agent_id}}"}}
"""


def test_a_payload_that_fails_its_schema_is_dead_lettered_and_acknowledged(
        tmp_path: Path, mosquitto: LocalMosquitto, amqp_url: str) -> None:
    """Bytes that are not JSON and a position without lat/lon are dead-lettered (stage and
    source topic in the headers) while the good message flows; after a restart of the engine
    on its persistent session nothing comes again: both were acknowledged once dead-lettered."""
    outbox = f"p-{uuid.uuid4().hex[:8]}"
    routes = routes_dir(tmp_path, DEAD_LETTERS.format(mqtt=mosquitto.url, amqp=amqp_url, outbox=outbox))
    good = {"agent_id": "uav1", "lat": -22.1, "lon": -47.9, "alt_msl": 600.0}

    async def scenario() -> tuple[list[Any], list[Any], dict[str, Any]]:
        connection = await aio_pika.connect(amqp_url)
        channel = await connection.channel()
        out = await Collector.bind(channel, outbox, "#")
        dead = await Collector.bind(channel, "rabbitros.dead-letter", "position-in")
        try:
            for run in range(2):
                engine = Engine(routes, REPO / "schemas")
                await engine.start()
                try:
                    if run == 0:
                        await publish(mosquitto, [("farm/uav1/position", b"{not json"),
                                                  ("farm/uav2/position", {"agent_id": "uav2"}),
                                                  ("farm/uav1/position", good)])
                        await out.wait_for(1, 20)
                        await dead.wait_for(2, 20)
                    else:  # a marker behind anything the broker might still redeliver
                        await publish(mosquitto, [("farm/uav3/position", {**good, "agent_id": "uav3"})])
                        await out.wait_for(2, 20)
                    status = engine.status()
                finally:
                    await engine.stop()
            return list(out.messages), list(dead.messages), status
        finally:
            await connection.close()

    delivered, dead_letters, status = asyncio.run(asyncio.wait_for(scenario(), 120))
    assert [json.loads(m.body)["agent_id"] for m in delivered] == ["uav1", "uav3"]
    assert len(dead_letters) == 2, [m.headers for m in dead_letters]
    stages = {m.headers["x-source-topic"]: m.headers["x-rabbitros-stage"] for m in dead_letters}
    assert stages == {"farm/uav1/position": "decode", "farm/uav2/position": "schema"}
    assert dead_letters[0].body == b"{not json"
    assert status["routes"]["position-in"]["failed"] == 0  # the second run saw only the marker


# ------------------------------------------------------------------- ROS 2 <-> MQTT

import rclpy  # noqa: E402,F401  (a missing rclpy fails the run, never skips it)

from engine.endpoints.ros2.node import Ros2Node  # noqa: E402
from engine.endpoints.ros2.rosmsg import resolve_type  # noqa: E402
from tests.endpoints.ros2.test_ros2_endpoint import DOMAIN, Peer  # noqa: E402
from tests.support.waiting import wait_for

NavSatFix = resolve_type("sensor_msgs/msg/NavSatFix")

ROS_TO_MQTT = """
connections:
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
  field: {{mqtt: "{mqtt}"}}
routes:
  - name: fix-out
    source:
      ros2: {{topic: /{tag}/fix, type: sensor_msgs/msg/NavSatFix}}
    mapping: "{{agent_id: header.frame_id, lat: latitude, lon: longitude, alt_msl: altitude}}"
    schema: position
    sink:
      mqtt: {{topic: "farm/{{agent_id}}/position", qos: 1, retain: true}}
"""


def test_ros2_to_mqtt_topic_from_a_canonical_field(tmp_path: Path, mosquitto: LocalMosquitto) -> None:
    """NavSatFix on ROS 2 becomes a canonical position published on farm/<frame_id>/position,
    retained: a subscriber that comes later gets each agent's last position."""
    tag = "m" + uuid.uuid4().hex[:8]
    routes = routes_dir(tmp_path, ROS_TO_MQTT.format(domain=DOMAIN, tag=tag, mqtt=mosquitto.url))
    peer = Peer()
    publisher = peer.publisher(NavSatFix, f"/{tag}/fix")
    peer.start()

    async def scenario() -> tuple[list[aiomqtt.Message], list[aiomqtt.Message]]:
        engine = Engine(routes, REPO / "schemas")
        await engine.start()
        try:
            async with Subscriber(mosquitto, "farm/+/position") as subscriber:
                await wait_for(lambda: publisher.get_subscription_count() > 0, 20, "the engine's ROS 2 subscriber")
                for seq in range(20):
                    fix = NavSatFix()
                    fix.header.frame_id = f"uav{seq % 2}"
                    fix.latitude, fix.longitude, fix.altitude = -22.0 + seq * 1e-4, -47.9, 600.0 + seq
                    publisher.publish(fix)
                live = list(await subscriber.wait_for(20))
            async with Subscriber(mosquitto, "farm/+/position") as late:
                return live, list(await late.wait_for(2))
        finally:
            await engine.stop()

    try:
        messages, retained = asyncio.run(asyncio.wait_for(scenario(), 90))
    finally:
        peer.close()
    assert sorted((str(m.topic), json.loads(m.payload)["alt_msl"], m.retain) for m in retained) == [
        ("farm/uav0/position", 618.0, True), ("farm/uav1/position", 619.0, True)]
    assert len(messages) == 20
    by_topic = Counter(str(m.topic) for m in messages)
    assert by_topic == {"farm/uav0/position": 10, "farm/uav1/position": 10}
    first = json.loads(messages[0].payload)
    assert first["agent_id"] == "uav0" and first["alt_msl"] == 600.0 and first["lat"] == -22.0


MQTT_TO_ROS = """
connections:
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
  field: {{mqtt: "{mqtt}"}}
routes:
  - name: fix-in
    source:
      mqtt: {{topic: "farm/+/fix"}}
    mapping: "{{agent_id: meta('topic'), lat: lat, lon: lon, alt_msl: alt_msl}}"
    schema: position
    sink:
      ros2: {{topic: /{tag}/fix, type: sensor_msgs/msg/NavSatFix}}
      mapping: "{{header: {{frame_id: agent_id}}, latitude: lat, longitude: lon, altitude: alt_msl}}"
"""


def test_mqtt_to_ros2_with_wildcards(tmp_path: Path, mosquitto: LocalMosquitto) -> None:
    """farm/+/fix from two agents reaches the ROS 2 topic as NavSatFix, each with the topic it
    came from (meta('topic'), not the body's agent_id); farm/uav1/other and farm/uav1/fix/raw
    do not match the filter and never arrive."""
    tag = "m" + uuid.uuid4().hex[:8]
    routes = routes_dir(tmp_path, MQTT_TO_ROS.format(domain=DOMAIN, tag=tag, mqtt=mosquitto.url))
    peer = Peer()
    received = peer.subscribe(NavSatFix, f"/{tag}/fix")
    peer.start()

    async def scenario() -> None:
        engine = Engine(routes, REPO / "schemas")
        await engine.start()
        try:
            ros = engine.runners["fix-in"].connections[-1]
            assert isinstance(ros, Ros2Node), "the route's last connection is the ROS 2 one"
            await wait_for(lambda: ros.node.count_subscribers(f"/{tag}/fix") > 0, 20, "the engine to see the ROS 2 subscriber")
            position = {"lat": -22.0, "lon": -47.9, "alt_msl": 600.0}
            await publish(mosquitto, [
                ("farm/uav1/other", {**position, "agent_id": "uav1"}),
                ("farm/uav1/fix/raw", {**position, "agent_id": "uav1"}),
                *((f"farm/uav{seq % 2 + 1}/fix", {**position, "agent_id": "not-the-topic", "alt_msl": float(seq)})
                  for seq in range(10)),
            ])
            await wait_for(lambda: len(received) >= 10, 30, "10 NavSatFix")
            await asyncio.sleep(0.5)  # quiet window: nothing more may arrive (the behaviour under test; no event says 'nothing')
        finally:
            await engine.stop()

    try:
        asyncio.run(asyncio.wait_for(scenario(), 90))
    finally:
        peer.close()
    assert len(received) == 10
    assert Counter(m.header.frame_id for m in received) == {"farm/uav1/fix": 5, "farm/uav2/fix": 5}
    assert sorted(m.altitude for m in received) == [float(seq) for seq in range(10)]


# ------------------------------------------------- QoS 1 while the engine is killed with -9

KILL_TOTAL = 4000


async def settled(count: Callable[[], int], total: int, quiet: float = 20.0, timeout: float = 240.0) -> None:
    """Until ``count()`` reaches ``total`` (then one more second for a duplicate in flight),
    or has not moved for ``quiet`` seconds: the caller then reports what was lost."""
    deadline = asyncio.get_running_loop().time() + timeout
    last, moved = -1, asyncio.get_running_loop().time()
    while count() < total:
        now = asyncio.get_running_loop().time()
        if count() != last:
            last, moved = count(), now
        if now - moved > quiet or now > deadline:
            return
        await asyncio.sleep(0.05)  # poll: a wait that ends when the count stalls; the caller names what was lost
    await asyncio.sleep(1.0)  # quiet window: nothing more may arrive (the behaviour under test; no event says 'nothing')


def kill(engine: EngineProcess) -> None:
    os.killpg(engine.process.pid, signal.SIGKILL)
    engine.process.wait(30)


@pytest.mark.soak
@pytest.mark.timeout(700)  # its scenario's own bound is 600 s
@pytest.mark.parametrize("protocol", ["5", "'3.1.1'"])
def test_qos1_engine_killed_twice_mid_stream_loses_nothing(tmp_path: Path, mosquitto: LocalMosquitto, amqp_url: str,
                                                            protocol: str) -> None:
    """A publisher streams 4,000 QoS 1 messages while the engine (a persistent session) is
    killed with -9 twice and restarted: every message reaches AMQP. What the engine held
    unacknowledged comes again from the broker right after CONNACK (before the route
    subscribes), and what was published while it was down is delivered when it is back."""
    outbox = f"k-{uuid.uuid4().hex[:8]}"
    routes = routes_dir(tmp_path, TO_AMQP.format(mqtt=mosquitto.url, amqp=amqp_url, outbox=outbox,
                                                 client_id=f"kill-1, protocol: {protocol}"))

    async def scenario() -> dict[str, Any]:
        connection = await aio_pika.connect(amqp_url)
        out = await Collector.bind(await connection.channel(), outbox, "#")

        def seen() -> int:
            return len({json.loads(m.body)["seq"] for m in out.messages})

        publisher: asyncio.Task[int] | None = None
        kills: list[int] = []
        try:
            for kill_at in (KILL_TOTAL // 4, KILL_TOTAL * 3 // 5, None):
                engine = EngineProcess(routes, tmp_path / f"status-{len(kills)}.json", {})
                try:
                    await asyncio.to_thread(engine.wait_started)
                    if publisher is None:  # the session exists now: the stream starts
                        publisher = asyncio.create_task(publish(
                            mosquitto, (weather(f"a{seq % 4}", seq) for seq in range(KILL_TOTAL)), pause=0.005))
                    if kill_at is None:
                        await settled(seen, KILL_TOTAL)
                        break
                    await wait_for(lambda: seen() >= kill_at, 240, f"{kill_at} messages before the kill")
                    kill(engine)
                    kills.append(seen())
                    await asyncio.sleep(0.5)  # outage: the stream goes on while the engine is down
                finally:
                    if engine.process.poll() is None:
                        engine.stop()
            assert publisher is not None
            sent = await publisher
        finally:
            await connection.close()
        counts = Counter(json.loads(m.body)["seq"] for m in out.messages)
        return {"sent": sent, "delivered": len(counts), "duplicates": sum(counts.values()) - len(counts),
                "lost": KILL_TOTAL - len(set(counts) & set(range(KILL_TOTAL))), "killed_after": kills}

    figures = asyncio.run(asyncio.wait_for(scenario(), 600))
    print(f"\nmqtt {protocol} qos1, engine kill -9 x2: {figures}")
    assert figures["sent"] == KILL_TOTAL
    assert figures["lost"] == 0 and figures["delivered"] == KILL_TOTAL
    assert len(figures["killed_after"]) == 2 and all(n < KILL_TOTAL for n in figures["killed_after"])


# ------------------------------------------------------- mosquitto stopped and started

RESTART = """
connections:
  field: {{mqtt: {{url: "{mqtt}"{client_id}}}}}
  gcs: {{amqp: "{amqp}"}}
routes:
  - name: weather-in
    source:
      mqtt: {{topic: "farm/+/weather"}}
    schema: raw_json
    sink:
      amqp: {{exchange: {outbox}, routing_key: "weather.{{agent_id}}"}}
  - name: cmd-out
    source:
      amqp: {{exchange: {inbox}, binding_key: "#", queue: {inbox}-q}}
    schema: raw_json
    sink:
      mqtt: {{topic: "farm/{{agent_id}}/cmd", qos: 2}}
"""


@pytest.mark.parametrize("session", ["persistent", "clean"])
def test_mosquitto_stopped_and_started_routes_resume_and_healthz_follows(
        tmp_path: Path, mosquitto: LocalMosquitto, amqp_url: str, session: str) -> None:
    """While mosquitto is down /healthz is 503 naming the MQTT connection; once it is back it
    is 200 again and both directions flow (the sink at QoS 2): a persistent session keeps its subscription in
    the broker's persistence file, a clean one is subscribed again by the engine."""
    tag = uuid.uuid4().hex[:8]
    client_id = ", client_id: restart-1" if session == "persistent" else ""
    routes = routes_dir(tmp_path, RESTART.format(mqtt=mosquitto.url, amqp=amqp_url, outbox=f"o-{tag}",
                                                 inbox=f"i-{tag}", client_id=client_id))
    port = listening_port()
    engine = EngineProcess(routes, tmp_path / "status.json", {}, "--admin", str(port))

    async def round_trip(out: Collector, inbox: aio_pika.abc.AbstractExchange, seq: int) -> None:
        async with Subscriber(mosquitto, "farm/+/cmd") as commands:
            await publish(mosquitto, [weather("a1", seq)])
            await inbox.publish(aio_pika.Message(json.dumps({"agent_id": "a1", "seq": seq}).encode()), "cmd")
            await wait_for(lambda: any(json.loads(m.body)["seq"] == seq for m in out.messages), 30, f"weather {seq} in AMQP")
            messages = await commands.wait_for(1, 30)
            assert str(messages[0].topic) == "farm/a1/cmd" and json.loads(messages[0].payload)["seq"] == seq

    def healthz() -> tuple[int, dict[str, Any]]:
        code, body = get(port, "/healthz")
        return code, json.loads(body)

    async def scenario() -> None:
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            out = await Collector.bind(channel, f"o-{tag}", "#")
            inbox = await channel.declare_exchange(f"i-{tag}", aio_pika.ExchangeType.TOPIC, durable=True)
            await asyncio.to_thread(engine.wait_started)
            assert (await asyncio.to_thread(healthz))[0] == 200
            await round_trip(out, inbox, 1)
            await asyncio.to_thread(mosquitto.halt)
            await wait_for(lambda: healthz()[0] == 503, 30, "/healthz to turn 503")
            code, document = await asyncio.to_thread(healthz)
            assert document["down"] == ["field"], document
            assert document["connections"]["field"]["state"] == "reconnecting"
            await asyncio.to_thread(mosquitto.start)
            await wait_for(lambda: healthz()[0] == 200, 30, "/healthz to turn 200 again")
            await round_trip(out, inbox, 2)
        finally:
            await connection.close()

    try:
        asyncio.run(asyncio.wait_for(scenario(), 180))
    finally:
        assert engine.stop() == 0, engine.log()


# ------------------------------------------------ two engines, one shared subscription

SHARED = """
connections:
  field: {{mqtt: {{url: "{mqtt}", client_id: "shared-${{ENGINE_NAME}}"}}}}
  gcs: {{amqp: "{amqp}"}}
routes:
  - name: weather-in
    source:
      mqtt: {{topic: "farm/+/weather", shared: workers}}
    schema: raw_json
    sink:
      amqp: {{exchange: {outbox}, routing_key: "${{ENGINE_NAME}}.{{agent_id}}"}}
"""
SHARED_TOTAL = 1000


@pytest.mark.soak
def test_two_engines_with_one_shared_group_split_the_stream_every_message_once(
        tmp_path: Path, mosquitto: LocalMosquitto, amqp_url: str) -> None:
    """Two engines, one route file, ``shared: workers``: the broker gives each QoS 1 message to
    one member of the group, each engine acknowledges it once settled, so every message
    reaches AMQP exactly once and both engines carry part of the stream. (Once needs QoS 1
    and engines that stay up; an engine that dies with messages unacknowledged gets them
    again on its persistent session, hence its own client_id per engine.)"""
    outbox = f"s-{uuid.uuid4().hex[:8]}"
    routes = routes_dir(tmp_path, SHARED.format(mqtt=mosquitto.url, amqp=amqp_url, outbox=outbox))

    async def scenario() -> list[Any]:
        connection = await aio_pika.connect(amqp_url)
        out = await Collector.bind(await connection.channel(), outbox, "#")
        engines = [EngineProcess(routes, tmp_path / f"status-{name}.json", {"ENGINE_NAME": name}) for name in ("e1", "e2")]
        try:
            for engine in engines:
                await asyncio.to_thread(engine.wait_started)
            await publish(mosquitto, (weather(f"a{seq % 5}", seq) for seq in range(SHARED_TOTAL)))
            await wait_for(lambda: len(out.messages) >= SHARED_TOTAL, 60, f"{SHARED_TOTAL} messages")
            await asyncio.sleep(1.0)  # quiet window: a duplicate would arrive meanwhile
            messages = list(out.messages)
        finally:
            exits = [await asyncio.to_thread(engine.stop) for engine in engines]
            await connection.close()
        assert exits == [0, 0], "\n".join(f"engine exited {code}: {engine.log()}" for code, engine in zip(exits, engines))
        return messages

    messages = asyncio.run(asyncio.wait_for(scenario(), 180))
    seqs = Counter(json.loads(m.body)["seq"] for m in messages)
    per_engine = Counter((m.routing_key or "").split(".")[0] for m in messages)
    print(f"\nshared subscription: {dict(per_engine)}, duplicates {sum(seqs.values()) - len(seqs)}")
    assert sorted(seqs) == list(range(SHARED_TOTAL)) and set(seqs.values()) == {1}
    assert set(per_engine) == {"e1", "e2"} and min(per_engine.values()) > SHARED_TOTAL // 10


# ------------------------------------------------------------ check and route tests

def test_check_names_mqtt_option_problems(tmp_path: Path) -> None:
    """``check`` reports, with file:line, a filter that is not one, QoS 2 on a source, a
    wildcard in a sink topic, a session_expiry that keeps no session, and two connections
    that would take one session (client_id) from each other."""
    (tmp_path / "bad.yaml").write_text("""
connections:
  field: {mqtt: {url: "mqtt://localhost:1883", session_expiry: 60}}
  one: {mqtt: {url: "mqtt://127.0.0.1:1884", client_id: engine-1}}
  two: {mqtt: {url: "mqtt://127.0.0.1:1884", client_id: engine-1}}
routes:
  - name: bad-filter
    source: {mqtt: {connection: field, topic: "farm/#/weather", qos: 2}}
    schema: raw_json
    sink: {mqtt: {connection: field, topic: "farm/+/cmd"}}
""")
    result = cli("check", "--routes", str(tmp_path), "--schemas", str(REPO / "schemas"))
    assert result.returncode == 1
    out = result.stdout + result.stderr
    assert "bad.yaml:3:" in out and "session_expiry keeps the session of a client_id" in out
    assert "'farm/#/weather' is not an MQTT topic filter" in out
    assert "qos 2 is not offered on a source" in out
    assert "a message is published on one topic, never on a filter" in out
    assert "connection 'two': mqtt:127.0.0.1:1884/engine-1 is already used by connection 'one'" in out


def test_route_test_renders_the_mqtt_topic_and_refuses_a_missing_field(tmp_path: Path) -> None:
    """``rabbitros-engine test`` renders the sink's topic from the canonical message, and a
    message without the field the topic needs fails at the sink stage, as the run would."""
    (tmp_path / "r.yaml").write_text("""
routes:
  - name: cmd-out
    source: {amqp: {queue: cmd}}
    schema: raw_json
    sink: {mqtt: {topic: "farm/{agent_id}/cmd"}}
""")
    (tmp_path / "r.test.yaml").write_text("""
tests:
  - route: cmd-out
    input: {agent_id: uav1, go: true}
    expect_routing_key: farm/uav1/cmd
  - route: cmd-out
    input: {agent_id: "uav1/#", go: true}
    expect_error: sink
  - route: cmd-out
    input: {go: true}
    expect_error: sink
""")
    result = cli("test", "--routes", str(tmp_path), "--schemas", str(REPO / "schemas"))
    assert result.returncode == 0, result.stdout + result.stderr


# ------------------------------------------------------------ last will and on_stop (VDA 5050 connection)

PRESENCE = """
connections:
  link:
    mqtt:
      url: "{mqtt}"
      will:
        topic: {topic}
        payload: {{headerId: "{{now_ms}}", timestamp: "{{now}}", version: 2.0.0, manufacturer: rabbitros,
                   serialNumber: robot1, connectionState: CONNECTIONBROKEN}}
      on_stop:
        topic: {topic}
        payload: {{headerId: "{{now_ms}}", timestamp: "{{now}}", version: 2.0.0, manufacturer: rabbitros,
                   serialNumber: robot1, connectionState: OFFLINE}}
routes:
  - name: robot1-connection
    source:
      mqtt: {{topic: presence/robot1}}
    schema: raw_json
    mapping: >-
      {{headerId: to_int(mul(now(), `1000`)), timestamp: iso8601(stamp()), version: '2.0.0',
      manufacturer: 'rabbitros', serialNumber: 'robot1', connectionState: 'ONLINE'}}
    sink:
      mqtt: {{topic: {topic}, qos: 1, retain: true}}
"""


async def retained_state(broker: LocalMosquitto, topic: str, state: str, timeout: float = 15.0) -> dict[str, Any]:
    """The retained message on ``topic`` once its connectionState is ``state`` (a new
    subscription each look: only then does the broker send what it retained)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    last: dict[str, Any] | None = None
    while loop.time() < deadline:
        async with mqtt_client(broker) as client:
            await client.subscribe(topic, qos=1)
            try:
                async with asyncio.timeout(1.0):
                    async for message in client.messages:
                        if message.retain:
                            last = json.loads(bytes(message.payload))
                            break
            except TimeoutError:
                pass
        if last is not None and last.get("connectionState") == state:
            return last
        await asyncio.sleep(0.2)  # poll: a deadline loop (each poll reads a retained message)
    raise AssertionError(f"retained {topic} is not {state} within {timeout} s: {last}")


@pytest.mark.parametrize("stop", ["kill -9", "clean"])
def test_connection_topic_is_online_then_connectionbroken_or_offline(tmp_path: Path, mosquitto: LocalMosquitto,
                                                                     schemas_dir: Path, stop: str) -> None:
    """VDA 5050's connection topic from one MQTT connection: ONLINE (a route, retained) while
    the engine runs; CONNECTIONBROKEN (the will, published by the broker) once the engine is
    killed -9; OFFLINE (on_stop, before the clean disconnection that drops the will) once it
    is stopped. Each is a valid VDA 5050 2.0 connection message, timestamps included."""
    from engine.common.schemas import SchemaRegistry

    topic = f"uagv/v2/rabbitros/robot1-{uuid.uuid4().hex[:6]}/connection"
    routes = routes_dir(tmp_path, PRESENCE.format(mqtt=mosquitto.url, topic=topic))
    connection_schema = SchemaRegistry(schemas_dir).get("vda5050/connection.v2")
    assert connection_schema is not None
    engine = EngineProcess(routes, tmp_path / "status.json", {})

    async def scenario() -> list[dict[str, Any]]:
        seen = []
        await asyncio.to_thread(engine.wait_started)
        await publish(mosquitto, [("presence/robot1", {"battery": 0.9})])
        seen.append(await retained_state(mosquitto, topic, "ONLINE"))
        if stop == "kill -9":
            kill(engine)
            seen.append(await retained_state(mosquitto, topic, "CONNECTIONBROKEN"))
        else:
            assert await asyncio.to_thread(engine.stop) == 0, engine.log()
            seen.append(await retained_state(mosquitto, topic, "OFFLINE"))
        return seen

    try:
        seen = asyncio.run(asyncio.wait_for(scenario(), 40))
    finally:
        engine.stop()
    for body in seen:
        connection_schema.validate(body)
    last = seen[-1]
    assert isinstance(last["headerId"], int) and last["timestamp"].endswith("Z"), last
    assert abs(last["headerId"] / 1000 - time.time()) < 60, last
