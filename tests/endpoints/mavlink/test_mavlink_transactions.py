"""MAVLink transactions the vehicle acknowledges: mission uploads and acknowledged commands.

Against an independent vehicle (MAVSDK's C++ MissionRawServer and ActionServer) through
RabbitMQ and the engine; against the simulated vehicle over the emulated SiK radio with 5 %
loss; and every outcome the protocols have (accepted, rejected, in progress, temporarily
rejected, silent, a vehicle not heard yet) against the simulated vehicle on UDP.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import subprocess
import sys
import time
import uuid
from collections.abc import AsyncIterator, Awaitable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import aio_pika
import pytest

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from engine.endpoints import mavlink  # noqa: E402
from engine.endpoints.base import EndpointError, MessageRejected, Outbound  # noqa: E402
from engine.endpoints.mavlink.connection import MavlinkConnection  # noqa: E402
from engine.language.mapping import compile_mapping  # noqa: E402
from engine.running.runtime import Engine  # noqa: E402
from rabbitros_sim.sik_radio import SikRadioPair  # noqa: E402
from rabbitros_sim.vehicle import SimVehicle  # noqa: E402
from tests.support.amqp_helpers import Collector  # noqa: E402
from tests.support.repo import REPO  # noqa: E402
from tests.support.mavsdk_vehicle import MavsdkAutopilot  # noqa: E402
from tests.support.udp_vehicle import free_udp_port  # noqa: E402
from tests.support.waiting import wait_for

WEEDS = [(-22.0004563, -47.9001234), (-22.0004571, -47.9001301), (-21.99951234, -47.89987651)]


def canonical_stamp() -> dict[str, int]:
    now = time.time_ns()
    return {"sec": now // 1_000_000_000, "nanosec": now % 1_000_000_000}


def canonical_mission(points: list[tuple[float, float]], alt_rel: float = 15.0) -> dict[str, Any]:
    """Waypoints ``alt_rel + i`` metres above home, holding ``2 + i`` s."""
    return canonical_waypoints([{"lat": lat, "lon": lon, "alt_rel": alt_rel + i, "hold_s": 2.0 + i}
                                for i, (lat, lon) in enumerate(points)])


def canonical_waypoints(waypoints: list[dict[str, Any]]) -> dict[str, Any]:
    return {"type": "mission", "agent_id": "uav1", "id": uuid.uuid4().hex, "stamp": canonical_stamp(),
            "mission_id": "spray-1", "task": "spray", "waypoints": waypoints}


def outbound(fields: Any) -> Outbound:
    return Outbound(b"", fields, fields, uuid.uuid4().hex, {})


def run(coro: Awaitable[Any], timeout: float) -> Any:
    return asyncio.run(asyncio.wait_for(coro, timeout))


@asynccontextmanager
async def gcs_and_vehicle(**vehicle: Any) -> AsyncIterator[tuple[MavlinkConnection, SimVehicle]]:
    """The engine's connection (udpin) and a simulated vehicle (udpout) in this loop."""
    port = free_udp_port()
    gcs = mavlink.TRANSPORT.connect("gcs", {"url": f"udpin:127.0.0.1:{port}"})
    await gcs.open()
    sim = SimVehicle(f"udpout:127.0.0.1:{port}", **vehicle)
    stop = asyncio.Event()
    running = asyncio.create_task(sim.run(stop))
    try:
        yield gcs, sim
    finally:
        stop.set()
        await running
        await gcs.close()


def write_routes(directory: Path, amqp_url: str, link: str, text: str) -> Path:
    """A routes directory with the connections ``bus`` (AMQP) and ``uav`` (MAVLink ``link``)."""
    directory.mkdir(exist_ok=True)
    baud = "" if link.startswith(("udp", "tcp")) else ", baud: 57600"
    (directory / "routes.yaml").write_text(
        f'connections:\n  bus: {{amqp: "{amqp_url}"}}\n  uav: {{mavlink: "{link}"{baud}}}\nroutes:\n{text}')
    return directory


def amqp_route(name: str, tag: str, binding_key: str, schema: str) -> str:
    """The head of a route from the test's exchange to a sink given after it."""
    return f"""  - name: {name}-{tag}
    source: {{amqp: {{connection: bus, exchange: farm-{tag}, binding_key: {binding_key}, queue: {name}-{tag}}}}}
    schema: {schema}
"""


