"""Route templates (``for_each``, issue 20): one route written once for a fleet.

Expanded routes are ordinary routes: named with the variables filled in, typed where a value
is exactly ``{var}``, a non-variable ``{field}`` left for the sink, checked with problems at
the template's line, tested, and reloaded one by one (the plan and a running engine whose
``for_each`` file is edited: only the added and removed robots' routes change).
"""

from __future__ import annotations

import asyncio
import json
import uuid
from pathlib import Path

import aio_pika
import pytest

from engine.common.schemas import SchemaRegistry
from engine.language.routes import RoutesInvalid, load_routes
from engine.ops.route_tests import load_checked, run_tests
from engine.running.plan import plan_reload
from engine.running.runtime import Engine
from engine.running.watch import watch_routes
from tests.support.amqp_helpers import Collector
from tests.support.waiting import wait_for

FLEET = """
connections:
  gcs: {amqp: "amqp://localhost:1/"}
  ros: {ros2: {node: fleet}}
  radio: {mavlink: "udpin:127.0.0.1:14999"}
routes:
  - name: "{agent}-battery"
    for_each: agents.yaml
    source: {ros2: {connection: ros, topic: "/{agent}/battery", type: std_msgs/msg/Float32}}
    mapping: "{agent_id: meta('agent'), level: data}"
    schema: raw_json
    sink: {amqp: {connection: gcs, exchange: fleet, routing_key: "battery.{agent}.{level}"}}
  - name: "uav{n}-position"
    for_each: [{n: 1, sys: 1, ex: 7}, {n: 2, sys: 2, ex: 8}]
    source: {mavlink: {connection: radio, message: GLOBAL_POSITION_INT, system_id: "{sys}"}}
    mapping: "{n: meta('n'), lat: lat}"
    schema: raw_json
    sink: {amqp: {connection: gcs, routing_key: "uav{n}.position", exchange: "{ex}"}}
  - name: supervisor
    source: {amqp: {connection: gcs, queue: supervisor}}
    schema: raw_json
    sink: {amqp: {connection: gcs, exchange: out, routing_key: k}}
"""


def _fleet(directory: Path, agents: list[str], routes: str = FLEET) -> Path:
    directory.mkdir(exist_ok=True)
    (directory / "fleet.yaml").write_text(routes)
    (directory / "agents.yaml").write_text("".join(f"- agent: {agent}\n" for agent in agents))
    return directory


@pytest.mark.fast
def test_for_each_expands_into_ordinary_routes(tmp_path: Path, schemas_dir: Path) -> None:
    config = load_routes(_fleet(tmp_path / "r", ["robot1", "robot2"]), SchemaRegistry(schemas_dir))
    assert sorted(config.routes) == ["robot1-battery", "robot2-battery", "supervisor", "uav1-position", "uav2-position"]
    robot = config.routes["robot2-battery"]
    assert robot.source.options.topic == "/robot2/battery"
    assert robot.sink.options.routing_key == "battery.robot2.{level}"  # {level} is no variable: filled at send time
    assert robot.variables == {"agent": "robot2"} and robot.line == 7  # the template's line
    uav = config.routes["uav2-position"]
    assert uav.source.options.system_id == 2  # exactly "{sys}": the item's integer
    assert uav.sink.options.exchange == "8"  # an integer where a string is wanted: its text
    assert config.data_files == frozenset({(tmp_path / "r" / "agents.yaml").resolve()})
    assert config.warnings == ()


TESTS = """
tests:
  - route: robot2-battery
    input: {data: 0.5}
    expect: {agent_id: robot2, level: 0.5}
    expect_routing_key: battery.robot2.0.5
"""


@pytest.mark.fast
def test_expanded_routes_are_tested_by_their_names(tmp_path: Path, schemas_dir: Path) -> None:
    directory = _fleet(tmp_path / "r", ["robot1", "robot2"])
    (directory / "fleet.test.yaml").write_text(TESTS)
    schemas = SchemaRegistry(schemas_dir)
    config, cases, problems, _ = load_checked(directory, schemas)
    assert config is not None and not problems, problems
    assert [r.reason for r in run_tests(cases, config, schemas)] == [""]
    (directory / "fleet.test.yaml").write_text(TESTS.replace("input:", "meta: {agent: robot9}\n    input:"))
    _, _, problems, _ = load_checked(directory, schemas)
    assert [p.message for p in problems] == [
        "meta 'agent' is a template variable of route 'robot2-battery' ('robot2'): the route sets it, a test cannot"]


