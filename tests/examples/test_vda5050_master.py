"""examples/vda5050 driven by a master control nobody here wrote: ``vda5050-sdk`` (PyPI, 0.2.0)'s
``MasterClient``, with its own validation on (every incoming message checked against the JSON
schemas it bundles, the protocol's major version compared), over a private mosquitto, the engine
running the example's routes, the simulated UAV over MAVLink/UDP (rabbitros_sim.vehicle) and a
robot on ROS 2 (a driver as README.md documents it: a goal Path in, instant actions as JSON in,
battery, pose and poses remaining out).

What a fleet control needs of a VDA 5050 vehicle: its factsheet, state and connection accepted;
an order dispatched (the SDK checks it against the factsheet first) runs to its end: no node
state left, every action FINISHED; startPause, stopPause and cancelOrder answered in
``actionStates`` and in ``paused`` / the cleared node states; a new order taken after a cancel;
an order the vehicle must not take answered with the standard's ``errors`` entry in the state,
and every topic's ``headerId`` a counter. The figures printed (seconds) are the closing note's.
"""

from __future__ import annotations

import asyncio
import json
import math
import os
import re
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from vda5050 import MasterClient, MasterConfig, OrderBuilder, ProgressIssue, VehicleKey
from vda5050.client.events import ErrorEvent, VehicleErrorEvent
from vda5050.model.common import Action, ActionParameter
from vda5050.model.enums import ActionStatus, BlockingType
from vda5050.model.factsheet import Factsheet
from vda5050.model.order import Order
from vda5050.model.state import State

from engine.endpoints.mqtt.broker import LocalMosquitto
from engine.endpoints.ros2.rosmsg import resolve_type
from engine.running.runtime import Engine
from tests.endpoints.mqtt.test_mqtt import Subscriber, publish
from tests.endpoints.ros2.test_ros2_endpoint import DOMAIN, Peer, String
from tests.support.repo import REPO
from tests.support.udp_vehicle import free_udp_port
from tests.support.waiting import wait_for

EXAMPLE = REPO / "examples" / "vda5050"
Path_ = resolve_type("nav_msgs/msg/Path")
BatteryState = resolve_type("sensor_msgs/msg/BatteryState")
Int16 = resolve_type("std_msgs/msg/Int16")
PoseWithCovarianceStamped = resolve_type("geometry_msgs/msg/PoseWithCovarianceStamped")

UAV, ROBOT = VehicleKey("rabbitros", "uav1"), VehicleKey("rabbitros", "robot1")
ITEM_SECONDS = 2.0
"""The simulated UAV reaches a mission item this long after the previous one."""
ROBOT_NODE_SECONDS = 1.0
"""The stand-in robot driver reaches its next pose this long after the previous one."""
WAIT = 30.0
"""Bound on any one wait (a loaded 2-core machine; the figures measured are far below)."""


# ------------------------------------------------------------------ the vehicles


def start_uav(port: int, *options: str) -> subprocess.Popen[str]:
    proc = subprocess.Popen(
        ["timeout", "-s", "KILL", "170", sys.executable, "-m", "rabbitros_sim.vehicle",
         "--device", f"udpin:127.0.0.1:{port}", "--duration", "160", "--mission-item-seconds", str(ITEM_SECONDS), *options],
        cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, stdout=subprocess.PIPE, text=True,
        start_new_session=True)
    assert proc.stdout is not None
    assert json.loads(proc.stdout.readline())["event"] == "ready"
    return proc


def stop_uav(proc: subprocess.Popen[str]) -> dict[str, Any]:
    if proc.poll() is not None:
        return {}
    os.kill(proc.pid, signal.SIGTERM)
    out, _ = proc.communicate(timeout=10)
    last: dict[str, Any] = json.loads(out.strip().splitlines()[-1])
    return last


