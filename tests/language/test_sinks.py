"""Several sinks per route (``sinks:``) and a sink's ``fallback:`` in the route language (issue
32): how they compile and are named, what ``check`` says of them (file:line, did-you-mean), and
route tests with an expected output per sink. The sending (one dead letter per message, a
fallback taking over and giving back) is tests/faults/test_sinks_fallback.py, on real brokers."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import pytest

from engine import endpoints
from engine.common.schemas import SchemaRegistry
from engine.endpoints.base import Inbound
from engine.language.routes import RoutesInvalid, load_routes
from engine.ops.route_tests import DrySink
from engine.running.fanout import REFUSED
from engine.running.pipeline import ConversionError, Filtered, Pipeline
from tests.language.test_route_tests import engine_cli
from tests.support.repo import REPO
from tests.support.schemas import known_schema

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier

SCHEMAS = SchemaRegistry(REPO / "schemas")

FAN = """connections:
  bus: {amqp: "amqp://guest:guest@nowhere.invalid:1/"}
  field: {mqtt: "mqtt://nowhere.invalid:1"}
routes:
  - name: fan
    source: {mqtt: {topic: "farm/+/fix"}}
    schema: position
    sinks:
      - amqp: {exchange: cloud, routing_key: "pos.{agent_id}"}
      - ros2: {topic: /fix, type: sensor_msgs/msg/NavSatFix}
        mapping: "{header: {frame_id: agent_id}, latitude: lat, longitude: lon, altitude: alt_msl}"
        when: "alt_msl > `0`"
      - name: spool
        amqp: {exchange: spool}
        mapping: "{who: agent_id}"
        fallback:
          after: 2.5
          mqtt: {topic: "spool/{agent_id}"}
  - name: plain
    source: {mqtt: {topic: "farm/+/other"}}
    schema: raw_json
    sink:
      amqp: {exchange: plain}
      mapping: "{x: x}"
"""


def routes(tmp_path: Path, text: str) -> Path:
    directory = tmp_path / "routes"
    directory.mkdir(exist_ok=True)
    (directory / "r.yaml").write_text(text)
    return directory


def problems_of(tmp_path: Path, text: str) -> list[str]:
    directory = routes(tmp_path, text)
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(directory, SCHEMAS, env={})
    return [str(problem).removeprefix(f"{directory}/") for problem in invalid.value.problems]


def test_sinks_compile_named_each_with_its_mapping_when_and_fallback(tmp_path: Path):
    config = load_routes(routes(tmp_path, FAN), SCHEMAS, env={})
    fan = config.routes["fan"]
    assert [sink.name for sink in fan.sinks] == ["amqp.0", "ros2", "spool"]
    assert fan.sink_mapping is None and fan.sink is fan.sinks[0].endpoint
    ros2, spool = fan.sinks[1], fan.sinks[2]
    assert ros2.mapping is not None, "the ros2 sink has its own mapping"
    assert ros2.when == "alt_msl > `0`" and ros2.mapping.startswith("{header:") and ros2.fallback is None
    assert spool.fallback is not None and spool.fallback.name == "spool.fallback" and spool.after == 2.5
    assert spool.fallback.endpoint.protocol == "mqtt" and spool.fallback.endpoint.connection == "field"
    assert {end.connection for end in fan.endpoints()} == {"field", "bus", "default-ros2"}
    plain = config.routes["plain"]  # one plain sink: no fan-out at all, as before
    assert plain.sinks == () and plain.sink_mapping == "{x: x}"


def test_check_names_each_sinks_problem_where_it_is_written(tmp_path: Path):
    problems = problems_of(tmp_path, """routes:
  - name: both
    source: {amqp: {queue: a}}
    schema: raw_json
    sink: {amqp: {exchange: x}}
    sinks:
      - amqp: {exchange: y}
  - name: neither
    source: {amqp: {queue: b}}
    schema: raw_json
  - name: twice
    source: {amqp: {queue: c}}
    schema: raw_json
    sinks:
      - name: out
        amqp: {exchange: y}
      - name: out
        amqp: {exchang: z}
        fallback:
          amqp: {exchange: f}
          mqtt: {topic: f}
  - name: typo
    source: {amqp: {queue: d}}
    schema: raw_json
    sinks:
      - amqp: {exchange: y}
        mapping: "{a: nosuchfunction(x)}"
      - amqp: {exchange: z}
        fallback: {after: -1, amqp: {exchange: f}}
