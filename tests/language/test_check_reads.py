"""``check`` reads every read (issue 32): each JMESPath and template the engine evaluates on the
canonical message is checked against what the route's schema can hold, nested, through
``$ref``, list elements and ``oneOf``: an error where the schema allows no other keys
(``additionalProperties: false``), a warning where it does, each with file:line and the field
meant. Reads of typed inputs (a ROS 2 or MAVLink source's message, a call's answer) are errors:
tests/language/test_check_hints.py. And the VDA 5050 example's ``allowedDeviationXy`` is found."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from engine.common.schemas import SchemaRegistry
from engine.language.routes import RoutesInvalid, load_routes
from tests.support.repo import REPO

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier

BUNDLED = REPO / "schemas"
DRAFT = "https://json-schema.org/draft/2020-12/schema"


def closed(properties: dict[str, Any]) -> dict[str, Any]:
    return {"type": "object", "properties": properties, "additionalProperties": False}


SENSOR = {
    "$schema": DRAFT, "$id": "https://acme.example/sensor.v1.json", **closed({
        "agent_id": {"type": "string"},
        "temperature_c": {"type": "number"},
        "readings": {"type": "array", "items": closed({"value": {"type": "number"}, "unit": {"type": "string"}})},
        "location": {"$ref": "envelope.v1.json#/$defs/point"},
        "stamp": {"$ref": "envelope.v1.json#/$defs/stamp"},
        "origin": {"oneOf": [closed({"gnss": {"type": "string"}}), closed({"rtk": {"type": "string"}})]},
    })}
SENSOR_LOOSE = {key: value for key, value in SENSOR.items() if key not in ("$id", "additionalProperties")}
"""As most canonical schemas are: other keys are not ruled out at the top."""
SENSOR_ANY = {**SENSOR_LOOSE, "additionalProperties": True}
"""Other keys allowed on purpose at the top."""


@pytest.fixture
def schemas(tmp_path: Path) -> SchemaRegistry:
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "sensor.v1.json").write_text(json.dumps(SENSOR))
    (mine / "sensor_loose.v1.json").write_text(json.dumps(SENSOR_LOOSE))
    (mine / "sensor_any.v1.json").write_text(json.dumps(SENSOR_ANY))
    return SchemaRegistry([BUNDLED, mine])


def checked(tmp_path: Path, schemas: SchemaRegistry, routes: str) -> tuple[list[str], list[str]]:
    """``(problems, warnings)`` of a routes directory holding ``routes``, without the directory."""
    directory = tmp_path / "routes"
    directory.mkdir()
    (directory / "r.yaml").write_text(routes)
    try:
        config = load_routes(directory, schemas, env={})
        problems, warnings = [], list(config.warnings)
    except RoutesInvalid as invalid:
        problems, warnings = invalid.problems, invalid.warnings
    return ([str(p).removeprefix(f"{directory}/") for p in problems],
            [str(w).removeprefix(f"{directory}/") for w in warnings])


def test_a_sink_mapping_reads_only_what_the_canonical_message_can_hold(tmp_path: Path, schemas: SchemaRegistry):
    problems, warnings = checked(tmp_path, schemas, """routes:
  - name: closed
    source: {amqp: {queue: a}}
    schema: sensor
    sink:
      amqp: {exchange: out}
      mapping: >-
        {temperature: temperatur_c, ok: temperature_c, v: readings[].valeu, u: readings[?unit == 'C'].value,
        first: readings[0].unit, o: origin.gnns, good: origin.rtk, where: location.lt, lat: location.lat,
        s: stamp.secs, n: stamp.nanosec, agent: agent_id, key: meta('routing_key'), x: to_string(@) | y}
  - name: loose
    source: {amqp: {queue: b}}
    schema: sensor_loose
    sink:
      amqp: {exchange: out}
      mapping: "{temperature: temperatur_c, v: readings[].valeu}"
  - name: any
    source: {amqp: {queue: c}}
    schema: sensor_any
    sink:
      amqp: {exchange: out}
      mapping: "{temperature: temperatur_c, v: readings[].valeu}"
  - name: raw
    source: {amqp: {queue: d}}
    schema: raw_json
    sink:
      amqp: {exchange: out}
      mapping: "{anything: goes.here}"