class RobotDriver:
    """The robot's driver as examples/vda5050/README.md documents its ROS 2 interface: it takes
    a goal ``nav_msgs/Path`` on /robot1/goal and drives it, one pose per ``ROBOT_NODE_SECONDS``
    (poses remaining on /robot1/poses_remaining, Nav2's feedback number), obeys startPause,
    stopPause and cancelOrder as JSON on /robot1/instant_actions, publishes its localisation on
    /robot1/pose (at the pose reached) and its battery on /robot1/battery twice a second."""

    def __init__(self, peer: Peer) -> None:
        self.goals = peer.subscribe(Path_, "/robot1/goal")
        self.actions = peer.subscribe(String, "/robot1/instant_actions")
        self.battery = peer.publisher(BatteryState, "/robot1/battery")
        self.pose = peer.publisher(PoseWithCovarianceStamped, "/robot1/pose")
        self.remaining = peer.publisher(Int16, "/robot1/poses_remaining")
        self.position = (1.0, 2.0, 0.0)

    def publish_pose(self) -> None:
        message = PoseWithCovarianceStamped()
        message.header.frame_id = "map"
        message.pose.pose.position.x, message.pose.pose.position.y = self.position[0], self.position[1]
        message.pose.pose.orientation.z, message.pose.pose.orientation.w = math.sin(self.position[2] / 2), math.cos(self.position[2] / 2)
        self.pose.publish(message)

    def publish_battery(self) -> None:
        message = BatteryState()
        now = time.time()
        message.header.stamp.sec, message.header.stamp.nanosec = int(now), int((now % 1) * 1e9)
        message.header.frame_id = "base_link"
        message.voltage, message.percentage = 25.2, 0.64
        message.power_supply_status = BatteryState.POWER_SUPPLY_STATUS_DISCHARGING
        message.power_supply_health = BatteryState.POWER_SUPPLY_HEALTH_GOOD
        self.battery.publish(message)

    async def run(self) -> None:
        goals_seen = actions_seen = 0
        poses: list[Any] = []
        paused = False
        next_pose_at = next_battery_at = 0.0
        while True:
            now = time.monotonic()
            if len(self.goals) > goals_seen:
                poses, goals_seen, paused = list(self.goals[-1].poses), len(self.goals), False
                self.remaining.publish(Int16(data=len(poses)))
                next_pose_at = now + ROBOT_NODE_SECONDS
            while len(self.actions) > actions_seen:
                for action in json.loads(self.actions[actions_seen].data)["actions"]:
                    if action["actionType"] in ("startPause", "stopPause"):
                        paused = action["actionType"] == "startPause"
                        next_pose_at = now + ROBOT_NODE_SECONDS
                    elif action["actionType"] == "cancelOrder":
                        poses = []
                actions_seen += 1
            if poses and not paused and now >= next_pose_at:
                reached = poses.pop(0).pose
                yaw = 2 * math.atan2(reached.orientation.z, reached.orientation.w)
                self.position = (reached.position.x, reached.position.y, yaw)
                self.remaining.publish(Int16(data=len(poses)))
                next_pose_at = now + ROBOT_NODE_SECONDS
            if now >= next_battery_at:
                self.publish_pose()
                self.publish_battery()
                next_battery_at = now + 0.5
            await asyncio.sleep(0.02)  # pacing: the simulated robot's tick


# ------------------------------------------------------------------ the master control


@dataclass
class Heard:
    """What the SDK's master control reported through its callbacks."""

    errors: list[ErrorEvent] = field(default_factory=list)
    """Messages its own validation refused (schema, major version): none may come."""
    issues: list[tuple[VehicleKey, ProgressIssue]] = field(default_factory=list)
    vehicle_errors: list[tuple[VehicleKey, VehicleErrorEvent]] = field(default_factory=list)
    factsheets: dict[VehicleKey, Factsheet] = field(default_factory=dict)
    connections: dict[VehicleKey, list[str]] = field(default_factory=dict)
    states: dict[VehicleKey, list[State]] = field(default_factory=dict)


MISMATCH = re.compile(r"vehicle reports orderId '(?P<reported>[^']*)' but master has '(?P<current>[^']*)'")
"""The SDK's ORDER_ID_MISMATCH text (vda5050/domain/order/monitor.py)."""


def in_flight(heard: Heard, key: VehicleKey, issue: ProgressIssue) -> bool:
    """An ORDER_ID_MISMATCH of a state that was on its way when the master dispatched the next
    order: the SDK's monitor checks each state against the order the master holds now, so a
    state the vehicle sent before the new order reached it (through mosquitto and the engine,
    longer on a loaded machine) is flagged. Such a mismatch names the vehicle's previous order,
    and the vehicle reported the master's order afterwards; anything else is a real mismatch."""
    found = MISMATCH.search(issue.detail) if issue.kind.value == "ORDER_ID_MISMATCH" else None
    if found is None:
        return False
    reported = [state.order_id for state in heard.states.get(key, [])]
    previous, current = found["reported"], found["current"]
    return previous in reported and current in reported and reported.index(previous) < len(reported) - 1 - reported[::-1].index(current)


