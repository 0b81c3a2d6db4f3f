"""Route tests without any middleware: ``*.test.yaml`` cases run through the compiled conversion.

A case gives a source message and what the route must make of it. It runs through the very
:class:`~engine.running.pipeline.Pipeline` the engine runs (decode, mapping, schema, sink mapping),
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

from engine import endpoints
from engine.common.schemas import SchemaRegistry
from engine.common.suggest import did_you_mean
from engine.endpoints.base import EndpointError, Inbound, MessageRejected, Outbound, Sink
from engine.language.route_checks import source_meta_names
from engine.language.route_yaml import Problem, parse_document
from engine.language.routes import RoutesInvalid, load_routes
from engine.language.specs import EndpointSpec, RoutesConfig, RouteSpec
from engine.language.stores import Stores, remember_entries
from engine.language.yaml_bounds import FileTooLarge, read_bounded
from engine.running.dedupe import SeenKeys, key_text
from engine.running.fanout import REFUSED
from engine.running.pipeline import ConversionError, Filtered, Pipeline, Windowed
from engine.language.window_options import WINDOW_END, WINDOW_START
from engine.running.replies import ReplyFailed

STAGES = ("input", "decode", "mapping", "schema", "when", "window", "sink mapping", "sink", "reply mapping", "reply schema")
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
                    "meta": {"type": "object", "description": "the source's metadata of the message, read by meta(name) "
                                                              "(routing_key, topic, system_id...)"},
                    "remembered": {"type": "object", "description": "what the stores hold for this case, read by recall(): "
                                                                    "{STORE: {KEY: value}}, or {STORE: value} for a store without per"},
                    "expect": {"description": "the canonical message"},
                    "expect_remembered": {"type": "object", "description": "what the stores hold after the case, the route's "
                                                                           "remember: applied as if the sink accepted "
                                                                           "(with expect_error: as the dead letter's when: failed): "
                                                                           "{STORE: {KEY: value}} (null: nothing), or {STORE: "
                                                                           "value} for a store without per"},
                    "ignore": {"type": "array", "items": {"type": "string"}, "description": "keys (a.b) left out"},
                    "expect_sink": {"description": "the sink mapping's output"},
                    "expect_sinks": {"type": "object", "description": "a route with several sinks (sinks:): each sink the message "
                                                                    "goes to (its when: says yes), by name, and its sink mapping's "
                                                                    "output; a sink not listed must not get it"},
                    "expect_routing_key": {"type": "string", "description": "the rendered routing key or topic"},
                    "expect_error": {"enum": list(STAGES)},
                    "expect_filtered": {"const": True, "description": "the route's when: rejects the message: nothing is sent "
                                                                      "(counted filtered)"},
                    "accepted": {"type": "array", "description": "dedupe: keys the route's sink accepted within the ttl, "
                                                                 "before this case's message"},
                    "expect_duplicate": {"type": "boolean", "description": "dedupe: true, the message's key is among accepted "
                                                                           "(nothing is sent, counted duplicates); false, it is sent"},
                    "response": {"description": "the sink's answer to the request, which the route's reply: mapping reads "
                                                "(what each sink answers: route-language.md, Calls)"},
                    "expect_reply": {"description": "the reply body the route makes of response"},
                    "window": {
                        "type": "object", "additionalProperties": False, "required": ["inputs"],
                        "description": "a window: route's case: its inputs go into one window, which then closes; expect "
                                       "lists the messages it emits (window_start and window_end left out: a test has no "
                                       "clock), expect_sink their sink mapping's outputs, in the order their keys came",
                        "properties": {
                            "inputs": {"type": "array", "minItems": 1, "description": "source messages, as input"},
                            "expect": {"type": "array", "description": "the window's messages"},
                            "expect_sink": {"type": "array", "description": "the sink mapping's output of each"},
                        },
                    },
                },
            },
        }
    },
}
_VALIDATOR = jsonschema.Draft202012Validator(TEST_FILE_SCHEMA)
_EXPECTATIONS = ("expect", "expect_sink", "expect_sinks", "expect_routing_key", "expect_reply", "expect_remembered", "expect_filtered",
                 "expect_duplicate", "window")


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
            text = read_bounded(path)
        except FileTooLarge as exc:
            problems.append(Problem(str(path), 1, str(exc)))
            continue
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
            elif "window" in body and ("input" in body or "input_raw" in body):
                problems.append(document.problem(where + ("window",), "a window case gives its inputs under window.inputs, "
                                                                      "not input"))
            elif "input" not in body and "input_raw" not in body and "window" not in body:
                problems.append(document.problem(where, f"test of route {route!r}: 'input' is required"))
            expectations = [key for key in _EXPECTATIONS if key in body]
            if "expect_error" in body and expectations and expectations != ["expect_remembered"]:
                problems.append(document.problem(where + (expectations[0],), f"{expectations[0]!r} and 'expect_error' exclude each other"))
            elif "expect_error" not in body and not expectations:
                problems.append(document.problem(where, f"test of route {route!r} expects nothing (expect, expect_sink, "
                                                        "expect_routing_key, expect_filtered, expect_duplicate or expect_error)"))
            elif "expect_filtered" in body and len(expectations) > 1:
                problems.append(document.problem(where + ("expect_filtered",), f"a filtered message is sent nowhere: "
                                                 f"{[key for key in expectations if key != 'expect_filtered'][0]!r} cannot hold"))
            if ("response" in body) != ("expect_reply" in body or body.get("expect_error", "").startswith("reply")):
                problems.append(document.problem(where, f"test of route {route!r}: 'response' and 'expect_reply' (or a reply "
                                                        "expect_error) go together"))
            if config is not None and route not in config.routes:
                problems.append(document.problem(where + ("route",), f"unknown route {route!r}{did_you_mean(route, config.routes)}"))
            elif config is not None:
                problems.extend(document.problem(where + (key,), message) for key, message in _sink_problems(config.routes[route], body))
                if "window" in body and config.routes[route].window is None:
                    problems.append(document.problem(where + ("window",), f"window: route {route!r} has no window:"))
                if ("accepted" in body or "expect_duplicate" in body) and config.routes[route].dedupe is None:
                    key = "accepted" if "accepted" in body else "expect_duplicate"
                    problems.append(document.problem(where + (key,), f"{key}: route {route!r} has no dedupe:"))
                problems.extend(document.problem(where + ("meta", key), message)
                                for key, message in _meta_key_problems(config.routes[route], body.get("meta") or {}))
                known = store_keys(config)
                problems.extend(document.problem(where + ("remembered", name), f"remembered: no route remembers into store "
                                                 f"{name!r}{did_you_mean(name, known) or ' (stores: ' + (', '.join(known) or 'none') + ')'}")
                                for name in body.get("remembered") or {} if name not in known)
                problems.extend(document.problem(where + ("expect_remembered", name), f"expect_remembered: route {route!r} "
                                                 f"remembers into no store {name!r} (it does into: "
                                                 f"{', '.join(e.store for e in remember_entries(config.routes[route].remember)) or 'none'})")
                                for name in body.get("expect_remembered") or {}
                                if name not in {e.store for e in remember_entries(config.routes[route].remember)})
            if len(problems) == before:
                cases.append(Case(str(path), line, route, body.get("name", ""), body))
    return cases, problems


def _sink_problems(spec: RouteSpec, body: Mapping[str, Any]) -> Iterator[tuple[str, str]]:
    """``expect_sinks`` on a route with several sinks, naming its sinks; ``expect_sink`` and
    ``expect_routing_key`` on a route with one."""
    names = [sink.name for sink in spec.sinks]
    if spec.sinks:
        for key in ("expect_sink", "expect_routing_key"):
            if key in body:
                yield key, f"{key}: route {spec.name!r} has several sinks ({', '.join(names)}): give expect_sinks: {{NAME: output}}"
        for name in body.get("expect_sinks") or {}:
            if name not in names:
                yield "expect_sinks", f"expect_sinks: route {spec.name!r} has no sink {name!r}{did_you_mean(name, names) or ' (sinks: ' + ', '.join(names) + ')'}"
    elif "expect_sinks" in body:
        yield "expect_sinks", f"expect_sinks: route {spec.name!r} has one sink: give expect_sink"


def _meta_key_problems(spec: RouteSpec, meta: Mapping[str, Any]) -> Iterator[tuple[str, str]]:
    """A case's ``meta`` keys the route's source never gives, or that the route fixes itself
    (its template variables)."""
    given_by_source = source_meta_names(spec.source, {})
    for key in meta:
        if key in spec.variables:
            yield key, f"meta {key!r} is a template variable of route {spec.name!r} ({spec.variables[key]!r}): the route sets it, a test cannot"
        elif key not in given_by_source:
            hint = did_you_mean(key, given_by_source) or f" (it gives {', '.join(given_by_source) or 'none'})"
            yield key, f"meta {key!r}: the {spec.source.protocol} source of route {spec.name!r} gives no {key!r}{hint}"


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


def store_keys(config: RoutesConfig) -> dict[str, bool]:
    """Each store some route remembers into, and whether it is keyed (``per``)."""
    return {entry.store: entry.per is not None
            for route in config.routes.values() for entry in remember_entries(route.remember)}


def run_case(case: Case, spec: RouteSpec, schemas: SchemaRegistry, keyed: Mapping[str, bool] | None = None) -> Result:
    """``keyed``: each store's ``per`` given or not (:func:`store_keys`), to read the case's
    ``remembered``; every case starts with stores holding only that, and ``sequence()`` at 1."""
    pipeline, stores = _case_pipeline(case, spec, schemas, keyed)
    body = case.body
    if "window" in body:
        return _window_case(case, spec, pipeline)
    expected_error = body.get("expect_error")
    reply: Any = None
    try:
        inbound = source_message(spec, body)
        try:
            outbound = pipeline.convert(inbound)
        except Filtered:
            if body.get("expect_filtered"):
                return Result(case, True)
            return Result(case, False, "the route's when: rejected the message (filtered: nothing sent)"
                                       + ("" if expected_error else "; add expect_filtered: true if that is right"))
        if body.get("expect_filtered"):
            return Result(case, False, "expected the route's when: to reject the message, but it passed",
                          _diff({"filtered": True}, {"canonical": _plain(outbound.canonical)}))
        if pipeline.dedupe is not None:
            key = pipeline.dedupe.key(outbound.canonical, outbound.meta)
            duplicate = key is not None and pipeline.dedupe.keys.seen(key)
            if duplicate != bool(body.get("expect_duplicate", False)):
                said = f"its dedupe key {key!r} is among accepted (a duplicate: nothing sent)" if duplicate else \
                    f"its dedupe key {key!r} is not among accepted: it is sent"
                return Result(case, False, said)
            if duplicate:
                return Result(case, True)
        destination = dry_run_sink(spec)(outbound) if not spec.sinks else _dry_run_sinks(spec, outbound)
        if "response" in body:
            try:
                reply = json.loads(pipeline.reply_shape.body(body["response"]))
            except ReplyFailed as failed:
                raise ConversionError(failed.stage, failed.error) from None
    except ConversionError as error:
        if expected_error == error.stage:
            if "expect_remembered" not in body:
                return Result(case, True)
            if pipeline.remember is not None:  # as the engine does once the dead letter is stored
                pipeline.remember.on_failed(error.canonical, inbound.meta, f"{error.stage}: {error.detail}")
            differs = _remembered_failures(body, stores, keyed, body.get("ignore") or ())
            if differs:
                return Result(case, False, "; ".join(reason for reason, _ in differs), [line for _, diff in differs for line in diff])
            return Result(case, True)
        want = f"expected a {expected_error} error" if expected_error else "expected it to pass"
        return Result(case, False, f"{want}, got a {error.stage} error: {error.detail}")
    if expected_error:
        return Result(case, False, f"expected a {expected_error} error, but the message converted",
                      _diff({"error": expected_error}, {"canonical": _plain(outbound.canonical), "routing_key": destination}))
    return _compare(case, pipeline, outbound, reply, destination, stores, keyed)


def _case_pipeline(case: Case, spec: RouteSpec, schemas: SchemaRegistry,
                   keyed: Mapping[str, bool] | None) -> tuple[Pipeline, Stores]:
    """The route's conversion as the engine compiles it, on a dry sink, with the stores and the
    de-duplication keys the case gives (in memory only: a route test writes no state)."""
    schema = schemas.get(spec.schema)
    assert schema is not None  # the route compiled
    reply_schema = schemas.get(spec.reply.schema) if spec.reply is not None and spec.reply.schema else None
    stores = Stores.given(case.body.get("remembered") or {}, keyed or {})
    seen = None
    if spec.dedupe is not None:
        seen = SeenKeys(spec.dedupe.path, spec.dedupe.ttl, spec.dedupe.max_keys)
        seen.accepted(text for text in map(key_text, case.body.get("accepted") or ()) if text is not None)
    return Pipeline.compile(spec, 0, schema, DrySink(), reply_schema, stores, seen), stores


def _compare(case: Case, pipeline: Pipeline, outbound: Outbound, reply: Any, destination: str | None, stores: Stores,
             keyed: Mapping[str, bool] | None) -> Result:
    """A converted message against every ``expect*`` of the case, all differences together."""
    body = case.body
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
    if "expect_sinks" in body:
        want, got = _without(body["expect_sinks"], ignore), _without(_plain(outbound.fields), ignore)
        if not same(want, got):
            failures.append(("the sinks the message goes to, or their sink mappings' outputs, differ", _diff(want, got)))
    if "expect_reply" in body:
        want, got = _without(body["expect_reply"], ignore), _without(reply, ignore)
        if not same(want, got):
            failures.append(("reply differs", _diff(want, got)))
    if "expect_remembered" in body:
        if pipeline.remember is not None:  # as the engine does: converted, then the sink accepted
            pipeline.remember.on_converted(outbound.canonical, outbound.meta)
            pipeline.remember.on_accepted(outbound.canonical, outbound.meta)
        failures.extend(_remembered_failures(body, stores, keyed, ignore))
    if "expect_routing_key" in body and body["expect_routing_key"] != destination:
        failures.append((f"routing key/topic is {destination!r}, expected {body['expect_routing_key']!r}", []))
    if failures:
        return Result(case, False, "; ".join(reason for reason, _ in failures), [line for _, diff in failures for line in diff])
    return Result(case, True)


def _window_case(case: Case, spec: RouteSpec, pipeline: Pipeline) -> Result:
    """A ``window`` case: every input into one window (a fixed clock), closed, its messages compared."""
    window, body = pipeline.window, case.body["window"]
    assert window is not None  # load_tests refuses a window case of a route without one
    window.clock = lambda: 0.0
    for index, value in enumerate(body["inputs"]):
        try:
            inbound = source_message(spec, {**case.body, "input": value})
            pipeline.convert(inbound)
        except Windowed as windowed:
            problem = window.add(windowed, inbound.meta)
            if problem is not None:
                return Result(case, False, f"input {index}: a window error: {problem}")
        except Filtered:
            continue
        except ConversionError as error:
            return Result(case, False, f"input {index}: a {error.stage} error: {error.detail}")
    outputs = window.close_now()
    ignore = (*(case.body.get("ignore") or ()), WINDOW_START, WINDOW_END)
    failures: list[tuple[str, list[str]]] = []
    if "expect" in body:
        want, got = [_without(e, ignore) for e in body["expect"]], [_without(_plain(e), ignore) for e, _ in outputs]
        if not same(want, got):
            failures.append(("window messages differ", _diff(want, got)))
    if "expect_sink" in body:
        try:
            sunk = [_without(_plain(pipeline.window_output(e, m).fields), ignore) for e, m in outputs]
        except ConversionError as error:
            return Result(case, False, f"a window message's {error.stage} error: {error.detail}")
        want = [_without(e, ignore) for e in body["expect_sink"]]
        if not same(want, sunk):
            failures.append(("sink mapping output of the window differs", _diff(want, sunk)))
    if failures:
        return Result(case, False, "; ".join(reason for reason, _ in failures), [line for _, diff in failures for line in diff])
    return Result(case, True)


def _remembered_failures(body: Mapping[str, Any], stores: Stores, keyed: Mapping[str, bool] | None,
                         ignore: Any) -> list[tuple[str, list[str]]]:
    """How the stores differ from the case's ``expect_remembered``."""
    failures: list[tuple[str, list[str]]] = []
    for store, wanted in body["expect_remembered"].items():
        by_key = (keyed or {}).get(store, True) and isinstance(wanted, Mapping)
        got = {key: stores.store(store).get(key) for key in wanted} if by_key else stores.store(store).get(None)
        if not same(_without(wanted, ignore), _without(_plain(got), ignore)):
            failures.append((f"store {store!r} holds other values", _diff(wanted, _plain(got))))
    return failures


