"""The route language without a broker: env substitution, mappings, templates, schemas."""

from __future__ import annotations

from pathlib import Path

import pytest

from engine.common.placeholders import MappingError, compile_template
from engine.common.redaction import reveal
from engine.common.schemas import SchemaError, SchemaRegistry, parse_json
from engine.language.mapping import compile_mapping, top_level_keys, unknown_functions
from engine.language.route_yaml import substitute_env
from engine.language.routes import RoutesInvalid, load_routes
from tests.support.schemas import known_schema

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier


def test_env_substitution_defaults_escapes_and_unset():
    env = {"USER_": "ops", "EMPTY": ""}
    assert substitute_env("${USER_}:${PASS:-guest}@h", env) == "ops:guest@h"
    assert substitute_env("${EMPTY:-x}", env) == ""
    assert substitute_env("cost $$5 ${USER_}", env) == "cost $5 ops"
    with pytest.raises(KeyError):
        substitute_env("${NOT_THERE}", env)


def test_unquoted_env_values_take_their_yaml_type(tmp_path: Path, schemas_dir: Path):
    (tmp_path / "a.yaml").write_text(
        "connections:\n  ros:\n    ros2:\n      domain_id: ${DOMAIN:-7}\n      node: '${NODE:-n42}'\n"
        "routes:\n  - {name: r, source: {ros2: {topic: /a}}, schema: raw_json, sink: {amqp: {exchange: e}}}\n"
    )
    config = load_routes(tmp_path, SchemaRegistry(schemas_dir), env={"DOMAIN": "12"})
    assert config.connections["ros"].settings == {"domain_id": 12, "node": "n42"}


def test_env_values_take_the_type_their_key_expects(tmp_path: Path, schemas_dir: Path):
    """Quoted or not, ``${VAR}`` becomes a number or boolean where the key wants one and text
    where it wants text; a free mapping keeps YAML's reading (unquoted typed, quoted text)."""
    (tmp_path / "a.yaml").write_text(
        "connections:\n"
        "  ros:\n    ros2:\n      domain_id: \"${ROS_DOMAIN_ID:-0}\"\n"
        "  gcs: {amqp: {url: \"amqp://localhost/\", publisher_confirms: \"${CONFIRMS:-false}\", heartbeat: '${BEAT}'}}\n"
        "routes:\n"
        "  - name: r\n"
        "    source: {ros2: {topic: /a}}\n"
        "    schema: raw_json\n"
        "    sink:\n      amqp:\n        connection: gcs\n        exchange: ${EXCHANGE}\n"
        "    max_attempts: \"${ATTEMPTS}\"\n"
        "  - name: q\n"
        "    source:\n"
        "      amqp:\n        queue: q\n        connection: gcs\n        queue_arguments:\n"
        "          x-max-length: ${LIMIT}\n          x-note: \"${LIMIT}\"\n"
        "    schema: raw_json\n"
        "    sink: {amqp: {exchange: e, connection: gcs}}\n"
    )
    env = {"EXCHANGE": "42", "BEAT": "5", "ATTEMPTS": "7", "LIMIT": "100"}
    config = load_routes(tmp_path, SchemaRegistry(schemas_dir), env=env)
    assert config.connections["ros"].settings == {"domain_id": 0}
    assert config.connections["ros"].options.domain_id == 0
    gcs = config.connections["gcs"].options
    assert gcs.publisher_confirms is False and gcs.heartbeat == 5
    assert config.routes["r"].delivery.max_attempts == 7
    assert config.routes["r"].sink.options.exchange == "42"
    assert config.routes["q"].source.options.queue_arguments == {"x-max-length": 100, "x-note": "100"}

    (tmp_path / "a.yaml").write_text("connections:\n  ros: {ros2: {domain_id: \"${DOMAIN}\"}}\n")
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(tmp_path, SchemaRegistry(schemas_dir), env={"DOMAIN": "seven"})
    assert [str(p).removeprefix(f"{tmp_path}/") for p in invalid.value.problems] == [
        "a.yaml:2: connections.ros.ros2.domain_id: 'seven' is not of type 'integer'"]