def master_control(broker: LocalMosquitto) -> tuple[MasterClient, Heard]:
    master = MasterClient(MasterConfig(broker_url=broker.url, protocol_version="2.0.0", validate_messages=True,
                                       validate_protocol_version=True, client_id="master-" + uuid.uuid4().hex[:8]))
    heard = Heard()
    master.on_error(heard.errors.append)
    master.on_progress_issue(lambda issue, key: heard.issues.append((key, issue)))
    master.on_vehicle_error(lambda event, key: heard.vehicle_errors.append((key, event)))
    master.on_factsheet(lambda factsheet, key: heard.factsheets.__setitem__(key, factsheet))
    master.on_connection(lambda connection, key: heard.connections.setdefault(key, []).append(connection.connection_state.value))
    master.on_state(lambda state, key: heard.states.setdefault(key, []).append(state))
    return master, heard


def fly_at(action_id: str, alt_rel: float = 15.0) -> list[Action]:
    return [Action(action_type="flyAt", action_id=action_id, blocking_type=BlockingType.NONE,
                   action_parameters=[ActionParameter(key="altRel", value=alt_rel)])]


def uav_order(order_id: str, nodes: int) -> Order:
    """``nodes`` waypoints on the farm map; the first at the origin, within the 100 m circle the
    simulated UAV flies (trivially reachable, as VDA 5050 asks of a new order's first node)."""
    builder = OrderBuilder(order_id=order_id, manufacturer="rabbitros", serial_number="uav1", version="2.0.0")
    for index in range(nodes):
        builder.add_node(f"{order_id}-n{index}", x=30.0 * index, y=20.0 * index, map_id="farm",
                         allowed_deviation_xy=150.0 if index == 0 else 2.0, actions=fly_at(f"{order_id}-fly{index}"))
        if index:
            builder.add_edge(f"{order_id}-n{index - 1}", f"{order_id}-n{index}", edge_id=f"{order_id}-e{index}")
    return builder.build()


def robot_order(order_id: str, start: tuple[float, float, float], nodes: int,
                first: tuple[str, int] | None = None) -> Order:
    """``nodes`` poses along x from ``start`` (the robot's own pose, so the first node is
    trivially reachable); ``first``: the first node's id and sequenceId (a new order after a
    cancel starts on the last node reached, VDA 5050 6.6.3.1)."""
    node_id, sequence = first or (f"{order_id}-n0", 0)
    builder = OrderBuilder(order_id=order_id, manufacturer="rabbitros", serial_number="robot1", version="2.0.0",
                           start_sequence_id=sequence)
    for index in range(nodes):
        builder.add_node(node_id if index == 0 else f"{order_id}-n{index}", x=start[0] + 2.0 * index, y=start[1],
                         theta=start[2] if index == 0 else 0.0, map_id="map")
        if index:
            builder.add_edge(builder.nodes[index - 1].node_id, builder.nodes[index].node_id, edge_id=f"{order_id}-e{index}")
    return builder.build()


def latest(master: MasterClient, key: VehicleKey) -> State | None:
    session = master._sessions.get(key)  # the SDK's own view of the vehicle
    return None if session is None else session.state


def finished(state: State | None, order: Order) -> bool:
    """The order ran to its end as a master sees it: this order, no node state left, every action
    of its nodes FINISHED."""
    if state is None or state.order_id != order.order_id or state.node_states or state.edge_states:
        return False
    wanted = {action.action_id for node in order.nodes for action in node.actions}
    done = {action.action_id for action in state.action_states if action.action_status is ActionStatus.FINISHED}
    return wanted <= done


def action_status(state: State | None, action_id: str) -> str | None:
    if state is None:
        return None
    return next((action.action_status.value for action in state.action_states if action.action_id == action_id), None)


