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
import re
from dataclasses import MISSING, dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any, Callable, Iterator, Literal, Mapping

import jsonschema

from engine import endpoints
from engine.common.options import OptionError, describe, evolve, fields_of, given, option, parse
from engine.common.placeholders import MappingError
from engine.common.processes import LOCAL_BROKER_ENV
from engine.common.redaction import Secret, json_default, revealed
from engine.common.schemas import SchemaRegistry
from engine.common.suggest import did_you_mean
from engine.endpoints.base import EndpointError, Transport
from engine.language import agents as agents_table
from engine.language.fieldcheck import mapping_field_problems, option_hint, reply_field_problems
from engine.language.readcheck import schema_checks
from engine.language.identity import connection_fingerprint, connection_key_files, exclusive_resource
from engine.language.mapping import compile_mapping, known_functions, literal_format_problems, meta_names, recall_names, unknown_functions
from engine.language.route_yaml import Document, Path_, Problem, parse_document
from engine.language.yaml_bounds import FileTooLarge, read_bounded
from engine.language.stage_options import (DEFAULT_MAX_ATTEMPTS, DEFAULT_MAX_MESSAGE_BYTES, BufferOptions, BufferSpec, DeadLetterSpec,
                                           DeadLettersOptions, DedupeOptions, DedupeSpec, FairOptions, ReplyOptions, RouteDelivery,
                                           ThrottleOptions)
from engine.language.stores import FAILURE_META, RememberOptions, remember_entries
from engine.language.templates import Expansion, expand_routes, is_items_text

ROUTE_FILE_SCHEMA: dict[str, Any] = json.loads(
    resources.files("engine.language").joinpath("route_file.schema.json").read_text(encoding="utf-8")
)
_ROUTE_FILE_VALIDATOR = jsonschema.Draft202012Validator(ROUTE_FILE_SCHEMA)
NAME_PATTERN = "^[A-Za-z0-9_][A-Za-z0-9_.-]*$"
"""Connection, route and lease names: safe in queue names, file names and metrics labels."""


# The route file's own keys, declared once (engine/common/options.py); engine/language/route_schema.py builds
# the route-file JSON Schema from these and from each protocol's option classes.

@dataclass(frozen=True, kw_only=True)
class ConnectionLimits:
    """Keys of ``connections.<name>`` beside the protocol key that every protocol has."""

    max_message_bytes: int = option(DEFAULT_MAX_MESSAGE_BYTES, minimum=1,
                                    description="larger messages in or out of this connection are dead-lettered unparsed")


@dataclass(frozen=True, kw_only=True)
class LeaseOptions:
    __schema_description__ = "active_standby: the lease queue's connection and timing"

    connection: str | None = option(None, description="connection holding the lease (one that holds leases: a broker); default: the sink's if it can, else the only one that can")
    heartbeat: float = option(1.0, exclusive_minimum=0, description="seconds between the active instance's heartbeats")
    name: str | None = option(None, pattern=NAME_PATTERN,
                              description="lease shared by routes that must fail over together (one robot's topics); default: the route name")


ENDPOINT_DESCRIPTION = "exactly one of " + " / ".join(endpoints.PROTOCOLS)


@dataclass(frozen=True, kw_only=True)
class RouteOptions:
    """One item of ``routes:``. ``source`` and ``sink`` hold one protocol key each, whose
    options the protocol's transport declares (``Transport.source_options``/``sink_options``)."""

    name: str = option(pattern=NAME_PATTERN, description="unique across the directory; names the route in logs, metrics, "
                                                         "dead-letter headers and /tap/NAME; with for_each, {var} in it takes each item's value")
    for_each: tuple[dict[str, Any], ...] | str | None = option(
        None, description="a route template: one route per item (an object of variables), listed here or in a YAML file of "
                          "such a list beside the route file (watched), or agents: one route per agent of the agents table that has "
                          "every variable the route uses ({agent} its name); {var} in the name and in any string value "
                          "takes the item's value, and mappings read it with meta('var')")
    description: str | None = option(None, description="free text")
    max_attempts: int = option(DEFAULT_MAX_ATTEMPTS, minimum=1,
                               description="deliveries tried on transient sink failures (across redeliveries) before dead-lettering")
    overflow: Literal["block", "drop_oldest", "drop_newest"] = option(
        "block", description="when the in-memory queue of a source that pushes messages is full: block stops taking (where the "
                             "protocol can be paused; each source's description says what it does otherwise), or drop the oldest / newest (counted)")
    buffer: Literal[False] | BufferOptions | None = option(
        None, description="messages held while the sink is down (default for sources that cannot redeliver: in memory, 10000); false: none")
    source: dict[str, Any] = option(description=ENDPOINT_DESCRIPTION)
    mapping: str | None = option(None, nullable=True, description="JMESPath from the source message to the canonical message; "
                                                                  "absent or null: identity (the original bytes are forwarded)")
    schema: str | None = option(None, description="required: the canonical schema the mapping's result must satisfy, NAME (newest "
                                                  "version) or NAME.vN (pinned), from schemas/; raw_json passes any object")
    when: str | None = option(None, description=(
        "condition: JMESPath on the canonical message (meta(name) reads the source's metadata); a message for which it "
        "gives false, null or an empty string, list or object is settled unsent and counted filtered, never dead-lettered"))
    dedupe: DedupeOptions | None = option(None)
    throttle: ThrottleOptions | None = option(None)
    fair: FairOptions | None = option(None)
    remember: RememberOptions | tuple[RememberOptions, ...] | None = option(None)
    priority: Literal["high", "normal", "low"] = option(
        "normal", description="on a link several routes share (a telemetry radio), the order of what is sent next: high before "
                              "normal before low, tunnel routes included; commands and missions always go first")
    max_age: float | None = option(None, exclusive_minimum=0, description=(
        "seconds from reception after which a message is worthless (telemetry): one older when it would be sent (from "
        "the buffer after an outage, a throttle slot, a retry) is dropped and counted expired; absent: every message arrives"))
    sink: dict[str, Any] = option(description=ENDPOINT_DESCRIPTION)
    reply: ReplyOptions | None = option(None)
    ordered: bool = option(False, description="one engine instance at a time carries the route, in order (sources whose broker offers it: a single active consumer)")
    instances: tuple[str, ...] | None = option(None, min_items=1,
                                               description="run the route only on these engine instances (--instance NAME, default the host name)")
    active_standby: bool = option(False, description="every instance runs the source, only the holder of the broker lease forwards")
    lease: LeaseOptions | None = option(None)
    record: bool = option(True, description="with --record DIR: record what the route receives and the canonical messages it "
                                            "sends (MCAP, docs/operations.md); false leaves the route out of the recording")


