"""Route tests without any middleware: ``*.test.yaml`` cases run through the compiled conversion.

A case gives a source message and what the route must make of it. It runs through the very
:class:`~engine.pipeline.Pipeline` the engine runs (decode, mapping, schema, sink mapping),
then through a dry run of the sink that renders the routing key or topic and, for typed
sinks, builds the ROS or MAVLink message from the sink mapping's fields, so a mismatch the
sink would reject is caught too. Nothing connects to anything: a route whose connection URL
points nowhere tests the same. ``vector test`` and ``rpk connect test`` are the models.

Test files live beside the routes (``routes/*.test.yaml``, or ``farm.test.yaml`` beside a
single ``farm.yaml``); the route loader never reads them as routes, ``check`` validates them.
"""

from __future__ import annotations

import copy
import difflib
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

import jsonschema

from engine.endpoints.base import EndpointError, Inbound, MessageRejected, Outbound, Sink
from engine.mapping import MappingError, compile_template
from engine.pipeline import ConversionError, Pipeline
from engine.route_yaml import Problem, parse_document
from engine.routes import RoutesConfig, RoutesInvalid, RouteSpec, load_routes
from engine.schemas import SchemaRegistry
from engine.suggest import did_you_mean

STAGES = ("input", "decode", "mapping", "schema", "sink mapping", "sink")
"""Where a message can be rejected, in pipeline order; ``expect_error`` names one."""

TEST_FILE_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "RabbitROS engine route tests",
    "type": "object",
    "additionalProperties": False,
    "required": ["tests"],
    "properties": {
        "tests": {
            "type": "array",
            "items": {
                "type": "object",
                "additionalProperties": False,
                "required": ["route"],
                "properties": {
                    "name": {"type": "string"},
                    "route": {"type": "string"},
                    "input": {"description": "the source message: a JSON document, or the field dict of a typed source"},
                    "input_raw": {"type": "string", "description": "the source bytes as they are (not JSON-encoded)"},
                    "expect": {"description": "the canonical message"},
                    "ignore": {"type": "array", "items": {"type": "string"}, "description": "keys (a.b) left out"},
                    "expect_sink": {"description": "the sink mapping's output"},
                    "expect_routing_key": {"type": "string", "description": "the rendered routing key or topic"},
                    "expect_error": {"enum": list(STAGES)},
                },
            },
        }
    },
}
_VALIDATOR = jsonschema.Draft202012Validator(TEST_FILE_SCHEMA)
_EXPECTATIONS = ("expect", "expect_sink", "expect_routing_key")


def test_files(routes: Path) -> list[Path]:
    """``*.test.yaml`` of a routes directory; for a single route file, ``<stem>.test.yaml`` beside it."""
    if routes.is_file():
        stem = routes.name.rsplit(".", 1)[0]
        return [p for p in (routes.with_name(f"{stem}.test.yaml"), routes.with_name(f"{stem}.test.yml")) if p.is_file()]
    if not routes.is_dir():
        return []
    return sorted(p for pattern in ("*.test.yaml", "*.test.yml") for p in routes.glob(pattern)
                  if p.is_file() and not p.name.startswith("."))


@dataclass
class Case:
    file: str
    line: int
    route: str
    name: str
    body: dict[str, Any]

    @property
    def where(self) -> str:
        return f"{self.file}:{self.line}"


@dataclass
class Result:
    case: Case
    passed: bool
    reason: str = ""
    diff: list[str] = field(default_factory=list)


def load_tests(routes: Path, config: RoutesConfig | None, env: Mapping[str, str] | None = None) -> tuple[list[Case], list[Problem]]:
    """Every case of every test file, and every problem (``file:line: message``) with them.
    With ``config``, cases must name one of its routes."""
    env = os.environ if env is None else env
    cases: list[Case] = []
    problems: list[Problem] = []
    for path in test_files(routes):
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            problems.append(Problem(str(path), 0, f"cannot read: {exc}"))
            continue
        document = parse_document(str(path), text, env, problems, _VALIDATOR)
        if document is None:
            continue
        for index, body in enumerate(document.data.get("tests") or ()):
            where = ("tests", index)
            line = document.line(where)
            route = body["route"]
            before = len(problems)
            if "input" in body and "input_raw" in body:
                problems.append(document.problem(where + ("input_raw",), "give either input or input_raw, not both"))
            elif "input" not in body and "input_raw" not in body:
                problems.append(document.problem(where, f"test of route {route!r}: 'input' is required"))
            expectations = [key for key in _EXPECTATIONS if key in body]
            if "expect_error" in body and expectations:
                problems.append(document.problem(where + (expectations[0],), f"{expectations[0]!r} and 'expect_error' exclude each other"))
            elif "expect_error" not in body and not expectations:
                problems.append(document.problem(where, f"test of route {route!r} expects nothing (expect, expect_sink, expect_routing_key or expect_error)"))
            if config is not None and route not in config.routes:
                problems.append(document.problem(where + ("route",), f"unknown route {route!r}{did_you_mean(route, config.routes)}"))
            if len(problems) == before:
                cases.append(Case(str(path), line, route, body.get("name", ""), body))
    return cases, problems