@pytest.fixture
def example_env(tmp_path: Path, mosquitto: LocalMosquitto, monkeypatch: pytest.MonkeyPatch) -> Iterator[int]:
    port = free_udp_port()
    monkeypatch.setenv("VDA5050_MQTT_URL", mosquitto.url)
    monkeypatch.setenv("VDA5050_CLIENT_ID", "vda-" + uuid.uuid4().hex[:8])
    monkeypatch.setenv("VDA5050_UAV_LINK", f"udpout:127.0.0.1:{port}")
    monkeypatch.setenv("ROS_DOMAIN_ID", str(DOMAIN))
    monkeypatch.setenv("HOME", str(tmp_path))  # the engine's dead-letter spool
    yield port


async def until(predicate: Callable[[], bool], what: str, heard: Heard) -> None:
    """Wait for ``predicate``; on timeout, say what the master control refused meanwhile."""
    try:
        await wait_for(predicate, WAIT, what)
    except AssertionError as timeout:
        refused = [(event.key and event.key.serial_number, str(event.error)[:300]) for event in heard.errors]
        raise AssertionError(f"{timeout}; the master control refused: {refused}") from None


async def timed(what: str, predicate: Callable[[], bool], figures: dict[str, float], since: float | None = None) -> None:
    started = time.monotonic() if since is None else since
    await wait_for(predicate, WAIT, what)
    figures[what] = time.monotonic() - started


# ------------------------------------------------------------------ the tests