""")
    always_null = "does not declare and allows no other key there (always null)"
    assert problems == [
        f"r.yaml:7: route 'closed': sink mapping reads 'origin.gnns', which schema 'sensor' {always_null}; did you mean 'origin.gnss'?",
        f"r.yaml:7: route 'closed': sink mapping reads 'readings[].valeu', which schema 'sensor' {always_null}; did you mean 'readings[].value'?",
        f"r.yaml:7: route 'closed': sink mapping reads 'stamp.secs', which schema 'sensor' {always_null}; did you mean 'stamp.sec'?",
        f"r.yaml:7: route 'closed': sink mapping reads 'temperatur_c', which schema 'sensor' {always_null}; did you mean 'temperature_c'?",
        f"r.yaml:16: route 'loose': sink mapping reads 'readings[].valeu', which schema 'sensor_loose' {always_null}; did you mean 'readings[].value'?",
        f"r.yaml:22: route 'any': sink mapping reads 'readings[].valeu', which schema 'sensor_any' {always_null}; did you mean 'readings[].value'?",
    ]
    assert warnings == [
        # the envelope's point does not rule other keys out: a warning, through the $ref
        "r.yaml:7: route 'closed': sink mapping reads 'location.lt', which schema 'sensor' does not declare; did you mean 'location.lat'?",
        "r.yaml:16: route 'loose': sink mapping reads 'temperatur_c', which schema 'sensor_loose' does not declare; did you mean 'temperature_c'?",
    ]  # sensor_any allows any other key at the top on purpose: temperatur_c may be there


def test_per_keys_and_sink_templates_read_the_canonical_message_too(tmp_path: Path, schemas: SchemaRegistry):
    """throttle/remember/latest_only ``per``, an AMQP routing key, an MQTT and a ROS 2 topic, a
    MAVLink target: each a read of the canonical message."""
    problems, warnings = checked(tmp_path, schemas, """connections:
  radio: {mavlink: "udpin:127.0.0.1:14999"}
routes:
  - name: keyed
    source: {amqp: {queue: a}}
    schema: sensor
    throttle: {max_rate: 1, per: agentid}
    remember: {store: s, per: origin.rtkk}
    buffer: {latest_only: {per: agent_id}}
    sink: {amqp: {exchange: out, routing_key: "t.{agent_idd}.{stamp.sec}"}}
  - name: loose-keys
    source: {amqp: {queue: b}}
    schema: sensor_loose
    throttle: {max_rate: 1, per: agentid}
    buffer: {latest_only: {per: agnt_id}}
    sink: {mqtt: {topic: "sensors/{agent}/t"}}
  - name: ros-topic
    source: {amqp: {queue: c}}
    schema: sensor_loose
    sink:
      ros2: {topic: "/{agnt_id}/t", type: std_msgs/msg/String}
      mapping: "{data: to_string(temperature_c)}"
  - name: target
    source: {amqp: {queue: d}}
    schema: command
    sink:
      mavlink: {connection: radio, message: COMMAND_LONG, target_system: "{vehicle}", target_component: 1}
      mapping: "{command: `400`, param1: params.arm}"
