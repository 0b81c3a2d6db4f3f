"""The route language: a directory of YAML files compiled into route specifications.

Loading is all-or-nothing and never connects to anything: every file is parsed with
line numbers, environment variables are substituted, the result is validated against
the route-file JSON Schema shipped with the package, and every route is checked
(connections, JMESPath, schemas, endpoint options). All problems are collected, each
as ``file:line: message``, so ``check`` and a reload report the same errors the same way.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from pathlib import Path
from typing import Any, Mapping

from engine import endpoints
from engine.common.redaction import json_default, revealed
from engine.common.schemas import SchemaRegistry
from engine.language import agents as agents_table
from engine.language.connection_loading import compile_connections, compile_dead_letters, private_broker_warnings
from engine.language.endpoint_specs import endpoint_spec, hand_agents, parse_leniently, placement_of, route_to_sink
from engine.language.mapping import recall_names
from engine.language.reading import ROUTE_FILE_VALIDATOR, ItemFiles, document_items, read_agents_table, route_files, together_hint
from engine.language.route_checks import captured_warnings, competing_consumers, remember_path, route_checks, shadowing_warnings, store_problems
from engine.language.route_options import RouteOptions
from engine.language.route_yaml import Document, Path_, Problem, parse_document
from engine.language.specs import ConnectionSpec, EndpointSpec, RoutesConfig, RouteSpec
from engine.language.stage_options import BufferSpec, DedupeSpec, RouteDelivery
from engine.language.stores import RememberOptions, remember_entries
from engine.language.templates import Expansion, expand_routes, is_items_text
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
    routes: dict[str, RouteSpec] = {}
    defined: dict[str, tuple[str, int]] = {}
    """Where each route name was first defined, whether or not that route compiled."""
    recalls: list[tuple[Document, Path_, str, str | None]] = []
    remembers: list[tuple[Document, Path_, RememberOptions]] = []
    for document in documents:
        for index, body in document_items(document, "routes", list):
            where: Path_ = ("routes", index)
            body = revealed(body)  # secrets belong to connections; route options are plain text
            before = len(problems)
            route, complete = parse_leniently(document, RouteOptions, body, where, problems)
            if route is None:
                continue
            name = route.name
            expansion: Expansion | None = document.expansions.get(index)
            variables = dict(expansion.variables) if expansion is not None else {}
            if name in defined:
                first_file, first_line = defined[name]
                template = " (a for_each route's name must hold a variable that differs by item)" if expansion is not None else ""
                problems.append(document.problem(where + ("name",), f"route {name!r} is already defined at {first_file}:{first_line}{together_hint(document, first_file)}{template}"))
            defined.setdefault(name, (document.file, document.line(where)))
            entries = remember_entries(route.remember)
            remembers.extend((document, remember_path(where, route, index), entry) for index, entry in enumerate(entries))
            for key_path, expression in ((where + ("mapping",), route.mapping), (where + ("sink", "mapping"), route.sink.get("mapping")),
                                         (where + ("when",), route.when),
                                         (where + ("dedupe", "key"), route.dedupe.key if route.dedupe else None),
                                         *((remember_path(where, route, index) + ("value",), entry.value)
                                           for index, entry in enumerate(entries))):
                recalls.extend((document, key_path, name, store) for store in dict.fromkeys(recall_names(expression)))
            agents_used: dict[str, Any] = {}
            """The agents table's entries the route uses (by name; ``@connection`` its connection's table)."""
            source, source_complete = endpoint_spec(document, where + ("source",), name, route.source, connections, problems,
                                                table, agents_used)
            sink, sink_complete = endpoint_spec(document, where + ("sink",), name, route.sink, connections, problems, table, agents_used)
            source, sink = hand_agents(source, sink, route, variables, table, agents_used)
            if not entries and sink is not None and not endpoints.transport(sink.protocol).delivers:
                problems.append(document.problem(where + ("sink",), (
                    f"route {name!r}: a {sink.protocol} sink delivers nowhere: the route needs remember: {{store: NAME}} "
                    "(what it remembers is all it does)")))
            mapping, schema_name, sink_mapping = route.mapping, route.schema, route.sink.get("mapping")
            route_checks(document, where, route, source, sink, (source_complete, sink_complete), schemas, problems, warnings,
                          variables, bool(table))
            if expansion is not None:
                warnings.extend(shadowing_warnings(document, where, route, expansion, schemas))
                warnings.extend(captured_warnings(document, where, route, source, expansion))
            if not (complete and source_complete and sink_complete):
                continue
            placement = placement_of(document, where, route, source, sink, connections, problems) if source and sink else None
            if len(problems) > before or not (source and sink and placement):
                continue
            if placement.ordered:
                source = EndpointSpec(source.protocol, source.connection, endpoints.transport(source.protocol).ordered_source(source.options))
            sink = EndpointSpec(sink.protocol, sink.connection, route_to_sink(sink.options, route))
            used = {source.connection: connections.get(source.connection), sink.connection: connections.get(sink.connection)}
            schema = schemas.get(schema_name)
            fingerprint = hashlib.sha256(
                json.dumps(
                    [body, {k: (v.fingerprint, v.max_message_bytes) if v else None for k, v in used.items()},
                     schema.digest if schema else None,
                     _reply_schema_digest(route, schemas)] + ([variables] if variables else [])
                    + ([agents_used] if agents_used else []),
                    sort_keys=True,
                    default=json_default,
                ).encode()
            ).hexdigest()[:16]
            delivery = RouteDelivery(
                max_attempts=route.max_attempts,
                overflow=route.overflow,
                max_message_bytes=connections[source.connection].max_message_bytes,
                sink_max_message_bytes=connections[sink.connection].max_message_bytes,
                max_age_ns=None if route.max_age is None else int(route.max_age * 1e9),
            )
            buffer = BufferSpec.parse(route.buffer, endpoints.transport(source.protocol).redelivers(source.options), _base_dir(document.file))
            if buffer is not None and buffer.spill_dir is not None and buffer.spill_dir.exists() and not buffer.spill_dir.is_dir():
                problems.append(document.problem(where + ("buffer", "spill_dir"), f"route {name!r}: spill_dir {str(buffer.spill_dir)!r} is not a directory"))
                continue
            routes[name] = RouteSpec(
                name, source, mapping, schema_name, sink, sink_mapping, fingerprint,
                document.file, document.line(where), throttle=route.throttle, delivery=delivery, buffer=buffer,
                placement=placement, reply=route.reply, variables=variables, fair=route.fair, remember=route.remember,
                when=route.when, dedupe=DedupeSpec.parse(route.dedupe, name, _base_dir(document.file)),
            )
    problems.extend(store_problems(recalls, remembers))
    return routes


def _reply_schema_digest(route: RouteOptions, schemas: SchemaRegistry) -> str | None:
    """A new version of the reply schema is a change of the route (as for its own schema)."""
    if route.reply is None or not route.reply.schema:
        return None
    schema = schemas.get(route.reply.schema)
    return schema.digest if schema is not None else None


def _base_dir(file: str) -> Path:
    return Path(file).resolve().parent