# -- the engine through RabbitMQ to MAVSDK ------------------------------------------------------


def test_canonical_mission_and_arm_through_rabbitmq_to_mavsdk(tmp_path: Path, amqp_url: str, schemas_dir: Path) -> None:
    """MAVSDK's MissionRawServer receives the waypoints in order, as NAV_WAYPOINT with degE7
    rounded, each in the frame of its altitude (the first ``alt_msl``: GLOBAL_INT, the others
    ``alt_rel``: GLOBAL_RELATIVE_ALT_INT); its ActionServer acknowledges the arm command; both
    AMQP messages are acknowledged once."""
    port = free_udp_port()
    tag = uuid.uuid4().hex[:8]
    routes = write_routes(tmp_path / "routes", amqp_url, f"udpout:127.0.0.1:{port}", amqp_route(
        "mission", tag, "mission.uav1", "mission") + """\
    sink: {mavlink: {connection: uav, mission: upload, target_system: 1, target_component: 1}}
""" + amqp_route("arm", tag, "command.uav1", "command") + """\
    sink:
      mavlink: {connection: uav, message: COMMAND_LONG, target_system: 1, target_component: 1, acknowledged: true}
      mapping: "{command: mav_enum_value('MAV_CMD_COMPONENT_ARM_DISARM', 'MAV_CMD'), param1: `1`}"
""")
    mission = canonical_mission(WEEDS)
    first = mission["waypoints"][0]
    first["alt_msl"] = 615.0 + first.pop("alt_rel")
    command = {"type": "command", "agent_id": "uav1", "id": uuid.uuid4().hex, "stamp": canonical_stamp(), "command": "arm"}
    autopilot = MavsdkAutopilot(port)

    async def scenario() -> dict[str, Any]:
        engine = Engine(routes, schemas_dir)
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            farm = await channel.declare_exchange(f"farm-{tag}", aio_pika.ExchangeType.TOPIC, durable=True)
            await farm.publish(aio_pika.Message(json.dumps(mission).encode()), "mission.uav1")
            await wait_for(lambda: bool(autopilot.missions), 20, "MAVSDK to receive the mission")
            await farm.publish(aio_pika.Message(json.dumps(command).encode()), "command.uav1")
            await wait_for(lambda: engine.status()["routes"][f"arm-{tag}"]["delivered"] == 1, 20, "the arm command acknowledged")
            await wait_for(lambda: engine.status()["routes"][f"mission-{tag}"]["delivered"] == 1, 20, "the mission acknowledged")
            status = engine.status()
        finally:
            await engine.stop()
        try:
            for queue in (f"mission-{tag}", f"arm-{tag}"):
                declared = await channel.declare_queue(queue, passive=True)
                assert declared.declaration_result.message_count == 0, f"{queue} still holds the message"
                await declared.delete(if_unused=False, if_empty=False)
        finally:
            await connection.close()
        return status

    try:
        status = run(scenario(), 60)
    finally:
        autopilot.close()
    items = autopilot.missions[-1]
    assert [(i.seq, i.frame, i.command) for i in items] == [(0, mavlink2.MAV_FRAME_GLOBAL_INT, mavlink2.MAV_CMD_NAV_WAYPOINT)] + \
        [(n, mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mavlink2.MAV_CMD_NAV_WAYPOINT) for n in range(1, len(WEEDS))]
    assert [(i.x, i.y) for i in items] == [(round(lat * 1e7), round(lon * 1e7)) for lat, lon in WEEDS]
    assert [(i.z, i.param1) for i in items] == [(630.0, 2.0)] + [(15.0 + n, 2.0 + n) for n in range(1, len(WEEDS))]
    assert [arm.arm for arm in autopilot.arm_requests] == [True]
    for name in (f"mission-{tag}", f"arm-{tag}"):
        route = status["routes"][name]
        assert (route["received"], route["delivered"], route["failed"]) == (1, 1, 0), (name, route)


# -- over the emulated SiK radio ----------------------------------------------------------------