def load_checked(routes: Path, schemas: SchemaRegistry) -> tuple[RoutesConfig | None, list[Case], list[Problem], list[Problem]]:
    """The routes and their tests, as ``check`` and ``test`` see them: the config (None when
    the routes do not compile), the cases, every problem of both, sorted, and the routes'
    warnings (given whether or not they compile)."""
    try:
        config = load_routes(routes, schemas)
    except RoutesInvalid as invalid:
        _, problems = load_tests(routes, None)
        return None, [], sorted(invalid.problems + problems), invalid.warnings
    cases, problems = load_tests(routes, config)
    return config, cases, problems, list(config.warnings)


class DrySink(Sink):
    """Stands in for the route's sink; the pipeline never calls it."""

    async def send(self, message: Outbound) -> None:  # pragma: no cover - never called
        raise EndpointError("a route test does not deliver")


def run_case(case: Case, spec: RouteSpec, schemas: SchemaRegistry) -> Result:
    schema = schemas.get(spec.schema)
    assert schema is not None  # the route compiled
    pipeline = Pipeline.compile(spec, 0, schema, DrySink())
    body = case.body
    expected_error = body.get("expect_error")
    try:
        inbound = source_message(spec, body)
        outbound = pipeline.convert(inbound)
        destination = dry_run_sink(spec)(outbound)
    except ConversionError as error:
        if expected_error == error.stage:
            return Result(case, True)
        want = f"expected a {expected_error} error" if expected_error else "expected it to pass"
        return Result(case, False, f"{want}, got a {error.stage} error: {error.detail}")
    if expected_error:
        return Result(case, False, f"expected a {expected_error} error, but the message converted",
                      _diff({"error": expected_error}, {"canonical": _plain(outbound.canonical), "routing_key": destination}))
    ignore = body.get("ignore") or ()
    failures: list[tuple[str, list[str]]] = []
    if "expect" in body:
        want, got = _without(body["expect"], ignore), _without(_plain(outbound.canonical), ignore)
        if not same(want, got):
            failures.append(("canonical message differs", _diff(want, got)))
    if "expect_sink" in body:
        want, got = _without(body["expect_sink"], ignore), _without(_plain(outbound.fields), ignore)
        if not same(want, got):
            failures.append(("sink mapping output differs", _diff(want, got)))
    if "expect_routing_key" in body and body["expect_routing_key"] != destination:
        failures.append((f"routing key/topic is {destination!r}, expected {body['expect_routing_key']!r}", []))
    if failures:
        return Result(case, False, "; ".join(reason for reason, _ in failures), [line for _, diff in failures for line in diff])
    return Result(case, True)


def source_message(spec: RouteSpec, body: Mapping[str, Any]) -> Inbound:
    """The message as the route's source would hand it over: bytes for byte sources, and for
    typed sources the field dict after a round trip through the real type (so defaults fill
    in and a field the type lacks is an ``input`` error, as on the wire)."""
    if "input_raw" in body:
        return Inbound(body=body["input_raw"].encode("utf-8"), meta={"test": True})
    value = body["input"]
    typed = _typed_source(spec)
    if typed is None:
        return Inbound(body=json.dumps(value, ensure_ascii=False).encode("utf-8"), meta={"test": True})
    try:
        return Inbound(fields=typed(value), meta={"test": True})
    except (EndpointError, ValueError, TypeError) as exc:
        raise ConversionError("input", f"not a valid source message: {exc}") from None


def _typed_source(spec: RouteSpec) -> Callable[[Any], dict[str, Any]] | None:
    options = spec.source.options
    if spec.source.protocol == "ros2":
        type_name = options.type
        from engine.endpoints import rosmsg

        cls = rosmsg.resolve_type(type_name)
        if rosmsg.type_name(cls) == "std_msgs/msg/String":
            return None

        def ros(value: Any) -> dict[str, Any]:
            if not isinstance(value, Mapping):
                raise ValueError(f"{type_name} input must be a mapping of fields")
            return rosmsg.to_dict(rosmsg.from_dict(cls, value))

        return ros
    if spec.source.protocol == "mavlink" and not options.json_tunnel and options.message:
        from engine.endpoints.mavlink import MESSAGES, build_message, message_fields
        from engine.endpoints.mavlink.codec import ADDED_FIELDS, received_nan

        mav_cls = MESSAGES[options.message]
        added = ADDED_FIELDS.get(options.message, ())

        def mavlink(value: Any) -> dict[str, Any]:
            """The message as the source gives it: its own fields (a null float is the NaN the
            source shows as null), plus those the source adds."""
            if not isinstance(value, Mapping):
                return message_fields(build_message(mav_cls, value))
            own = received_nan(mav_cls, {k: v for k, v in value.items() if k not in added})
            return {**message_fields(build_message(mav_cls, own)), **{k: value[k] for k in added if k in value}}

        return mavlink
    return None