class RoutesInvalid(Exception):
    """The directory does not compile; ``problems`` lists every reason, ``warnings`` what
    ``check`` would warn about as well."""

    def __init__(self, problems: list[Problem], warnings: list[Problem] | None = None) -> None:
        super().__init__("\n".join(map(str, problems)))
        self.problems = problems
        self.warnings = warnings or []


@dataclass(frozen=True)
class ConnectionSpec:
    name: str
    protocol: str
    settings: Mapping[str, Any]
    """As written (the fingerprint's input); ``options`` is the typed value endpoints use."""
    file: str = field(default="", compare=False)
    line: int = field(default=0, compare=False)
    fingerprint: str = ""
    """Settings and the contents of the key files they name (engine.language.identity)."""
    exclusive: str | None = None
    """The resource only one open connection can hold (``udp:14550``), if any."""
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    """Messages larger than this, in or out of this connection, are dead-lettered unparsed."""
    options: Any = field(default=None, compare=False)
    """The transport's ``connection_options`` instance, parsed once at load (None if invalid)."""
    key_files: tuple[Path, ...] = ()
    """Absolute paths of the files it reads when it opens (signing keys): watched for edits."""


@dataclass(frozen=True)
class EndpointSpec:
    protocol: str
    connection: str
    options: Any
    """The transport's ``source_options``/``sink_options`` instance, parsed once at load."""


@dataclass(frozen=True)
class RouteSpec:
    name: str
    source: EndpointSpec
    mapping: str | None
    schema: str
    sink: EndpointSpec
    sink_mapping: str | None
    fingerprint: str
    file: str = field(default="", compare=False)
    line: int = field(default=0, compare=False)
    throttle: ThrottleOptions | None = None
    """At most max_rate messages/s per value of the canonical field ``per``."""
    delivery: RouteDelivery = field(default=RouteDelivery(), compare=False)
    """max_attempts, overflow and the size limits (the fingerprint covers them)."""
    buffer: BufferSpec | None = field(default=None, compare=False)
    """Where messages wait while the sink is down (``buffer:``); the fingerprint covers it."""
    placement: Placement = field(default_factory=lambda: Placement())
    """Which engine instances carry the route (scale-out); the default: every instance."""
    reply: ReplyOptions | None = None
    """How the sink's answers to a request are shaped (``reply:``; engine/running/replies.py)."""
    fair: FairOptions | None = None
    """One queue per agent in the source's inbox, taken round-robin (``fair:``; engine/running/fairness.py)."""
    variables: Mapping[str, Any] = field(default_factory=dict, compare=False)
    """The route's template variables (its ``for_each`` item; the fingerprint covers them):
    ``meta(name)`` gives them as constants folded into the compiled mapping."""
    remember: RememberOptions | tuple[RememberOptions, ...] | None = None
    """The stores its canonical messages are kept in, and when (engine/language/stores.py)."""
    when: str | None = None
    """The route's condition (``when:``): messages it rejects are settled unsent, counted ``filtered``."""
    dedupe: DedupeSpec | None = field(default=None, compare=False)
    """The route's ``dedupe:`` (engine/running/dedupe.py), its key file resolved; the fingerprint covers it."""
    record: bool = field(default=True, compare=False)
    """Recorded under ``--record`` (engine/running/record.py); a change needs no restart of the route."""


@dataclass(frozen=True)
class Placement:
    """Where a route runs when several engine instances share a routes directory.

    ``instances``: only on these instances (by ``--instance`` name). ``active_standby``:
    on every instance that can see the source, but only the holder of the broker lease
    ``lease_name`` (on AMQP connection ``lease_connection``) forwards. ``ordered`` (AMQP
    sources): single active consumer, one instance at a time, in order."""

    instances: tuple[str, ...] | None = None
    active_standby: bool = False
    ordered: bool = False
    lease_name: str = ""
    lease_connection: str | None = None
    lease_heartbeat: float = 1.0

    def runs_on(self, instance: str) -> bool:
        return self.instances is None or instance in self.instances


@dataclass(frozen=True)
class RoutesConfig:
    """A compiled directory: what the engine runs, identified by a content hash."""

    directory: Path
    connections: Mapping[str, ConnectionSpec]
    routes: Mapping[str, RouteSpec]
    content_hash: str
    warnings: tuple[Problem, ...] = ()
    """Accepted but probably not what was meant (two routes consuming one AMQP queue)."""
    dead_letters: DeadLetterSpec = DeadLetterSpec()
    """The engine's one dead-letter destination (``dead_letters:``, resolved)."""
    data_files: frozenset[Path] = frozenset()
    """``for_each`` files the routes were expanded from (absolute paths): an edit is a change."""

    @property
    def key_files(self) -> frozenset[Path]:
        """Every key file a connection reads: a new key written there is a configuration change."""
        return frozenset(path for connection in self.connections.values() for path in connection.key_files)

    @property
    def watched_files(self) -> frozenset[Path]:
        """Files outside the route files whose edits are configuration changes: key files and
        ``for_each`` files."""
        return self.key_files | self.data_files


def route_files(directory: Path) -> list[Path]:
    """``*.yaml``/``*.yml`` files, skipping editors' hidden and backup files; a single file
    given instead of a directory is a directory of one file."""
    if directory.is_file():
        return [directory]
    return sorted(
        path
        for pattern in ("*.yaml", "*.yml")
        for path in directory.glob(pattern)
        if path.is_file() and not path.name.startswith(".") and not path.name.endswith("~")
        and not is_test_file(path)
    )