""")
    always_null = "does not declare and allows no other key there (always null)"
    assert problems == [
        f"r.yaml:7: route 'keyed': throttle per reads 'agentid', which schema 'sensor' {always_null}; did you mean 'agent_id'?",
        f"r.yaml:8: route 'keyed': remember per reads 'origin.rtkk', which schema 'sensor' {always_null}; did you mean 'origin.rtk'?",
        f"r.yaml:10: route 'keyed': sink routing_key reads 'agent_idd', which schema 'sensor' {always_null}; did you mean 'agent_id'?",
    ]
    assert warnings == [
        "r.yaml:14: route 'loose-keys': throttle per reads 'agentid', which schema 'sensor_loose' does not declare; did you mean 'agent_id'?",
        "r.yaml:15: route 'loose-keys': buffer latest_only per reads 'agnt_id', which schema 'sensor_loose' does not declare; did you mean 'agent_id'?",
        "r.yaml:16: route 'loose-keys': sink topic reads 'agent', which schema 'sensor_loose' does not declare; did you mean 'agent_id'?",
        "r.yaml:21: route 'ros-topic': sink topic reads 'agnt_id', which schema 'sensor_loose' does not declare; did you mean 'agent_id'?",
        "r.yaml:27: route 'target': sink target_system reads 'vehicle', which schema 'command' does not declare "
        "(it declares: agent_id, command, id, params, stamp, target, type)",
    ]


def test_check_exits_1_on_a_read_the_input_cannot_hold_and_0_on_a_warning(tmp_path: Path):
    """The issue's case, as ``check`` prints it: ``{temperature: temperatur_c}``."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "sensor.v1.json").write_text(json.dumps(SENSOR))
    (mine / "sensor_loose.v1.json").write_text(json.dumps(SENSOR_LOOSE))
    results = []
    for schema in ("sensor", "sensor_loose"):
        routes = tmp_path / schema
        routes.mkdir()
        (routes / "r.yaml").write_text(f"""routes:
  - name: temperature
    source: {{amqp: {{queue: q}}}}
    schema: {schema}
    sink:
      amqp: {{exchange: out}}
      mapping: "{{temperature: temperatur_c}}"
""")
        results.append(subprocess.run([sys.executable, "-m", "engine", "check", "--routes", str(routes), "--schemas", str(BUNDLED),
                                       "--schemas", str(mine)], capture_output=True, text=True, timeout=120, cwd=REPO))
    error, warning = results
    assert error.returncode == 1 and error.stderr == (
        f"{tmp_path}/sensor/r.yaml:7: route 'temperature': sink mapping reads 'temperatur_c', which schema 'sensor' does not "
        "declare and allows no other key there (always null); did you mean 'temperature_c'?\n")
    assert warning.returncode == 0 and warning.stderr == (
        f"{tmp_path}/sensor_loose/r.yaml:7: warning: route 'temperature': sink mapping reads 'temperatur_c', which schema "
        "'sensor_loose' does not declare; did you mean 'temperature_c'?\n")


def test_check_finds_the_vda5050_examples_misspelt_read(tmp_path: Path):
    """The example as it was (``allowedDeviationXy``; the standard's schema says
    ``allowedDeviationXY``): a copy holding the misspelling, whatever the example holds now."""
    example = tmp_path / "vda5050"
    shutil.copytree(REPO / "examples" / "vda5050", example)
    routes = example / "vda5050.yaml"
    routes.write_text(routes.read_text().replace("nodePosition.allowedDeviationXY", "nodePosition.allowedDeviationXy"))
    result = subprocess.run([sys.executable, "-m", "engine", "check", "--routes", str(example), "--schemas", str(BUNDLED)],
                            capture_output=True, text=True, timeout=120, cwd=REPO)
    line = next(number for number, text in enumerate(routes.read_text().splitlines(), 1)
                if "param2: default(nodePosition.allowedDeviationXy" in text)
    mapping_line = max(number for number, text in enumerate(routes.read_text().splitlines()[:line], 1) if "mapping:" in text)
    wanted = re.compile(re.escape(f"{routes}:{mapping_line}: warning: route 'uav1-order': sink mapping reads "
                                  "'nodes[].nodePosition.allowedDeviationXy', which schema 'vda5050/order")
                        + r"(\.v2)?" + re.escape("' does not declare; did you mean 'nodes[].nodePosition.allowedDeviationXY'?"))
    assert result.returncode == 0 and any(wanted.fullmatch(line) for line in result.stderr.splitlines()), result.stderr


def test_a_read_of_a_key_the_routes_mapping_never_sets_is_an_error(tmp_path: Path, schemas: SchemaRegistry):
    """``raw_json`` allows anything, but the mapping ``{seq: ..., agent_id: ..., pos: {...}}``
    makes exactly those keys: a read of another one is always null."""
    problems, warnings = checked(tmp_path, schemas, """routes:
  - name: exact
    source: {amqp: {queue: a}}
    mapping: "{seq: seq, agent_id: agent, pos: {lat: la, lon: lo}, points: pts[].{p: p}, extra: x}"
    schema: raw_json
    throttle: {max_rate: 1, per: agentid}
    sink:
      amqp: {exchange: out, routing_key: "out.{agent_id}.{pos.lt}"}
      mapping: "{s: sq, a: agent_id, lat: pos.lat, p: points[].pp, deeper: extra.anything}"
  - name: merged
    source: {amqp: {queue: b}}
    mapping: "merge(@, {seq: seq})"
    schema: raw_json
    sink:
      amqp: {exchange: out, routing_key: "out.{agent_id}"}
      mapping: "{s: sq}"
""")
    never = "which the route's mapping never sets (always null)"
    assert problems == [
        f"r.yaml:6: route 'exact': throttle per reads 'agentid', {never}; did you mean 'agent_id'?",
        f"r.yaml:8: route 'exact': sink routing_key reads 'pos.lt', {never}; did you mean 'pos.lat'?",
        f"r.yaml:9: route 'exact': sink mapping reads 'points[].pp', {never}; did you mean 'points[].p'?",
        f"r.yaml:9: route 'exact': sink mapping reads 'sq', {never}; did you mean 'seq'?",
    ] and warnings == []