def dry_run_sink(spec: RouteSpec) -> Callable[[Outbound], str | None]:
    """What the sink would do short of sending: the rendered routing key or topic, and for a
    typed sink the message built from the fields; a failure is a ``sink`` error."""
    protocol, options = spec.sink.protocol, spec.sink.options
    if protocol == "amqp":
        render = compile_template(options.routing_key)

        def amqp(outbound: Outbound) -> str | None:
            try:
                return render(outbound.canonical)
            except MappingError as exc:
                raise ConversionError("sink", str(exc)) from None

        return amqp
    if protocol == "mqtt":
        from engine.endpoints.mqtt.topics import topic_renderer

        render_topic = topic_renderer(options.topic, f"route {spec.name!r}: mqtt sink")

        def mqtt(outbound: Outbound) -> str | None:
            try:
                return render_topic(outbound.canonical)
            except MessageRejected as exc:
                raise ConversionError("sink", str(exc)) from None

        return mqtt
    if protocol == "ros2":
        from engine.endpoints import rosmsg
        from engine.endpoints.ros2 import STRING_TYPE, _topic_template, typed_message

        topic = options.topic
        resolve = _topic_template(topic)
        cls = rosmsg.resolve_type(options.type)
        typed = rosmsg.type_name(cls) != STRING_TYPE
        where = f"route {spec.name!r}, ros2 topic {topic!r}"  # as the sink names it

        def ros(outbound: Outbound) -> str | None:
            try:
                rendered = topic if resolve is None else resolve(outbound.canonical, where)
                if typed:
                    typed_message(cls, outbound, where)
            except MessageRejected as exc:
                raise ConversionError(exc.stage, str(exc)) from None
            return rendered

        return ros
    if protocol == "mavlink":
        from engine.endpoints.mavlink.messages import dry_run

        build = dry_run(options)

        def mavlink(outbound: Outbound) -> str | None:
            try:
                build(outbound.fields)
            except MessageRejected as exc:
                raise ConversionError(exc.stage, str(exc)) from None
            return None

        return mavlink
    return lambda outbound: None


def run_tests(cases: list[Case], config: RoutesConfig, schemas: SchemaRegistry) -> Iterator[Result]:
    for case in cases:
        yield run_case(case, config.routes[case.route], schemas)


def format_result(result: Result, base: Path | None = None) -> list[str]:
    case = result.case
    label = f"{case.route}" + (f": {case.name}" if case.name else "")
    if result.passed:
        return [f"ok    {case.where}  {label}"]
    lines = [f"FAIL  {case.where}  {label}: {result.reason}"]
    lines.extend("      " + line for line in result.diff)
    return lines


def same(expected: Any, actual: Any) -> bool:
    """Equal as JSON, numbers within 1e-9 (relative) so float arithmetic in a mapping
    (``90.00000000000001``) does not fail a test, NaN equal to NaN (``.nan`` in YAML: what
    ``nan()`` gives a MAVLink sink); booleans are not numbers."""
    if isinstance(expected, dict) and isinstance(actual, dict):
        return expected.keys() == actual.keys() and all(same(v, actual[k]) for k, v in expected.items())
    if isinstance(expected, list) and isinstance(actual, list):
        return len(expected) == len(actual) and all(same(a, b) for a, b in zip(expected, actual))
    numbers = (int, float)
    if (isinstance(expected, numbers) and isinstance(actual, numbers)
            and not isinstance(expected, bool) and not isinstance(actual, bool)):
        return math.isclose(expected, actual, rel_tol=1e-9, abs_tol=1e-12) or (expected != expected and actual != actual)
    return type(expected) is type(actual) and expected == actual


def _plain(value: Any) -> Any:
    """What the message is as JSON (tuples become lists, and so on)."""
    return json.loads(json.dumps(value, default=str))


def _without(value: Any, ignore: Any) -> Any:
    value = copy.deepcopy(value)
    for dotted in ignore:
        *parents, last = dotted.split(".")
        target = value
        for key in parents:
            target = target.get(key) if isinstance(target, dict) else None
        if isinstance(target, dict):
            target.pop(last, None)
    return value


def _diff(expected: Any, actual: Any) -> list[str]:
    def lines(value: Any) -> list[str]:
        return json.dumps(value, indent=2, sort_keys=True, ensure_ascii=False).splitlines()

    return list(difflib.unified_diff(lines(expected), lines(actual), "expected", "actual", lineterm="", n=2))