@pytest.mark.fast
def test_check_reports_template_problems_at_their_lines(tmp_path: Path, schemas_dir: Path) -> None:
    bad = (FLEET.replace("for_each: [{n: 1, sys: 1, ex: 7}, {n: 2, sys: 2, ex: 8}]",
                         "for_each: [{n: 1, sys: 1, ex: 7}, oops, {n-x: 3}]")
           .replace('name: "{agent}-battery"', 'name: "battery"')
           .replace("meta('agent')", "meta('agnet')")
           .replace('name: "uav{n}-position"', 'name: "uav{nn}-position"'))
    directory = _fleet(tmp_path / "r", ["robot1", "robot2"], bad)
    (directory / "spare.yaml").write_text("- agent: robot5\n")  # a list no route names
    with pytest.raises(RoutesInvalid) as caught:
        load_routes(directory, SchemaRegistry(schemas_dir))
    shown = [f"{Path(p.file).name}:{p.line}: {p.message}" for p in caught.value.problems]
    assert "fleet.yaml:14: routes[1].for_each[1]: 'oops' is not an object of template variables" in shown, shown
    assert "fleet.yaml:14: routes[1].for_each[2]: variable name 'n-x' must be a letter or _ then letters, digits, _" in shown, shown
    assert any(s.startswith("fleet.yaml:7: route 'battery' is already defined at") and "must hold a variable" in s for s in shown), shown
    assert any("route 'battery': meta('agnet'): the ros2 source gives no 'agnet'; did you mean 'agent'?" in s for s in shown), shown
    assert "fleet.yaml:13: route name 'uav{nn}-position': {nn} is not a for_each variable (variables: n, sys, ex); did you mean 'n'?" \
        in shown, shown
    assert [f"{Path(w.file).name}: {w.message}" for w in caught.value.warnings] == [
        "spare.yaml: a YAML list, so not a route file; no route names it in for_each (left out)"]

    (directory / "agents.yaml").write_text("- agent: robot1\n- agnet: robot2\n")
    with pytest.raises(RoutesInvalid) as caught:
        load_routes(directory, SchemaRegistry(schemas_dir))
    assert any(p.message == "routes[0].for_each[1] (in agents.yaml): no agent (the route uses {agent}, which other items give)"
               for p in caught.value.problems), caught.value.problems

    (directory / "agents.yaml").unlink()
    with pytest.raises(RoutesInvalid) as caught:
        load_routes(directory, SchemaRegistry(schemas_dir))
    assert any("cannot read for_each file" in p.message for p in caught.value.problems)


@pytest.mark.fast
def test_variable_shadowing_a_canonical_field_is_warned(tmp_path: Path, schemas_dir: Path) -> None:
    routes = FLEET.replace("schema: raw_json\n    sink: {amqp: {connection: gcs, exchange: fleet, routing_key: \"battery",
                           "schema: battery\n    sink: {amqp: {connection: gcs, exchange: fleet, routing_key: \"battery", 1)
    routes = routes.replace("battery.{agent}.{level}", "battery.{agent_id}").replace("- agent: ", "- agent_id: ")
    routes = routes.replace("{agent}", "{agent_id}").replace("meta('agent')", "meta('agent_id')")
    directory = tmp_path / "r"
    directory.mkdir()
    (directory / "fleet.yaml").write_text(routes.replace("{agent_id: meta('agent_id'), level: data}",
                                                         "{agent_id: meta('agent_id'), voltage: data}"))
    (directory / "agents.yaml").write_text("- agent_id: robot1\n")
    config = load_routes(directory, SchemaRegistry(schemas_dir))
    assert [w.message for w in config.warnings] == [
        "route 'robot1-battery': {agent_id} in sink.amqp.routing_key is the for_each variable ('robot1'), not the canonical "
        "field 'agent_id' of battery: the variable wins (rename the variable to read the field at send time)"]


