"""What can be known of a route before anything flows, as generators of problems: mappings,
schema, the endpoints' own checks, metadata reads, ``fair:``, ``reply:``, stores; and the
warnings (competing consumers, shadowed fields, captured variables). Composed in
:func:`route_checks`, which the loader calls once per route."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Mapping

from engine import endpoints
from engine.common.placeholders import MappingError
from engine.common.schemas import SchemaRegistry
from engine.common.suggest import did_you_mean
from engine.endpoints.base import EndpointError
from engine.language import agents as agents_table
from engine.language.fieldcheck import mapping_field_problems, option_hint, reply_field_problems
from engine.language.mapping import compile_mapping, known_functions, literal_format_problems, meta_names, unknown_functions
from engine.language.readcheck import schema_checks
from engine.language.route_options import RouteOptions
from engine.language.route_yaml import Document, Path_, Problem
from engine.language.specs import EndpointSpec, RouteSpec
from engine.language.stage_options import FairOptions
from engine.language.stores import FAILURE_META, RememberOptions, remember_entries
from engine.language.templates import Expansion
from engine.language.window_options import window_expressions, window_problems


def competing_consumers(routes: Mapping[str, RouteSpec]) -> tuple[Problem, ...]:
    """Two routes consuming one AMQP queue split its messages between them (competing
    consumers): legal, but rarely what two routes mean, so ``check`` warns."""
    warnings = []
    seen: dict[tuple[str, str], RouteSpec] = {}
    for route in routes.values():
        try:
            name = endpoints.transport(route.source.protocol).competing_consumers(route.name, route.source.options)
        except EndpointError:
            continue
        if name is None:
            continue
        first = seen.setdefault((route.source.connection, name), route)
        if first is not route:
            warnings.append(Problem(route.file, route.line, (
                f"route {route.name!r} consumes {name}, as route {first.name!r} does ({first.file}:{first.line}): "
                "they compete, each message goes to only one of them (give each route its own queue to get every message)"
            )))
    return tuple(warnings)


def store_problems(recalls: list[tuple[Document, Path_, str, str | None]],
                    remembers: list[tuple[Document, Path_, RememberOptions]]) -> Iterator[Problem]:
    """``recall('NAME')`` of a store no route remembers into could only ever read null: an
    error, with the names there are; two routes giving one store different ``max_age`` or
    ``per`` would make a value's meaning depend on the route that wrote it last."""
    stores: dict[str, tuple[Document, Path_, RememberOptions]] = {}
    for document, where, remember in remembers:
        first = stores.setdefault(remember.store, (document, where, remember))
        for key in ("max_age", "per"):
            if getattr(first[2], key) != getattr(remember, key):
                yield document.problem(where + (key,), (
                    f"store {remember.store!r}: {key} {getattr(remember, key)!r} differs from {getattr(first[2], key)!r} "
                    f"given at {first[0].file}:{first[0].line(first[1])} (one store, one meaning)"))
    for document, where, route, name in recalls:
        if name is None:
            yield document.problem(where, f"route {route!r}: recall() takes a store name in quotes, as recall('position', serialNumber)")
        elif name not in stores:
            hint = did_you_mean(name, stores) or (f" (stores: {', '.join(sorted(stores))})" if stores else
                                                  " (no route remembers anything: give one remember: {store: NAME})")
            yield document.problem(where, f"route {route!r}: recall({name!r}): no route remembers into store {name!r}{hint}")


@dataclass(frozen=True)
class CheckedRoute:
    """One route as its checks see it: where it is written, its options, its two ends as far
    as they parsed (``complete`` false for an end with an option at fault), its template."""

    document: Document
    where: Path_
    route: RouteOptions
    source: EndpointSpec | None
    sink: EndpointSpec | None
    complete: tuple[bool, bool]
    schemas: SchemaRegistry
    variables: Mapping[str, Any] = field(default_factory=dict)
    """The route's template variables (its ``for_each`` item)."""
    has_agents: bool = False
    """Whether the directory has an agents table."""
    expansion: Expansion | None = None
    """How the route was expanded from a ``for_each`` template, if it was."""
    sink_path: Path_ = ("sink",)
    """Where the sink checked is written: ``sink``, or an item of ``sinks:`` or its ``fallback``
    (a route with several sinks is checked once per sink, each as ``route.sink``)."""

    def problem(self, key_path: Path_, message: str) -> Problem:
        return self.document.problem(key_path, f"route {self.route.name!r}: {message}")