def test_unquoted_env_in_a_flow_mapping_says_to_quote_it(tmp_path: Path, schemas_dir: Path):
    (tmp_path / "a.yaml").write_text(
        "connections:\n  ros:\n    ros2: {node: n,\n           domain_id: ${ROS_DOMAIN_ID:-0}}\n"
        "routes: [a, x${Y}]\n")
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(tmp_path, SchemaRegistry(schemas_dir), env={})
    assert [str(p).removeprefix(f"{tmp_path}/") for p in invalid.value.problems] == [
        "a.yaml:4: invalid YAML: did not find expected ',' or '}'; inside a flow mapping ({...}) an unquoted ${VAR} "
        "is read as a nested mapping: quote the value, \"${ROS_DOMAIN_ID:-0}\" (a quoted ${VAR} still becomes a "
        "number or boolean where the key expects one)"]
    (tmp_path / "a.yaml").write_text("routes: [a, x${Y}]\n")
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(tmp_path, SchemaRegistry(schemas_dir), env={})
    assert "inside a flow list ([...]) an unquoted ${VAR} is read as a nested mapping: quote the value, \"x${Y}\"" \
        in str(invalid.value.problems[0])


def test_field_functions():
    mapping = compile_mapping(
        "{lat: deg_e7_to_deg(lat), alt: mm_to_m(alt), v: cm_to_m(vx), hdg: cdeg_to_deg(hdg),"
        " r: round(mul(`2.345`, `2`), `1`), d: default(missing, 'x'), s: format('{a}-{b}', @), i: to_int('42')}"
    )
    assert mapping({"lat": -220000000, "alt": 12345, "vx": -150, "hdg": 9000, "a": 1, "b": "z"}) == {
        "lat": -22.0, "alt": 12.345, "v": -1.5, "hdg": 90.0, "r": 4.7, "d": "x", "s": "1-z", "i": 42,
    }
    stamp = compile_mapping("stamp()")(None)
    assert set(stamp) == {"sec", "nanosec"} and stamp["sec"] > 1_700_000_000
    assert len(compile_mapping("uuid()")(None)) == 32
    with pytest.raises(MappingError):
        compile_mapping("div(`1`, `0`)")({})
    with pytest.raises(MappingError):
        compile_mapping("mul(a, `2`)")({"a": "text"})


def test_static_mapping_inspection():
    assert unknown_functions("{a: nope(b), c: round(d)}") == ["nope"]
    assert top_level_keys("{latitude: lat, longitude: lon}") == ["latitude", "longitude"]
    assert top_level_keys("a.b") is None


def test_templates_interpolate_canonical_fields():
    render = compile_template("canonical.{type}.{agent.id}")
    assert render({"type": "weeds", "agent": {"id": "uav1"}}) == "canonical.weeds.uav1"
    assert compile_template("fixed")({}) == "fixed"
    with pytest.raises(MappingError, match="agent_id"):
        compile_template("x.{agent_id}")({})


def test_schema_registry_versions_and_errors_name_the_field(schemas_dir: Path):
    registry = SchemaRegistry(schemas_dir)
    assert not registry.problems
    for name in ("envelope", "position", "attitude", "battery", "status", "weed_detection", "mission", "command", "ack", "raw_json"):
        assert registry.get(name) is not None, name
    weeds = known_schema(registry, "weed_detection")
    assert weeds is registry.get("weed_detection.v1")
    weeds.validate({"agent_id": "uav1", "points": [{"lat": 1, "lon": 2, "p": 0.5}]})
    with pytest.raises(SchemaError, match=r"\$\.points\[0\]\.p"):
        weeds.validate({"agent_id": "uav1", "points": [{"lat": 1, "lon": 2, "p": 5}]})
    with pytest.raises(SchemaError, match="agent_id"):
        weeds.validate({"agent_id": "", "points": []})
    with pytest.raises(SchemaError, match="line 1 column 2"):
        parse_json(b"{oops}")
    with pytest.raises(SchemaError, match="NaN"):
        parse_json(b'{"x": NaN}')