def is_test_file(path: Path) -> bool:
    """``*.test.yaml`` files hold route tests (``rabbitros-engine test``), never routes."""
    return path.name.endswith((".test.yaml", ".test.yml"))


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
    table = _agents_table(texts, env, problems)
    item_files.agents = table
    for path, text in texts:
        expand = functools.partial(expand_routes, str(path), read_items=item_files.reader(path))
        document = parse_document(str(path), text, env, problems, _ROUTE_FILE_VALIDATOR, keep_invalid=True, expand=expand)
        if document is not None:
            documents.append(document)
    for schema_path, message in schemas.problems:
        problems.append(Problem(str(schema_path), 0, message))
    connections = _compile_connections(documents, problems)
    warnings: list[Problem] = []
    routes = _compile_routes(documents, connections, schemas, problems, warnings, table)
    dead_letters = _compile_dead_letters(documents, connections, problems)
    warnings.extend(_competing_consumers(routes))
    warnings.extend(_private_broker_warnings(connections, env))
    warnings.extend(item_files.unused())
    if problems:
        raise RoutesInvalid(sorted(set(problems)), sorted(set(warnings)))
    digest.update(json.dumps(sorted((n, r.fingerprint) for n, r in routes.items())).encode())  # schemas, key files, items
    return RoutesConfig(directory, connections, routes, digest.hexdigest()[:12],
                        warnings=tuple(sorted(set(warnings))), dead_letters=dead_letters,
                        data_files=frozenset(item_files.read))


_ITEMS_VALIDATOR = jsonschema.Draft202012Validator({"type": "array", "items": {"type": "object"}})


class ItemFiles:
    """``for_each`` files as the loader reads them: each once per load, with ``${VAR}`` and
    line numbers, relative to the route file naming it; those in the routes directory come
    from the texts already read (they are not route files)."""

    def __init__(self, env: Mapping[str, str], problems: list[Problem]) -> None:
        self.env = env
        self.problems = problems
        self.texts: dict[Path, str] = {}
        """List-topped files of the routes directory, by absolute path."""
        self.read: dict[Path, list[Any] | None] = {}
        self.agents: agents_table.Table = {}
        """The directory's agents table: ``for_each: agents`` expands over it."""

    def reader(self, route_file: Path) -> Callable[[str, Path_], tuple[list[Any] | None, str | None]]:
        def read(name: str, where: Path_) -> tuple[list[Any] | None, str | None]:
            if name == agents_table.AGENTS:
                if not self.agents:
                    return None, "for_each: agents expands over the agents table, and no file has a top-level agents: mapping"
                return agents_table.items(self.agents), None
            path = (route_file.parent / name).resolve()
            if path not in self.read:
                self.read[path] = self._load(path)
            items = self.read[path]
            if items is None:
                return None, f"route template: for_each file {name!r} ({path}) is not a readable YAML list of objects (see its own problems)"
            return items, None

        return read

    def _load(self, path: Path) -> list[Any] | None:
        text = self.texts.get(path)
        if text is None:
            try:
                text = read_bounded(path)
            except FileTooLarge as exc:
                self.problems.append(Problem(str(path), 1, str(exc)))
                return None
            except (OSError, UnicodeDecodeError) as exc:
                self.problems.append(Problem(str(path), 0, f"cannot read for_each file: {exc}"))
                return None
        if not is_items_text(text) and not any(line.strip() and not line.lstrip().startswith("#") for line in text.splitlines()):
            return []  # every item deleted (comments may stay): no routes from the template
        before = len(self.problems)
        document = parse_document(str(path), text, self.env, self.problems, _ITEMS_VALIDATOR)
        if document is None or len(self.problems) > before:
            return None
        return document.data if isinstance(document.data, list) else None

    def unused(self) -> list[Problem]:
        return [Problem(str(path), 1, "a YAML list, so not a route file; no route names it in for_each (left out)")
                for path in sorted(self.texts) if path not in self.read]


_AGENTS_KEY = re.compile(r"^agents\s*:", re.MULTILINE)
_VARIABLE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def _agents_table(texts: list[tuple[Path, str]], env: Mapping[str, str], problems: list[Problem]) -> dict[str, dict[str, Any]]:
    """The directory's agents table (engine/language/agents.py): every file's top-level ``agents:``,
    read before the routes are expanded (``for_each: agents`` needs it); names unique across
    the directory. The schema's problems are reported where the file itself is read."""
    table: dict[str, dict[str, Any]] = {}
    where_defined: dict[str, tuple[str, int]] = {}
    for path, text in texts:
        if not _AGENTS_KEY.search(text):
            continue
        document = parse_document(str(path), text, env, [], _ROUTE_FILE_VALIDATOR, keep_invalid=True)
        if document is None:
            continue
        body = document.data.get(agents_table.AGENTS)
        if not isinstance(body, dict):
            continue
        for name, entry in body.items():
            line = document.line((agents_table.AGENTS, name))
            if name in where_defined:
                first_file, first_line = where_defined[name]
                problems.append(Problem(str(path), line, f"agent {name!r} is already defined at {first_file}:{first_line}"
                                                         f"{_together(document, first_file)}"))
                continue
            where_defined[name] = (str(path), line)
            if not isinstance(entry, dict) or any(not isinstance(key, str) or not _VARIABLE.match(key) for key in entry):
                continue  # the schema says what it should be
            if agents_table.AGENT in entry:
                problems.append(Problem(str(path), line, f"agent {name!r}: {agents_table.AGENT!r} is the agent's name "
                                                         f"(for_each: agents gives it as {{agent}}); use another key"))
                continue
            table[name] = revealed(entry)
    return table