Finding = tuple[Problem, bool]
"""``(problem, is_error)``: an error stops the directory loading, a warning is shown by ``check``."""


def route_checks(checked: CheckedRoute) -> Iterator[Finding]:
    """What can be known of a route before anything flows: its mappings compile and call
    known functions, its schema exists, its endpoints accept their options, a typed source
    has the fields the mapping reads; and (warnings) the schema declares the keys it sets, a
    template's variables shadow no field, a source's captures are meant.
    Each part is checked even when another failed, so one run shows every problem; an
    endpoint with an option at fault (``complete`` false) still tells the mapping check its
    type, but its transport's checks wait for the option to be fixed (they would only
    repeat the fault in other words)."""
    for check in _ERROR_CHECKS:
        yield from ((problem, True) for problem in check(checked))
    yield from _schema_checks(checked)
    if checked.expansion is not None:
        yield from ((problem, False) for problem in shadowing_warnings(
            checked.document, checked.where, checked.route, checked.expansion, checked.schemas, checked.sink_path))
        yield from ((problem, False) for problem in captured_warnings(
            checked.document, checked.where, checked.route, checked.source, checked.expansion))


def _mapping_checks(checked: CheckedRoute) -> Iterator[Problem]:
    """The route's mappings (its own, the sink's, each ``remember`` value) compile."""
    where, route = checked.where, checked.route
    values = [(remember_path(where, route, index) + ("value",), entry.value)
              for index, entry in enumerate(remember_entries(route.remember)) if entry.value is not None]
    for key_path, expression in (*_expressions(checked), *values):
        for message in _mapping_problems(expression):
            yield checked.problem(key_path, message)


def _expressions(checked: CheckedRoute) -> tuple[tuple[Path_, str | None], ...]:
    """The route's JMESPath expressions on its messages, each where it is written: its mapping,
    its sink's, its ``when:``, its ``dedupe:`` key and its ``window:``'s ``per`` and aggregates' arguments."""
    where, route = checked.where, checked.route
    sink = route.sink or {}
    return ((where + ("mapping",), route.mapping), (where + checked.sink_path + ("mapping",), sink.get("mapping")),
            (where + checked.sink_path + ("when",), sink.get("when")), (where + ("when",), route.when), (where + ("dedupe", "key"), route.dedupe.key if route.dedupe else None),
            *((where + ("window",) + key, text) for key, text in window_expressions(route.window)))


def _window_checks(checked: CheckedRoute) -> Iterator[Problem]:
    """A ``window:``'s aggregates: known functions, arguments where needed, no field named twice."""
    route = checked.route
    for key, message in window_problems(route.window):
        yield checked.problem(checked.where + ("window",) + key, f"window: {message}")
    if route.window is not None:  # they act on single messages; a window's message is made after them
        for other in ("throttle", "dedupe", "reply"):
            if getattr(route, other) is not None:
                yield checked.problem(checked.where + (other,), f"{other}: not with window: (a window's message is made "
                                                                 "from many; use a second route for single messages)")


def _schema_checks(checked: CheckedRoute) -> Iterator[Finding]:
    """The schema is named and exists; what the mapping makes against what it declares."""
    where, schemas, schema_name = checked.where, checked.schemas, checked.route.schema
    if schema_name is None:
        yield checked.problem(where, "'schema' is required (use raw_json to pass any object)"), True
    elif schemas.get(schema_name) is None:
        yield checked.problem(where + ("schema",), f"unknown schema {schema_name!r} (known: {', '.join(n for n in schemas.names() if '.v' not in n)}){did_you_mean(schema_name, schemas.names())}"), True
    else:
        yield from schema_checks(checked.document, where, checked.route, checked.sink, schemas, source_variables(checked.source),
                                 checked.sink_path)


