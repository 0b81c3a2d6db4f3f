"""The agents table (issue 20): routes name vehicles ``uav2`` instead of ``2``.

Against three pymavlink vehicles (systems 1-3) on one UDP link and a real RabbitMQ: a route per
agent from ``for_each: agents`` (the robot in the table, without a system id, gets none), one
fleet route whose ``meta('agent')`` names the vehicle heard, a command route whose
``target_system: "{vehicle}"`` reads an agent's name from the message (a name no agent has is
dead-lettered naming the field, never sent). At load: unknown names with a did-you-mean, and an
edited entry changes only the routes that use it."""

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

AGENTS = """\
agents:
  uav1: {connection: radio, system_id: 1}
  uav2: {connection: radio, system_id: 2}
  uav3: {connection: radio, system_id: 3}
  robot1: {namespace: /robot1}
"""

ROUTES = """
connections:
  gcs: {{amqp: "{url}"}}
  radio: {{mavlink: "udpin:127.0.0.1:{port}", heartbeat: 1}}
routes:
  - name: "{{agent}}-position"
    for_each: agents
    source: {{mavlink: {{connection: "{{connection}}", message: GLOBAL_POSITION_INT, system_id: "{{system_id}}"}}}}
    mapping: "{{vehicle: meta('agent'), route: 'own', lat: lat}}"
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: {outbox}, routing_key: "own.{{agent}}"}}}}
  - name: fleet-position
    source: {{mavlink: {{message: GLOBAL_POSITION_INT}}}}
    mapping: "{{vehicle: meta('agent'), system: meta('system_id'), lat: lat}}"
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: {outbox}, routing_key: "fleet.{{vehicle}}"}}}}
  - name: fleet-commands
    source: {{amqp: {{connection: gcs, exchange: {commands}, binding_key: cmd, queue: {queue}}}}}
    schema: raw_json
    sink:
      mavlink: {{message: COMMAND_LONG, acknowledged: true, target_system: "{{vehicle}}", target_component: 1, timeout: 1.0}}
      mapping: "{{command: `400`, param1: `1`, param2: param}}"
  - name: arm-uav3
    source: {{amqp: {{connection: gcs, exchange: {commands}, binding_key: "arm3", queue: {queue}-arm3}}}}
    schema: raw_json
    sink:
      mavlink: {{message: COMMAND_LONG, acknowledged: true, target_system: uav3, target_component: 1, timeout: 1.0}}
      mapping: "{{command: `400`, param1: `1`, param2: param}}"
"""


def _directory(tmp_path: Path, **names: object) -> Path:
    directory = tmp_path / "routes"
    directory.mkdir()
    (directory / "agents.yaml").write_text(AGENTS)
    (directory / "fleet.yaml").write_text(ROUTES.format(**names))
    return directory


def test_routes_name_vehicles_from_the_agents_table(tmp_path: Path, schemas_dir: Path, amqp_url: str) -> None:
    tag = uuid.uuid4().hex[:8]
    names = {"outbox": f"out-{tag}", "commands": f"cmd-{tag}", "queue": f"q-{tag}"}
    port = free_udp_port()
    directory = _directory(tmp_path, url=amqp_url, port=port, **names)
    vehicles = {system_id: FleetVehicle(system_id, port) for system_id in (1, 2, 3)}
    wanted = ["uav1", "uav2", "uav3", "uav2", "uav9"]  # uav9: no such agent (dead-lettered)

    async def scenario() -> tuple[list[dict], list[aio_pika.abc.AbstractIncomingMessage], list[str]]:
        engine = Engine(directory, schemas_dir)
        async with started_with_client(engine, amqp_url) as connection:
            running = sorted(engine.runners)
            channel = await connection.channel()
            positions = await Collector.bind(channel, names["outbox"], "#")
            dead = await Collector.bind(channel, "rabbitros.dead-letter", "fleet-commands")
            for vehicle in vehicles.values():
                vehicle.start()
            await wait_for(lambda: len({m.routing_key for m in positions.messages}) >= 6, 20, "positions under 6 routing keys",
                           lambda: sorted({str(m.routing_key) for m in positions.messages}))
            exchange = await channel.declare_exchange(names["commands"], aio_pika.ExchangeType.TOPIC, durable=True)
            for number, agent in enumerate(wanted):
                await exchange.publish(aio_pika.Message(json.dumps({"param": number, "vehicle": agent}).encode()), "cmd")
            await exchange.publish(aio_pika.Message(json.dumps({"param": 9}).encode()), "arm3")
            await wait_for(lambda: sum(len(v.received()) for v in vehicles.values()) >= 5, 20, "5 commands at the vehicles",
                           lambda: {agent: len(v.received()) for agent, v in vehicles.items()})
            letters = await dead.wait_for(1)
            got = [json.loads(m.body) | {"key": m.routing_key} for m in positions.messages]
        for vehicle in vehicles.values():
            vehicle.stop.set()
        return got, letters, running

    try:
        positions, letters, running = asyncio.run(scenario())
    finally:
        for vehicle in vehicles.values():
            vehicle.stop.set()
            vehicle.join(5)
    assert running == ["arm-uav3", "fleet-commands", "fleet-position", "uav1-position", "uav2-position", "uav3-position"]
    keys = Counter(p["key"] for p in positions)
    assert set(keys) == {"own.uav1", "own.uav2", "own.uav3", "fleet.uav1", "fleet.uav2", "fleet.uav3"}, keys
    for position in positions:
        system = -220000000 - position["lat"]  # each vehicle's own stream
        assert position["vehicle"] == f"uav{system}", position
        assert position["key"].endswith(position["vehicle"]), position
    params = {system_id: sorted({int(msg.param2) for msg in vehicle.received()})  # at least once: a lost ack repeats
              for system_id, vehicle in vehicles.items()}
    assert params == {1: [0], 2: [1, 3], 3: [2, 9]}, params
    assert [vehicle.foreign for vehicle in vehicles.values()] == [0, 0, 0]
    assert [m.headers["x-rabbitros-stage"] for m in letters] == ["sink"]
    error = header_text(letters[0], "x-rabbitros-error")
    assert "target_system: field 'vehicle' is 'uav9', which is no agent on this connection" in error, error