def source_message(spec: RouteSpec, body: Mapping[str, Any]) -> Inbound:
    """The message as the route's source would hand it over: bytes for byte sources, and for
    typed sources the field dict after a round trip through the real type (so defaults fill
    in and a field the type lacks is an ``input`` error, as on the wire)."""
    meta = {"test": True, **(body.get("meta") or {})}
    if "input_raw" in body:
        return Inbound(body=body["input_raw"].encode("utf-8"), meta=meta)
    value = body["input"]
    typed = _typed_source(spec)
    if typed is None:
        return Inbound(body=json.dumps(value, ensure_ascii=False).encode("utf-8"), meta=meta)
    try:
        return Inbound(fields=typed(value), meta=meta)
    except (EndpointError, ValueError, TypeError) as exc:
        raise ConversionError("input", f"not a valid source message: {exc}") from None


def _typed_source(spec: RouteSpec) -> Callable[[Any], dict[str, Any]] | None:
    return endpoints.transport(spec.source.protocol).test_input(spec.source.options)


def _dry_run_sinks(spec: RouteSpec, outbound: Outbound) -> str | None:
    """A route with several sinks: what a sink's ``when:`` or mapping refused is the case's
    ``sink mapping`` error (the engine dead-letters it, naming the sink), then each sink chosen
    is dry-run with its own fields (:func:`dry_run_sink`)."""
    refused = outbound.meta.get(REFUSED)
    if refused:
        raise ConversionError("sink mapping", "; ".join(f"sink {name!r}: {error}" for name, error in refused.items()))
    fields = outbound.fields if isinstance(outbound.fields, dict) else {}
    for sink in spec.sinks:
        if sink.name in fields:
            copy_ = Outbound(outbound.body, outbound.canonical, fields[sink.name], outbound.message_id, outbound.meta,
                             captured=outbound.captured)
            dry_run_sink(spec, sink.endpoint)(copy_)
    return None