def test_mission_over_lossy_sik_radio_arrives_complete_and_is_acked_once(tmp_path: Path, amqp_url: str,
                                                                         schemas_dir: Path) -> None:
    """30 waypoints (plus ArduPilot's home placeholder) over a 57,600 baud radio losing 5 % of
    its air packets: the vehicle holds exactly the mission sent, the AMQP message is
    acknowledged once, and the vehicle's MISSION_ACK comes back as a canonical ack."""
    tag = uuid.uuid4().hex[:8]
    points = [(-22.0 + i * 1.1e-5, -47.9 - i * 0.7e-5) for i in range(30)]
    mission = canonical_mission(points)

    async def scenario() -> tuple[dict[str, Any], SimVehicle, list[Any]]:
        async with SikRadioPair(str(tmp_path / "gcs"), str(tmp_path / "uav"), loss=0.05, seed=12) as pair:
            routes = write_routes(tmp_path / "routes", amqp_url, pair.link_a, amqp_route(
                "mission", tag, "mission.uav1", "mission") + f"""\
    sink: {{mavlink: {{connection: uav, mission: upload, target_system: 1, target_component: 1, home_placeholder: true}}}}
  - name: acks-{tag}
    source: {{mavlink: {{connection: uav, message: MISSION_ACK, system_id: 1}}}}
    mapping: >-
      {{type: 'ack', agent_id: 'uav1', ref_id: ref_id, detail: mav_enum(type, 'MAV_MISSION_RESULT'),
      result: (type == `0` && 'accepted') || 'rejected'}}
    schema: ack
    sink: {{amqp: {{connection: bus, exchange: farm-{tag}, routing_key: canonical.ack.uav1}}}}
""")
            sim = SimVehicle(pair.link_b)
            stop = asyncio.Event()
            running = asyncio.create_task(sim.run(stop))
            engine = Engine(routes, schemas_dir)
            await engine.start()
            connection = await aio_pika.connect(amqp_url)
            try:
                channel = await connection.channel()
                acks = await Collector.bind(channel, f"farm-{tag}", "canonical.ack.#")
                farm = await channel.declare_exchange(f"farm-{tag}", aio_pika.ExchangeType.TOPIC, durable=True)
                await farm.publish(aio_pika.Message(json.dumps(mission).encode()), "mission.uav1")
                await wait_for(lambda: engine.status()["routes"][f"mission-{tag}"]["delivered"] == 1, 90, "the upload")
                received = await acks.wait_for(1, 10)
                status = engine.status()
            finally:
                await engine.stop()
                stop.set()
                await running
            declared = await channel.declare_queue(f"mission-{tag}", passive=True)
            assert declared.declaration_result.message_count == 0
            await declared.delete(if_unused=False, if_empty=False)
            await connection.close()
            return status, sim, received

    status, sim, acks = run(scenario(), 150)
    route = status["routes"][f"mission-{tag}"]
    assert (route["received"], route["delivered"], route["failed"], route["sink_errors"]) == (1, 1, 0, 0), route
    items = sim.autopilot.mission
    assert len(items) == len(points) + 1 and items[0]["frame"] == mavlink2.MAV_FRAME_GLOBAL_INT, "home placeholder first"
    assert [i["seq"] for i in items] == list(range(len(points) + 1))
    assert [(i["x"], i["y"], i["z"]) for i in items[1:]] == \
        [(round(lat * 1e7), round(lon * 1e7), 15.0 + n) for n, (lat, lon) in enumerate(points)]
    assert sim.stats.missions_accepted == 1
    body = json.loads(acks[0].body)
    assert (body["result"], body["detail"], body["ref_id"]) == ("accepted", "MAV_MISSION_ACCEPTED", mission["id"])


# -- refusals through the engine: dead letters where the route says so -----------------------------