def _compile_connections(
    documents: list[Document], problems: list[Problem]
) -> dict[str, ConnectionSpec]:
    connections: dict[str, ConnectionSpec] = {}
    for document in documents:
        for name, body in _items(document, "connections", dict):
            where = ("connections", name)
            if not isinstance(body, dict):
                continue  # the schema said what it should be
            protocols = [p for p in endpoints.PROTOCOLS if p in body]
            if len(protocols) != 1:
                if not document.reported(where):
                    problems.append(document.problem(where, f"connection {name!r} must name exactly one of {', '.join(endpoints.PROTOCOLS)}"))
                continue
            protocol = protocols[0]
            if name in connections:
                first = connections[name]
                problems.append(document.problem(where, f"connection {name!r} is already defined at {first.file}:{first.line}{_together(document, first.file)}"))
                continue
            misplaced = _misplaced(protocol, body)
            if misplaced is not None:  # reported, and left out of the options: routes still find the connection
                problems.append(document.problem(where + (misplaced[0],), f"{misplaced[0]!r} applies only to {misplaced[1]} connections"))
            settings, options, checks = _connection_options(protocol, body)
            for key, message in checks:
                key_path = where + (key if isinstance(key, tuple) else (protocol,) if key is None else (protocol, key))
                if not document.reported(key_path) and not document.reported(where + (protocol,)):
                    problems.append(document.problem(key_path, f"connection {name!r}: {message}"))
            connection = _identified(ConnectionSpec(
                name, protocol, settings, document.file, document.line(where),
                max_message_bytes=body.get("max_message_bytes", ConnectionLimits.max_message_bytes), options=options,
            ))
            holder = next((c for c in connections.values() if connection.exclusive and c.exclusive == connection.exclusive), None)
            if holder is not None:
                problems.append(document.problem(where + (protocol,), f"connection {name!r}: {connection.exclusive} is already used by connection {holder.name!r} at {holder.file}:{holder.line}"))
            connections[name] = connection
    return connections


def _together(document: Document, other_file: str) -> str:
    """For a name defined in two files: why both count (alternatives side by side, as two
    versions of one example, collide)."""
    if other_file == document.file:
        return ""
    return " (every file of a routes directory is loaded together: keep alternative files in separate directories)"


def _items(document: Document, key: str, kind: type[Any]) -> Iterator[Any]:
    """``connections`` (a mapping's items) or ``routes`` (a list's items, numbered) of a
    document; nothing when the value is of another shape (the schema reported it)."""
    value = document.data.get(key)
    if not isinstance(value, kind):
        return iter(())
    return iter(value.items()) if kind is dict else enumerate(value)


def _beside_keys(transport: Transport) -> frozenset[str]:
    """Connection options written beside the protocol key (``baud:`` next to ``mavlink:``)."""
    if not transport.options_beside:
        return frozenset()
    return frozenset(f.name for f in fields_of(transport.connection_options)) - {transport.connection_shorthand}


_LIMIT_KEYS = frozenset(f.name for f in fields_of(ConnectionLimits))


def _beside_owners() -> dict[str, str]:
    owners: dict[str, str] = {}
    for protocol in endpoints.PROTOCOLS:
        try:
            owners.update(dict.fromkeys(_beside_keys(endpoints.transport(protocol)), protocol))
        except EndpointError:
            continue
    return owners


def _misplaced(protocol: str, body: Mapping[str, Any]) -> tuple[str, str] | None:
    """``(key, protocol it belongs to)`` for a connection option written beside the wrong
    protocol key (``baud:`` beside ``amqp:``)."""
    extra = [key for key in body if key not in endpoints.PROTOCOLS and key not in _LIMIT_KEYS]
    if not extra:
        return None
    try:
        own = _beside_keys(endpoints.transport(protocol))
    except EndpointError:  # reported with the connection's options
        return None
    wrong = [key for key in extra if key not in own]
    return (wrong[0], _beside_owners().get(wrong[0], "other")) if wrong else None


def _connection_options(protocol: str, body: Mapping[str, Any]) -> tuple[dict[str, Any], Any, list[tuple[Any, str]]]:
    """``(settings as written, typed options or None, problems)`` of one connection; each
    problem is ``(option key or key path or None, message)``."""
    try:
        transport = endpoints.transport(protocol)
    except EndpointError as exc:
        value = body[protocol]
        return ({"url": value} if isinstance(value, (str, Secret)) else dict(value) if isinstance(value, Mapping) else {}), None, [(None, str(exc))]
    settings = _connection_settings(transport, body)
    if not transport.accepts_secrets:
        settings = revealed(settings)
    try:
        options = parse(transport.connection_options, settings)
    except OptionError as exc:
        return settings, None, [(_connection_key(transport, path), describe(path, message))
                                for path, message in exc.problems]
    try:
        return settings, options, list(transport.check_connection(options))
    except EndpointError as exc:
        return settings, options, [(None, str(exc))]


def _connection_settings(transport: Transport, body: Mapping[str, Any]) -> dict[str, Any]:
    """The connection's options as one mapping: the protocol key's value (a string stands
    for the shorthand option, the url) and the options beside it."""
    value = body[transport.name]
    if isinstance(value, (str, Secret)) and transport.connection_shorthand:
        settings: dict[str, Any] = {transport.connection_shorthand: value}
    else:
        settings = dict(value) if isinstance(value, Mapping) else {}  # another shape: the schema reported it
    settings.update({key: body[key] for key in _beside_keys(transport) if key in body})
    return settings


def _connection_key(transport: Transport, path: Path_) -> Path_:
    """Where in ``connections.<name>`` an option's key path points."""
    if transport.options_beside:
        return (transport.name,) if path[:1] == (transport.connection_shorthand,) else path
    return (transport.name, *path)


def _default_connection(protocol: str) -> ConnectionSpec:
    transport = endpoints.transport(protocol)
    settings = dict(transport.default_connection_settings(os.environ))
    try:
        options = parse(transport.connection_options, settings)
    except OptionError as exc:
        raise EndpointError(f"default {protocol} connection: {exc}") from None
    return _identified(ConnectionSpec(f"default-{protocol}", protocol, settings, options=options))


def _private_broker_warnings(connections: Mapping[str, ConnectionSpec], env: Mapping[str, str]) -> list[Problem]:
    """With ``--local-broker``, each connection that names a broker other than the private one
    (its transport says, ``Transport.private_broker_warning``): it keeps going where it says (a
    route file means what it says, and one with two brokers must not become one with a single
    broker under a flag), so say so at load."""
    node = env.get(LOCAL_BROKER_ENV)
    if node is None:
        return []
    named = f"--local-broker's private node ({node})" if node else "--local-broker's private node"
    warnings = []
    for spec in connections.values():
        if spec.options is None or spec.name.startswith("default-"):
            continue
        try:
            warning = endpoints.transport(spec.protocol).private_broker_warning(spec.options, env)
        except EndpointError:
            continue
        if warning:
            warnings.append(Problem(spec.file, spec.line, f"connection {spec.name!r} {warning.replace('{private}', named)}"))
    return warnings