def test_route_defaults_and_fingerprints(tmp_path: Path, schemas_dir: Path):
    route = "routes:\n  - {name: r, source: {amqp: {queue: q}}, mapping: MAP, schema: raw_json, sink: {amqp: {exchange: e}}}\n"
    (tmp_path / "a.yaml").write_text(route.replace("MAP", "'@'"))
    registry = SchemaRegistry(schemas_dir)
    first = load_routes(tmp_path, registry, env={})
    assert first.routes["r"].source.connection == "default-amqp"
    assert reveal(first.connections["default-amqp"].settings["url"]).startswith("amqp://")
    again = load_routes(tmp_path, registry, env={})
    assert again.routes["r"].fingerprint == first.routes["r"].fingerprint
    (tmp_path / "a.yaml").write_text(route.replace("MAP", "'{a: b}'"))
    changed = load_routes(tmp_path, registry, env={})
    assert changed.routes["r"].fingerprint != first.routes["r"].fingerprint
    assert changed.content_hash != first.content_hash


def test_ambiguous_connection_and_duplicate_yaml_keys(tmp_path: Path, schemas_dir: Path):
    (tmp_path / "a.yaml").write_text(
        "connections:\n  one: {amqp: 'amqp://a/'}\n  two: {amqp: 'amqp://b/'}\n"
        "routes:\n  - {name: r, source: {amqp: {queue: q}}, schema: raw_json, sink: {amqp: {exchange: e, exchange: f}}}\n"
    )
    with pytest.raises(RoutesInvalid) as caught:
        load_routes(tmp_path, SchemaRegistry(schemas_dir), env={})
    text = str(caught.value)
    assert "duplicate key 'exchange'" in text
    assert f"{tmp_path / 'a.yaml'}:5:" in text
    (tmp_path / "a.yaml").write_text((tmp_path / "a.yaml").read_text().replace(", exchange: f", ""))
    with pytest.raises(RoutesInvalid, match="several connections"):
        load_routes(tmp_path, SchemaRegistry(schemas_dir), env={})


def test_delivery_keys_and_the_dead_letter_destination(tmp_path: Path, schemas_dir: Path):
    """max_attempts, overflow and max_message_bytes reach the route's delivery settings and
    its fingerprint; dead_letters resolves to one destination, with file:line errors."""
    from engine.language.stage_options import DeadLetterSpec, RouteDelivery

    (tmp_path / "a.yaml").write_text(
        "connections:\n  gcs: {amqp: 'amqp://a/', max_message_bytes: 1000}\n  ros: {ros2: {}}\n"
        "routes:\n"
        "  - {name: r, max_attempts: 2, overflow: drop_oldest, source: {ros2: {topic: /a}}, schema: raw_json,"
        " sink: {amqp: {exchange: e}}}\n"
        "  - {name: s, source: {amqp: {queue: q}}, schema: raw_json, sink: {ros2: {topic: /b}}}\n"
    )
    config = load_routes(tmp_path, SchemaRegistry(schemas_dir), env={})
    assert config.routes["r"].delivery == RouteDelivery(max_attempts=2, overflow="drop_oldest", sink_max_message_bytes=1000)
    assert config.routes["s"].delivery == RouteDelivery(max_message_bytes=1000)
    assert config.dead_letters == DeadLetterSpec(connection="gcs")
    before = config.routes["s"].fingerprint
    (tmp_path / "a.yaml").write_text((tmp_path / "a.yaml").read_text().replace("1000", "2000"))
    assert load_routes(tmp_path, SchemaRegistry(schemas_dir), env={}).routes["s"].fingerprint != before

    (tmp_path / "b.yaml").write_text("dead_letters: {connection: ros, max_length: 10}\n")
    with pytest.raises(RoutesInvalid, match=r"b.yaml:1: dead_letters: connection 'ros' \(ros2\) is not one that keeps dead letters \(connections that do: gcs\)"):
        load_routes(tmp_path, SchemaRegistry(schemas_dir), env={})
    (tmp_path / "b.yaml").write_text("dead_letters: {spool_dir: /tmp/x}\nroutes: []\n")
    assert load_routes(tmp_path, SchemaRegistry(schemas_dir), env={}).dead_letters.spool_dir == "/tmp/x"
    (tmp_path / "b.yaml").write_text("routes:\n  - {name: t, overflow: later, source: {ros2: {topic: /c}}, schema: raw_json, sink: {ros2: {topic: /d}}}\n")
    with pytest.raises(RoutesInvalid, match=r"b.yaml:2: routes\[0\].overflow: 'later' is not one of"):
        load_routes(tmp_path, SchemaRegistry(schemas_dir), env={})