def test_refused_mission_and_command_are_dead_lettered_with_the_result_name(tmp_path: Path, amqp_url: str,
                                                                             schemas_dir: Path) -> None:
    """A mission the vehicle refuses is a dead letter; so is a refused command on a route with
    ``refusals: dead_letter`` (a refusal is an answer otherwise: test_command_bounds.py)."""
    port = free_udp_port()
    tag = uuid.uuid4().hex[:8]
    routes = write_routes(tmp_path / "routes", amqp_url, f"udpin:127.0.0.1:{port}", amqp_route(
        "mission", tag, "mission.uav1", "mission") + """\
    sink: {mavlink: {connection: uav, mission: upload}}
""" + amqp_route("arm", tag, "command.uav1", "command") + """\
    sink:
      mavlink: {connection: uav, message: COMMAND_INT, target_system: 1, acknowledged: true, refusals: dead_letter}
      mapping: "{command: 'MAV_CMD_DO_REPOSITION', frame: `6`, x: deg_to_deg_e7(params.lat), y: deg_to_deg_e7(params.lon)}"
""")
    command = {"type": "command", "agent_id": "uav1", "id": "c1", "stamp": canonical_stamp(), "command": "goto",
               "params": {"lat": -22.0001, "lon": -47.9002}}

    async def scenario() -> tuple[list[Any], SimVehicle]:
        engine = Engine(routes, schemas_dir)
        await engine.start()
        sim = SimVehicle(f"udpout:127.0.0.1:{port}", mission_result="MAV_MISSION_NO_SPACE",
                         command_results=["MAV_RESULT_DENIED"])
        stop = asyncio.Event()
        running = asyncio.create_task(sim.run(stop))
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            dead = await Collector.bind(channel, "rabbitros.dead-letter", f"mission-{tag}")
            dead_commands = await Collector.bind(channel, "rabbitros.dead-letter", f"arm-{tag}")
            farm = await channel.declare_exchange(f"farm-{tag}", aio_pika.ExchangeType.TOPIC, durable=True)
            await farm.publish(aio_pika.Message(json.dumps(canonical_mission(WEEDS)).encode()), "mission.uav1")
            await farm.publish(aio_pika.Message(json.dumps(command).encode()), "command.uav1")
            letters = [*await dead.wait_for(1, 20), *await dead_commands.wait_for(1, 20)]
        finally:
            await engine.stop()
            stop.set()
            await running
            await connection.close()
        return letters, sim

    letters, sim = run(scenario(), 60)
    errors = {m.routing_key: m.headers["x-rabbitros-error"] for m in letters}
    assert set(errors) == {f"mission-{tag}", f"arm-{tag}"}, errors
    assert "MAV_MISSION_NO_SPACE" in errors[f"mission-{tag}"]
    assert "MAV_RESULT_DENIED" in errors[f"arm-{tag}"] and "MAV_CMD_DO_REPOSITION" in errors[f"arm-{tag}"]
    assert sim.autopilot.commands[0]["x"] == -220001000 and sim.autopilot.commands[0]["message"] == "COMMAND_INT"


FIELD_M = 392.0
"""A field this many metres above sea level: 20 m above it is alt_rel 20 or alt_msl 412."""
MIXED = [{"lat": -22.0004, "lon": -47.9004, "alt_msl": FIELD_M + 20, "hold_s": 1.0},
         {"lat": -22.0005, "lon": -47.9005, "alt_rel": 20.0}]
"""One height two ways in one mission: each waypoint keeps its own reference."""
UNSAID = {
    "neither": ([MIXED[0], {"lat": -22.0005, "lon": -47.9005}],
                "mission: 'waypoints[1]' gives no altitude: set one of 'alt_msl' (metres above mean sea level, "
                "MAV_FRAME_GLOBAL_INT) or 'alt_rel' (metres above home, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT); "
                "an altitude is never guessed"),
    "both": ([{**MIXED[1], "alt_msl": FIELD_M + 20}], "mission: 'waypoints[0]' gives both 'alt_msl' and 'alt_rel': "),
    "bare alt": ([{"lat": -22.0006, "lon": -47.9006, "alt": FIELD_M + 20}],  # above the sea? or 412 m above home?
                 "mission: 'waypoints[0]' gives no altitude, only 'alt', which does not say above what: "),
}
"""Missions whose altitude would have to be guessed, and the start of their error (all of it for one)."""