def test_an_independent_master_control_runs_orders_pauses_resumes_and_cancels_both_vehicles(
        example_env: int, mosquitto: LocalMosquitto) -> None:
    """vda5050-sdk's MasterClient accepts both factsheets, states and connections (its own
    validation on, nothing refused, no MAP_NOT_ENABLED), dispatches an order to each vehicle that
    runs to its end, pauses, resumes and cancels each with instant actions it sees FINISHED, and
    dispatches a new order after the cancel."""
    peer = Peer()
    driver = RobotDriver(peer)
    peer.start()
    uav = start_uav(example_env)
    figures: dict[str, float] = {}

    async def scenario() -> Heard:
        engine = Engine(EXAMPLE, REPO / "schemas")
        await engine.start()
        master, heard = master_control(mosquitto)
        driving = asyncio.create_task(driver.run())
        try:
            await master.connect()
            started = time.monotonic()
            await until(lambda: set(heard.factsheets) == {UAV, ROBOT}, "both factsheets accepted", heard)
            await until(lambda: all(latest(master, key) for key in (UAV, ROBOT)), "both states accepted", heard)
            figures["start_to_both_states_s"] = time.monotonic() - started

            # an order to each vehicle runs to its end
            spray = uav_order("spray-1", 3)
            result = await master.dispatch(spray, UAV)
            assert result.accepted, result
            dispatched = time.monotonic()
            start = driver.position
            row = robot_order("row-1", start, 3)
            result = await master.dispatch(row, ROBOT)
            assert result.accepted, result
            await timed("robot_order_to_every_node_finished_s", lambda: finished(latest(master, ROBOT), row), figures)
            await timed("uav_order_to_every_node_finished_s", lambda: finished(latest(master, UAV), spray), figures, dispatched)

            # the UAV: pause, resume, cancel a running order; a new order after
            spray = uav_order("spray-2", 4)
            result = await master.dispatch(spray, UAV)
            assert result.accepted, result
            await wait_for(lambda: (s := latest(master, UAV)) is not None and s.order_id == "spray-2" and s.driving,
                           WAIT, "the UAV flying spray-2")
            await master.pause(UAV, action_id="uav-pause")
            await timed("uav_pause_to_paused_state_s", lambda: (s := latest(master, UAV)) is not None and s.paused is True
                        and not s.driving and action_status(s, "uav-pause") == "FINISHED", figures)
            await master.resume(UAV, action_id="uav-resume")
            await timed("uav_resume_to_driving_state_s", lambda: (s := latest(master, UAV)) is not None and s.paused is False
                        and s.driving and action_status(s, "uav-resume") == "FINISHED", figures)
            await master.cancel_order(UAV, action_id="uav-cancel")
            await timed("uav_cancel_to_cancelled_state_s", lambda: (s := latest(master, UAV)) is not None
                        and action_status(s, "uav-cancel") == "FINISHED" and not s.node_states and not s.edge_states
                        and not s.driving and s.order_id == "spray-2", figures)
            cancelled = latest(master, UAV)
            assert cancelled is not None and not cancelled.paused
            assert all(action.action_status in (ActionStatus.FINISHED, ActionStatus.FAILED) for action in cancelled.action_states)
            spray = uav_order("spray-3", 2)
            result = await master.dispatch(spray, UAV)
            assert result.accepted, result
            await timed("uav_order_after_cancel_to_every_node_finished_s", lambda: finished(latest(master, UAV), spray), figures)

            # the robot: the same
            row = robot_order("row-2", driver.position, 4)
            result = await master.dispatch(row, ROBOT)
            assert result.accepted, result
            await wait_for(lambda: (s := latest(master, ROBOT)) is not None and s.order_id == "row-2" and s.driving,
                           WAIT, "the robot driving row-2")
            await master.pause(ROBOT, action_id="robot-pause")
            await timed("robot_pause_to_paused_state_s", lambda: (s := latest(master, ROBOT)) is not None and s.paused is True
                        and not s.driving and action_status(s, "robot-pause") == "FINISHED", figures)
            await master.resume(ROBOT, action_id="robot-resume")
            await timed("robot_resume_to_driving_state_s", lambda: (s := latest(master, ROBOT)) is not None
                        and s.paused is False and s.driving and action_status(s, "robot-resume") == "FINISHED", figures)
            await master.cancel_order(ROBOT, action_id="robot-cancel")
            await timed("robot_cancel_to_cancelled_state_s", lambda: (s := latest(master, ROBOT)) is not None
                        and action_status(s, "robot-cancel") == "FINISHED" and not s.node_states and not s.edge_states
                        and not s.driving and s.order_id == "row-2", figures)
            last = latest(master, ROBOT)
            assert last is not None
            row = robot_order("row-3", driver.position, 2, first=(last.last_node_id, last.last_node_sequence_id))
            result = await master.dispatch(row, ROBOT)
            assert result.accepted, result
            await timed("robot_order_after_cancel_to_every_node_finished_s", lambda: finished(latest(master, ROBOT), row), figures)
            for key in (UAV, ROBOT):
                assert heard.connections.get(key, [])[-1:] == ["ONLINE"], heard.connections
            return heard
        finally:
            driving.cancel()
            await master.disconnect()
            await engine.stop()

    try:
        heard = asyncio.run(asyncio.wait_for(scenario(), 170))
    finally:
        peer.close()
        stop_uav(uav)
    print(" ".join(f"{key}={value:.2f}" for key, value in figures.items()))

    assert heard.errors == [], [(event.key, str(event.error)) for event in heard.errors]
    kinds = {(key.serial_number, issue.kind.value) for key, issue in heard.issues if not in_flight(heard, key, issue)}
    assert not {kind for _, kind in kinds} & {"MAP_NOT_ENABLED", "ORDER_ID_MISMATCH", "UNKNOWN_NODE", "POSITION_MAP_MISMATCH"}, kinds
    assert heard.vehicle_errors == [], heard.vehicle_errors
    for key in (UAV, ROBOT):
        factsheet = heard.factsheets[key]
        assert factsheet.protocol_features is not None and factsheet.protocol_features.agv_actions