""")
    assert problems == [
        "r.yaml:2: route 'both': give exactly one of sink: (one sink) and sinks: (a list of sinks)",
        "r.yaml:8: route 'neither': give exactly one of sink: (one sink) and sinks: (a list of sinks)",
        "r.yaml:17: route 'twice': sink name 'out' is used twice in the route (give each sink its own name:)",
        "r.yaml:18: unknown key 'exchang' at routes[2].sinks[1].amqp (allowed: connection, content_type, durable, exchange, "
        "exchange_type, mandatory, persistent, routing_key, timeout, unroutable); did you mean 'exchange'?",
        f"r.yaml:19: route 'twice': sinks[1].fallback must name exactly one of {', '.join(endpoints.PROTOCOLS)}",
        "r.yaml:27: route 'typo': unknown function nosuchfunction() in '{a: nosuchfunction(x)}'",
        "r.yaml:29: routes[3].sinks[1].fallback.after: -1 is less than the minimum of 0",
    ], problems


def test_a_message_is_mapped_once_per_chosen_sink_and_one_sinks_refusal_waits_in_its_meta(tmp_path: Path):
    config = load_routes(routes(tmp_path, FAN), SCHEMAS, env={})
    spec = config.routes["fan"]
    pipeline = Pipeline.compile(spec, 1, known_schema(SCHEMAS, "position"), DrySink())
    high = pipeline.convert(Inbound(body=b'{"agent_id": "uav1", "lat": 1.0, "lon": 2.0, "alt_msl": 5.0}', meta={}))
    assert high.fields == {"amqp.0": high.canonical, "spool": {"who": "uav1"},
                           "ros2": {"header": {"frame_id": "uav1"}, "latitude": 1.0, "longitude": 2.0, "altitude": 5.0}}
    low = pipeline.convert(Inbound(body=b'{"agent_id": "uav1", "lat": 1.0, "lon": 2.0, "alt_msl": -5.0}', meta={}))
    assert set(low.fields) == {"amqp.0", "spool"}  # the ros2 sink's when: says no
    assert REFUSED not in low.meta
    only = Pipeline.compile(replace(spec, sinks=spec.sinks[1:2]), 1, known_schema(SCHEMAS, "position"), DrySink())
    with pytest.raises(Filtered):  # the one sink's when: says no: nothing is sent, counted filtered
        only.convert(Inbound(body=b'{"agent_id": "uav1", "lat": 1.0, "lon": 2.0, "alt_msl": -5.0}', meta={}))


def test_a_sink_whose_mapping_refuses_leaves_the_others_and_all_refusing_is_one_sink_mapping_error(tmp_path: Path):
    config = load_routes(routes(tmp_path, FAN.replace('        when: "alt_msl > `0`"\n', "")), SCHEMAS, env={})
    spec = config.routes["fan"]
    pipeline = Pipeline.compile(spec, 1, known_schema(SCHEMAS, "position"), DrySink())
    no_altitude = b'{"agent_id": "uav1", "lat": 1.0, "lon": 2.0}'  # the NavSatFix needs one
    outbound = pipeline.convert(Inbound(body=no_altitude, meta={}))
    assert set(outbound.fields) == {"amqp.0", "spool"}
    assert list(outbound.meta[REFUSED]) == ["ros2"] and outbound.meta[REFUSED]["ros2"].startswith("sink mapping: "), outbound.meta
    alone = Pipeline.compile(replace(spec, sinks=spec.sinks[1:2]), 1, known_schema(SCHEMAS, "position"), DrySink())
    with pytest.raises(ConversionError) as refused:  # every chosen sink's mapping fails: one dead letter
        alone.convert(Inbound(body=no_altitude, meta={}))
    assert refused.value.stage == "sink mapping" and refused.value.detail.startswith("sink 'ros2': "), refused.value


def test_route_tests_give_each_sinks_output(tmp_path: Path):
    directory = routes(tmp_path, FAN)
    (directory / "fan.test.yaml").write_text("""tests:
  - name: every sink
    route: fan
    input: {agent_id: uav1, lat: 1.0, lon: 2.0, alt_msl: 5.0}
    expect_sinks:
      amqp.0: {agent_id: uav1, lat: 1.0, lon: 2.0, alt_msl: 5.0}
      ros2: {header: {frame_id: uav1}, latitude: 1.0, longitude: 2.0, altitude: 5.0}
      spool: {who: uav1}
  - name: the robot's when says no
    route: fan
    input: {agent_id: uav1, lat: 1.0, lon: 2.0, alt_msl: -1.0}
    expect_sinks:
      amqp.0: {agent_id: uav1, lat: 1.0, lon: 2.0, alt_msl: -1.0}
      spool: {who: uav1}
  - name: wrong, the robot does not get it
    route: fan
    input: {agent_id: uav1, lat: 1.0, lon: 2.0, alt_msl: -1.0}
    expect_sinks:
      amqp.0: {agent_id: uav1, lat: 1.0, lon: 2.0, alt_msl: -1.0}
      ros2: {header: {frame_id: uav1}, latitude: 1.0, longitude: 2.0, altitude: -1.0}
      spool: {who: uav1}
