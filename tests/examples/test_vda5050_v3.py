"""VDA 5050 3.0.0: examples/vda5050/v3 run against a private mosquitto, the simulated UAV and the
robot driver of tests/test_vda5050_master.py, every message on both sides checked against the
VDA's 3.0 schemas (schemas/vda5050/*.v3.json).

vda5050-sdk 0.2.0 speaks 2.x only (its models and bundled schemas are 2.1's), so the master
control here is a plain MQTT client whose orders and instant actions are validated against the
3.0 schemas before they are sent; what the engine publishes (state, visualization, connection,
factsheet) is validated as it arrives. An order to each vehicle runs to its end (no node state
left, every action FINISHED), a pause shows as ``paused`` with its instant action FINISHED in
``instantActionStates``, a cancel clears the node states, and every topic's headerId counts.
"""

from __future__ import annotations

import asyncio
import json
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from engine.common.schemas import SchemaRegistry
from engine.endpoints.mqtt.broker import LocalMosquitto
from engine.running.runtime import Engine
from tests.endpoints.mqtt.test_mqtt import Subscriber, publish
from tests.endpoints.ros2.test_ros2_endpoint import DOMAIN, Peer
from tests.support.schemas import known_schema
from tests.examples.test_vda5050_master import WAIT, RobotDriver, start_uav, stop_uav
from tests.support.repo import REPO
from tests.support.udp_vehicle import free_udp_port
from tests.support.waiting import wait_for

EXAMPLE = REPO / "examples" / "vda5050" / "v3"
SCHEMAS = SchemaRegistry(REPO / "schemas")
TOPIC = "uagv/v3/rabbitros/{serial}/{topic}"


def header(serial: str, header_id: int) -> dict[str, Any]:
    return {"headerId": header_id, "timestamp": "2026-11-27T12:00:00.000Z", "version": "3.0.0", "manufacturer": "rabbitros",
            "serialNumber": serial}


def order(serial: str, order_id: str, points: list[tuple[float, float, float]], map_id: str, header_id: int,
          fly_at: float | None = None) -> dict[str, Any]:
    """A 3.0 order through ``points`` (x, y, theta), every node released; the UAV's nodes say
    their altitude with its flyAt action."""
    nodes = [{"nodeId": f"{order_id}-n{i}", "sequenceId": 2 * i, "released": True,
              "nodePosition": {"x": x, "y": y, "theta": theta, "mapId": map_id,
                               "allowedDeviationXY": {"a": 150.0 if i == 0 else 2.0, "b": 150.0 if i == 0 else 2.0, "theta": 0.0}},
              "actions": [] if fly_at is None else [{"actionType": "flyAt", "actionId": f"{order_id}-fly{i}", "blockingType": "NONE",
                                                    "actionParameters": [{"key": "altRel", "value": fly_at}]}]}
             for i, (x, y, theta) in enumerate(points)]
    edges = [{"edgeId": f"{order_id}-e{i}", "sequenceId": 2 * i - 1, "released": True, "startNodeId": f"{order_id}-n{i - 1}",
              "endNodeId": f"{order_id}-n{i}", "actions": []} for i in range(1, len(points))]
    body = {**header(serial, header_id), "orderId": order_id, "orderUpdateId": 0, "nodes": nodes, "edges": edges}
    known_schema(SCHEMAS, "vda5050/order.v3").validate(body)
    return body


def instant(serial: str, action_type: str, action_id: str, header_id: int) -> dict[str, Any]:
    body = {**header(serial, header_id), "actions": [{"actionType": action_type, "actionId": action_id, "blockingType": "NONE"}]}
    known_schema(SCHEMAS, "vda5050/instant_actions.v3").validate(body)
    return body


@pytest.fixture
def example_env(tmp_path: Path, mosquitto: LocalMosquitto, monkeypatch: pytest.MonkeyPatch) -> Iterator[int]:
    port = free_udp_port()
    monkeypatch.setenv("VDA5050_MQTT_URL", mosquitto.url)
    monkeypatch.setenv("VDA5050_CLIENT_ID", "vda3-" + uuid.uuid4().hex[:8])
    monkeypatch.setenv("VDA5050_UAV_LINK", f"udpout:127.0.0.1:{port}")
    monkeypatch.setenv("ROS_DOMAIN_ID", str(DOMAIN))
    monkeypatch.setenv("HOME", str(tmp_path))
    yield port


