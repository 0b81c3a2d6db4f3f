"""The route language: a directory of YAML files compiled into route specifications.

Loading is all-or-nothing and never connects to anything: every file is parsed with
line numbers, environment variables are substituted, the result is validated against
the route-file JSON Schema shipped with the package, and every route is checked
(connections, JMESPath, schemas, endpoint options). All problems are collected, each
as ``file:line: message``, so ``check`` and a reload report the same errors the same way.

This module composes the steps; each concern has its own module: reading.py (the directory,
``for_each`` files, the agents table), connection_loading.py (``connections:``, dead letters),
endpoint_specs.py (a route's two ends, its placement), route_checks.py (the checks, as
generators of problems), route_options.py (the keys declared) and specs.py (the values made).
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from pathlib import Path
from dataclasses import dataclass, field, replace
from typing import Any, Literal, Mapping

from engine import endpoints
from engine.common.redaction import json_default, revealed
from engine.common.schemas import SchemaRegistry
from engine.language import agents as agents_table
from engine.language.connection_loading import compile_connections, compile_dead_letters, private_broker_warnings
from engine.language.endpoint_specs import endpoint_spec, hand_agents, parse_leniently, placement_of, route_to_sink
from engine.language.mapping import recall_names
from engine.language.reading import ROUTE_FILE_VALIDATOR, ItemFiles, document_items, read_agents_table, route_files, together_hint
from engine.language.route_checks import CheckedRoute, competing_consumers, remember_path, route_checks, store_problems
from engine.language.route_options import RouteOptions
from engine.language.route_yaml import Document, Path_, Problem, parse_document
from engine.language.sink_items import SinkItem, SinkPart, duplicate_names, fans_out, sink_items
from engine.language.specs import ConnectionSpec, EndpointSpec, RoutesConfig, RouteSpec, SinkSpec
from engine.language.stage_options import BufferSpec, DedupeSpec, RouteDelivery
from engine.language.stores import RememberOptions, remember_entries
from engine.language.templates import Expansion, expand_routes, is_items_text
from engine.language.window_options import window_expressions
from engine.language.yaml_bounds import FileTooLarge, read_bounded


class RoutesInvalid(Exception):
    """The directory does not compile; ``problems`` lists every reason, ``warnings`` what
    ``check`` would warn about as well."""

    def __init__(self, problems: list[Problem], warnings: list[Problem] | None = None) -> None:
        super().__init__("\n".join(map(str, problems)))
        self.problems = problems
        self.warnings = warnings or []


def load_routes(
    directory: Path,
    schemas: SchemaRegistry,
    env: Mapping[str, str] | None = None,
) -> RoutesConfig:
    """Compile ``directory``; raise :class:`RoutesInvalid` listing every problem."""
    env = os.environ if env is None else env
    problems: list[Problem] = []
    documents: list[Document] = []
    digest = hashlib.sha256()
    if not directory.exists():
        raise RoutesInvalid([Problem(str(directory), 0, "routes directory does not exist")])
    texts: list[tuple[Path, str]] = []
    item_files = ItemFiles(env, problems)
    for path in route_files(directory):
        try:
            text = read_bounded(path)
        except FileTooLarge as exc:
            problems.append(Problem(str(path), 1, str(exc)))
            continue
        except (OSError, UnicodeDecodeError) as exc:
            problems.append(Problem(str(path), 0, f"cannot read: {exc}"))
            continue
        digest.update(path.name.encode() + b"\0" + text.encode() + b"\0")
        if is_items_text(text):
            item_files.texts[path.resolve()] = text  # a for_each file, read where a route names it
        else:
            texts.append((path, text))
    table = read_agents_table(texts, env, problems)
    item_files.agents = table
    for path, text in texts:
        expand = functools.partial(expand_routes, str(path), read_items=item_files.reader(path))
        document = parse_document(str(path), text, env, problems, ROUTE_FILE_VALIDATOR, keep_invalid=True, expand=expand)
        if document is not None:
            documents.append(document)
    for schema_path, message in schemas.problems:
        problems.append(Problem(str(schema_path), 0, message))
    connections = compile_connections(documents, problems)
    warnings: list[Problem] = []
    routes = _compile_routes(documents, connections, schemas, problems, warnings, table)
    dead_letters = compile_dead_letters(documents, connections, problems)
    warnings.extend(competing_consumers(routes))
    warnings.extend(private_broker_warnings(connections, env))
    warnings.extend(item_files.unused())
    if problems:
        raise RoutesInvalid(sorted(set(problems)), sorted(set(warnings)))
    digest.update(json.dumps(sorted((n, r.fingerprint) for n, r in routes.items())).encode())  # schemas, key files, items
    return RoutesConfig(directory, connections, routes, digest.hexdigest()[:12],
                        warnings=tuple(sorted(set(warnings))), dead_letters=dead_letters,
                        data_files=frozenset(item_files.read))


def _compile_routes(
    documents: list[Document],
    connections: dict[str, ConnectionSpec],
    schemas: SchemaRegistry,
    problems: list[Problem],
    warnings: list[Problem],
    table: agents_table.Table,
) -> dict[str, RouteSpec]:
    """Every ``routes:`` item of every document compiled (:class:`_RouteCompiler`); then what
    only the whole directory can tell: every store recalled is remembered into."""
    compiler = _RouteCompiler(connections, schemas, problems, warnings, table)
    routes: dict[str, RouteSpec] = {}
    for document in documents:
        for index, body in document_items(document, "routes", list):
            spec = compiler.route(document, index, body)
            if spec is not None:
                routes[spec.name] = spec
    problems.extend(store_problems(compiler.recalls, compiler.remembers))
    return routes


@dataclass
class _RouteCompiler:
    """Compiles one ``routes:`` item at a time, in named steps (:meth:`route`), reporting into
    the loader's ``problems`` and ``warnings``; it remembers across items what the directory
    checks as a whole (names defined, stores remembered into and recalled)."""

    connections: dict[str, ConnectionSpec]
    schemas: SchemaRegistry
    problems: list[Problem]
    warnings: list[Problem]
    table: agents_table.Table
    defined: dict[str, tuple[str, int]] = field(default_factory=dict)
    """Where each route name was first defined, whether or not that route compiled."""
    recalls: list[tuple[Document, Path_, str, str | None]] = field(default_factory=list)
    remembers: list[tuple[Document, Path_, RememberOptions]] = field(default_factory=list)

    def route(self, document: Document, index: int, body: Any) -> RouteSpec | None:
        """The route of item ``index``, or None after reporting why it cannot run. Every step
        runs even after another reported a problem, so one load shows them all."""
        where: Path_ = ("routes", index)
        body = revealed(body)  # secrets belong to connections; route options are plain text
        before = len(self.problems)
        route, complete = parse_leniently(document, RouteOptions, body, where, self.problems)
        if route is None:
            return None
        expansion: Expansion | None = document.expansions.get(index)
        variables = dict(expansion.variables) if expansion is not None else {}
        self._claim_name(document, where, route.name, expansion)
        items = self._sink_items(document, where, route)
        self._note_stores(document, where, route, items)
        agents_used: dict[str, Any] = {}
        """The agents table's entries the route uses (by name; ``@connection`` its connection's table)."""
        source, source_complete = endpoint_spec(document, where + ("source",), route.name, route.source, self.connections,
                                                self.problems, self.table, agents_used)
        ends: list[tuple[SinkPart, EndpointSpec | None]] = []
        all_complete, source_now = source_complete, source
        for part in (part for item in items for part in item.parts()):
            # each sink is checked as the route's one sink (its own mapping, when, templates): the
            # checks that do not look at the sink find the same problems again, reported once (a set)
            seen_as = replace(route, sink=dict(part.body), sinks=None)
            sink, sink_complete = endpoint_spec(document, where + part.path, route.name, part.body, self.connections,
                                                self.problems, self.table, agents_used, side="sink")
            handed_source, sink = hand_agents(source, sink, seen_as, variables, self.table, agents_used)
            if part is items[0].primary:
                source_now = handed_source
            self._check_delivers(document, where + part.path, route, sink)
            self._check_split(document, where + part.path, route.name, sink)
            checked = CheckedRoute(document, where, seen_as, source, sink, (source_complete, sink_complete), self.schemas, variables,
                                   bool(self.table), expansion, sink_path=part.path)
            for problem, error in route_checks(checked):
                (self.problems if error else self.warnings).append(problem)
            ends.append((part, sink))
            all_complete = all_complete and sink_complete
        if not items:
            return None
        source = source_now
        if not (complete and all_complete) or source is None or any(sink is None for _, sink in ends):
            return None
        first = ends[0][1]
        assert first is not None
        placement = placement_of(document, where, route, source, first, self.connections, self.problems)
        if len(self.problems) > before or placement is None:
            return None
        if placement.ordered:
            ordered = endpoints.transport(source.protocol).ordered_source(source.options, placement.partitions,
                                                                          placement.partition_key or "")
            source = EndpointSpec(source.protocol, source.connection, ordered)
        sinks = tuple(EndpointSpec(sink.protocol, sink.connection, route_to_sink(sink.options, route)) for _, sink in ends if sink is not None)
        buffer = self._buffer(document, where, route, source)
        if buffer is False:
            return None
        fanned = self._sink_specs(items, sinks) if fans_out(route) else ()
        sink_mapping = None if fanned else items[0].primary.body.get("mapping")
        return RouteSpec(
            route.name, source, route.mapping, route.schema, sinks[0], sink_mapping,
            self._fingerprint(body, route, source, sinks, variables, agents_used),
            document.file, document.line(where), throttle=route.throttle, delivery=self._delivery(route, source, sinks), buffer=buffer,
            placement=placement, reply=route.reply, variables=variables, fair=route.fair, remember=route.remember,
            when=route.when, dedupe=DedupeSpec.parse(route.dedupe, route.name, _base_dir(document.file)), window=route.window,
            record=route.record, sinks=fanned,
        )

    def _sink_items(self, document: Document, where: Path_, route: RouteOptions) -> list[SinkItem]:
        """The route's sinks; exactly one of ``sink:`` and ``sinks:``, each sink's name its own."""
        if (route.sink is None) == (route.sinks is None):
            self.problems.append(document.problem(where, f"route {route.name!r}: give exactly one of sink: (one sink) "
                                                         "and sinks: (a list of sinks)"))
            return []
        items = sink_items(route)
        for key_path, message in duplicate_names(items):
            self.problems.append(document.problem(where + key_path, f"route {route.name!r}: {message}"))
        return items

    @staticmethod
    def _sink_specs(items: list[SinkItem], ends: tuple[EndpointSpec, ...]) -> tuple[SinkSpec, ...]:
        """The fan-out's sinks (engine/running/fanout.py), each with its endpoint as compiled."""
        specs, at = [], 0
        for item in items:
            primary = ends[at]
            at += 1
            fallback = None
            if item.fallback is not None:
                fallback = SinkSpec(item.fallback.name, ends[at], item.fallback.body.get("mapping"))
                at += 1
            specs.append(SinkSpec(item.primary.name, primary, item.primary.body.get("mapping"), item.when, fallback, item.after))
        return tuple(specs)

    def _claim_name(self, document: Document, where: Path_, name: str, expansion: Expansion | None) -> None:
        """A route name is unique across the directory."""
        if name in self.defined:
            first_file, first_line = self.defined[name]
            template = " (a for_each route's name must hold a variable that differs by item)" if expansion is not None else ""
            self.problems.append(document.problem(where + ("name",), f"route {name!r} is already defined at {first_file}:{first_line}{together_hint(document, first_file)}{template}"))
        self.defined.setdefault(name, (document.file, document.line(where)))

    def _note_stores(self, document: Document, where: Path_, route: RouteOptions, items: list[SinkItem]) -> None:
        """The stores the route remembers into and those its mappings ``recall()`` (checked
        against each other once every route is read: :func:`store_problems`)."""
        entries = remember_entries(route.remember)
        self.remembers.extend((document, remember_path(where, route, index), entry) for index, entry in enumerate(entries))
        sink_reads = [(where + part.path + (key,), part.body.get(key)) for item in items for part in item.parts()
                      for key in ("mapping", "when")]
        for key_path, expression in ((where + ("mapping",), route.mapping), *sink_reads,
                                     (where + ("when",), route.when),
                                     (where + ("dedupe", "key"), route.dedupe.key if route.dedupe else None),
                                     *((where + ("window",) + key, text) for key, text in window_expressions(route.window)),
                                     *((remember_path(where, route, index) + ("value",), entry.value)
                                       for index, entry in enumerate(entries))):
            if isinstance(expression, str) or expression is None:
                self.recalls.extend((document, key_path, route.name, store) for store in dict.fromkeys(recall_names(expression)))

    def _check_split(self, document: Document, where: Path_, route: str, sink: EndpointSpec | None) -> None:
        """What a sink cannot do on a connection split over the workers (``Transport.split_problems``)."""
        spec = self.connections.get(sink.connection) if sink is not None else None
        if sink is None or spec is None or spec.options is None:
            return
        transport = endpoints.transport(sink.protocol)
        if transport.splits_connection(spec.options):
            for key, message in transport.split_problems("sink", sink.options):
                self.problems.append(document.problem(where + (sink.protocol,) + ((key,) if key else ()),
                                                      f"route {route!r}: sink: {message}"))

    def _check_delivers(self, document: Document, where: Path_, route: RouteOptions, sink: EndpointSpec | None) -> None:
        """A sink that delivers nowhere (a store's) makes sense only on a route that remembers."""
        if not remember_entries(route.remember) and sink is not None and not endpoints.transport(sink.protocol).delivers:
            self.problems.append(document.problem(where, (
                f"route {route.name!r}: a {sink.protocol} sink delivers nowhere: the route needs remember: {{store: NAME}} "
                "(what it remembers is all it does)")))

    def _fingerprint(self, body: Any, route: RouteOptions, source: EndpointSpec, sinks: tuple[EndpointSpec, ...],
                     variables: Mapping[str, Any], agents_used: Mapping[str, Any]) -> str:
        """What identifies the route's running form: its item as written, its connections'
        fingerprints and size limits, its schemas' contents, its template item and the agents
        it uses; a reload restarts the routes whose fingerprint changed."""
        used = {end.connection: self.connections.get(end.connection) for end in (source, *sinks)}
        schema = self.schemas.get(route.schema) if route.schema is not None else None
        return hashlib.sha256(
            json.dumps(
                [body, {k: (v.fingerprint, v.max_message_bytes) if v else None for k, v in used.items()},
                 schema.digest if schema else None,
                 _reply_schema_digest(route, self.schemas)] + ([variables] if variables else [])
                + ([agents_used] if agents_used else []),
                sort_keys=True,
                default=json_default,
            ).encode()
        ).hexdigest()[:16]

    def _delivery(self, route: RouteOptions, source: EndpointSpec, sinks: tuple[EndpointSpec, ...]) -> RouteDelivery:
        return RouteDelivery(
            max_attempts=route.max_attempts,
            overflow=route.overflow,
            max_message_bytes=self.connections[source.connection].max_message_bytes,
            sink_max_message_bytes=min(self.connections[sink.connection].max_message_bytes for sink in sinks),
            max_age_ns=None if route.max_age is None else int(route.max_age * 1e9),
        )

    def _buffer(self, document: Document, where: Path_, route: RouteOptions, source: EndpointSpec) -> BufferSpec | None | Literal[False]:
        """Where messages wait while the sink is down (None: nowhere); False after a problem."""
        buffer = BufferSpec.parse(route.buffer, endpoints.transport(source.protocol).redelivers(source.options), _base_dir(document.file))
        if buffer is not None and buffer.spill_dir is not None and buffer.spill_dir.exists() and not buffer.spill_dir.is_dir():
            self.problems.append(document.problem(where + ("buffer", "spill_dir"), f"route {route.name!r}: spill_dir {str(buffer.spill_dir)!r} is not a directory"))
            return False
        return buffer


def _reply_schema_digest(route: RouteOptions, schemas: SchemaRegistry) -> str | None:
    """A new version of the reply schema is a change of the route (as for its own schema)."""
    if route.reply is None or not route.reply.schema:
        return None
    schema = schemas.get(route.reply.schema)
    return schema.digest if schema is not None else None


def _base_dir(file: str) -> Path:
    return Path(file).resolve().parent
