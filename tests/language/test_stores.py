"""Remembered values (engine/language/stores.py): ``remember:`` writes a named latest-value store once the
sink accepted a message, ``recall('NAME', key)`` reads it, ``sequence()`` counts per route.

Checked at load (a store no route remembers into, a memory sink without remember, two routes
giving one store different meanings), given by route tests as ``remembered:``, and written on
acceptance only, through a real route (MQTT -> memory and MQTT -> MQTT on a private mosquitto):
a message the schema refuses is never remembered, and a reload keeps both the store and the count.
"""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

import pytest

from engine.common.options import parse
from engine.common.placeholders import MappingError
from engine.common.schemas import SchemaRegistry
from engine.endpoints.mqtt.broker import LocalMosquitto
from engine.language.mapping import compile_mapping
from engine.language.routes import RoutesInvalid, load_routes
from engine.language.stores import RememberOptions, Remembers, Stores
from engine.ops.route_tests import load_checked, run_tests
from engine.running.pipeline import Pipeline
from engine.running.runtime import Engine
from tests.support.repo import REPO

from tests.endpoints.mqtt.test_mqtt import Subscriber, publish
from tests.support.waiting import wait_for

SCHEMAS = SchemaRegistry(REPO / "schemas")


@pytest.mark.fast
def test_recall_reads_the_store_by_key_and_sequence_counts_per_route() -> None:
    stores = Stores()
    stores.store("positions").put("uav1", {"x": 1.0})
    mapping = compile_mapping("{n: sequence(), x: recall('positions', agent).x, other: recall('positions', 'uav2')}",
                              stores=stores, route="r")
    assert mapping({"agent": "uav1"}) == {"n": 1, "x": 1.0, "other": None}
    again = compile_mapping("{n: sequence()}", stores=stores, route="r")  # a reload's new generation
    assert again({}) == {"n": 2}
    assert compile_mapping("{n: sequence()}", stores=stores, route="other")({}) == {"n": 1}
    with pytest.raises(MappingError, match="store name in quotes"):
        compile_mapping("recall(name, agent)")
    stores.store("positions").max_age_ns = 1  # a value older than max_age is not given any more
    time.sleep(0.001)  # pacing: the stored value grows older than max_age (1 ns)
    assert mapping({"agent": "uav1"})["x"] is None


ROUTES = """
connections:
  field: {mqtt: "mqtt://localhost:1"}
routes:
  - name: positions-in
    source: {mqtt: {connection: field, topic: "farm/+/position"}}
    schema: raw_json
    remember: {store: positions, per: agent}
    sink: {memory: {}}
  - name: status-out
    source: {mqtt: {connection: field, topic: "farm/+/battery"}}
    mapping: "{agent: agent, n: sequence(), charge: charge, x: recall('positions', agent).x}"
    schema: raw_json
    sink: {mqtt: {connection: field, topic: "farm/{agent}/status"}}
"""


def _write(directory: Path, routes: str, tests: str | None = None) -> Path:
    directory.mkdir(exist_ok=True)
    (directory / "routes.yaml").write_text(routes)
    if tests is not None:
        (directory / "routes.test.yaml").write_text(tests)
    return directory


@pytest.mark.fast
def test_check_refuses_unknown_stores_a_memory_sink_without_remember_and_two_meanings(tmp_path: Path) -> None:
    bad = (ROUTES.replace("recall('positions', agent)", "recall('position', agent)")
           .replace("    remember: {store: positions, per: agent}\n", "")
           + """  - name: more-positions
    source: {mqtt: {connection: field, topic: "farm/+/fix"}}
    schema: raw_json
    remember: {store: fixes, per: agent}
    sink: {memory: {}}
  - name: fixes-by-id
    source: {mqtt: {connection: field, topic: "farm/+/fix2"}}
    schema: raw_json
    remember: {store: fixes, per: id}
    sink: {memory: {}}
""")
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(_write(tmp_path / "bad", bad), SCHEMAS)
    messages = [problem.message for problem in invalid.value.problems]
    assert any("route 'positions-in': a memory sink delivers nowhere: the route needs remember: {store: NAME}" in m
               for m in messages), messages
    assert any("route 'status-out': recall('position'): no route remembers into store 'position'" in m for m in messages), messages
    assert any("store 'fixes': per 'id' differs from 'agent'" in m for m in messages), messages
    config = load_routes(_write(tmp_path / "good", ROUTES), SCHEMAS)
    assert config.routes["positions-in"].remember is not None