def test_unknown_agents_are_check_errors(tmp_path: Path, schemas_dir: Path) -> None:
    directory = _directory(tmp_path, url="amqp://localhost:1/", port=14995, outbox="o", commands="c", queue="q")
    fleet = directory / "fleet.yaml"
    fleet.write_text(fleet.read_text().replace("target_system: uav3,", "target_system: uva3,"))
    (directory / "more.yaml").write_text("agents:\n  uav1: {system_id: 7}\n")
    with pytest.raises(RoutesInvalid) as caught:
        load_routes(directory, SchemaRegistry(schemas_dir))
    problems = [str(p) for p in caught.value.problems]
    assert any("route 'arm-uav3': sink: target_system: unknown agent 'uva3'; did you mean 'uav3'?" in p for p in problems), problems
    assert any(p.startswith(f"{directory / 'more.yaml'}:2: agent 'uav1' is already defined at {directory / 'agents.yaml'}:2")
               for p in problems), problems
    (directory / "more.yaml").unlink()
    (directory / "agents.yaml").unlink()
    fleet.write_text(fleet.read_text().replace("  - name: \"{agent}-position\"\n    for_each: agents\n", "  - name: x\n"))
    with pytest.raises(RoutesInvalid) as caught:
        load_routes(directory, SchemaRegistry(schemas_dir))
    problems = [str(p) for p in caught.value.problems]
    assert any("route 'fleet-position': meta('agent'): the name of the agent heard needs the agents table" in p
               for p in problems), problems


def test_an_edited_agent_changes_only_the_routes_that_use_it(tmp_path: Path, schemas_dir: Path) -> None:
    directory = _directory(tmp_path, url="amqp://localhost:1/", port=14994, outbox="o", commands="c", queue="q")
    schemas = SchemaRegistry(schemas_dir)
    before = {name: route.fingerprint for name, route in load_routes(directory, schemas).routes.items()}
    (directory / "agents.yaml").write_text(AGENTS.replace("robot1: {namespace: /robot1}", "robot1: {namespace: /robot9}"))
    assert {name: route.fingerprint for name, route in load_routes(directory, schemas).routes.items()} == before
    (directory / "agents.yaml").write_text(AGENTS.replace("uav1: {connection: radio, system_id: 1}",
                                                          "uav1: {connection: radio, system_id: 4}"))
    after = load_routes(directory, schemas).routes
    changed = sorted(name for name, route in after.items() if route.fingerprint != before[name])
    # uav1's own route, and the two that look any agent on the radio up (meta('agent'), "{vehicle}")
    assert changed == ["fleet-commands", "fleet-position", "uav1-position"], changed
    assert after["uav1-position"].source.options.system_id == 4


def test_route_tests_resolve_agent_names(tmp_path: Path, schemas_dir: Path) -> None:
    directory = _directory(tmp_path, url="amqp://localhost:1/", port=14993, outbox="o", commands="c", queue="q")
    (directory / "fleet.test.yaml").write_text("""
tests:
  - route: fleet-commands
    input: {vehicle: uav2, param: 5}
    expect_sink: {command: 400, param1: 1, param2: 5}
  - route: fleet-commands
    input: {vehicle: uav9, param: 5}
    expect_error: sink
  - route: fleet-position
    input: {lat: 1}
    meta: {agent: uav3, system_id: 3}
    expect: {vehicle: uav3, system: 3, lat: 1}
    expect_routing_key: fleet.uav3
""")
    from engine.ops.route_tests import load_checked, run_tests

    schemas = SchemaRegistry(schemas_dir)
    config, cases, problems, _ = load_checked(directory, schemas)
    assert config is not None and not problems, problems
    assert [r.reason for r in run_tests(cases, config, schemas)] == ["", "", ""]


def test_a_new_agent_adds_its_routes_and_leaves_the_others_running(tmp_path: Path, schemas_dir: Path) -> None:
    from engine.running.plan import plan_reload

    directory = _directory(tmp_path, url="amqp://localhost:1/", port=14992, outbox="o", commands="c", queue="q")
    schemas = SchemaRegistry(schemas_dir)
    before = load_routes(directory, schemas)
    (directory / "agents.yaml").write_text(AGENTS + "  uav4: {connection: radio, system_id: 4}\n  robot2: {namespace: /r2}\n")
    plan = plan_reload(before, load_routes(directory, schemas))
    assert plan.add == ("uav4-position",) and plan.remove == ()
    assert set(plan.keep) == {"arm-uav3", "uav1-position", "uav2-position", "uav3-position"}, plan
    # the two routes that look any agent on the radio up take the new table: the source that names
    # the agent heard is replaced, the sink that resolves names gets a new pipeline
    assert (plan.replace_source, plan.swap_pipeline) == (("fleet-position",), ("fleet-commands",)), plan