def test_orders_the_vehicles_must_not_take_are_answered_with_errors_and_every_topic_counts_its_header_ids(
        example_env: int, mosquitto: LocalMosquitto) -> None:
    """An order with another major version, another manufacturer or another serial number, and
    an order update older than the current one: none reaches its vehicle, and the vehicle's state
    names each with the standard's error (validationError / orderUpdateError, the order's
    headerId among its references), which the SDK reports as an order rejection; a repeat of the
    current order is discarded without one. Every topic's headerId counts 1, 2, 3...
    (connection included, to its OFFLINE on a clean stop)."""
    peer = Peer()
    driver = RobotDriver(peer)
    peer.start()
    uav = start_uav(example_env)

    master: MasterClient  # bound by scenario(), read by the closures below

    def names(key: VehicleKey, error_type: str, named: str, header_id: int) -> Callable[[], bool]:
        def found() -> bool:
            state = latest(master, key)
            return state is not None and any(
                error.error_type == error_type and named in (error.error_description or "")
                and any(ref.reference_key == "headerId" and ref.reference_value == str(header_id)
                        for ref in error.error_references or [])
                for error in state.errors or [])
        return found

    async def scenario() -> tuple[Heard, dict[str, list[int]], int]:
        nonlocal master
        engine = Engine(EXAMPLE, REPO / "schemas")
        await engine.start()
        master, heard = master_control(mosquitto)
        driving = asyncio.create_task(driver.run())
        try:
            async with Subscriber(mosquitto, "uagv/v2/rabbitros/#") as wire:
                await master.connect()
                await wait_for(lambda: all(latest(master, key) for key in (UAV, ROBOT)), WAIT, "both states")
                row = robot_order("row-1", driver.position, 2)
                result = await master.dispatch(row, ROBOT)
                assert result.accepted, result
                await wait_for(lambda: finished(latest(master, ROBOT), row), WAIT, "row-1 to its end")
                # an update of row-1 that fits (it starts at its last node): taken
                last = row.to_wire()["nodes"][-1]
                update = {**row.to_wire(), "orderUpdateId": 2, "headerId": 100, "nodes": [last], "edges": []}
                await publish(mosquitto, [("uagv/v2/rabbitros/robot1/order", update)])
                await wait_for(lambda: (s := latest(master, ROBOT)) is not None and s.order_update_id == 2, WAIT,
                               "the robot to take the update row-1/2")
                goals = len(driver.goals)
                wrong = [("uav1", {**uav_order("v3", 1).to_wire(), "version": "3.0.0", "headerId": 101}, "validationError", "3.0.0"),
                         ("robot1", {**row.to_wire(), "orderId": "m", "manufacturer": "acme", "headerId": 102}, "validationError", "acme"),
                         ("uav1", {**uav_order("sn", 1).to_wire(), "serialNumber": "uav2", "headerId": 103}, "validationError", "uav2"),
                         ("robot1", {**update, "orderUpdateId": 1, "headerId": 104}, "orderUpdateError", "older")]
                for serial, body, error_type, named in wrong:
                    await publish(mosquitto, [(f"uagv/v2/rabbitros/{serial}/order", body)])
                    await wait_for(names(VehicleKey("rabbitros", serial), error_type, named, body["headerId"]), WAIT,
                                   f"{serial}'s state to name {error_type} ({named})")
                # a repeat of the current order (the same orderUpdateId) is discarded, without an error
                await publish(mosquitto, [("uagv/v2/rabbitros/robot1/order", {**update, "headerId": 105})])

                def robot_errors_cleared() -> bool:
                    state = latest(master, ROBOT)
                    assert state is not None, "the master control holds the robot's state"
                    return not (state.errors or [])

                await wait_for(robot_errors_cleared, WAIT, "the robot's errors cleared by the repeat (the latest order's check)")
                assert len(driver.goals) == goals, "no order that does not fit reached the robot"
                await engine.stop()
                await wait_for(lambda: sum(str(m.topic).endswith("/connection") and b"OFFLINE" in m.payload
                                           for m in wire.messages) == 2, WAIT, "both OFFLINE")
            await master.disconnect()
        finally:
            driving.cancel()
            await engine.stop()
        ids: dict[str, list[int]] = {}
        for message in wire.messages:
            ids.setdefault(str(message.topic), []).append(json.loads(message.payload)["headerId"])
        return heard, ids, goals

    try:
        heard, ids, goals = asyncio.run(asyncio.wait_for(scenario(), 150))
    finally:
        peer.close()
        stopped = stop_uav(uav)
    assert heard.errors == [], [(event.key, str(event.error)) for event in heard.errors]
    assert stopped and stopped["mission"] == [], "no order reached the UAV"
    rejections = {(key.serial_number, event.error.error_type) for key, event in heard.vehicle_errors if event.is_order_rejection}
    assert rejections == {("uav1", "validationError"), ("robot1", "validationError"), ("robot1", "orderUpdateError")}, rejections
    kinds = {kind for _, kind in (topic.rsplit("/", 1) for topic in ids)}
    assert kinds >= {"state", "visualization", "connection", "factsheet", "order"}, kinds
    for topic, headers in ids.items():
        if topic.rsplit("/", 1)[1] in ("state", "visualization", "connection", "factsheet"):
            assert headers == list(range(headers[0], headers[0] + len(headers))), (topic, headers)