@pytest.mark.fast
def test_route_tests_give_what_the_stores_hold(tmp_path: Path) -> None:
    tests = """
tests:
  - route: status-out
    input: {agent: uav1, charge: 80}
    remembered: {positions: {uav1: {agent: uav1, x: 4.5}}}
    expect: {agent: uav1, n: 1, charge: 80, x: 4.5}
  - route: status-out
    input: {agent: uav1, charge: 79}
    expect: {agent: uav1, n: 1, charge: 79, x: null}
  - route: status-out
    input: {agent: uav1, charge: 79}
    remembered: {positons: {uav1: {}}}
    expect: {agent: uav1, n: 1, charge: 79, x: null}
"""
    config, cases, problems, _ = load_checked(_write(tmp_path, ROUTES, tests), SCHEMAS)
    assert [p.message for p in problems] == ["remembered: no route remembers into store 'positons'; did you mean 'positions'?"]
    assert config is not None
    assert [r.passed for r in run_tests(cases, config, SCHEMAS)] == [True, True]


def test_a_route_remembers_what_its_sink_accepted_and_a_reload_keeps_stores_and_counts(
        tmp_path: Path, mosquitto: LocalMosquitto, monkeypatch: pytest.MonkeyPatch) -> None:
    """Positions remembered once their sink accepted them: one its sink refuses (its topic
    needs the agent it lacks) is not, though it converted; a status route reads them, and an
    edit of it (a reload restarting it) keeps counting and knowing."""
    monkeypatch.setenv("HOME", str(tmp_path))  # the dead letter's spool
    routes = ROUTES.replace("mqtt://localhost:1", mosquitto.url).replace(
        "sink: {memory: {}}", 'sink: {mqtt: {connection: field, topic: "farm/{agent}/seen"}}', 1)
    directory = _write(tmp_path / "routes", routes)
    schemas_dir = REPO / "schemas"

    async def scenario() -> list[dict[str, object]]:
        engine = Engine(directory, schemas_dir)
        await engine.start()
        try:
            async with Subscriber(mosquitto, "farm/+/status") as out:
                await publish(mosquitto, [("farm/uav1/position", {"agent": "uav1", "x": 1.5}),
                                          ("farm/uav2/position", {"x": 9})])  # no agent for its topic: a sink dead letter

                def settled() -> bool:
                    route = engine.status()["routes"]["positions-in"]
                    return route["delivered"] == 1 and route["failed"] == 1
                await wait_for(settled, 20, "one position delivered, one dead-lettered")
                assert engine.status()["stores"] == {"positions": 1}  # remembered at conversion, it would be 2 (key null)
                await publish(mosquitto, [("farm/uav1/battery", {"agent": "uav1", "charge": 80})])
                await out.wait_for(1)
                (directory / "routes.yaml").write_text(routes.replace("charge: charge", "charge: charge, edited: `true`"))
                await engine.reload()
                await publish(mosquitto, [("farm/uav1/battery", {"agent": "uav1", "charge": 79})])
                await out.wait_for(2)
                return [json.loads(m.payload) for m in out.messages]
        finally:
            await engine.stop()

    first, second = asyncio.run(asyncio.wait_for(scenario(), 60))
    assert first == {"agent": "uav1", "n": 1, "charge": 80, "x": 1.5}
    assert second == {"agent": "uav1", "n": 2, "charge": 79, "x": 1.5, "edited": True}


@pytest.mark.fast
def test_a_message_refused_after_its_mapping_is_remembered_when_failed_with_the_stage(tmp_path: Path) -> None:
    """``remember ... when: failed`` reads the canonical message its mapping gave when the schema,
    ``when:`` or the sink mapping refused it (the runner's Dead carries it to the dead-lettering,
    engine/running/dead_lettering.py; a route test applies it with ``expect_error`` and
    ``expect_remembered``): a VDA 5050 order refused by its schema is reported with its headerId.
    The engine's own path is driven by tests/examples/test_vda5050_master.py."""
    routes = ROUTES.replace("""    remember: {store: positions, per: agent}
    sink: {memory: {}}""", """    remember: {store: positions, per: agent}
    sink: {memory: {}}
  - name: commands-in
    source: {mqtt: {connection: field, topic: "farm/+/command"}}
    schema: command
    remember:
      - {store: refusals, per: agent, when: failed, value: "{agent: agent, id: id, why: meta('failure')}"}
    sink: {mqtt: {connection: field, topic: "farm/out"}}
    """, 1)
    tests = """
tests:
  - route: commands-in
    input: {agent: uav1, id: 7}
    expect_error: schema
    expect_remembered: {refusals: {uav1: {agent: uav1, id: 7, why: 'schema: schema command.v1: $: "agent_id" is a required property'}}}
"""
    config, cases, problems, _ = load_checked(_write(tmp_path, routes, tests), SCHEMAS)
    assert [p.message for p in problems] == [] and config is not None
    [result] = run_tests(cases, config, SCHEMAS)
    assert result.passed, (result.reason, result.diff)