def test_a_remember_value_reads_the_canonical_message(tmp_path: Path, schemas: SchemaRegistry):
    """``remember``'s ``value`` mapping (one entry, or each of a list) and ``per``."""
    problems, warnings = checked(tmp_path, schemas, """routes:
  - name: kept
    source: {amqp: {queue: a}}
    schema: sensor
    remember:
      - {store: temperatures, per: agent_id, value: "{t: temperatur_c, at: stamp.sec}"}
      - {store: readings, per: agnt_id, value: "readings[].valeu"}
    sink: {amqp: {exchange: out}}
  - name: one
    source: {amqp: {queue: b}}
    schema: sensor_loose
    remember: {store: last, value: "{t: temperatur_c}"}
    sink: {amqp: {exchange: out}}
""")
    always_null = "does not declare and allows no other key there (always null)"
    assert problems == [
        f"r.yaml:6: route 'kept': remember value reads 'temperatur_c', which schema 'sensor' {always_null}; did you mean 'temperature_c'?",
        f"r.yaml:7: route 'kept': remember per reads 'agnt_id', which schema 'sensor' {always_null}; did you mean 'agent_id'?",
        f"r.yaml:7: route 'kept': remember value reads 'readings[].valeu', which schema 'sensor' {always_null}; did you mean 'readings[].value'?",
    ]
    assert warnings == [
        "r.yaml:12: route 'one': remember value reads 'temperatur_c', which schema 'sensor_loose' does not declare; did you mean 'temperature_c'?"]


def test_conditions_dedupe_keys_windows_and_each_sinks_reads_are_checked(tmp_path: Path, schemas: SchemaRegistry):
    """The route's ``when:``, each sink's ``when:`` and mapping (``sinks:``, a fallback's), the
    ``dedupe`` key and a window's ``per`` and aggregates read the canonical message; a sink's
    ``when:`` on a window route reads what the window emits."""
    problems, warnings = checked(tmp_path, schemas, """routes:
  - name: fan
    source: {amqp: {queue: a}}
    schema: sensor
    when: "temperatur_c > `20`"
    dedupe: {key: agentid, ttl: 60}
    sinks:
      - amqp: {exchange: out}
        when: "origin.gnsss"
      - mqtt: {topic: t}
        mapping: "{t: temperature_c, who: agent_idd}"
        fallback:
          amqp: {exchange: spool}
          mapping: "{t: temprature_c}"
  - name: windowed
    source: {amqp: {queue: b}}
    schema: sensor
    window: {seconds: 1, per: agnt_id, emit: {hot: "max(temperatur_c)"}}
    sinks:
      - amqp: {exchange: out}
        when: "hott"
      - mqtt: {topic: t}
""")
    null = "which schema 'sensor' does not declare and allows no other key there (always null)"
    assert problems == [
        f"r.yaml:5: route 'fan': when reads 'temperatur_c', {null}; did you mean 'temperature_c'?",
        f"r.yaml:6: route 'fan': dedupe key reads 'agentid', {null}; did you mean 'agent_id'?",
        f"r.yaml:9: route 'fan': sink when reads 'origin.gnsss', {null}; did you mean 'origin.gnss'?",
        f"r.yaml:11: route 'fan': sink mapping reads 'agent_idd', {null}; did you mean 'agent_id'?",
        f"r.yaml:14: route 'fan': sink mapping reads 'temprature_c', {null}; did you mean 'temperature_c'?",
        f"r.yaml:18: route 'windowed': window emit.hot reads 'temperatur_c', {null}; did you mean 'temperature_c'?",
        f"r.yaml:18: route 'windowed': window per reads 'agnt_id', {null}; did you mean 'agent_id'?",
        "r.yaml:21: route 'windowed': sink when reads 'hott', which the route's window never sets (always null); did you mean 'hot'?",
    ], problems
    assert warnings == []