def test_an_instant_action_the_vehicle_refuses_is_failed_with_the_reason(example_env: int, mosquitto: LocalMosquitto) -> None:
    """The UAV's autopilot answers every command DENIED: the startPause the master control sends
    is RUNNING, then FAILED with the refusal as its resultDescription (the command became a dead
    letter), so the master's wait for it ends; the vehicle is not reported paused."""
    peer = Peer()
    _driver = RobotDriver(peer)  # kept referenced: it drives the robot for the whole test
    peer.start()
    uav = start_uav(example_env, "--command-result", "MAV_RESULT_DENIED")

    async def scenario() -> State:
        engine = Engine(EXAMPLE, REPO / "schemas")
        await engine.start()
        master, heard = master_control(mosquitto)
        try:
            await master.connect()
            await until(lambda: latest(master, UAV) is not None and UAV in heard.factsheets, "the UAV's state and factsheet", heard)
            spray = uav_order("spray-1", 3)
            result = await master.dispatch(spray, UAV)
            assert result.accepted, result
            await until(lambda: (s := latest(master, UAV)) is not None and s.driving, "the UAV flying spray-1", heard)
            await master.pause(UAV, action_id="refused-pause")
            assert await master.wait_for_action(UAV, "refused-pause", timeout=WAIT), latest(master, UAV)
            state = latest(master, UAV)
            assert state is not None
            assert heard.errors == [], [(event.key, str(event.error)) for event in heard.errors]
            return state
        finally:
            await master.disconnect()
            await engine.stop()

    try:
        state = asyncio.run(asyncio.wait_for(scenario(), 120))
    finally:
        peer.close()
        stop_uav(uav)
    [refused] = [action for action in state.action_states if action.action_id == "refused-pause"]
    assert refused.action_status is ActionStatus.FAILED and "DENIED" in (refused.result_description or ""), refused
    assert state.paused is not True and state.driving


def test_a_new_order_while_the_current_one_runs_is_refused_and_the_running_order_completes(
        example_env: int, mosquitto: LocalMosquitto) -> None:
    """VDA 5050 2.0 figure 8, step 3: a new orderId while the vehicle still executes its order
    (node states left) is rejected. Each vehicle, given another order mid-way through its first,
    names it in its state with an ``orderError`` (the order's headerId among its references, which
    the SDK reports as an order rejection), is not given it (the robot gets no second Path, the
    UAV's mission stays the first order's), and runs the first order to its end. On main the
    second order was taken and replaced the running one."""
    peer = Peer()
    driver = RobotDriver(peer)
    peer.start()
    uav = start_uav(example_env)

    master: MasterClient  # bound by scenario(), read by the closures below

    def refused(key: VehicleKey, header_id: int) -> Callable[[], bool]:
        def found() -> bool:
            state = latest(master, key)
            return state is not None and any(
                error.error_type == "orderError" and any(
                    ref.reference_key == "headerId" and ref.reference_value == str(header_id) for ref in error.error_references or [])
                for error in state.errors or [])
        return found

    async def scenario() -> Heard:
        nonlocal master
        engine = Engine(EXAMPLE, REPO / "schemas")
        await engine.start()
        master, heard = master_control(mosquitto)
        driving = asyncio.create_task(driver.run())
        try:
            await master.connect()
            await until(lambda: all(latest(master, key) for key in (UAV, ROBOT)), "both states", heard)
            spray = uav_order("spray-1", 3)
            assert (await master.dispatch(spray, UAV)).accepted
            row = robot_order("row-1", driver.position, 4)
            assert (await master.dispatch(row, ROBOT)).accepted
            await until(lambda: (s := latest(master, ROBOT)) is not None and s.order_id == "row-1" and s.driving
                        and len(s.node_states) < 4, "the robot driving row-1, past its first node", heard)
            await until(lambda: (s := latest(master, UAV)) is not None and s.order_id == "spray-1" and s.driving,
                        "the UAV flying spray-1", heard)
            # published as a master that does not track the vehicle would (the SDK's dispatch may refuse a busy vehicle itself)
            other_row = {**robot_order("row-2", driver.position, 2).to_wire(), "headerId": 201}
            other_spray = {**uav_order("spray-2", 2).to_wire(), "headerId": 202}
            await publish(mosquitto, [("uagv/v2/rabbitros/robot1/order", other_row), ("uagv/v2/rabbitros/uav1/order", other_spray)])
            await until(refused(ROBOT, 201), "the robot's state to refuse row-2 with an orderError", heard)
            await until(refused(UAV, 202), "the UAV's state to refuse spray-2 with an orderError", heard)
            for key, order_id in ((ROBOT, "row-1"), (UAV, "spray-1")):
                state = latest(master, key)
                assert state is not None and state.order_id == order_id and state.node_states, state
            await until(lambda: finished(latest(master, ROBOT), row), "row-1 to its end", heard)
            await until(lambda: finished(latest(master, UAV), spray), "spray-1 to its end", heard)
            assert len(driver.goals) == 1 and len(driver.goals[0].poses) == 4, "the robot was given row-1 only"
            return heard
        finally:
            driving.cancel()
            await master.disconnect()
            await engine.stop()

    try:
        heard = asyncio.run(asyncio.wait_for(scenario(), 150))
    finally:
        peer.close()
        stopped = stop_uav(uav)
    assert heard.errors == [], [(event.key, str(event.error)) for event in heard.errors]
    assert stopped and len(stopped["mission"]) == 3, "the UAV kept spray-1's mission"
    rejections = {(key.serial_number, event.error.error_type) for key, event in heard.vehicle_errors if event.is_order_rejection}
    assert rejections == {("uav1", "orderError"), ("robot1", "orderError")}, rejections