@pytest.mark.fast
def test_a_pipeline_without_stores_recalls_nothing() -> None:
    """``check`` and other callers compile without the engine's stores: a fresh, empty set."""
    assert Pipeline.__dataclass_fields__["remember"].default is None
    assert compile_mapping("recall('x', `1`)")({}) is None


# ------------------------------------------------------------------ keyed state several routes update

@pytest.mark.fast
def test_remember_entries_apply_when_converted_accepted_or_failed_with_a_computed_value() -> None:
    """A list of entries, each at its moment, each with a ``value`` that may read the store's
    value so far: an action state RUNNING when converted, FINISHED when accepted, FAILED with
    meta('failure') when dead-lettered; a null value forgets the key."""
    stores = Stores()
    entries = tuple(parse(RememberOptions, entry) for entry in [
        {"store": "actions", "per": "agent", "when": "converted",
         "value": "upsert(recall('actions', agent) || `[]`, [{id: id, status: 'RUNNING'}], 'id')"},
        {"store": "actions", "per": "agent", "value": "upsert(recall('actions', agent) || `[]`, [{id: id, status: 'FINISHED'}], 'id')"},
        {"store": "actions", "per": "agent", "when": "failed",
         "value": "upsert(recall('actions', agent) || `[]`, [{id: id, status: 'FAILED', why: meta('failure')}], 'id')"},
        {"store": "last", "per": "agent", "when": "converted", "value": "forget != `true` && id || null"}])
    remembers = Remembers.compile(entries, stores, lambda value: compile_mapping(value, None, stores, "r"))
    assert remembers is not None and (len(remembers.converted), len(remembers.accepted), len(remembers.failed)) == (2, 1, 1)
    actions = stores.store("actions")
    remembers.on_converted({"agent": "uav1", "id": "a"}, {})
    remembers.on_converted({"agent": "uav1", "id": "b"}, {})
    assert actions.get("uav1") == [{"id": "a", "status": "RUNNING"}, {"id": "b", "status": "RUNNING"}]
    remembers.on_accepted({"agent": "uav1", "id": "a"}, {})
    remembers.on_failed({"agent": "uav1", "id": "b"}, {"topic": "t"}, "sink: refused")
    assert actions.get("uav1") == [{"id": "a", "status": "FINISHED"}, {"id": "b", "status": "FAILED", "why": "sink: refused"}]
    assert stores.store("last").get("uav1") == "b"
    remembers.on_converted({"agent": "uav1", "id": "c", "forget": True}, {})
    assert stores.store("last").get("uav1") is None and stores.status() == {"actions": 1, "last": 0}


@pytest.mark.fast
def test_check_names_a_bad_remember_value_and_route_tests_expect_what_is_remembered(tmp_path: Path) -> None:
    routes = ROUTES.replace("    remember: {store: positions, per: agent}\n", """    remember:
      - {store: positions, per: agent}
      - {store: trail, per: agent, when: converted, value: "upsert(recall('trail', agent) || `[]`, [{t: t, x: x}], 't')"}
""")
    bad = (routes.replace("recall('trail', agent) || `[]`", "recall('trial', agent) || `[]`").replace("[{t: t, x: x}]", "[{t: t, x: x}")
           .replace("      - {store: positions, per: agent}\n", "      - {store: positions, per: agent, value: \"meta('failure')\"}\n"))
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(_write(tmp_path / "bad", bad), SCHEMAS)
    messages = [f"{problem.file.rsplit('/', 1)[-1]}:{problem.line}: {problem.message}" for problem in invalid.value.problems]
    assert any(m.startswith("routes.yaml:10: route 'positions-in': bad JMESPath") for m in messages), messages
    assert any("routes.yaml:9: route 'positions-in': meta('failure'): the mqtt source gives no 'failure'" in m for m in messages), messages
    tests = """
tests:
  - route: positions-in
    input: {agent: uav1, t: 1, x: 4.5}
    remembered: {trail: {uav1: [{t: 0, x: 4.0}]}}
    expect_remembered: {trail: {uav1: [{t: 0, x: 4.0}, {t: 1, x: 4.5}], uav2: null}, positions: {uav1: {agent: uav1, t: 1, x: 4.5}}}
  - route: positions-in
    input: {agent: uav1, t: 1, x: 4.5}
    expect_remembered: {trail: {uav1: []}}
  - route: status-out
    input: {agent: uav1, charge: 80}
    expect_remembered: {trail: {uav1: []}}
"""
    config, cases, problems, _ = load_checked(_write(tmp_path / "good", routes, tests), SCHEMAS)
    assert [p.message for p in problems] == ["expect_remembered: route 'status-out' remembers into no store 'trail' (it does into: none)"]
    assert config is not None
    results = list(run_tests(cases, config, SCHEMAS))
    assert [r.passed for r in results] == [True, False]
    assert "store 'trail' holds other values" in results[1].reason
