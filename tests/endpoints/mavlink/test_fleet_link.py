"""Many vehicles on one link (issue 20): twelve pymavlink vehicles (systems 1-12) share one UDP
link. One source without ``system_id`` carries every vehicle's telemetry with
``meta('system_id')`` to a routing key per vehicle; one acknowledged command sink with
``target_system: "{vehicle}"`` sends each command to the vehicle its message names, which
acknowledges it; the link writes it only to the UDP peer that vehicle was heard from."""

from __future__ import annotations

import asyncio
import json
import uuid
from collections import Counter
from pathlib import Path

import aio_pika
import pytest

from engine.common.schemas import SchemaRegistry
from engine.language.routes import RoutesInvalid, load_routes
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector, header_text, started_with_client
from tests.support.udp_vehicle import FleetVehicle, free_udp_port
from tests.support.waiting import wait_for

ROUTES = """
connections:
  gcs: {{amqp: "{url}"}}
  radio: {{mavlink: "udpin:127.0.0.1:{port}", heartbeat: 1}}
routes:
  - name: fleet-position
    source: {{mavlink: {{connection: radio, message: GLOBAL_POSITION_INT}}}}
    mapping: "{{vehicle: meta('system_id'), link: meta('connection'), seq: time_boot_ms, lat: lat}}"
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: {outbox}, routing_key: "uav.{{vehicle}}.position"}}}}
  - name: fleet-commands
    source: {{amqp: {{connection: gcs, exchange: {commands}, binding_key: "#", queue: {queue}}}}}
    schema: raw_json
    sink:
      mavlink: {{connection: radio, message: COMMAND_LONG, acknowledged: true, target_system: "{{vehicle}}", target_component: 1,
                timeout: 0.3}}
      mapping: "{{command: `400`, param1: `1`, param2: param}}"
"""


def test_twelve_vehicles_on_one_udp_link(tmp_path: Path, schemas_dir: Path, amqp_url: str) -> None:
    tag = uuid.uuid4().hex[:8]
    names = {"outbox": f"out-{tag}", "commands": f"cmd-{tag}", "queue": f"q-{tag}"}
    port = free_udp_port()
    directory = tmp_path / "routes"
    directory.mkdir()
    (directory / "fleet.yaml").write_text(ROUTES.format(url=amqp_url, port=port, **names))
    # more vehicles than the 8 peers a udpin link once remembered: a command for a forgotten one went
    # to the 8 others and not to it
    vehicles = {system_id: FleetVehicle(system_id, port, rate=10.0) for system_id in range(1, 13)}
    wanted = [1, 2, 3, 2, 3, 3, 12, 7, 11, 99]  # 99: a message that names no vehicle (dead-lettered)

    async def scenario() -> tuple[list[dict], list[aio_pika.abc.AbstractIncomingMessage]]:
        engine = Engine(directory, schemas_dir)
        async with started_with_client(engine, amqp_url) as connection:
            channel = await connection.channel()
            positions = await Collector.bind(channel, names["outbox"], "uav.#")
            dead = await Collector.bind(channel, "rabbitros.dead-letter", "fleet-commands")
            for vehicle in vehicles.values():
                vehicle.start()
            await positions.wait_for(120)
            exchange = await channel.declare_exchange(names["commands"], aio_pika.ExchangeType.TOPIC, durable=True)
            for number, system_id in enumerate(wanted):
                body = {"param": number} if system_id == 99 else {"param": number, "vehicle": system_id}
                await exchange.publish(aio_pika.Message(json.dumps(body).encode()), "cmd")
            await wait_for(lambda: sum(len(v.received()) for v in vehicles.values()) >= len(wanted) - 1, 20,
                           f"{len(wanted) - 1} commands at the vehicles", lambda: {k: len(v.received()) for k, v in vehicles.items()})
            letters = await dead.wait_for(1)
            got = [json.loads(m.body) | {"key": m.routing_key} for m in positions.messages]
        for vehicle in vehicles.values():
            vehicle.stop.set()
        return got, letters

    try:
        positions, letters = asyncio.run(scenario())
    finally:
        for vehicle in vehicles.values():
            vehicle.stop.set()
            vehicle.join(5)
    by_vehicle = Counter(p["vehicle"] for p in positions)
    assert set(by_vehicle) == set(vehicles), by_vehicle
    for position in positions:
        assert position["key"] == f"uav.{position['vehicle']}.position"
        assert position["link"] == "radio"
        assert position["lat"] == -220000000 - position["vehicle"]  # each vehicle's own stream
    for system_id, vehicle in vehicles.items():
        params = sorted(int(msg.param2) for msg in vehicle.received())
        assert params == [n for n, s in enumerate(wanted) if s == system_id], (system_id, params)
        assert all(msg.target_system == system_id and msg.target_component == 1 for msg in vehicle.received())
    # each command went only to the peer its vehicle was heard from
    assert [vehicle.foreign for vehicle in vehicles.values()] == [0] * len(vehicles)
    assert [m.headers["x-rabbitros-stage"] for m in letters] == ["sink"]
    assert "the canonical message has no field 'vehicle'" in header_text(letters[0], "x-rabbitros-error")


def test_check_knows_where_a_field_target_applies(tmp_path: Path, schemas_dir: Path) -> None:
    """Message, command and mission sinks read a ``{field}`` target per message; a JSON tunnel
    names its receiver with a number."""
    routes = ROUTES.format(url="amqp://localhost:1/", port=14998, outbox="o", commands="c", queue="q")
    no_mapping = routes.replace("      mapping: \"{command: `400`, param1: `1`, param2: param}\"\n", "")
    mission = no_mapping.replace("message: COMMAND_LONG, acknowledged: true,", "mission: upload,")
    tunnel = no_mapping.replace("message: COMMAND_LONG, acknowledged: true,", "json_tunnel: true,").replace(
        "                timeout: 0.3", "")
    for name, text in (("mission", mission), ("tunnel", tunnel)):
        directory = tmp_path / name
        directory.mkdir()
        (directory / "fleet.yaml").write_text(text)
        if name == "mission":
            load_routes(directory, SchemaRegistry(schemas_dir))
            continue
        with pytest.raises(RoutesInvalid) as caught:
            load_routes(directory, SchemaRegistry(schemas_dir))
        assert any('target_system: a "{field}" target is read per message by message, command and mission sinks; a '
                   'json_tunnel sink' in p.message for p in caught.value.problems), caught.value.problems


def test_route_tests_read_the_target_from_the_message(tmp_path: Path, schemas_dir: Path) -> None:
    directory = tmp_path / "r"
    directory.mkdir()
    (directory / "fleet.yaml").write_text(ROUTES.format(url="amqp://localhost:1/", port=14997, outbox="o", commands="c", queue="q"))
    (directory / "fleet.test.yaml").write_text("""
tests:
  - route: fleet-commands
    input: {vehicle: 2, param: 5}
    expect_sink: {command: 400, param1: 1, param2: 5}
  - route: fleet-commands
    input: {vehicle: 300, param: 5}
    expect_error: sink
  - route: fleet-position
    input: {time_boot_ms: 7, lat: 1}
    meta: {system_id: 3}
    expect: {vehicle: 3, link: null, seq: 7, lat: 1}
    expect_routing_key: uav.3.position
""")
    from engine.ops.route_tests import load_checked, run_tests

    schemas = SchemaRegistry(schemas_dir)
    config, cases, problems, _ = load_checked(directory, schemas)
    assert config is not None and not problems, problems
    assert [r.reason for r in run_tests(cases, config, schemas)] == ["", "", ""]
