"""Several sinks for one route and a sink's fallback (issue 32), against the real parts: one MQTT
source (a private mosquitto) to RabbitMQ, ROS 2 (rclpy) and a second private mosquitto (the
relay) through ``sinks:``, the engine in process.

* a message the schema refuses is one dead letter, whatever the number of sinks; one that only
  the robot's sink mapping refuses (no altitude for its NavSatFix) goes to the other sinks and
  is one dead letter naming the robot, which ``dead-letters replay`` would send to it alone;
* the relay's ``fallback:`` (an AMQP exchange) takes over while the relay's mosquitto is
  stopped (after its ``after`` second) and gives back once it is started again: every message
  arrives exactly once at the relay or at its fallback, none lost, none at both;
* an AMQP sink on an exchange no queue is bound to, with a fallback: the broker returns every
  message (counted ``unroutable``) and the fallback gets each one, once;
* the other sinks get every message exactly once throughout (an accepted copy is never sent
  again when another sink is retried).

Prints the figures (per phase: arrived where); run with ``-s`` to see them."""

from __future__ import annotations

import asyncio
import json
import uuid
from collections import Counter
from pathlib import Path
from typing import Any

import aiomqtt
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy

from engine.endpoints.mqtt.broker import LocalMosquitto
from engine.endpoints.ros2.rosmsg import resolve_type
from engine.running.runtime import Engine
from tests.endpoints.mqtt.test_mqtt import Subscriber
from tests.support.amqp_helpers import Collector, started_with_client
from tests.support.ros_nodes import SpunNode
from tests.support.waiting import wait_for
from tests.support.workers import ros_domain

pytestmark = pytest.mark.soak

NavSatFix = resolve_type("sensor_msgs/msg/NavSatFix")
PHASE = 20
DEADLINE_S = 45.0

ROUTES = """
connections:
  field: {{mqtt: "{field}"}}
  relay: {{mqtt: "{relay}"}}
  gcs: {{amqp: "{amqp}"}}
  ros: {{ros2: {{domain_id: {domain}, node: engine_{tag}}}}}
dead_letters: {{connection: gcs}}
routes:
  - name: fan
    source:
      mqtt: {{connection: field, topic: "farm/+/fix"}}
    schema: position
    sinks:
      - name: cloud
        amqp: {{connection: gcs, exchange: cloud-{tag}, routing_key: "pos.{{agent_id}}"}}
      - name: robot
        ros2: {{connection: ros, topic: /{tag}/fix, type: sensor_msgs/msg/NavSatFix}}
        mapping: "{{header: {{frame_id: agent_id}}, latitude: lat, longitude: lon, altitude: alt_msl}}"
      - name: relay
        mqtt: {{connection: relay, topic: "relay/{{agent_id}}"}}
        fallback:
          after: 1
          amqp: {{connection: gcs, exchange: spool-{tag}, routing_key: spool}}
      - name: nobody
        amqp: {{connection: gcs, exchange: nobody-{tag}, routing_key: unbound}}
        fallback:
          after: 1
          amqp: {{connection: gcs, exchange: nobody-spool-{tag}, routing_key: spool}}
"""


def position(seq: int) -> dict[str, Any]:
    return {"agent_id": "uav1", "lat": -22.0, "lon": -47.9, "alt_msl": float(seq)}


async def publish(broker: LocalMosquitto, bodies: list[dict[str, Any]]) -> None:
    async with aiomqtt.Client("127.0.0.1", broker.port, timeout=30) as client:
        for body in bodies:
            await client.publish("farm/uav1/fix", json.dumps(body).encode(), qos=1)


def relayed_seqs(subscriber: Subscriber) -> list[int]:
    """The ``alt_msl`` (the seq) of each message on the relay's mosquitto."""
    return [int(json.loads(bytes(m.payload)).get("alt_msl", -1)) for m in subscriber.messages]


def seqs(collector: Collector) -> list[int]:
    """Each message's seq (its altitude; -1: the one without, which only the robot refuses)."""
    return [int(json.loads(m.body).get("alt_msl", -1)) for m in collector.messages]