def _source_checks(checked: CheckedRoute) -> Iterator[Problem]:
    """Fields a typed source does not have, ``meta(name)`` it never gives, ``fair:`` it cannot serve."""
    source, where, route, variables, has_agents = checked.source, checked.where, checked.route, checked.variables, checked.has_agents
    if source is None:
        return
    for message in mapping_field_problems(source.protocol, source.options, route.mapping):
        yield checked.problem(where + ("mapping",), message)
    for key_path, expression in _expressions(checked):
        for message in _meta_problems(source, expression, variables, has_agents):
            yield checked.problem(key_path, message)
    for index, entry in enumerate(remember_entries(route.remember)):  # a failed entry's value also reads meta('failure')
        given = {**variables, FAILURE_META: None} if entry.when == "failed" else variables
        for message in _meta_problems(source, entry.value, given, has_agents):
            yield checked.problem(remember_path(where, route, index) + ("value",), message)
    for key, message in _fair_problems(source, route.fair, variables):
        yield checked.problem(where + ("fair",) + key, f"fair: {message}")


def remember_path(where: Path_, route: RouteOptions, index: int) -> Path_:
    """Where a route's ``remember`` entry is written: the mapping itself, or an item of the list."""
    return where + (("remember", index) if isinstance(route.remember, tuple) else ("remember",))


def source_variables(source: EndpointSpec | None) -> tuple[str, ...]:
    """The names a route's source captures from where each message came (``Transport.source_variables``)."""
    if source is None:
        return ()
    try:
        return endpoints.transport(source.protocol).source_variables(source.options)
    except EndpointError:
        return ()


def captured_warnings(document: Document, where: Path_, route: RouteOptions, source: EndpointSpec | None,
                       expansion: Expansion) -> Iterator[Problem]:
    """In a ``for_each`` route, a source's ``{name}`` that no item fills is captured from each
    message's origin instead (a ROS 2 topic pattern): say so, as a misspelt variable would
    silently become one."""
    variables = list(expansion.variables)
    for captured in source_variables(source):
        yield document.problem(where + ("source",), (
            f"route {route.name!r}: {{{captured}}} in the source is no for_each variable (variables: {', '.join(variables)}): "
            f"it is captured from each message (every matching topic, meta({captured!r})){did_you_mean(captured, variables)}"))


def source_meta_names(source: EndpointSpec, variables: Mapping[str, Any]) -> tuple[str, ...]:
    """What ``meta(name)`` can read on a route with this source: what its protocol's source
    gives each message (``Transport.meta_names``), then the route's template variables."""
    try:
        names = endpoints.transport(source.protocol).meta_names(source.options)
    except EndpointError:
        names = ()
    return tuple(dict.fromkeys((*names, *variables)))


def _fair_problems(source: EndpointSpec, fair: FairOptions | None,
                   variables: Mapping[str, Any]) -> Iterator[tuple[Path_, str]]:
    """``fair`` needs a source that queues its messages in the engine, and ``per`` naming
    metadata that source gives each message (a template variable is one value: no agents)."""
    if fair is None:
        return
    try:
        queues = endpoints.transport(source.protocol).queues_per_agent(source.options)
    except EndpointError:
        return
    if not queues:
        yield (), (f"this {source.protocol} source does not queue its messages in the engine (its broker or "
                   "sender holds the backlog), so there are no per-agent queues to share out")
        return
    given_meta = [name for name in source_meta_names(source, {}) if name not in variables]
    if fair.per not in given_meta:
        hint = did_you_mean(fair.per, given_meta) or f" (it gives {', '.join(given_meta)})"
        yield ("per",), f"per: the {source.protocol} source gives no {fair.per!r} for each message{hint}"


def _interprets_agents(source: EndpointSpec) -> bool:
    """Whether the source's ``meta('agent')`` comes from the agents table (MAVLink's ids), not
    from the message itself (a ROS 2 topic's ``{agent}`` segment)."""
    try:
        return bool(endpoints.transport(source.protocol).agent_options)
    except EndpointError:
        return False


def _meta_problems(source: EndpointSpec, expression: str | None, variables: Mapping[str, Any],
                   has_agents: bool = False) -> Iterator[str]:
    """``meta(name)`` calls naming what the source never gives (the mapping would read null)."""
    known = source_meta_names(source, variables)
    for wanted in dict.fromkeys(n for n in meta_names(expression) if n is not None):
        if wanted == agents_table.AGENT and wanted in known and wanted not in variables and not has_agents \
                and _interprets_agents(source):
            yield (f"meta({wanted!r}): the name of the agent heard needs the agents table (a top-level agents: mapping "
                   f"naming each agent's ids), and there is none")
            continue
        if wanted not in known:
            hint = did_you_mean(wanted, known) or f" (it gives {', '.join(known)})" if known else " (it gives none)"
            yield f"meta({wanted!r}): the {source.protocol} source gives no {wanted!r}{hint}"