def test_vda5050_3_orders_pauses_and_cancels_both_vehicles_with_every_message_valid_3_0(
        example_env: int, mosquitto: LocalMosquitto) -> None:
    peer = Peer()
    driver = RobotDriver(peer)
    peer.start()
    uav = start_uav(example_env)
    figures: dict[str, float] = {}

    async def scenario() -> dict[str, list[dict[str, Any]]]:
        engine = Engine(EXAMPLE, REPO / "schemas")
        await engine.start()
        driving = asyncio.create_task(driver.run())
        try:
            async with Subscriber(mosquitto, "uagv/v3/rabbitros/#") as wire:
                def latest(serial: str) -> dict[str, Any] | None:
                    topic = TOPIC.format(serial=serial, topic="state")
                    states = [m for m in wire.messages if str(m.topic) == topic]
                    return json.loads(states[-1].payload) if states else None

                def state_is(serial: str, wanted: Callable[[dict[str, Any]], bool]) -> Callable[[], bool]:
                    return lambda: (s := latest(serial)) is not None and wanted(s)

                def ran_to_its_end(body: dict[str, Any]) -> Callable[[dict[str, Any]], bool]:
                    actions = {a["actionId"] for n in body["nodes"] for a in n["actions"]}
                    return lambda s: (s["orderId"] == body["orderId"] and not s["nodeStates"] and not s["edgeStates"]
                                      and actions <= {a["actionId"] for a in s["actionStates"] if a["actionStatus"] == "FINISHED"})

                async def timed(what: str, serial: str, wanted: Callable[[dict[str, Any]], bool], since: float | None = None) -> None:
                    started = time.monotonic() if since is None else since
                    await wait_for(state_is(serial, wanted), WAIT, what)
                    figures[what] = time.monotonic() - started

                await wait_for(lambda: all(latest(serial) for serial in ("uav1", "robot1")), WAIT, "both states")
                spray = order("uav1", "spray-1", [(0.0, 0.0, 0.0), (30.0, 20.0, 0.0), (60.0, 40.0, 0.0)], "farm", 1, fly_at=15)
                await publish(mosquitto, [(TOPIC.format(serial="uav1", topic="order"), spray)])
                dispatched = time.monotonic()
                x, y, yaw = driver.position
                row = order("robot1", "row-1", [(x, y, yaw), (x + 2, y, 0.0), (x + 4, y, 0.0)], "map", 1)
                await publish(mosquitto, [(TOPIC.format(serial="robot1", topic="order"), row)])
                await timed("robot_order_to_every_node_finished_s", "robot1", ran_to_its_end(row))
                await timed("uav_order_to_every_node_finished_s", "uav1", ran_to_its_end(spray), dispatched)

                spray = order("uav1", "spray-2", [(0.0, 0.0, 0.0), (30.0, 20.0, 0.0), (60.0, 40.0, 0.0), (90.0, 60.0, 0.0)], "farm", 2,
                              fly_at=15)
                await publish(mosquitto, [(TOPIC.format(serial="uav1", topic="order"), spray)])
                await wait_for(state_is("uav1", lambda s: s["orderId"] == "spray-2" and s["driving"]), WAIT, "the UAV flying spray-2")
                await publish(mosquitto, [(TOPIC.format(serial="uav1", topic="instantActions"), instant("uav1", "startPause", "p1", 1))])
                await timed("uav_pause_to_paused_state_s", "uav1", lambda s: s.get("paused") is True and not s["driving"] and
                            {"actionId": "p1", "actionType": "startPause", "actionStatus": "FINISHED"} in s["instantActionStates"])
                await publish(mosquitto, [(TOPIC.format(serial="uav1", topic="instantActions"), instant("uav1", "cancelOrder", "c1", 2))])
                await timed("uav_cancel_to_cancelled_state_s", "uav1", lambda s: not s["nodeStates"] and not s["driving"]
                            and s["orderId"] == "spray-2" and s.get("paused") is False
                            and {"actionId": "c1", "actionType": "cancelOrder", "actionStatus": "FINISHED"} in s["instantActionStates"])
                await wait_for(lambda: {m.topic.value.rsplit("/", 1)[1] for m in wire.messages}
                               >= {"state", "visualization", "connection", "factsheet", "order", "instantActions"}, WAIT, "every topic")
                status = engine.status()
                assert all(route["failed"] == 0 for route in status["routes"].values()), status["routes"]
                await engine.stop()
                await wait_for(lambda: sum(m.topic.value.endswith("/connection") and b"OFFLINE" in m.payload
                                           for m in wire.messages) == 2, WAIT, "both OFFLINE")
        finally:
            driving.cancel()
            await engine.stop()
        by_topic: dict[str, list[dict[str, Any]]] = {}
        for message in wire.messages:
            by_topic.setdefault(str(message.topic), []).append(json.loads(message.payload))
        return by_topic

    try:
        by_topic = asyncio.run(asyncio.wait_for(scenario(), 150))
    finally:
        peer.close()
        stop_uav(uav)
    print(" ".join(f"{key}={value:.2f}" for key, value in figures.items()))

    validated: dict[str, int] = {}
    for topic, bodies in by_topic.items():
        kind = topic.rsplit("/", 1)[1]
        if kind in ("state", "visualization", "connection", "factsheet"):
            schema = SCHEMAS.get(f"vda5050/{kind}.v3")
            assert schema is not None
            for body in bodies:
                schema.validate(body)
                validated[kind] = validated.get(kind, 0) + 1
            ids = [body["headerId"] for body in bodies]
            assert ids == list(range(ids[0], ids[0] + len(ids))), (topic, ids)
    assert set(validated) == {"state", "visualization", "connection", "factsheet"} and validated["state"] >= 10, validated
    uav_factsheet = by_topic["uagv/v3/rabbitros/uav1/factsheet"][-1]
    assert uav_factsheet["typeSpecification"]["localizationTypes"] == ["GNSS"]
    states = by_topic["uagv/v3/rabbitros/uav1/state"]
    assert all(s["version"] == "3.0.0" and "powerSupply" in s for s in states)
    visualization = by_topic["uagv/v3/rabbitros/uav1/visualization"][-1]
    assert visualization["referenceStateHeaderId"] in [s["headerId"] for s in states], visualization