def dry_run_sink(spec: RouteSpec, endpoint: EndpointSpec | None = None) -> Callable[[Outbound], str | None]:
    """What the sink would do short of sending (its transport's ``sink_dry_run``): the
    rendered routing key or topic, and for a typed sink the message built from the fields;
    what the sink would refuse is an error of the stage it names (``sink`` by default).
    ``endpoint``: one of the route's several sinks (default: its one sink)."""
    endpoint = endpoint or spec.sink
    dry_run = endpoints.transport(endpoint.protocol).sink_dry_run(spec.name, endpoint.options)

    def sink(outbound: Outbound) -> str | None:
        try:
            return dry_run(outbound)
        except MessageRejected as exc:
            raise ConversionError(exc.stage, str(exc)) from None

    return sink


def run_tests(cases: list[Case], config: RoutesConfig, schemas: SchemaRegistry) -> Iterator[Result]:
    keyed = store_keys(config)
    for case in cases:
        yield run_case(case, config.routes[case.route], schemas, keyed)


def failing_tests(config: RoutesConfig, schemas: SchemaRegistry) -> list[Problem]:
    """What ``run --test-on-reload`` refuses a generation for, as a syntax error is refused:
    the problems of the directory's route test files, and each failing case at its
    ``file:line``, with why (the first line of what ``test`` prints; the diff is there)."""
    cases, problems = load_tests(config.directory, config)
    for result in run_tests(cases, config, schemas):
        if not result.passed:
            case = result.case
            label = case.route + (f": {case.name}" if case.name else "")
            problems.append(Problem(case.file, case.line, f"route test {label!r} fails: {result.reason}"
                                                          " (--test-on-reload refuses a generation whose route tests fail)"))
    return sorted(problems)


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