""")
    result = engine_cli("test", "--routes", str(directory))
    out = result.stdout
    assert result.returncode == 1, out + result.stderr
    assert re.search(r"^ok +\S+fan.test.yaml:2 +fan: every sink$", out, re.M), out
    assert re.search(r"^ok +\S+fan.test.yaml:9 +fan: the robot's when says no$", out, re.M), out
    assert re.search(r"^FAIL +\S+fan.test.yaml:15 +fan: wrong, the robot does not get it: the sinks the message goes to", out, re.M), out
    assert out.splitlines()[-1] == "2 passed, 1 failed"


def test_route_tests_name_a_sink_the_route_lacks(tmp_path: Path):
    directory = routes(tmp_path, FAN)
    (directory / "fan.test.yaml").write_text("""tests:
  - route: fan
    input: {agent_id: uav1, lat: 1.0, lon: 2.0}
    expect_sinks: {amqp0: {}}
  - route: fan
    input: {agent_id: uav1, lat: 1.0, lon: 2.0}
    expect_sink: {}
""")
    result = engine_cli("test", "--routes", str(directory))
    assert result.returncode == 2, result.stdout + result.stderr
    text = result.stdout + result.stderr
    assert "fan.test.yaml:4: expect_sinks: route 'fan' has no sink 'amqp0'; did you mean 'amqp.0'?" in text, text
    assert "fan.test.yaml:7: expect_sink: route 'fan' has several sinks (amqp.0, ros2, spool): give expect_sinks: {NAME: output}" in text, text


def test_a_single_sink_with_a_fallback_or_a_when_is_a_fan_out_of_one(tmp_path: Path):
    config = load_routes(routes(tmp_path, """routes:
  - name: spooled
    source: {amqp: {queue: a}}
    schema: raw_json
    sink:
      amqp: {exchange: cloud}
      fallback: {mqtt: {topic: spool}}
  - name: chosen
    source: {amqp: {queue: b}}
    schema: raw_json
    sink:
      amqp: {exchange: cloud}
      when: ok
"""), SCHEMAS, env={})
    spooled, chosen = config.routes["spooled"].sinks, config.routes["chosen"].sinks
    assert [(s.name, s.fallback.name if s.fallback else None, s.after) for s in spooled] == [("amqp", "amqp.fallback", 5.0)]
    assert [(s.name, s.when) for s in chosen] == [("amqp", "ok")]
