"""The route-file schema is generated from the option declarations (engine/common/options.py), and
the parser of those declarations reports every problem with its key path."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import jsonschema
import pytest

from engine import endpoints
from engine.common.options import OptionError, evolve, given, option, parse, schema
from engine.common.redaction import Secret
from engine.common.schemas import SchemaRegistry
from engine.endpoints.amqp.options import AmqpConnectionOptions, AmqpSourceOptions
from engine.endpoints.ros2.node import Ros2Node
from engine.language import route_schema
from engine.language.route_keys import anchor
from engine.language.route_schema import KEYS_PATH, REGENERATE, SCHEMA_PATH, render, render_reference, route_file_schema
from engine.language.routes import RoutesInvalid, load_routes
from tests.support.repo import REPO

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier


def test_shipped_schema_is_the_generated_one() -> None:
    shipped = SCHEMA_PATH.read_text(encoding="utf-8")
    assert shipped == render(), f"{SCHEMA_PATH.name} is stale; regenerate it with: {REGENERATE}"


def test_generated_schema_is_valid_and_covers_every_protocol() -> None:
    generated = route_file_schema()
    jsonschema.Draft202012Validator.check_schema(generated)
    connection = generated["properties"]["connections"]["additionalProperties"]["properties"]
    route = generated["properties"]["routes"]["items"]["properties"]
    for protocol in endpoints.PROTOCOLS:
        assert protocol in connection and protocol in route["source"]["properties"] and protocol in route["sink"]["properties"]
    assert {"baud", "signing", "tunnel", "max_message_bytes"} <= set(connection)  # beside mavlink:, and every protocol's
    assert connection["amqp"]["anyOf"][0] == {"type": "string"}  # the url shorthand
    assert route["source"]["properties"]["amqp"]["properties"]["prefetch"] == {
        "type": "integer", "minimum": 1, "maximum": 65535, "default": 256, "description": "unacknowledged messages in flight from the broker"}
    assert "ordered" not in route["source"]["properties"]["amqp"]["properties"]  # internal: set by the loader


def test_a_declaration_change_makes_the_shipped_schema_stale(monkeypatch: pytest.MonkeyPatch) -> None:
    """The freshness test can fail: a new option changes the generated text."""
    before = render()
    monkeypatch.setattr(endpoints.transport("amqp"), "sink_options", AmqpSourceOptions)
    assert render() != before


# --- the key reference, docs/route-keys.md -------------------------------------------------------


def schema_keys(node: Any, path: str = "") -> dict[str, dict[str, Any]]:
    """Every key of the schema by its path (``routes[].sink.mavlink.retries``), walked here
    independently of engine/language/route_keys.py: ``properties``, a list's ``items``, a mapping's
    ``additionalProperties`` (``<name>``) and the alternatives of ``anyOf``."""
    found: dict[str, dict[str, Any]] = {}
    if not isinstance(node, dict):
        return found
    for key, prop in node.get("properties", {}).items():
        found[f"{path}.{key}".lstrip(".")] = prop
        found.update(schema_keys(prop, f"{path}.{key}".lstrip(".")))
    if isinstance(node.get("additionalProperties"), dict):
        found[f"{path}.<name>"] = node["additionalProperties"]
        found.update(schema_keys(node["additionalProperties"], f"{path}.<name>"))
    if isinstance(node.get("items"), dict):
        found.update(schema_keys(node["items"], f"{path}[]"))
    for alternative in node.get("anyOf", ()):
        found.update(schema_keys(alternative, path))
    return found


def reference_keys(text: str) -> set[str]:
    """The key paths docs/route-keys.md documents: each section's path and its rows' keys."""
    keys, section = set(), None
    for line in text.splitlines():
        if line.startswith("## "):
            section = "" if line == "## Top level" else line[3:].strip("`")
        elif line.startswith("| `") and section is not None:
            key = line.split("`")[1]
            keys.add(f"{section}.{key}".lstrip("."))
    return keys


def test_shipped_key_reference_is_the_generated_one() -> None:
    shipped = KEYS_PATH.read_text(encoding="utf-8")
    assert shipped == render_reference(), f"docs/{KEYS_PATH.name} is stale; regenerate it with: {REGENERATE}"


def test_the_key_reference_documents_every_key_the_schema_accepts() -> None:
    """The 93 distinct keys (129 key paths) the schema had when this test was written, less the
    mission sink's default_alt (a waypoint's altitude is never guessed), and whatever is declared
    since: every one is a row of its section, and no row is not a key."""
    keys = schema_keys(route_file_schema())
    assert len(keys) >= 129 and {"routes[].sink.mavlink.acknowledged", "routes[].buffer.spill_dir",
                                 "connections.<name>.amqp.urls", "dead_letters.spool_dir"} <= set(keys)
    assert reference_keys(KEYS_PATH.read_text(encoding="utf-8")) == set(keys)


def test_every_key_has_a_description() -> None:
    """What an editor shows and the reference's meaning column: add ``description=`` to the
    option() of a key listed here (or ``__schema_description__`` to its option class)."""
    def described(prop: dict[str, Any]) -> bool:
        return bool(prop.get("description")) or any(a.get("description") for a in prop.get("anyOf", ()))
    undocumented = sorted(path for path, prop in schema_keys(route_file_schema()).items() if not described(prop))
    assert undocumented == []


def test_a_declaration_change_makes_the_key_reference_stale(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """The freshness test can fail: an option added, or a description changed, is in the
    generated reference and not in the shipped one; ``--check`` says so and ``--write`` fixes it."""
    shipped = KEYS_PATH.read_text(encoding="utf-8")

    @dataclass(frozen=True, kw_only=True)
    class WithPriority(AmqpSourceOptions):
        message_priority: int = option(0, minimum=0, maximum=255, description="AMQP message priority")

    monkeypatch.setattr(endpoints.transport("amqp"), "sink_options", WithPriority)
    changed = render_reference()
    assert changed != shipped
    assert "| `message_priority` | integer, 0..255 | `0` | AMQP message priority |" in changed.split('id="routes-sink-amqp"')[1]
    assert "routes[].sink.amqp.message_priority" in reference_keys(changed)
    assert "routes[].sink.amqp.message_priority" not in reference_keys(shipped)
    monkeypatch.undo()

    prefetch = AmqpSourceOptions.__dataclass_fields__["prefetch"]
    monkeypatch.setattr(prefetch, "metadata", {**prefetch.metadata, "description": "a changed description"})
    monkeypatch.setattr(route_schema, "SCHEMA_PATH", tmp_path / SCHEMA_PATH.name)
    monkeypatch.setattr(route_schema, "KEYS_PATH", tmp_path / KEYS_PATH.name)
    (tmp_path / SCHEMA_PATH.name).write_text(SCHEMA_PATH.read_text(encoding="utf-8"), encoding="utf-8")
    (tmp_path / KEYS_PATH.name).write_text(shipped, encoding="utf-8")
    assert route_schema.main(["--check"]) == 1
    assert route_schema.main(["--write"]) == 0 and route_schema.main(["--check"]) == 0
    assert "a changed description" in (tmp_path / KEYS_PATH.name).read_text(encoding="utf-8")


def test_the_key_reference_links_resolve() -> None:
    text = KEYS_PATH.read_text(encoding="utf-8")
    ids = set(re.findall(r'<a id="([^"]+)"></a>', text))
    assert set(re.findall(r"\]\(#([^)]+)\)", text)) <= ids
    assert anchor("routes[].source.amqp") == "routes-source-amqp" and anchor("connections.<name>.amqp") == "connections-name-amqp"


@dataclass(frozen=True, kw_only=True)
class Inner:
    depth: int = option(10, minimum=1)
    mode: Literal["fast", "safe"] = option("safe", description="how")


@dataclass(frozen=True, kw_only=True)
class Outer:
    name: str = option(pattern="^[a-z]+$")
    rate: float = option(1.0, exclusive_minimum=0)
    tags: tuple[str, ...] = option((), min_items=1)
    extra: dict[str, Any] | None = option(None)
    either: str | int | None = option(None)
    inner: Inner = option(Inner())
    maybe: Inner | None = option(None)
    note: str | None = option(None, nullable=True)


def problems(data: Any) -> list[tuple[tuple[str | int, ...], str]]:
    with pytest.raises(OptionError) as caught:
        parse(Outer, data, ("routes", 0))
    return list(caught.value.problems)


def test_parse_fills_defaults_and_records_what_was_written() -> None:
    value = parse(Outer, {"name": "a", "tags": ["x"], "inner": {"mode": "fast"}, "either": 3, "note": None})
    assert value == Outer(name="a", tags=("x",), inner=Inner(mode="fast"), either=3)
    assert value.rate == 1.0 and value.inner.depth == 10 and value.maybe is None
    assert given(value) == {"name", "tags", "inner", "either", "note"} and given(value.inner) == {"mode"}
    assert given(evolve(value, rate=2.0)) == given(value)
    assert parse(Outer, value) is value


def test_unknown_key_names_its_path_and_suggests() -> None:
    [(path, message)] = problems({"name": "a", "inner": {"dept": 3}})
    assert path == ("routes", 0, "inner", "dept")
    assert message == "unknown key 'dept' at routes[0].inner (allowed: depth, mode); did you mean 'depth'?"


def test_type_bound_enum_pattern_and_required_problems_all_reported() -> None:
    found = dict(problems({"rate": 0, "tags": [], "inner": {"depth": 0, "mode": "slow"}, "either": 1.5, "extra": [1],
                           "note": 5, "maybe": "x"}))
    assert found == {
        ("routes", 0, "rate"): "0 is less than or equal to the minimum of 0",
        ("routes", 0, "tags"): "[] should be non-empty",
        ("routes", 0, "extra"): "[1] is not of type 'object'",
        ("routes", 0, "either"): "1.5 is not valid under any of the given schemas",
        ("routes", 0, "inner", "depth"): "0 is less than the minimum of 1",
        ("routes", 0, "inner", "mode"): "'slow' is not one of ['fast', 'safe']",
        ("routes", 0, "maybe"): "'x' is not of type 'object'",
        ("routes", 0, "note"): "5 is not of type 'string'",
        ("routes", 0, "name"): "'name' is a required property",
    }
    assert dict(problems({"name": "A1"})) == {("routes", 0, "name"): "'A1' does not match '^[a-z]+$'"}
    assert dict(problems({"name": True})) == {("routes", 0, "name"): "True is not of type 'string'"}
    assert str(OptionError(("routes", 0, "rate"), "0 is less than the minimum of 1")) == "routes[0].rate: 0 is less than the minimum of 1"


def test_schema_of_a_declaration() -> None:
    generated = schema(Outer)
    assert generated["required"] == ["name"] and generated["additionalProperties"] is False
    properties = generated["properties"]
    assert properties["rate"] == {"type": "number", "exclusiveMinimum": 0, "default": 1.0}
    assert properties["tags"] == {"type": "array", "items": {"type": "string"}, "minItems": 1, "default": []}
    assert properties["either"] == {"type": ["string", "integer"]}
    assert properties["note"] == {"type": ["string", "null"]}
    assert properties["inner"]["properties"]["mode"] == {"enum": ["fast", "safe"], "default": "safe", "description": "how"}
    assert properties["maybe"] == schema(Inner)
    jsonschema.Draft202012Validator.check_schema(generated)


def test_secrets_pass_only_where_declared() -> None:
    url = Secret("amqp://u:p@host/")
    assert parse(AmqpConnectionOptions, {"url": url}).url is url
    assert parse(AmqpConnectionOptions, {"urls": [url]}).urls == (url,)
    with pytest.raises(OptionError, match="is not of type 'string'"):
        parse(AmqpSourceOptions, {"queue": Secret("q")})


def test_loader_carries_typed_options_and_fingerprints_follow_them(tmp_path: Path) -> None:
    schemas = SchemaRegistry(REPO / "schemas")
    routes = tmp_path / "routes"
    routes.mkdir()
    text = """