def _identified(spec: ConnectionSpec) -> ConnectionSpec:
    return replace(
        spec,
        fingerprint=connection_fingerprint(spec.protocol, spec.settings, spec.options),
        exclusive=exclusive_resource(spec.protocol, spec.options),
        key_files=tuple(Path(name).expanduser().resolve() for name in connection_key_files(spec.protocol, spec.options)),
    )


def _competing_consumers(routes: Mapping[str, RouteSpec]) -> tuple[Problem, ...]:
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
        for index, body in _items(document, "routes", list):
            where: Path_ = ("routes", index)
            body = revealed(body)  # secrets belong to connections; route options are plain text
            before = len(problems)
            route, complete = _parse_leniently(document, RouteOptions, body, where, problems)
            if route is None:
                continue
            name = route.name
            expansion: Expansion | None = document.expansions.get(index)
            variables = dict(expansion.variables) if expansion is not None else {}
            if name in defined:
                first_file, first_line = defined[name]
                template = " (a for_each route's name must hold a variable that differs by item)" if expansion is not None else ""
                problems.append(document.problem(where + ("name",), f"route {name!r} is already defined at {first_file}:{first_line}{_together(document, first_file)}{template}"))
            defined.setdefault(name, (document.file, document.line(where)))
            entries = remember_entries(route.remember)
            remembers.extend((document, _remember_path(where, route, index), entry) for index, entry in enumerate(entries))
            for key_path, expression in ((where + ("mapping",), route.mapping), (where + ("sink", "mapping"), route.sink.get("mapping")),
                                         (where + ("when",), route.when),
                                         (where + ("dedupe", "key"), route.dedupe.key if route.dedupe else None),
                                         *((_remember_path(where, route, index) + ("value",), entry.value)
                                           for index, entry in enumerate(entries))):
                recalls.extend((document, key_path, name, store) for store in dict.fromkeys(recall_names(expression)))
            agents_used: dict[str, Any] = {}
            """The agents table's entries the route uses (by name; ``@connection`` its connection's table)."""
            source, source_complete = _endpoint(document, where + ("source",), name, route.source, connections, problems,
                                                table, agents_used)
            sink, sink_complete = _endpoint(document, where + ("sink",), name, route.sink, connections, problems, table, agents_used)
            source, sink = _hand_agents(source, sink, route, variables, table, agents_used)
            if not entries and sink is not None and not endpoints.transport(sink.protocol).delivers:
                problems.append(document.problem(where + ("sink",), (
                    f"route {name!r}: a {sink.protocol} sink delivers nowhere: the route needs remember: {{store: NAME}} "
                    "(what it remembers is all it does)")))
            mapping, schema_name, sink_mapping = route.mapping, route.schema, route.sink.get("mapping")
            _route_checks(document, where, route, source, sink, (source_complete, sink_complete), schemas, problems, warnings,
                          variables, bool(table))
            if expansion is not None:
                warnings.extend(_shadowing_warnings(document, where, route, expansion, schemas))
                warnings.extend(_captured_warnings(document, where, route, source, expansion))
            if not (complete and source_complete and sink_complete):
                continue
            placement = _placement(document, where, route, source, sink, connections, problems) if source and sink else None
            if len(problems) > before or not (source and sink and placement):
                continue
            if placement.ordered:
                source = EndpointSpec(source.protocol, source.connection, endpoints.transport(source.protocol).ordered_source(source.options))
            sink = EndpointSpec(sink.protocol, sink.connection, _route_to_sink(sink.options, route))
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
                record=route.record,
            )
    problems.extend(_store_problems(recalls, remembers))
    return routes