@pytest.mark.fast
def test_editing_the_list_plans_only_the_robots_that_changed(tmp_path: Path, schemas_dir: Path) -> None:
    schemas = SchemaRegistry(schemas_dir)
    directory = _fleet(tmp_path / "r", ["robot1", "robot2", "robot3"])
    before = load_routes(directory, schemas)
    (directory / "agents.yaml").write_text("- agent: robot2\n- agent: robot3\n- agent: robot4\n")
    after = load_routes(directory, schemas)
    plan = plan_reload(before, after)
    assert plan.add == ("robot4-battery",)
    assert plan.remove == ("robot1-battery",)
    assert plan.swap_pipeline == () and plan.replace_source == ()
    assert plan.keep == ("robot2-battery", "robot3-battery", "supervisor", "uav1-position", "uav2-position")

    (directory / "agents.yaml").write_text("# every robot left the farm\n")
    emptied = plan_reload(after, load_routes(directory, schemas))
    assert emptied.remove == ("robot2-battery", "robot3-battery", "robot4-battery") and emptied.add == ()


LIVE = """
connections:
  gcs: {{amqp: "{url}"}}
routes:
  - name: "{{agent}}-fix"
    for_each: ../agents.yaml
    source: {{amqp: {{connection: gcs, exchange: {inbox}, binding_key: "{{agent}}.fix", queue: "{tag}-{{agent}}"}}}}
    mapping: "{{agent: meta('agent'), key: meta('routing_key'), lat: lat}}"
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: {outbox}, routing_key: "fix.{{agent}}"}}}}
"""


def test_a_for_each_file_edited_while_the_engine_runs(tmp_path: Path, schemas_dir: Path, amqp_url: str) -> None:
    """The file lives outside the routes directory: the engine watches it (RoutesConfig.data_files)."""
    tag = uuid.uuid4().hex[:8]
    names = {"inbox": f"in-{tag}", "outbox": f"out-{tag}"}
    directory = tmp_path / "routes"
    directory.mkdir()
    (directory / "fleet.yaml").write_text(LIVE.format(url=amqp_url, tag=tag, **names))
    agents = tmp_path / "agents.yaml"
    agents.write_text("- agent: robot1\n- agent: robot2\n")

    async def scenario() -> None:
        engine = Engine(directory, schemas_dir)
        await engine.start()
        stop = asyncio.Event()
        reloads: list[bool] = []

        async def reload() -> None:
            reloads.append(await engine.reload())

        watcher = asyncio.create_task(watch_routes(directory, lambda: asyncio.ensure_future(reload()), stop,
                                                   schemas_dir, engine.key_files))
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            output = await Collector.bind(channel, names["outbox"], "fix.#")
            inbox = await channel.declare_exchange(names["inbox"], aio_pika.ExchangeType.TOPIC, durable=True)

            async def send(agent: str, lat: float) -> None:
                await inbox.publish(aio_pika.Message(json.dumps({"lat": lat}).encode()), f"{agent}.fix")

            await send("robot1", 1.0)
            await send("robot2", 2.0)
            await output.wait_for(2)
            kept = engine.runners["robot2-fix"]
            assert engine.status()["routes"]["robot2-fix"]["generation"] == 1

            agents.write_text("- agent: robot2\n- agent: robot3\n")
            await wait_for(lambda: "robot3-fix" in engine.runners, 20, "the route robot3-fix added by the reload",
                           lambda: (sorted(engine.runners), reloads))
            assert sorted(engine.runners) == ["robot2-fix", "robot3-fix"], reloads
            status = engine.status()["routes"]
            assert status["robot3-fix"]["generation"] == 2
            assert status["robot2-fix"]["generation"] == 1  # untouched: same runner, same pipeline
            assert engine.runners["robot2-fix"] is kept

            await send("robot2", 2.5)
            await send("robot3", 3.0)
            received = await output.wait_for(4)
        finally:
            stop.set()
            await connection.close()
            await asyncio.wait_for(watcher, 10)
            await engine.stop()
        got = sorted((m.routing_key, json.loads(m.body)["agent"], json.loads(m.body)["key"], json.loads(m.body)["lat"])
                     for m in received)
        assert got == [("fix.robot1", "robot1", "robot1.fix", 1.0), ("fix.robot2", "robot2", "robot2.fix", 2.0),
                       ("fix.robot2", "robot2", "robot2.fix", 2.5), ("fix.robot3", "robot3", "robot3.fix", 3.0)]

    asyncio.run(scenario())