def test_an_order_the_vda_schema_refuses_is_answered_with_a_validation_error(example_env: int, mosquitto: LocalMosquitto) -> None:
    """VDA 5050 2.0 6.6.4.1 / figure 8 step 1: an order that is not valid (here a node without
    its sequenceId, and an orderUpdateId given as a string) is rejected with a ``validationError``
    in the state, the order's headerId among its references, which the SDK reports as an order
    rejection; neither vehicle is given it. On main it was only a dead letter: the state said
    nothing."""
    peer = Peer()
    driver = RobotDriver(peer)
    peer.start()
    uav = start_uav(example_env)

    master: MasterClient  # bound by scenario(), read by the closures below

    def refused(key: VehicleKey, header_id: int) -> Callable[[], bool]:
        def found() -> bool:
            state = latest(master, key)
            return state is not None and any(
                error.error_type == "validationError" and "schema" in (error.error_description or "") and any(
                    ref.reference_key == "headerId" and ref.reference_value == str(header_id) for ref in error.error_references or [])
                for error in state.errors or [])
        return found

    async def scenario() -> Heard:
        nonlocal master
        engine = Engine(EXAMPLE, REPO / "schemas")
        await engine.start()
        master, heard = master_control(mosquitto)
        driving = asyncio.create_task(driver.run())
        try:
            await master.connect()
            await until(lambda: all(latest(master, key) for key in (UAV, ROBOT)), "both states", heard)
            row = robot_order("row-1", driver.position, 2).to_wire()
            del row["nodes"][1]["sequenceId"]
            spray = {**uav_order("spray-1", 2).to_wire(), "orderUpdateId": "0", "headerId": 302}
            await publish(mosquitto, [("uagv/v2/rabbitros/robot1/order", {**row, "headerId": 301}),
                                      ("uagv/v2/rabbitros/uav1/order", spray)])
            await until(refused(ROBOT, 301), "the robot's state to name the invalid order with a validationError", heard)
            await until(refused(UAV, 302), "the UAV's state to name the invalid order with a validationError", heard)
            for key in (ROBOT, UAV):
                state = latest(master, key)
                assert state is not None and state.order_id == "" and not state.node_states, state
            assert not driver.goals, "the robot was given no goal"
            return heard
        finally:
            driving.cancel()
            await master.disconnect()
            await engine.stop()

    try:
        heard = asyncio.run(asyncio.wait_for(scenario(), 120))
    finally:
        peer.close()
        stopped = stop_uav(uav)
    assert heard.errors == [], [(event.key, str(event.error)) for event in heard.errors]
    assert stopped and stopped["mission"] == [], "no order reached the UAV"
    rejections = {(key.serial_number, event.error.error_type) for key, event in heard.vehicle_errors if event.is_order_rejection}
    assert rejections == {("uav1", "validationError"), ("robot1", "validationError")}, rejections