def shadowing_warnings(document: Document, where: Path_, route: RouteOptions, expansion: Expansion,
                        schemas: SchemaRegistry, sink_path: Path_ = ("sink",)) -> Iterator[Problem]:
    """A ``{var}`` the template filled in at load where the route's canonical message has a
    field of the same name: the variable wins (the field is never read there), so say so."""
    declared = schemas.declared(route.schema) if route.schema else None
    if declared is None or declared.open:
        return
    for path, names in expansion.placeholders.items():
        if path[:len(sink_path)] != sink_path and path[:1] != ("throttle",):
            continue
        for variable in names:
            if variable in declared.keys:
                yield document.problem(where + path, (
                    f"route {route.name!r}: {{{variable}}} in {'.'.join(map(str, path))} is the for_each variable "
                    f"({expansion.variables[variable]!r}), not the canonical field {variable!r} of {route.schema}: the variable wins "
                    f"(rename the variable to read the field at send time)"))


def _reply_checks(checked: CheckedRoute) -> Iterator[Problem]:
    """``reply:`` needs a source that can answer its sender; its mapping compiles and reads only
    fields the sink's answer has (when the sink's transport knows them); its schema exists."""
    reply, where, source, sink = checked.route.reply, checked.where, checked.source, checked.sink
    if reply is None:
        return
    if source is not None and not endpoints.transport(source.protocol).source_answers(source.options):
        able = [p for p in endpoints.PROTOCOLS if _replies(p)]
        yield checked.problem(where + ("reply",), f"reply: this {source.protocol} source cannot "
                                                  f"answer its sender (protocols whose sources can: {', '.join(able)}; "
                                                  "see Calls in route-language.md)")
    for message in _mapping_problems(reply.mapping):
        yield checked.problem(where + ("reply", "mapping"), f"reply: {message}")
    if sink is not None:
        for message in reply_field_problems(sink.protocol, sink.options, reply.mapping):
            yield checked.problem(where + ("reply", "mapping"), f"reply: {message}")
    if reply.schema is not None and checked.schemas.get(reply.schema) is None:
        yield checked.problem(where + ("reply", "schema"), f"reply: unknown schema {reply.schema!r}"
                                                           f"{did_you_mean(reply.schema, checked.schemas.names())}")


def _replies(protocol: str) -> bool:
    try:
        return endpoints.transport(protocol).replies
    except EndpointError:
        return False


def _mapping_problems(expression: str | None) -> Iterator[str]:
    if expression is None:
        return
    try:
        compile_mapping(expression)
    except MappingError as exc:
        yield f"bad JMESPath {expression!r}: {exc}"
        return
    for function in unknown_functions(expression):
        yield f"unknown function {function}() in {expression!r}{did_you_mean(function, known_functions())}"
    yield from literal_format_problems(expression)


def _endpoint_checks(checked: CheckedRoute) -> Iterator[Problem]:
    """The transport's own checks of each endpoint that parsed completely (the other may not have)."""
    route = checked.route
    ends = (("source", ("source",), checked.source if checked.complete[0] else None, route.mapping),
            ("sink", checked.sink_path, checked.sink if checked.complete[1] else None, (route.sink or {}).get("mapping")))
    for side, path, spec, expression in ends:
        if spec is None:
            continue
        base = checked.where + path + (spec.protocol,)
        try:
            transport = endpoints.transport(spec.protocol)
            check = transport.check_source if side == "source" else transport.check_sink
            results = list(check(spec.options, expression))
        except EndpointError as exc:
            results = [(None, str(exc))]
        for key, message in results:
            message += "" if "did you mean" in message else option_hint(spec.protocol, key, spec.options)
            yield checked.problem(base + ((key,) if key else ()), f"{side}: {message}")


_ERROR_CHECKS: tuple[Callable[[CheckedRoute], Iterator[Problem]], ...] = (_mapping_checks, _endpoint_checks, _reply_checks, _source_checks,
                                                                         _window_checks)
"""Every check whose findings are all errors (the schema's checks, which also warn, are composed
beside them in :func:`route_checks`). Problems are sorted when reported: the order is for reading."""