def test_one_source_to_several_sinks_one_dead_letter_and_a_fallback_that_takes_over_and_gives_back(
        tmp_path: Path, mosquitto: LocalMosquitto, amqp_url: str, schemas_dir: Path) -> None:
    tag = "f" + uuid.uuid4().hex[:8]
    relay = LocalMosquitto(directory=tmp_path / "relay", keep_dir=True, lifetime=900)
    relay.start()
    domain = ros_domain(16)
    (tmp_path / "routes").mkdir()
    (tmp_path / "routes" / "fan.yaml").write_text(ROUTES.format(field=mosquitto.url, relay=relay.url, amqp=amqp_url,
                                                                domain=domain, tag=tag))
    peer = SpunNode(domain, f"robot_{tag}")
    robot: list[Any] = []
    peer.node.create_subscription(NavSatFix, f"/{tag}/fix", robot.append, QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))

    async def scenario() -> dict[str, Any]:
        engine = Engine(tmp_path / "routes", schemas_dir)
        async with started_with_client(engine, amqp_url) as client:
            channel = await client.channel()
            cloud = await Collector.bind(channel, f"cloud-{tag}")
            spool = await Collector.bind(channel, f"spool-{tag}")
            nobody_spool = await Collector.bind(channel, f"nobody-spool-{tag}")
            dead = await Collector.bind(channel, "rabbitros.dead-letter", "fan")

            def route() -> dict[str, Any]:
                return engine.status()["routes"]["fan"]

            def sinks() -> dict[str, Any]:
                return route().get("sinks") or {}

            await wait_for(lambda: sinks().get("robot", {}).get("can_take"), DEADLINE_S, "the robot's subscriber to match",
                           detail=sinks)
            figures: dict[str, Any] = {}

            # phase 1: every sink takes; one bad message (a latitude that is no number) among them, and
            # one without an altitude, which the robot's NavSatFix needs (its sink mapping refuses it)
            no_altitude = {key: value for key, value in position(0).items() if key != "alt_msl"}
            async with Subscriber(relay, "relay/#") as relayed:
                await publish(mosquitto, [position(seq) for seq in range(PHASE)] + [{**position(999), "lat": "north"}, no_altitude])
                await wait_for(lambda: len(cloud.messages) > PHASE and len(relayed.messages) > PHASE and len(robot) >= PHASE
                               and len(nobody_spool.messages) > PHASE and len(dead.messages) >= 2, DEADLINE_S, "phase 1",
                               detail=lambda: (len(cloud.messages), len(relayed.messages), len(robot), len(nobody_spool.messages), route()))
                figures["relay 1"] = relayed_seqs(relayed)

            # phase 2: the relay's mosquitto stopped: after 1 s its fallback takes what the relay cannot
            await asyncio.to_thread(relay.halt)
            await wait_for(lambda: not sinks()["relay"]["can_take"], DEADLINE_S, "the relay to be seen down", detail=sinks)
            await publish(mosquitto, [position(seq) for seq in range(PHASE, 2 * PHASE)])
            await wait_for(lambda: len(spool.messages) >= PHASE and len(cloud.messages) > 2 * PHASE, DEADLINE_S, "phase 2",
                           detail=lambda: (len(spool.messages), len(cloud.messages), route()))
            figures["during the outage"] = {"status": sinks()}

            # phase 3: the relay is back: new messages go to it again (the fallback gives back)
            await asyncio.to_thread(relay.start)
            await wait_for(lambda: sinks()["relay"]["can_take"], DEADLINE_S, "the relay to be seen back", detail=sinks)
            async with Subscriber(relay, "relay/#") as relayed:
                await publish(mosquitto, [position(seq) for seq in range(2 * PHASE, 3 * PHASE)])
                await wait_for(lambda: len(relayed.messages) >= PHASE and len(cloud.messages) > 3 * PHASE and len(robot) >= 3 * PHASE
                               and len(nobody_spool.messages) > 3 * PHASE, DEADLINE_S, "phase 3",
                               detail=lambda: (len(relayed.messages), len(cloud.messages), len(robot), len(nobody_spool.messages), route()))
                await wait_for(lambda: route()["delivered"] >= 3 * PHASE, DEADLINE_S, "the route's counters")
                figures["relay 3"] = relayed_seqs(relayed)
            figures.update(cloud=seqs(cloud), spool=seqs(spool), nobody_spool=seqs(nobody_spool), route=route(),
                           robot=[int(m.altitude) for m in robot], dead=[dict(m.headers) for m in dead.messages])
            return figures

    try:
        result = asyncio.run(asyncio.wait_for(scenario(), 240))
    finally:
        peer.close()
        relay.kill()
    every = list(range(3 * PHASE))
    relayed = result["relay 1"] + result["relay 3"]
    print({key: result[key] for key in ("relay 1", "relay 3", "spool", "during the outage")})
    print({key: value for key, value in result["route"].items() if key in ("delivered", "dead_lettered", "unroutable", "sinks", "retries")})
    # one bad message, four sinks: one dead letter, at the schema stage; the message only the robot
    # refuses: one dead letter naming the robot (and only the robot: the others have it)
    stages = {letter["x-rabbitros-stage"]: letter for letter in result["dead"]}
    assert len(result["dead"]) == 2 and set(stages) == {"schema", "sink mapping"}, result["dead"]
    refused = stages["sink mapping"]
    assert "sink 'robot'" in refused["x-rabbitros-error"] and refused["x-source-sinks_unsent"] == "robot", refused
    assert result["route"]["dead_lettered"] == {"schema": 1, "sink mapping": 1}, result["route"]
    # the relay or its fallback, each message exactly once: the fallback took the outage, the relay the rest
    assert sorted(result["relay 1"]) == [-1, *range(PHASE)] and sorted(result["relay 3"]) == list(range(2 * PHASE, 3 * PHASE)), result
    assert sorted(result["spool"]) == list(range(PHASE, 2 * PHASE)), result["spool"]
    assert sorted(relayed + result["spool"]) == [-1, *every]
    # the sinks that could always take: every message once (never sent again for another sink's retry)
    assert sorted(result["cloud"]) == [-1, *every] and sorted(result["robot"]) == every, (Counter(result["cloud"]), Counter(result["robot"]))
    # no queue bound: every message returned, counted unroutable, and taken by the fallback once
    assert sorted(result["nobody_spool"]) == [-1, *every], result["nobody_spool"]
    assert result["route"]["unroutable"] >= 1 and result["route"]["delivered"] == 3 * PHASE, result["route"]
    sinks = result["route"]["sinks"]
    assert sinks["relay"]["delivered"] == 2 * PHASE + 1 and sinks["relay.fallback"]["delivered"] == PHASE, sinks
    assert sinks["nobody"]["delivered"] == 0 and sinks["nobody.fallback"]["delivered"] == 3 * PHASE + 1, sinks