connections:
  bus:
    amqp: amqp://guest:guest@localhost:5672/
  radio:
    mavlink: udpin:0.0.0.0:14550
    heartbeat: 0
routes:
  - name: r
    schema: raw_json
    ordered: true
    source: {amqp: {queue: q, prefetch: 10}}
    sink: {mavlink: {json_tunnel: true}}
"""
    (routes / "a.yaml").write_text(text)
    config = load_routes(routes, schemas)
    route = config.routes["r"]
    assert isinstance(route.source.options, AmqpSourceOptions)
    assert route.source.options.prefetch == 10 and route.source.options.ordered and route.source.options.durable
    radio = config.connections["radio"]
    assert radio.options.heartbeat == 0 and radio.options.url == "udpin:0.0.0.0:14550" and radio.exclusive == "udp:14550"
    bus_url = config.connections["bus"].options.url
    assert isinstance(bus_url, Secret) and bus_url.reveal() == "amqp://guest:guest@localhost:5672/"  # kept a secret
    assert load_routes(routes, schemas).routes["r"].fingerprint == route.fingerprint
    (routes / "a.yaml").write_text(text.replace("prefetch: 10", "prefetch: 11"))
    assert load_routes(routes, schemas).routes["r"].fingerprint != route.fingerprint
    (routes / "a.yaml").write_text(text.replace("heartbeat: 0", "heartbeat: 2"))
    changed = load_routes(routes, schemas)
    assert changed.connections["radio"].fingerprint != radio.fingerprint
    assert changed.routes["r"].fingerprint != route.fingerprint
    (routes / "a.yaml").write_text(text.replace("localhost:5672/\n", "localhost:5672/\n    tunnel: {}\n"))
    with pytest.raises(RoutesInvalid) as caught:
        load_routes(routes, schemas)
    assert [(p.line, p.message) for p in caught.value.problems] == [(5, "'tunnel' applies only to mavlink connections")]


def test_shipped_schema_file_is_json() -> None:
    assert json.loads(SCHEMA_PATH.read_text(encoding="utf-8"))["$schema"].endswith("2020-12/schema")


def test_ros2_domain_defaults_to_the_environment_as_before(monkeypatch: pytest.MonkeyPatch) -> None:
    """A ros2 connection without domain_id joins ROS_DOMAIN_ID, as every ROS 2 program does."""
    transport = endpoints.transport("ros2")
    monkeypatch.setenv("ROS_DOMAIN_ID", "7")
    from_environment, configured = transport.connect("ros", {"node": "n"}), transport.connect("ros", {"node": "n", "domain_id": 3})
    assert isinstance(from_environment, Ros2Node) and isinstance(configured, Ros2Node), "ros2 connects a Ros2Node"
    assert from_environment.domain_id == 7
    assert configured.domain_id == 3