def _store_problems(recalls: list[tuple[Document, Path_, str, str | None]],
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


def _reply_schema_digest(route: RouteOptions, schemas: SchemaRegistry) -> str | None:
    """A new version of the reply schema is a change of the route (as for its own schema)."""
    if route.reply is None or not route.reply.schema:
        return None
    schema = schemas.get(route.reply.schema)
    return schema.digest if schema is not None else None


def _route_checks(
    document: Document,
    where: Path_,
    route: RouteOptions,
    source: EndpointSpec | None,
    sink: EndpointSpec | None,
    complete: tuple[bool, bool],
    schemas: SchemaRegistry,
    problems: list[Problem],
    warnings: list[Problem],
    variables: Mapping[str, Any] = {},
    has_agents: bool = False,
) -> None:
    """What can be known of a route before anything flows: its mappings compile and call
    known functions, its schema exists, its endpoints accept their options, a typed source
    has the fields the mapping reads; and (warnings) the schema declares the keys it sets.
    Each part is checked even when another failed, so one run shows every problem; an
    endpoint with an option at fault (``complete`` false) still tells the mapping check its
    type, but its transport's checks wait for the option to be fixed (they would only
    repeat the fault in other words)."""
    name, mapping, sink_mapping = route.name, route.mapping, route.sink.get("mapping")
    values = [(_remember_path(where, route, index) + ("value",), entry.value)
              for index, entry in enumerate(remember_entries(route.remember)) if entry.value is not None]
    expressions = ((where + ("mapping",), mapping), (where + ("sink", "mapping"), sink_mapping), (where + ("when",), route.when),
                   (where + ("dedupe", "key"), route.dedupe.key if route.dedupe else None))
    for key_path, expression in (*expressions, *values):
        for message in _mapping_problems(expression):
            problems.append(document.problem(key_path, f"route {name!r}: {message}"))
    schema_name = route.schema
    if schema_name is None:
        problems.append(document.problem(where, f"route {name!r}: 'schema' is required (use raw_json to pass any object)"))
    elif schemas.get(schema_name) is None:
        problems.append(document.problem(where + ("schema",), f"route {name!r}: unknown schema {schema_name!r} (known: {', '.join(n for n in schemas.names() if '.v' not in n)}){did_you_mean(schema_name, schemas.names())}"))
    else:
        for problem, error in schema_checks(document, where, route, sink, schemas, source_variables(source)):
            (problems if error else warnings).append(problem)
    _endpoint_checks(document, where, name, source if complete[0] else None, sink if complete[1] else None,
                     mapping, sink_mapping, problems)
    _reply_checks(document, where, route, source, sink, schemas, problems)
    if source:  # fields a typed source does not have
        for message in mapping_field_problems(source.protocol, source.options, mapping):
            problems.append(document.problem(where + ("mapping",), f"route {name!r}: {message}"))
        for key_path, expression in expressions:
            for message in _meta_problems(source, expression, variables, has_agents):
                problems.append(document.problem(key_path, f"route {name!r}: {message}"))
        for index, entry in enumerate(remember_entries(route.remember)):  # a failed entry's value also reads meta('failure')
            given = {**variables, FAILURE_META: None} if entry.when == "failed" else variables
            for message in _meta_problems(source, entry.value, given, has_agents):
                problems.append(document.problem(_remember_path(where, route, index) + ("value",), f"route {name!r}: {message}"))
        problems.extend(document.problem(where + ("fair",) + key, f"route {name!r}: fair: {message}")
                        for key, message in _fair_problems(source, route.fair, variables))


def _remember_path(where: Path_, route: RouteOptions, index: int) -> Path_:
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


def _captured_warnings(document: Document, where: Path_, route: RouteOptions, source: EndpointSpec | None,
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


def _shadowing_warnings(document: Document, where: Path_, route: RouteOptions, expansion: Expansion,
                        schemas: SchemaRegistry) -> Iterator[Problem]:
    """A ``{var}`` the template filled in at load where the route's canonical message has a
    field of the same name: the variable wins (the field is never read there), so say so."""
    declared = schemas.declared(route.schema) if route.schema else None
    if declared is None or declared.open:
        return
    for path, names in expansion.placeholders.items():
        if path[:1] not in (("sink",), ("throttle",)):
            continue
        for variable in names:
            if variable in declared.keys:
                yield document.problem(where + path, (
                    f"route {route.name!r}: {{{variable}}} in {'.'.join(map(str, path))} is the for_each variable "
                    f"({expansion.variables[variable]!r}), not the canonical field {variable!r} of {route.schema}: the variable wins "
                    f"(rename the variable to read the field at send time)"))


def _reply_checks(document: Document, where: Path_, route: RouteOptions, source: EndpointSpec | None,
                  sink: EndpointSpec | None, schemas: SchemaRegistry, problems: list[Problem]) -> None:
    """``reply:`` needs a source that can answer its sender; its mapping compiles and reads only
    fields the sink's answer has (when the sink's transport knows them); its schema exists."""
    reply, name = route.reply, route.name
    if reply is None:
        return
    if source is not None and not endpoints.transport(source.protocol).source_answers(source.options):
        able = [p for p in endpoints.PROTOCOLS if _replies(p)]
        problems.append(document.problem(where + ("reply",), f"route {name!r}: reply: this {source.protocol} source cannot "
                                                             f"answer its sender (protocols whose sources can: {', '.join(able)}; "
                                                             "see Calls in route-language.md)"))
    for message in _mapping_problems(reply.mapping):
        problems.append(document.problem(where + ("reply", "mapping"), f"route {name!r}: reply: {message}"))
    if sink is not None:
        for message in reply_field_problems(sink.protocol, sink.options, reply.mapping):
            problems.append(document.problem(where + ("reply", "mapping"), f"route {name!r}: reply: {message}"))
    if reply.schema is not None and schemas.get(reply.schema) is None:
        problems.append(document.problem(where + ("reply", "schema"), f"route {name!r}: reply: unknown schema {reply.schema!r}"
                                                                      f"{did_you_mean(reply.schema, schemas.names())}"))


def _replies(protocol: str) -> bool:
    try:
        return endpoints.transport(protocol).replies
    except EndpointError:
        return False


def _parse_leniently(
    document: Document, cls: type[Any], body: Any, where: Path_, problems: list[Problem],
    label: Callable[[Path_, str], str] = describe,
) -> tuple[Any, bool]:
    """``(options, complete)``: ``body`` parsed as ``cls``. On problems (reported here unless
    the schema reported the key already) it is parsed again without the keys at fault, so the
    rest of the item can still be checked; ``complete`` is then false and the item must not
    run. ``(None, False)`` when even that fails (a required key is at fault)."""
    try:
        return parse(cls, body, where), True
    except OptionError as exc:
        problems.extend(document.problem(path, label(path, message))
                        for path, message in exc.problems if not document.reported(path))
        at_fault = {path[len(where)] for path, _ in exc.problems if len(path) > len(where)}
    required = {f.name for f in fields_of(cls) if f.default is MISSING and f.default_factory is MISSING}
    if not isinstance(body, Mapping) or not at_fault or at_fault & required:
        return None, False
    try:
        return parse(cls, {key: value for key, value in body.items() if key not in at_fault}, where), False
    except OptionError:
        return None, False


def _compile_dead_letters(
    documents: list[Document], connections: dict[str, ConnectionSpec], problems: list[Problem]
) -> DeadLetterSpec:
    """``dead_letters: {connection, max_length}`` or ``{spool_dir, spool_max_bytes}``, from at
    most one file; default: the only connection that keeps dead letters (a broker's, see
    ``Connection.keeps_dead_letters``), else the local spool."""
    found = [(document, document.data["dead_letters"]) for document in documents if document.data.get("dead_letters")]
    if len(found) > 1:
        first = found[0][0]
        for other, _ in found[1:]:
            problems.append(other.problem(("dead_letters",), f"dead_letters is already defined at {first.file}:{first.line(('dead_letters',))}"))
    document: Document | None
    document, body = found[0] if found else (None, {})
    try:
        options = parse(DeadLettersOptions, body, ("dead_letters",))
    except OptionError as exc:
        assert document is not None
        problems.extend(document.problem(path, describe(path, message)) for path, message in exc.problems if not document.reported(path))
        return DeadLetterSpec()
    keepers = _capable(connections, "keeps_dead_letters")
    name = options.connection
    spec = DeadLetterSpec(max_length=options.max_length, spool_dir=options.spool_dir, spool_max_bytes=options.spool_max_bytes)
    if name is not None:
        if name not in keepers:
            assert document is not None
            problems.append(document.problem(("dead_letters", "connection"), f"dead_letters: {_incapable(name, 'keeps dead letters', keepers, connections)}"))
        return DeadLetterSpec(name, spec.max_length, spec.spool_dir, spec.spool_max_bytes)
    if options.spool_dir is not None or not keepers:
        return spec
    if len(keepers) > 1:
        where = document or documents[0]
        problems.append(where.problem(("dead_letters",), f"several connections ({', '.join(keepers)}) could keep dead letters; name one with dead_letters: {{connection: ...}}"))
        return spec
    return DeadLetterSpec(keepers[0], spec.max_length, spec.spool_dir, spec.spool_max_bytes)


def _capable(connections: Mapping[str, ConnectionSpec], capability: str) -> list[str]:
    """The connections whose protocol's connections have ``capability`` (a
    :class:`~engine.endpoints.base.Connection` class attribute such as ``keeps_dead_letters``)."""
    capable = []
    for name, spec in sorted(connections.items()):
        try:
            connection_type = endpoints.transport(spec.protocol).connection_type
        except EndpointError:  # not installed: reported where its routes are checked
            continue
        if getattr(connection_type, capability):
            capable.append(name)
    return capable


def _incapable(wanted: str, doing: str, capable: list[str], connections: Mapping[str, ConnectionSpec]) -> str:
    """Why ``wanted`` is no connection that ``doing`` (keeps dead letters...), and those that do."""
    if wanted not in connections:
        hint = did_you_mean(wanted, capable) or did_you_mean(wanted, connections)
        if hint:
            return f"unknown connection {wanted!r}{hint}"
        problem = f"unknown connection {wanted!r}"
    else:
        problem = f"connection {wanted!r} ({connections[wanted].protocol}) is not one that {doing}"
    named = [name for name in capable if not name.startswith("default-")]
    return f"{problem} (connections that do: {', '.join(named)})" if named else f"{problem} (no connection {doing})"


def _base_dir(file: str) -> Path:
    return Path(file).resolve().parent


def _placement(
    document: Document,
    where: Path_,
    options: RouteOptions,
    source: EndpointSpec,
    sink: EndpointSpec,
    connections: Mapping[str, ConnectionSpec],
    problems: list[Problem],
) -> Placement | None:
    """The route's scale-out keys (``instances``, ``active_standby``, ``lease``, ``ordered``)."""
    before = len(problems)
    route, ordered, active_standby = options.name, options.ordered, options.active_standby
    lease = options.lease if options.lease is not None and given(options.lease) else None
    source_transport = endpoints.transport(source.protocol)
    if ordered and not source_transport.supports_ordered:
        problems.append(document.problem(where + ("ordered",), f"route {route!r}: ordered does not apply to a {source.protocol} source (it is carried by one instance: use instances or active_standby)"))
    if active_standby and source_transport.shares_sources:
        problems.append(document.problem(where + ("active_standby",), f"route {route!r}: a {source.protocol} source is shared by competing consumers; use ordered: true for one instance at a time"))
    if lease and not active_standby:
        problems.append(document.problem(where + ("lease",), f"route {route!r}: lease needs active_standby: true"))
    lease_connection = None
    if active_standby:
        lease_connection = lease.connection if lease is not None else None
        holders = _capable(connections, "holds_leases")
        if lease_connection is None:
            if sink.connection in holders:
                lease_connection = sink.connection
            elif len(holders) != 1:
                problems.append(document.problem(where + ("active_standby",), f"route {route!r}: active_standby needs a connection that holds leases (a broker) for its lease; name one with lease: {{connection: NAME}}" + (f" ({', '.join(holders)})" if holders else "")))
            else:
                lease_connection = holders[0]
        elif lease_connection not in holders:
            problems.append(document.problem(where + ("lease", "connection"), f"route {route!r}: lease: {_incapable(lease_connection, 'holds leases', holders, connections)}"))
    if len(problems) > before:
        return None
    lease = lease or LeaseOptions()
    return Placement(
        instances=options.instances,
        active_standby=active_standby,
        ordered=ordered,
        lease_name=lease.name or route,
        lease_connection=lease_connection,
        lease_heartbeat=float(lease.heartbeat),
    )


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


def _endpoint(
    document: Document,
    where: Path_,
    route: str,
    body: Mapping[str, Any],
    connections: dict[str, ConnectionSpec],
    problems: list[Problem],
    table: agents_table.Table,
    used: dict[str, Any] | None = None,
) -> tuple[EndpointSpec | None, bool]:
    """``(spec, complete)`` of a route's source or sink; an incomplete spec (an option at
    fault left out) serves only to check the rest of the route."""
    protocols = [p for p in endpoints.PROTOCOLS if p in body]
    if len(protocols) != 1:
        if not document.reported(where):
            problems.append(document.problem(where, f"route {route!r}: {where[-1]} must name exactly one of {', '.join(endpoints.PROTOCOLS)}"))
        return None, False
    protocol = protocols[0]
    side = where[-1]
    try:
        transport = endpoints.transport(protocol)
    except EndpointError as exc:
        problems.append(document.problem(where + (protocol,), f"route {route!r}: {side}: {exc}"))
        return None, False
    named = _agent_names(document, where + (protocol,), route, transport, body[protocol], table, problems, used)
    if named is None:
        return None, False
    options, complete = _parse_leniently(
        document, transport.source_options if side == "source" else transport.sink_options, named,
        where + (protocol,), problems,
        lambda path, message: message if message.startswith("unknown key") else f"route {route!r}: {describe(path, message)}")
    if options is None:
        return None, False
    wanted = options.connection
    if wanted is None:
        candidates = sorted(n for n, c in connections.items() if c.protocol == protocol)
        if len(candidates) > 1:
            problems.append(document.problem(where + (protocol,), f"route {route!r}: several {protocol} connections ({', '.join(candidates)}); name one with 'connection:'"))
            return None, False
        if candidates:
            wanted = candidates[0]
        else:
            try:
                default = _default_connection(protocol)
            except EndpointError as exc:
                problems.append(document.problem(where + (protocol,), f"route {route!r}: {exc}"))
                return None, False
            connections.setdefault(default.name, default)
            wanted = default.name
    connection = connections.get(wanted)
    if connection is None or connection.protocol != protocol:
        problems.append(document.problem(where + (protocol, "connection"), f"route {route!r}: {_wrong_connection(wanted, protocol, connections)}"))
        return None, False
    return EndpointSpec(protocol, wanted, options), complete


def _agent_names(document: Document, where: Path_, route: str, transport: Transport, body: Any,
                 table: agents_table.Table, problems: list[Problem], used: dict[str, Any] | None) -> Any:
    """The endpoint's options with each agent's name (``target_system: uav2``) replaced by the
    entry's value the transport reads for that option (``Transport.agent_options``), and its
    connection the agent's when it names none; None after a problem (an unknown agent, with a
    did-you-mean; an agent on another connection than the endpoint's)."""
    if not isinstance(body, Mapping) or not transport.agent_options:
        return body
    out = dict(body)
    side = where[-2]
    for key, entry_key in transport.agent_options.items():
        name = body.get(key)
        if not agents_table.is_name(name):
            continue
        value, connection, problem = agents_table.resolve(table, name, entry_key)
        if problem is None and connection is not None and out.get("connection", connection) != connection:
            problem = f"agent {name!r} is reached over connection {connection!r}, not {out['connection']!r}"
        if problem is not None:
            problems.append(document.problem(where + (key,), f"route {route!r}: {side}: {key}: {problem}"))
            return None
        out[key] = value
        if connection is not None:
            out["connection"] = connection
        if used is not None:
            used[name] = table[name]
    return out


def _hand_agents(source: EndpointSpec | None, sink: EndpointSpec | None, route: RouteOptions,
                 variables: Mapping[str, Any], table: agents_table.Table,
                 used: dict[str, Any]) -> tuple[EndpointSpec | None, EndpointSpec | None]:
    """Give the agents on its connection to an endpoint that looks them up per message: a sink
    whose transport says so (a ``{field}`` target that may hold a name), a source whose route
    reads ``meta('agent')`` (not a template variable). Each table handed is one the route uses."""
    if not table:
        return source, sink
    reads_agent = agents_table.AGENT not in variables and any(
        agents_table.AGENT in meta_names(expression) for expression in (route.mapping, route.sink.get("mapping")))
    handed = []
    for spec, wanted in ((source, reads_agent), (sink, True)):
        if spec is None or not wanted:
            handed.append(spec)
            continue
        transport = endpoints.transport(spec.protocol)
        if not transport.agent_options or (spec is sink and not transport.looks_up_agents(spec.options)) or \
                (spec is source and agents_table.AGENT not in transport.meta_names(spec.options)):
            handed.append(spec)
            continue
        keys = set(transport.agent_options.values())  # only the agents this protocol can address (UAVs, not robots)
        on_link = {name: entry for name, entry in agents_table.on_connection(table, spec.connection).items() if keys & set(entry)}
        used[f"@{spec.connection}"] = on_link
        handed.append(EndpointSpec(spec.protocol, spec.connection, evolve(spec.options, agents=on_link)))
    return handed[0], handed[1]


def _wrong_connection(wanted: str, protocol: str, connections: Mapping[str, ConnectionSpec]) -> str:
    """Why ``wanted`` cannot serve a ``protocol`` endpoint, and the names that could."""
    same = sorted(name for name, spec in connections.items() if spec.protocol == protocol and not name.startswith("default-"))
    if wanted in connections:
        problem = f"connection {wanted!r} is {connections[wanted].protocol}, not {protocol}"
    else:
        problem = f"unknown connection {wanted!r}"
    hint = did_you_mean(wanted, same) if wanted not in connections else ""
    if hint:
        return problem + hint
    if wanted not in connections and (guess := did_you_mean(wanted, connections)):
        return problem + guess
    if same:
        return f"{problem} ({protocol} connections: {', '.join(same)})"
    return f"{problem} (no {protocol} connection is defined; leave 'connection' out for the default one)"


def _endpoint_checks(
    document: Document,
    where: Path_,
    route: str,
    source: EndpointSpec | None,
    sink: EndpointSpec | None,
    mapping: str | None,
    sink_mapping: str | None,
    problems: list[Problem],
) -> None:
    """The transport's own checks of each endpoint that parsed (the other may not have)."""
    for side, spec, expression in (("source", source, mapping), ("sink", sink, sink_mapping)):
        if spec is None:
            continue
        base = where + (side, spec.protocol)
        try:
            transport = endpoints.transport(spec.protocol)
            check = transport.check_source if side == "source" else transport.check_sink
            results = list(check(spec.options, expression))
        except EndpointError as exc:
            results = [(None, str(exc))]
        for key, message in results:
            message += "" if "did you mean" in message else option_hint(spec.protocol, key, spec.options)
            problems.append(document.problem(base + ((key,) if key else ()), f"route {route!r}: {side}: {message}"))


def _route_to_sink(options: Any, route: RouteOptions) -> Any:
    """The sink's options with what the route says that a sink on a slow shared link uses
    (engine/endpoints/base.py ``EndpointOptions``): its ``priority``, whether it is telemetry
    (``buffer.latest_only``: a waiting message may be replaced by a newer one with its key)
    and its ``max_age``. Unchanged when the route says none of it."""
    changes: dict[str, Any] = {}
    if route.priority != "normal":
        changes["priority"] = route.priority
    latest = route.buffer.latest_only if route.buffer else None
    if latest is not None:
        changes["latest_per"] = tuple(latest.per.split(".")) if latest.per else ()
    if route.max_age is not None:
        changes["max_age"] = route.max_age
    return evolve(options, **changes) if changes else options