def test_each_waypoint_flies_in_the_frame_of_its_altitude_and_none_is_guessed(tmp_path: Path, amqp_url: str,
                                                                           schemas_dir: Path) -> None:
    """``alt_msl`` arrives as MISSION_ITEM_INT in MAV_FRAME_GLOBAL_INT with z = alt_msl, ``alt_rel``
    in MAV_FRAME_GLOBAL_RELATIVE_ALT_INT with z = alt_rel, mixed in one mission; a mission with a
    waypoint giving no altitude, a bare ``alt`` or both is dead-lettered at the ``sink mapping``
    stage naming the waypoint, and nothing of it reaches the vehicle (published before the good
    one, on the same route). ``rabbitros-engine test`` on the same routes reports the same errors."""
    port = free_udp_port()
    tag = uuid.uuid4().hex[:8]
    routes = write_routes(tmp_path / "routes", amqp_url, f"udpin:127.0.0.1:{port}", amqp_route(
        "mission", tag, "mission.uav1", "mission") + """\
    sink: {mavlink: {connection: uav, mission: upload}}
""")
    refused = {name: canonical_waypoints(points) for name, (points, _) in UNSAID.items()}
    good = canonical_waypoints(MIXED)

    async def scenario() -> tuple[list[Any], dict[str, Any], SimVehicle]:
        engine = Engine(routes, schemas_dir)
        await engine.start()
        sim = SimVehicle(f"udpout:127.0.0.1:{port}")
        stop = asyncio.Event()
        running = asyncio.create_task(sim.run(stop))
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            dead = await Collector.bind(channel, "rabbitros.dead-letter", f"mission-{tag}")
            farm = await channel.declare_exchange(f"farm-{tag}", aio_pika.ExchangeType.TOPIC, durable=True)
            for mission in (*refused.values(), good):
                await farm.publish(aio_pika.Message(json.dumps(mission).encode()), "mission.uav1")
            route = lambda: engine.status()["routes"][f"mission-{tag}"]  # noqa: E731
            await wait_for(lambda: route()["delivered"] + route()["failed"] == len(refused) + 1, 30, "every mission settled")
            letters = await dead.wait_for(len(refused), 10)
            status = route()
        finally:
            await engine.stop()
            stop.set()
            await running
            await connection.close()
        return letters, status, sim

    letters, status, sim = run(scenario(), 60)
    assert (status["received"], status["delivered"], status["failed"]) == (4, 1, 3), status
    assert [(i["seq"], i["command"], i["frame"], i["x"], i["y"], i["z"], i["param1"]) for i in sim.autopilot.mission] == [
        (0, mavlink2.MAV_CMD_NAV_WAYPOINT, mavlink2.MAV_FRAME_GLOBAL_INT, -220004000, -479004000, 412.0, 1.0),
        (1, mavlink2.MAV_CMD_NAV_WAYPOINT, mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, -220005000, -479005000, 20.0, 0.0)]
    assert (sim.stats.missions_accepted, sim.stats.mission_items_received) == (1, 2), "nothing of the refused ones was uploaded"
    errors = {json.loads(m.body)["id"]: (m.headers["x-rabbitros-stage"], m.headers["x-rabbitros-error"]) for m in letters}
    assert set(errors) == {mission["id"] for mission in refused.values()}, errors
    for name, (_, error) in UNSAID.items():
        stage, got = errors[refused[name]["id"]]
        assert stage == "sink mapping" and got.startswith(error), (name, stage, got)

    # rabbitros-engine test on the same routes: the same errors, word for word
    cases = [{"name": name, "route": f"mission-{tag}", "input": refused[name], "expect_error": "sink mapping"}
             for name in UNSAID]
    cases += [{"name": "mixed", "route": f"mission-{tag}", "input": good, "expect": good},
              {"name": "expects the guess", "route": f"mission-{tag}", "input": refused["neither"], "expect": refused["neither"]}]
    (routes / "routes.test.yaml").write_text(json.dumps({"tests": cases}))
    result = subprocess.run([sys.executable, "-m", "engine", "test", "--routes", str(routes), "--schemas", str(schemas_dir)],
                            capture_output=True, text=True, timeout=120, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    lines = result.stdout.splitlines()
    assert result.returncode == 1 and lines[-1] == "4 passed, 1 failed", result.stdout + result.stderr
    [failed] = [line for line in lines if line.startswith("FAIL")]
    assert failed.endswith(f"expects the guess: expected it to pass, got a sink mapping error: {UNSAID['neither'][1]}"), failed


def test_a_mission_to_a_silent_vehicle_is_a_dead_letter_at_its_bound(tmp_path: Path, amqp_url: str,
                                                                      schemas_dir: Path) -> None:
    """No answer after the retries (within ``command_timeout``): the upload is cancelled on the
    vehicle and the message is a dead letter at once, naming the vehicle and when it was last
    heard; the route does not upload it again later (issue 31: a stale mission)."""
    port = free_udp_port()
    tag = uuid.uuid4().hex[:8]
    routes = write_routes(tmp_path / "routes", amqp_url, f"udpin:127.0.0.1:{port}", amqp_route(
        "mission", tag, "mission.uav1", "mission") + """\
    sink: {mavlink: {connection: uav, mission: upload, timeout: 0.2, retries: 2}}
""")

    async def scenario() -> tuple[dict[str, Any], list[Any], SimVehicle]:
        engine = Engine(routes, schemas_dir)
        await engine.start()
        sim = SimVehicle(f"udpout:127.0.0.1:{port}", mission_result="silent")
        stop = asyncio.Event()
        running = asyncio.create_task(sim.run(stop))
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            dead = await Collector.bind(channel, "rabbitros.dead-letter", f"mission-{tag}")
            farm = await channel.declare_exchange(f"farm-{tag}", aio_pika.ExchangeType.TOPIC, durable=True)
            await farm.publish(aio_pika.Message(json.dumps(canonical_mission(WEEDS)).encode()), "mission.uav1")
            await wait_for(lambda: bool(dead.messages), 30, "the dead letter")
            status = engine.status()
        finally:
            await engine.stop()
            stop.set()
            await running
        try:
            declared = await channel.declare_queue(f"mission-{tag}", passive=True)
            pending = declared.declaration_result.message_count
            assert pending is not None, "a passive Queue.Declare's DeclareOk carries the message count"
            await declared.delete(if_unused=False, if_empty=False)
        finally:
            await connection.close()
        return status, [*dead.messages, *([None] * pending)], sim

    status, outcome, sim = run(scenario(), 60)
    route = status["routes"][f"mission-{tag}"]
    assert route["delivered"] == 0 and route["sink_errors"] == 0 and route["retries"] == 0, route
    assert len(outcome) == 1 and outcome[0] is not None, "dead-lettered once, not queued again"
    error = outcome[0].headers["x-rabbitros-error"]
    assert "vehicle 1/1, last heard " in error and "the mission upload (3 items) got no answer to MISSION_COUNT after 3 sends" \
        in error and "within command_timeout 0.6 s" in error, error
    assert sim.stats.missions_accepted == 0


# -- every outcome, the sink against the simulated vehicle on UDP ---------------------------------


def test_mission_items_mapping_legacy_requests_and_bad_input() -> None:
    """Explicit items (names or numbers) give full control; a vehicle asking with the legacy
    MISSION_REQUEST gets MISSION_ITEM_INT; items the protocol cannot carry are rejected."""
    mapping = compile_mapping(
        "{items: [{command: 'MAV_CMD_NAV_TAKEOFF', frame: 'MAV_FRAME_GLOBAL_RELATIVE_ALT_INT', z: `10`}, "
        "{command: 'MAV_CMD_NAV_WAYPOINT', frame: `6`, x: deg_to_deg_e7(lat), y: deg_to_deg_e7(lon), z: `10`, param2: `0.5`}, "
        "{command: 'MAV_CMD_DO_SET_SERVO', frame: 'MAV_FRAME_MISSION', param1: `9`, param2: `1900`}, "
        "{command: `20`, frame: `2`, autocontinue: `0`}]}")
    assert mapping is not None

    async def scenario() -> None:
        async with gcs_and_vehicle(legacy_requests=True) as (gcs, sim):
            sink = gcs.sink("items", {"mission": "upload", "target_system": 1})
            await sink.send(outbound(mapping({"lat": -22.5, "lon": -47.25})))
            assert [(i["command"], i["frame"], i["autocontinue"]) for i in sim.autopilot.mission] == [
                (22, 6, 1), (16, 6, 1), (183, 2, 1), (20, 2, 0)]
            assert (sim.autopilot.mission[1]["x"], sim.autopilot.mission[1]["param2"]) == (-225000000, 0.5)
            assert sim.autopilot.mission[2]["param2"] == 1900.0
            for fields, error in (({"items": [{"command": 16, "lat": 1}]}, "unknown field(s) lat"),
                                  ({"items": [{"command": 16, "x": 1, "z": 10}]}, "items[0]: no frame"),
                                  ({"items": [{"command": "MAV_CMD_FLY_TO_THE_MOON", "frame": 6}]}, "not a MAV_CMD name"),
                                  ({"items": [{"command": 16, "frame": 6, "x": 2**40}]}, "outside int32_t"),
                                  ({"agent_id": "uav1", "waypoints": [{"lat": 1.0, "lon": 2.0}]},
                                   "'waypoints[0]' gives no altitude: set one of 'alt_msl'"),
                                  ({"agent_id": "uav1", "waypoints": []}, "no waypoints"),
                                  ({"items": [{"command": 16, "frame": 6, "x": 1}, {"command": 16, "frame": 6, "param4": None}]},
                                   "field 'items[1].param4' is null"),
                                  ({"items": [{"command": 16, "lon": 1}]}, "unknown field(s) lon (fields"),
                                  ({"items": [{"command": 16, "parma1": 1}]}, "parma1; did you mean 'param1'?"),
                                  ({"agent_id": "uav1", "waypoints": [{"lat": 1.0, "lon": 2.0, "alt_rel": None}]},
                                   "field 'waypoints[0].alt_rel' is null")):
                with pytest.raises(MessageRejected, match=re.escape(error)):
                    await sink.send(outbound(fields))
            assert gcs.stats["missions_uploaded"] == 1
            assert len(sim.autopilot.mission) == 4, "nothing of the refused missions was uploaded"

    run(scenario(), 30)


def test_commands_in_progress_temporarily_rejected_and_silent() -> None:
    async def scenario() -> None:
        results = ["MAV_RESULT_IN_PROGRESS", "MAV_RESULT_ACCEPTED", "MAV_RESULT_TEMPORARILY_REJECTED",
                   "MAV_RESULT_ACCEPTED", "silent"]
        async with gcs_and_vehicle(command_results=results) as (gcs, sim):
            options = {"message": "COMMAND_LONG", "target_system": 1, "acknowledged": True,
                       "timeout": 0.3, "retries": 2, "retry_delay": 0.1}
            sink = gcs.sink("cmd", options)
            started = time.monotonic()
            await sink.send(outbound({"command": 400, "param1": 1}))  # IN_PROGRESS, then ACCEPTED after 0.5 s
            assert time.monotonic() - started >= 0.45 and sim.autopilot.armed
            await sink.send(outbound({"command": "MAV_CMD_DO_SET_SERVO", "param1": 9, "param2": 1500}))
            assert [c["confirmation"] for c in sim.autopilot.commands[1:]] == [0, 1], "resent after TEMPORARILY_REJECTED"
            with pytest.raises(MessageRejected, match="MAV_CMD_NAV_RETURN_TO_LAUNCH not acknowledged after 3 sends within "
                                                      "command_timeout 0.9 s"):
                await sink.send(outbound({"command": 20}))
            assert [c["confirmation"] for c in sim.autopilot.commands[3:]] == [0, 1, 2], "confirmation counts resends"
            assert gcs.stats["commands_acknowledged"] == 2 and gcs.stats["command_timeouts"] == 1

    run(scenario(), 30)


def test_a_transaction_waits_for_a_vehicle_not_heard_yet() -> None:
    """The sink waits (within vehicle_timeout) for the target's HEARTBEAT; the connection
    sends its own HEARTBEAT and lists the vehicles it heard."""
    async def scenario() -> None:
        port = free_udp_port()
        gcs = mavlink.TRANSPORT.connect("gcs", {"url": f"udpin:127.0.0.1:{port}", "source_system": 250})
        await gcs.open()
        try:
            sink = gcs.sink("m", {"mission": "upload", "target_system": 1, "vehicle_timeout": 0.3})
            with pytest.raises(EndpointError, match="vehicle 1/1 has not been heard"):
                await sink.send(outbound(canonical_mission(WEEDS)))
            sink = gcs.sink("m", {"mission": "upload", "target_system": 1, "vehicle_timeout": 10})
            upload = asyncio.create_task(sink.send(outbound(canonical_mission(WEEDS))))
            await asyncio.sleep(0.3)  # quiet window: the upload waits for the unheard vehicle (the behaviour under test)
            assert not upload.done()
            sim = SimVehicle(f"udpout:127.0.0.1:{port}")
            stop = asyncio.Event()
            running = asyncio.create_task(sim.run(stop))
            heartbeats: list[Any] = []
            inner = sim.port.on_message

            def on_message(msg: Any) -> None:
                if msg.get_type() == "HEARTBEAT":
                    heartbeats.append(msg)
                inner(msg)

            sim.port.on_message = on_message
            await asyncio.wait_for(upload, 10)
            await wait_for(lambda: bool(heartbeats), 3, "the engine's HEARTBEAT")
            stop.set()
            await running
        finally:
            await gcs.close()
        assert len(sim.autopilot.mission) == len(WEEDS)
        assert heartbeats[0].type == mavlink2.MAV_TYPE_GCS and heartbeats[0].get_srcSystem() == 250
        assert [(v["system_id"], v["component_id"], v["autopilot"], v["type"]) for v in gcs.vehicles] == \
            [(1, 1, "MAV_AUTOPILOT_GENERIC", "MAV_TYPE_QUADROTOR")]
        assert gcs.stats["vehicles_heard"] == 1

    run(scenario(), 30)


def test_sink_options_are_checked_before_connecting() -> None:
    check = mavlink.TRANSPORT.check_sink
    assert list(check({"mission": "upload", "target_system": 1, "home_placeholder": True}, None)) == []
    assert list(check({"mission": "download"}, None)) == [("mission", "mission must be 'upload'")]
    assert list(check({"mission": "upload", "message": "COMMAND_LONG"}, None)) == \
        [("message", "'message' is not used by a mission sink: it applies to message sources and sinks (not json_tunnel)")]
    assert list(check({"mission": "upload", "retries": -1}, None)) == [("retries", "retries must be an integer >= 0")]
    assert list(check({"mission": "upload"}, "{waypoints: waypoints}")) == []  # a canonical mission's shape
    assert "did you mean 'waypoints'" in str(list(check({"mission": "upload"}, "{wayponts: waypoints}")))
    assert "not both" in str(list(check({"mission": "upload"}, "{items: a, waypoints: b}")))
    assert list(check({"message": "HEARTBEAT", "acknowledged": True}, None)) == \
        [("acknowledged", "acknowledged applies to COMMAND_LONG and COMMAND_INT sinks")]
    assert list(check({"message": "COMMAND_LONG", "timeout": 1}, None)) == \
        [("timeout", "'timeout' is not used by a message sink: it applies to acknowledged commands "
                     "(acknowledged: true) and missions (mission: upload)")]


def test_enum_functions_in_mappings() -> None:
    mapping = compile_mapping("{state: mav_enum(system_status, 'MAV_STATE'), unknown: mav_enum(`99`, 'MAV_STATE'), "
                              "arm: mav_enum_value('MAV_CMD_COMPONENT_ARM_DISARM', 'MAV_CMD'), "
                              "short: mav_enum_value('ACTIVE', 'MAV_STATE'), flags: mav_flags(base_mode, 'MAV_MODE_FLAG')}")
    assert mapping is not None
    assert mapping({"system_status": 4, "base_mode": 129}) == {
        "state": "MAV_STATE_ACTIVE", "unknown": None, "arm": 400, "short": 4,
        "flags": ["MAV_MODE_FLAG_CUSTOM_MODE_ENABLED", "MAV_MODE_FLAG_SAFETY_ARMED"]}
    bad = compile_mapping("mav_enum_value('ARM', 'MAV_CMD')")
    assert bad is not None
    with pytest.raises(ValueError, match="'ARM' is not a MAV_CMD name"):
        bad({})
    with pytest.raises(ValueError, match="unknown MAVLink enum 'MAV_NOPE'"):
        compile_mapping("mav_enum(`1`, 'MAV_NOPE')")({})


def test_a_stale_accepted_ack_does_not_complete_an_upload() -> None:
    """A MISSION_ACK ACCEPTED that arrives before every item was asked for (a late repeat of
    the previous upload's ACK) must not acknowledge this upload."""
    async def scenario() -> None:
        async with gcs_and_vehicle(mission_result="silent") as (gcs, sim):
            sink = gcs.sink("m", {"mission": "upload", "target_system": 1, "timeout": 0.3, "retries": 1})
            await gcs.wait_for_vehicle(1, 1, asyncio.get_running_loop().time() + 5)
            upload = asyncio.create_task(sink.send(outbound(canonical_mission(WEEDS))))
            await asyncio.sleep(0.1)  # settle: the upload's MISSION_COUNT goes out before the stale ACK (the race under test)
            sim.port.post(mavlink2.MAVLink_mission_ack_message(255, 190, mavlink2.MAV_MISSION_ACCEPTED, 0))
            with pytest.raises(MessageRejected, match=r"the mission upload \(3 items\) got no answer to MISSION_COUNT"):
                await upload

    run(scenario(), 20)
