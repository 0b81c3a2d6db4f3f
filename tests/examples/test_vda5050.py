"""VDA 5050: the VDA's schemas load as the family ``vda5050/``, and examples/vda5050 runs, as it
is, against a private mosquitto, a ROS 2 robot (rclpy) and the simulated UAV over UDP.

A master control (a plain aiomqtt client) sends an order to each vehicle: the robot's ROS 2
subscriber gets its nav_msgs/Path, the UAV holds the uploaded mission (the simulator reports
it when it stops); a startPause reaches the UAV as an acknowledged command and the robot's
driver as JSON; every `state`, `visualization` and `connection` message the engine publishes
validates against the VDA's own schema, and says what the vehicles reported.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Any

import pytest
import yaml

from engine.common.schemas import SchemaRegistry
from engine.endpoints.mavlink.dialect import mavlink2
from engine.endpoints.mqtt.broker import LocalMosquitto
from engine.endpoints.ros2.rosmsg import resolve_type
from engine.running.runtime import Engine
from engine.running.watch import watch_routes
from tests.support.repo import REPO
from tests.support.schemas import known_schema

from tests.operator.test_cli import cli
from tests.endpoints.mqtt.test_mqtt import Subscriber, mqtt_client, publish, retained_state
from tests.endpoints.ros2.test_ros2_endpoint import DOMAIN, Peer, String
from tests.support.udp_vehicle import free_udp_port
from tests.support.waiting import wait_for

EXAMPLE = REPO / "examples" / "vda5050"
Path_ = resolve_type("nav_msgs/msg/Path")
BatteryState = resolve_type("sensor_msgs/msg/BatteryState")
Int16 = resolve_type("std_msgs/msg/Int16")
PoseWithCovarianceStamped = resolve_type("geometry_msgs/msg/PoseWithCovarianceStamped")


# ------------------------------------------------------------------ the schemas as a family


def test_the_vda_schemas_load_as_a_family_and_only_one_level_deep(tmp_path: Path) -> None:
    registry = SchemaRegistry(REPO / "schemas")
    assert not registry.problems
    vda = [name for name in registry.names() if name.startswith("vda5050/")]
    assert vda == [f"vda5050/{name}{version}" for name in ("connection", "factsheet", "instant_actions", "order", "state", "visualization")
                   for version in ("", ".v2", ".v3")]
    newest = registry.get("vda5050/state")  # unpinned: the newest, 3.0; the 2.0 routes pin .v2
    assert newest is not None and newest.path == REPO / "schemas" / "vda5050" / "state.v3.json"
    state = registry.get("vda5050/state.v2")
    assert state is not None and state.path == REPO / "schemas" / "vda5050" / "state.v2.json"
    with pytest.raises(ValueError, match=r"schema vda5050/state.v2: \$: \"batteryState\" is a required property"):
        state.validate({"headerId": 1, "timestamp": "2026-11-23T17:00:00Z", "version": "2.0.0", "manufacturer": "m",
                        "serialNumber": "s", "orderId": "", "orderUpdateId": 0, "lastNodeId": "", "lastNodeSequenceId": 0,
                        "nodeStates": [], "edgeStates": [], "actionStates": [], "driving": False,
                        "operatingMode": "AUTOMATIC", "errors": [], "safetyState": {"eStop": "NONE", "fieldViolation": False}})

    # a family directory is named as schema files are; deeper directories are not read
    (tmp_path / "Bad-Family").mkdir()
    (tmp_path / "Bad-Family" / "x.v1.json").write_text('{"type": "object"}')
    (tmp_path / "fine" / "deeper").mkdir(parents=True)
    (tmp_path / "fine" / "deeper" / "y.v1.json").write_text('{"type": "object"}')
    (tmp_path / "fine" / "z.v3.json").write_text('{"type": "object"}')
    registry = SchemaRegistry(tmp_path)
    assert registry.names() == ["fine/z", "fine/z.v3"]
    assert [(path.relative_to(tmp_path).as_posix(), text) for path, text in registry.problems] == [
        ("Bad-Family/x.v1.json", "schema file names must look like name.v1.json")]


def test_an_edit_of_a_family_schema_is_seen_by_the_watcher(tmp_path: Path) -> None:
    """A running engine reloads when schemas/vda5050/state.v2.json changes, as for any schema."""
    routes, family = tmp_path / "routes", tmp_path / "schemas" / "vda5050"
    routes.mkdir()
    family.mkdir(parents=True)
    (family / "state.v2.json").write_text('{"type": "object"}')

    async def scenario() -> int:
        calls: list[float] = []
        stop = asyncio.Event()
        task = asyncio.create_task(watch_routes(routes, lambda: calls.append(time.monotonic()), stop, tmp_path / "schemas"))
        try:
            await asyncio.sleep(0)  # the watch task's first step sets the watch up (engine/running/watch.py), before our next
            (family / "state.v2.json").write_text('{"type": "object", "required": ["headerId"]}')
            await wait_for(lambda: len(calls) > 0, 10, "the watcher to see the family schema's edit")
            return len(calls)
        finally:
            stop.set()
            await asyncio.wait_for(task, 10)

    assert asyncio.run(scenario()) >= 1


# ------------------------------------------------------------------ the example, offline


@pytest.mark.parametrize("example", ["examples/vda5050", "examples/vda5050/v3"])
def test_the_example_checks_clean_and_every_route_has_passing_route_tests(example: str) -> None:
    """``check`` without a warning and ``test`` green, as the README says to run them (the schemas
    found as schemas/ of the working directory); every route has at least one case. VDA 5050 2.0
    and, in v3/, 3.0."""
    checked = cli("check", "--routes", example, timeout=120)
    assert checked.returncode == 0 and checked.stderr == "", checked.stderr
    assert checked.stdout.endswith(": ok\n") and "16 routes, 6 connections" in checked.stdout, checked.stdout
    tested = cli("test", "--routes", example, timeout=120)
    assert tested.returncode == 0, tested.stdout[-3000:] + tested.stderr
    cases = yaml.safe_load((REPO / example / "vda5050.test.yaml").read_text())["tests"]
    routes = [route["name"].format(**item) for route in yaml.safe_load((REPO / example / "vda5050.yaml").read_text())["routes"]
              for item in route.get("for_each", [{}])]
    assert f"{len(cases)} passed, 0 failed" in tested.stdout
    assert sorted({case["route"] for case in cases}) == sorted(routes)


# ------------------------------------------------------------------ the example, running

ORDER_HEADER = {"timestamp": "2026-11-23T17:00:00.000Z", "version": "2.0.0", "manufacturer": "rabbitros"}


def fly_at(alt_rel: float, action_id: str) -> list[dict[str, Any]]:
    return [{"actionType": "flyAt", "actionId": action_id, "blockingType": "NONE",
             "actionParameters": [{"key": "altRel", "value": alt_rel}]}]


UAV_ORDER: dict[str, Any] = {**ORDER_HEADER, "headerId": 1, "serialNumber": "uav1", "orderId": "spray-1", "orderUpdateId": 0,
             "nodes": [{"nodeId": "p1", "sequenceId": 0, "released": True, "actions": fly_at(15, "f1"),
                        "nodePosition": {"x": 0.0, "y": 0.0, "mapId": "farm"}},
                       {"nodeId": "p2", "sequenceId": 2, "released": True, "actions": fly_at(15, "f2"),
                        "nodePosition": {"x": 103.26215, "y": 110.73027, "mapId": "farm"}},
                       {"nodeId": "p3", "sequenceId": 4, "released": False, "actions": [],
                        "nodePosition": {"x": 500.0, "y": 500.0, "mapId": "farm"}}],
             "edges": [{"edgeId": "e1", "sequenceId": 1, "released": True, "startNodeId": "p1", "endNodeId": "p2",
                        "actions": []}]}
ROBOT_ORDER = {**ORDER_HEADER, "headerId": 1, "serialNumber": "robot1", "orderId": "row-7", "orderUpdateId": 0,
               "nodes": [{"nodeId": "a", "sequenceId": 0, "released": True, "actions": [],
                          "nodePosition": {"x": 1.0, "y": 2.0, "theta": 0.0, "mapId": "map"}},
                         {"nodeId": "b", "sequenceId": 2, "released": True, "actions": [],
                          "nodePosition": {"x": 11.0, "y": 2.0, "theta": math.pi / 2, "mapId": "map"}}],
               "edges": [{"edgeId": "ab", "sequenceId": 1, "released": True, "startNodeId": "a", "endNodeId": "b",
                          "actions": []}]}
PAUSE = {**ORDER_HEADER, "headerId": 2, "serialNumber": "uav1",
         "actions": [{"actionType": "startPause", "actionId": "pause-1", "blockingType": "HARD"}]}
RESUME = {**ORDER_HEADER, "headerId": 3, "serialNumber": "uav1",
          "actions": [{"actionType": "stopPause", "actionId": "resume-1", "blockingType": "HARD"}]}
ITEM_SECONDS = 3.0
"""The simulated UAV reaches a mission item this long after the previous one: long enough for
the pause to arrive while it flies to the first node, on a loaded machine too."""


def start_vehicle(port: int) -> subprocess.Popen[str]:
    proc = subprocess.Popen(
        ["timeout", "-s", "KILL", "100", sys.executable, "-m", "rabbitros_sim.vehicle",
         "--device", f"udpin:127.0.0.1:{port}", "--duration", "90", "--mission-item-seconds", str(ITEM_SECONDS)],
        cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, stdout=subprocess.PIPE, text=True,
        start_new_session=True)
    assert proc.stdout is not None
    assert json.loads(proc.stdout.readline())["event"] == "ready"
    return proc


def stop_vehicle(proc: subprocess.Popen[str]) -> dict[str, Any]:
    os.kill(proc.pid, signal.SIGTERM)
    out, _ = proc.communicate(timeout=10)
    last: dict[str, Any] = json.loads(out.strip().splitlines()[-1])
    assert last["event"] == "stopped", out[-2000:]
    return last


async def retained(broker: LocalMosquitto, topic: str, timeout: float = 5.0) -> dict[str, Any]:
    """The message the broker retained on ``topic`` (a fresh subscription gets it at once)."""
    async with mqtt_client(broker) as client:
        await client.subscribe(topic, qos=1)
        async with asyncio.timeout(timeout):
            async for message in client.messages:
                if message.retain:
                    return json.loads(bytes(message.payload))
    raise AssertionError(f"nothing retained on {topic}")


def test_vda5050_example_commands_the_robot_and_the_uav_and_publishes_valid_states(
        tmp_path: Path, mosquitto: LocalMosquitto, monkeypatch: pytest.MonkeyPatch) -> None:
    """The orders reach both vehicles; each `state` says the order, what is reached and what
    remains (from the UAV's MISSION_CURRENT and the robot driver's poses remaining), driving
    and paused, the position (the latest visualization) and the battery; a factsheet per
    vehicle is retained; every message validates, and each topic's headerIds count by 1."""
    port = free_udp_port()
    monkeypatch.setenv("VDA5050_MQTT_URL", mosquitto.url)
    monkeypatch.setenv("VDA5050_CLIENT_ID", "vda-" + uuid.uuid4().hex[:8])
    monkeypatch.setenv("VDA5050_UAV_LINK", f"udpout:127.0.0.1:{port}")
    monkeypatch.setenv("ROS_DOMAIN_ID", str(DOMAIN))
    monkeypatch.setenv("HOME", str(tmp_path))  # the engine's dead-letter spool, should there be any
    schemas = SchemaRegistry(REPO / "schemas")

    peer = Peer()
    goals = peer.subscribe(Path_, "/robot1/goal")
    driver = peer.subscribe(String, "/robot1/instant_actions")
    battery = peer.publisher(BatteryState, "/robot1/battery")
    pose = peer.publisher(PoseWithCovarianceStamped, "/robot1/pose")
    remaining = peer.publisher(Int16, "/robot1/poses_remaining")
    peer.start()
    vehicle = start_vehicle(port)
    figures: dict[str, float] = {}
    seen: dict[str, dict[str, Any]] = {}

    async def scenario() -> dict[str, list[Any]]:
        engine = Engine(EXAMPLE, REPO / "schemas")
        await engine.start()

        def delivered(route: str) -> int:
            return int(engine.status()["routes"][route]["delivered"])

        try:
            async with Subscriber(mosquitto, "uagv/v2/rabbitros/#") as master:
                def states(agent: str) -> list[dict[str, Any]]:
                    return [json.loads(m.payload) for m in master.messages if str(m.topic) == f"uagv/v2/rabbitros/{agent}/state"]

                async def state(agent: str, label: str, wanted: Any, since: float) -> None:
                    """Wait for a state of ``agent`` ``wanted`` accepts; keep it as ``seen[label]``
                    and the time since ``since`` as a figure."""
                    def found() -> bool:
                        match = next((body for body in states(agent) if wanted(body)), None)
                        if match is not None:
                            seen[label] = match
                        return match is not None
                    await wait_for(found, 20, f"a state of {agent}: {label}")
                    figures[f"{label}_s"] = time.monotonic() - since

                await wait_for(lambda: all(p.get_subscription_count() > 0 for p in (battery, pose, remaining)),
                               20, "the engine's ROS 2 subscriptions")
                # the UAV: its order, then states with its progress; paused and resumed
                started = time.monotonic()
                await publish(mosquitto, [("uagv/v2/rabbitros/uav1/order", UAV_ORDER)])
                await wait_for(lambda: delivered("uav1-order") == 1, 20, "the UAV to accept its mission")
                figures["order_to_mission_accepted_s"] = time.monotonic() - started
                await state("uav1", "order_to_uav_state_flying_it", lambda b: b["orderId"] == "spray-1" and b["driving"], started)
                paused_at = time.monotonic()
                await publish(mosquitto, [("uagv/v2/rabbitros/uav1/instantActions", PAUSE)])
                await wait_for(lambda: delivered("uav1-instant-actions") == 1, 20, "the UAV to acknowledge the pause")
                figures["pause_to_command_ack_s"] = time.monotonic() - paused_at
                await state("uav1", "pause_to_paused_state", lambda b: b.get("paused") is True, paused_at)
                await publish(mosquitto, [("uagv/v2/rabbitros/uav1/instantActions", RESUME)])
                await state("uav1", "order_to_uav_state_at_p1", lambda b: b["lastNodeId"] == "p1", started)

                # the robot: its order; its driver reports one pose of two remaining
                started = time.monotonic()
                await publish(mosquitto, [("uagv/v2/rabbitros/robot1/order", ROBOT_ORDER)])
                await wait_for(lambda: len(goals) == 1, 20, "the robot's Path")
                figures["order_to_robot_goal_s"] = time.monotonic() - started
                await publish(mosquitto, [("uagv/v2/rabbitros/robot1/instantActions", {**PAUSE, "serialNumber": "robot1"})])
                await wait_for(lambda: len(driver) == 1, 20, "the robot's driver to get the pause")
                remaining.publish(Int16(data=1))
                localisation = PoseWithCovarianceStamped()
                localisation.header.frame_id = "map"
                localisation.pose.pose.position.x, localisation.pose.pose.position.y = 3.5, -1.25
                localisation.pose.pose.orientation.z = localisation.pose.pose.orientation.w = math.sqrt(0.5)
                pose.publish(localisation)
                await wait_for(lambda: delivered("robot1-progress") == 1 and delivered("robot1-visualization") == 1, 20,
                               "the engine to remember the robot's progress and position")
                message = BatteryState()
                message.header.stamp.sec, message.header.frame_id = 1_763_917_200, "base_link"
                message.voltage, message.percentage = 25.2, 0.64
                message.power_supply_status = BatteryState.POWER_SUPPLY_STATUS_DISCHARGING
                message.power_supply_health = BatteryState.POWER_SUPPLY_HEALTH_GOOD
                battery.publish(message)
                await state("robot1", "order_to_robot_state_at_a", lambda b: b["lastNodeId"] == "a", started)

                def topics() -> set[str]:
                    return {str(m.topic) for m in master.messages}

                wanted = {f"uagv/v2/rabbitros/{agent}/{topic}" for agent in ("uav1", "robot1")
                          for topic in ("state", "visualization", "connection", "factsheet")}
                await wait_for(lambda: wanted <= topics(), 20, f"every VDA 5050 topic of both vehicles: {wanted}")
                by_topic: dict[str, list[Any]] = {}
                for m in master.messages:
                    by_topic.setdefault(str(m.topic), []).append(json.loads(m.payload))
                status = engine.status()
                assert all(route["failed"] == 0 for route in status["routes"].values()), status["routes"]
                assert status["stores"] == {"connections_sent": 2, "factsheets_sent": 2, "instant_actions": 2, "order_checks": 2,
                                           "orders": 2, "positions": 2, "progress": 2, "states": 2, "order_schema_checks": 0}, status["stores"]
        finally:
            await engine.stop()
        for agent in ("uav1", "robot1"):  # on_stop, before the clean disconnection that drops the will
            topic = f"uagv/v2/rabbitros/{agent}/connection"
            by_topic[topic].append(await retained_state(mosquitto, topic, "OFFLINE"))
            by_topic[f"retained {agent} factsheet"] = [await retained(mosquitto, f"uagv/v2/rabbitros/{agent}/factsheet")]
        return by_topic

    try:
        by_topic = asyncio.run(asyncio.wait_for(scenario(), 90))
    finally:
        peer.close()
        stopped = stop_vehicle(vehicle) if vehicle.poll() is None else {}

    # every state, visualization, connection and factsheet the engine published is valid VDA 5050 2.0
    validated: dict[str, int] = {}
    for topic, bodies in by_topic.items():
        kind = topic.rsplit("/", 1)[1] if "/" in topic else topic.rsplit(" ", 1)[1]
        if kind in ("state", "visualization", "connection", "factsheet"):
            for body in bodies:
                known_schema(schemas, f"vda5050/{kind}.v2").validate(body)
                validated[kind] = validated.get(kind, 0) + 1
            ids = [body["headerId"] for body in bodies]
            if kind != "connection" and "/" in topic:  # headerId +1 each
                assert ids == list(range(ids[0], ids[0] + len(ids))), (topic, ids)
            elif "/" in topic:  # an ONLINE may come between the collection and the stop: OFFLINE counts on from it
                assert ids == sorted(set(ids)), (topic, ids)
    print(" ".join(f"{key}={value:.2f}" for key, value in figures.items()), "validated", validated)

    # the robot got its released nodes as a Path, theta as the orientation
    [goal] = goals
    assert goal.header.frame_id == "map" and len(goal.poses) == 2
    assert (goal.poses[1].pose.position.x, goal.poses[1].pose.position.y) == (11.0, 2.0)
    assert math.isclose(goal.poses[1].pose.orientation.z, math.sqrt(0.5)) and math.isclose(goal.poses[1].pose.orientation.w, math.sqrt(0.5))
    assert json.loads(driver[0].data) == {**PAUSE, "serialNumber": "robot1"}

    # the UAV holds the two released nodes, 15 m above home, where the farm map puts them
    assert stopped, "the vehicle exited before the end of the test"
    assert [(item["command"], item["frame"], item["z"]) for item in stopped["mission"]] == \
        [(mavlink2.MAV_CMD_NAV_WAYPOINT, mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 15.0)] * 2, stopped["mission"]
    assert [(item["x"], item["y"]) for item in stopped["mission"]] == [(-220000000, -479000000), (-219990000, -478990000)]
    assert stopped["stats"]["commands_received"] >= 2

    # the UAV's states: flying to p1 with the whole order ahead, paused, then past p1
    all_nodes = [{"nodeId": n["nodeId"], "sequenceId": n["sequenceId"], "released": n["released"]} for n in UAV_ORDER["nodes"]]
    edges = [{"edgeId": "e1", "sequenceId": 1, "released": True}]
    flying = seen["order_to_uav_state_flying_it"]
    assert (flying["orderId"], flying["orderUpdateId"], flying["lastNodeId"], flying["paused"]) == ("spray-1", 0, "", False)
    assert flying["nodeStates"] == all_nodes and flying["edgeStates"] == edges
    assert 0 <= flying["batteryState"]["batteryCharge"] <= 100 and flying["batteryState"]["batteryVoltage"] > 10
    assert flying["agvPosition"]["mapId"] == "farm" and abs(flying["agvPosition"]["x"]) < 2000, flying
    paused = seen["pause_to_paused_state"]
    assert (paused["driving"], paused["lastNodeId"], paused["nodeStates"]) == (False, "", all_nodes)
    at_p1 = seen["order_to_uav_state_at_p1"]
    assert (at_p1["lastNodeId"], at_p1["lastNodeSequenceId"], at_p1["nodeStates"]) == ("p1", 0, all_nodes[1:])
    assert at_p1["edgeStates"] == edges and at_p1["errors"] == []

    # the robot's state: past node a, driving on to b, where its localisation puts it
    robot = seen["order_to_robot_state_at_a"]
    # past node a, paused by the startPause its driver was given (the engine derives it: the driver reports no pause)
    assert (robot["orderId"], robot["lastNodeId"], robot["driving"], robot["paused"]) == ("row-7", "a", False, True)
    assert robot["actionStates"] == [{"actionId": "pause-1", "actionType": "startPause", "actionStatus": "FINISHED"}]
    assert robot["nodeStates"] == [{"nodeId": "b", "sequenceId": 2, "released": True}]
    assert robot["edgeStates"] == [{"edgeId": "ab", "sequenceId": 1, "released": True}]
    assert robot["batteryState"] == {"batteryCharge": pytest.approx(64.0), "charging": False, "batteryVoltage": pytest.approx(25.2)}
    assert robot["timestamp"] == "2025-11-23T17:00:00.000Z"
    assert robot["agvPosition"] == {"x": 3.5, "y": -1.25, "theta": pytest.approx(math.pi / 2), "mapId": "map", "positionInitialized": True}
    for agent in ("uav1", "robot1"):
        states = [body["connectionState"] for body in by_topic[f"uagv/v2/rabbitros/{agent}/connection"]]
        assert states[-2:] == ["ONLINE", "OFFLINE"], states
        [factsheet] = by_topic[f"retained {agent} factsheet"]
        assert factsheet["serialNumber"] == agent and factsheet["protocolFeatures"]["agvActions"], factsheet
