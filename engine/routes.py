"""The route language: a directory of YAML files compiled into route specifications.

Loading is all-or-nothing and never connects to anything: every file is parsed with
line numbers, environment variables are substituted, the result is validated against
the route-file JSON Schema shipped with the package, and every route is checked
(connections, JMESPath, schemas, endpoint options). All problems are collected, each
as ``file:line: message``, so ``check`` and a reload report the same errors the same way.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Iterator, Mapping

import jsonschema
import yaml

from engine import endpoints
from engine.delivery import DEFAULT_MAX_MESSAGE_BYTES, DeadLetterSpec, RouteDelivery
from engine.endpoints.base import EndpointError
from engine.mapping import MappingError, compile_mapping, unknown_functions
from engine.schemas import SchemaRegistry

ROUTE_FILE_SCHEMA: dict[str, Any] = json.loads(
    resources.files("engine").joinpath("route_file.schema.json").read_text(encoding="utf-8")
)
_ROUTE_FILE_VALIDATOR = jsonschema.Draft202012Validator(ROUTE_FILE_SCHEMA)
_ENV_REFERENCE = re.compile(r"\$\$|\$\{([A-Za-z_][A-Za-z0-9_]*)(?::-([^}]*))?\}")
_MAVLINK_ONLY = ("baud", "source_system", "source_component", "signing", "rate", "heartbeat", "mav_type", "tunnel")

Path_ = tuple[str | int, ...]


@dataclass(frozen=True, order=True)
class Problem:
    file: str
    line: int
    message: str

    def __str__(self) -> str:
        return f"{self.file}:{self.line}: {self.message}"


class RoutesInvalid(Exception):
    """The directory does not compile; ``problems`` lists every reason."""

    def __init__(self, problems: list[Problem]) -> None:
        super().__init__("\n".join(map(str, problems)))
        self.problems = problems


@dataclass(frozen=True)
class ConnectionSpec:
    name: str
    protocol: str
    settings: Mapping[str, Any]
    file: str = field(default="", compare=False)
    line: int = field(default=0, compare=False)
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    """Messages larger than this, in or out of this connection, are dead-lettered unparsed."""


@dataclass(frozen=True)
class EndpointSpec:
    protocol: str
    connection: str
    options: Mapping[str, Any]


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
    delivery: RouteDelivery = field(default=RouteDelivery(), compare=False)
    """max_attempts, overflow and the size limits (the fingerprint covers them)."""


@dataclass(frozen=True)
class RoutesConfig:
    """A compiled directory: what the engine runs, identified by a content hash."""

    directory: Path
    connections: Mapping[str, ConnectionSpec]
    routes: Mapping[str, RouteSpec]
    content_hash: str
    dead_letters: DeadLetterSpec = DeadLetterSpec()
    """The engine's one dead-letter destination (``dead_letters:``, resolved)."""


def default_amqp_url() -> str:
    return os.environ.get("RABBITROS_AMQP_URL", "amqp://guest:guest@localhost:5672/")


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
    )


def load_routes(
    directory: Path,
    schemas: SchemaRegistry,
    env: Mapping[str, str] | None = None,
) -> RoutesConfig:
    """Compile ``directory``; raise :class:`RoutesInvalid` listing every problem."""
    env = os.environ if env is None else env
    problems: list[Problem] = []
    documents: list[_Document] = []
    digest = hashlib.sha256()
    if not directory.exists():
        raise RoutesInvalid([Problem(str(directory), 0, "routes directory does not exist")])
    for path in route_files(directory):
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            problems.append(Problem(str(path), 0, f"cannot read: {exc}"))
            continue
        digest.update(path.name.encode() + b"\0" + text.encode() + b"\0")
        document = _parse_document(str(path), text, env, problems)
        if document is not None:
            documents.append(document)
    for schema_path, message in schemas.problems:
        problems.append(Problem(str(schema_path), 0, message))
    connections = _compile_connections(documents, problems)
    routes = _compile_routes(documents, connections, schemas, problems)
    dead_letters = _compile_dead_letters(documents, connections, problems)
    if problems:
        raise RoutesInvalid(sorted(set(problems)))
    return RoutesConfig(directory, connections, routes, digest.hexdigest()[:12], dead_letters)


@dataclass
class _Document:
    file: str
    data: dict[str, Any]
    lines: dict[Path_, int]

    def line(self, path: Path_) -> int:
        while path not in self.lines and path:
            path = path[:-1]
        return self.lines.get(path, 1)

    def problem(self, path: Path_, message: str) -> Problem:
        return Problem(self.file, self.line(path), message)


_Loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
"""libyaml's parser where PyYAML was built with it (the wheels are): the same nodes and line
marks, parsed several times faster (1,000 routes: check 0.85 s -> 0.27 s here)."""


def _parse_document(
    file: str, text: str, env: Mapping[str, str], problems: list[Problem]
) -> _Document | None:
    loader = _Loader(text)
    try:
        root = loader.get_single_node()
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark else 1
        problems.append(Problem(file, line, f"invalid YAML: {exc.problem or exc.context}"))
        return None
    except yaml.YAMLError as exc:
        problems.append(Problem(file, 1, f"invalid YAML: {exc}"))
        return None
    finally:
        loader.dispose()
    if root is None:
        return _Document(file, {}, {})
    lines: dict[Path_, int] = {}
    data = _to_python(loader, root, (), lines, env, file, problems)
    document = _Document(file, data if data is not None else {}, lines)
    errors = [p for error in _ROUTE_FILE_VALIDATOR.iter_errors(data) for p in _schema_problems(document, error)]
    problems.extend(errors)
    return None if errors else document


def _to_python(
    loader: yaml.SafeLoader,
    node: yaml.Node,
    path: Path_,
    lines: dict[Path_, int],
    env: Mapping[str, str],
    file: str,
    problems: list[Problem],
) -> Any:
    lines.setdefault(path, node.start_mark.line + 1)
    if isinstance(node, yaml.MappingNode):
        out: dict[str, Any] = {}
        for key_node, value_node in node.value:
            key = loader.construct_object(key_node)
            if not isinstance(key, str):
                problems.append(Problem(file, key_node.start_mark.line + 1, f"key {key!r} must be a string"))
                continue
            if key in out:
                problems.append(Problem(file, key_node.start_mark.line + 1, f"duplicate key {key!r}"))
                continue
            lines[path + (key,)] = key_node.start_mark.line + 1
            out[key] = _to_python(loader, value_node, path + (key,), lines, env, file, problems)
        return out
    if isinstance(node, yaml.SequenceNode):
        return [
            _to_python(loader, item, path + (index,), lines, env, file, problems)
            for index, item in enumerate(node.value)
        ]
    value = loader.construct_object(node)
    if isinstance(value, str) and "$" in value:
        try:
            substituted = substitute_env(value, env)
        except KeyError as exc:
            problems.append(
                Problem(file, node.start_mark.line + 1, f"environment variable {exc.args[0]} is not set (use ${{{exc.args[0]}:-default}} for a default)")
            )
            return value
        return _typed(substituted) if not node.style else substituted  # plain: None (Python) or "" (libyaml)
    return value


def _typed(text: str) -> Any:
    """An unquoted ``${VAR}`` takes the YAML type of its value (``domain_id: ${ROS_DOMAIN_ID}``
    is a number); quoting it keeps a string."""
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        return text
    return value if isinstance(value, (int, float, bool)) and not isinstance(value, str) else text


def substitute_env(text: str, env: Mapping[str, str]) -> str:
    """``${VAR}`` and ``${VAR:-default}``; ``$$`` is a literal ``$``. Unset without default raises."""

    def replace(match: re.Match[str]) -> str:
        if match.group(0) == "$$":
            return "$"
        name, default = match.group(1), match.group(2)
        if name in env:
            return env[name]
        if default is not None:
            return default
        raise KeyError(name)

    return _ENV_REFERENCE.sub(replace, text)


def _schema_problems(document: _Document, error: jsonschema.ValidationError) -> Iterator[Problem]:
    path = tuple(error.absolute_path)
    if error.validator == "additionalProperties" and isinstance(error.instance, dict):
        allowed = sorted(error.schema.get("properties", {}))
        for key in error.instance:
            if key not in allowed:
                yield document.problem(
                    path + (key,), f"unknown key {key!r} at {_dotted(path)} (allowed: {', '.join(allowed)})"
                )
        return
    if error.context:
        error = jsonschema.exceptions.best_match(error.context)
        path = tuple(error.absolute_path)
    yield document.problem(path, f"{_dotted(path)}: {error.message}")


def _dotted(path: Path_) -> str:
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "top level"


def _compile_connections(
    documents: list[_Document], problems: list[Problem]
) -> dict[str, ConnectionSpec]:
    connections: dict[str, ConnectionSpec] = {}
    for document in documents:
        for name, body in (document.data.get("connections") or {}).items():
            where = ("connections", name)
            protocols = [p for p in endpoints.PROTOCOLS if p in body]
            if len(protocols) != 1:
                problems.append(document.problem(where, f"connection {name!r} must name exactly one of amqp, ros2, mavlink"))
                continue
            protocol = protocols[0]
            if name in connections:
                first = connections[name]
                problems.append(document.problem(where, f"connection {name!r} is already defined at {first.file}:{first.line}"))
                continue
            extra = [key for key in _MAVLINK_ONLY if key in body]
            if protocol != "mavlink" and extra:
                problems.append(document.problem(where + (extra[0],), f"{extra[0]!r} applies only to mavlink connections"))
                continue
            settings = _connection_settings(protocol, body)
            try:
                checks = list(endpoints.transport(protocol).check_connection(settings))
            except EndpointError as exc:
                checks = [(None, str(exc))]
            for key, message in checks:
                problems.append(document.problem(where + ((protocol,) if key is None else (protocol, key)), f"connection {name!r}: {message}"))
            connections[name] = ConnectionSpec(
                name, protocol, settings, document.file, document.line(where),
                body.get("max_message_bytes", DEFAULT_MAX_MESSAGE_BYTES),
            )
    return connections


def _connection_settings(protocol: str, body: Mapping[str, Any]) -> dict[str, Any]:
    value = body[protocol]
    if protocol == "ros2":
        return dict(value or {})
    if isinstance(value, str):
        settings: dict[str, Any] = {"url": value}
    else:
        settings = dict(value)
    settings.update({key: body[key] for key in _MAVLINK_ONLY if key in body})
    return settings


def _default_connection(protocol: str) -> ConnectionSpec:
    settings = dict(endpoints.transport(protocol).default_settings)
    if protocol == "amqp":
        settings["url"] = default_amqp_url()
    return ConnectionSpec(f"default-{protocol}", protocol, settings)


def _compile_routes(
    documents: list[_Document],
    connections: dict[str, ConnectionSpec],
    schemas: SchemaRegistry,
    problems: list[Problem],
) -> dict[str, RouteSpec]:
    routes: dict[str, RouteSpec] = {}
    for document in documents:
        for index, body in enumerate(document.data.get("routes") or ()):
            where: Path_ = ("routes", index)
            name = body["name"]
            before = len(problems)
            if name in routes:
                first = routes[name]
                problems.append(document.problem(where + ("name",), f"route {name!r} is already defined at {first.file}:{first.line}"))
            source = _endpoint(document, where + ("source",), name, body["source"], connections, problems)
            sink = _endpoint(document, where + ("sink",), name, body["sink"], connections, problems)
            mapping = body.get("mapping")
            sink_mapping = body["sink"].get("mapping")
            for key_path, expression in ((where + ("mapping",), mapping), (where + ("sink", "mapping"), sink_mapping)):
                for message in _mapping_problems(expression):
                    problems.append(document.problem(key_path, f"route {name!r}: {message}"))
            schema_name = body.get("schema")
            if schema_name is None:
                problems.append(document.problem(where, f"route {name!r}: 'schema' is required (use raw_json to pass any object)"))
            elif schemas.get(schema_name) is None:
                problems.append(document.problem(where + ("schema",), f"route {name!r}: unknown schema {schema_name!r} (known: {', '.join(n for n in schemas.names() if '.v' not in n)})"))
            if source and sink:
                _endpoint_checks(document, where, name, source, sink, mapping, sink_mapping, problems)
            if len(problems) > before or not (source and sink):
                continue
            used = {source.connection: connections.get(source.connection), sink.connection: connections.get(sink.connection)}
            fingerprint = hashlib.sha256(
                json.dumps(
                    [body, {k: (v.protocol, v.settings, v.max_message_bytes) if v else None for k, v in used.items()}],
                    sort_keys=True,
                    default=str,
                ).encode()
            ).hexdigest()[:16]
            delivery = RouteDelivery(
                max_attempts=body.get("max_attempts", RouteDelivery.max_attempts),
                overflow=body.get("overflow", RouteDelivery.overflow),
                max_message_bytes=connections[source.connection].max_message_bytes,
                sink_max_message_bytes=connections[sink.connection].max_message_bytes,
            )
            routes[name] = RouteSpec(
                name, source, mapping, schema_name, sink, sink_mapping, fingerprint,
                document.file, document.line(where), delivery,
            )
    return routes


def _compile_dead_letters(
    documents: list[_Document], connections: dict[str, ConnectionSpec], problems: list[Problem]
) -> DeadLetterSpec:
    """``dead_letters: {connection, max_length}`` or ``{spool_dir, spool_max_bytes}``, from at
    most one file; default: the only AMQP connection, else the local spool."""
    found = [(document, document.data["dead_letters"]) for document in documents if document.data.get("dead_letters")]
    if len(found) > 1:
        first = found[0][0]
        for document, _ in found[1:]:
            problems.append(document.problem(("dead_letters",), f"dead_letters is already defined at {first.file}:{first.line(('dead_letters',))}"))
    document, body = found[0] if found else (None, {})
    amqp = sorted(name for name, spec in connections.items() if spec.protocol == "amqp")
    name = body.get("connection")
    spec = DeadLetterSpec(
        max_length=body.get("max_length", DeadLetterSpec.max_length),
        spool_dir=body.get("spool_dir"),
        spool_max_bytes=body.get("spool_max_bytes", DeadLetterSpec.spool_max_bytes),
    )
    if name is not None:
        if name not in connections:
            assert document is not None
            problems.append(document.problem(("dead_letters", "connection"), f"dead_letters: unknown connection {name!r}"))
        elif connections[name].protocol != "amqp":
            assert document is not None
            problems.append(document.problem(("dead_letters", "connection"), f"dead_letters: connection {name!r} is {connections[name].protocol}, not amqp"))
        return DeadLetterSpec(name, spec.max_length, spec.spool_dir, spec.spool_max_bytes)
    if "spool_dir" in body or not amqp:
        return spec
    if len(amqp) > 1:
        where = document or documents[0]
        problems.append(where.problem(("dead_letters",), f"several amqp connections ({', '.join(amqp)}) could keep dead letters; name one with dead_letters: {{connection: ...}}"))
        return spec
    return DeadLetterSpec(amqp[0], spec.max_length, spec.spool_dir, spec.spool_max_bytes)


def _mapping_problems(expression: str | None) -> Iterator[str]:
    if expression is None:
        return
    try:
        compile_mapping(expression)
    except MappingError as exc:
        yield f"bad JMESPath {expression!r}: {exc}"
        return
    for function in unknown_functions(expression):
        yield f"unknown function {function}() in {expression!r}"


def _endpoint(
    document: _Document,
    where: Path_,
    route: str,
    body: Mapping[str, Any],
    connections: dict[str, ConnectionSpec],
    problems: list[Problem],
) -> EndpointSpec | None:
    protocols = [p for p in endpoints.PROTOCOLS if p in body]
    if len(protocols) != 1:
        problems.append(document.problem(where, f"route {route!r}: {where[-1]} must name exactly one of amqp, ros2, mavlink"))
        return None
    protocol = protocols[0]
    options = dict(body[protocol] or {})
    wanted = options.pop("connection", None)
    if wanted is None:
        candidates = sorted(n for n, c in connections.items() if c.protocol == protocol)
        if len(candidates) > 1:
            problems.append(document.problem(where + (protocol,), f"route {route!r}: several {protocol} connections ({', '.join(candidates)}); name one with 'connection:'"))
            return None
        if candidates:
            wanted = candidates[0]
        else:
            try:
                default = _default_connection(protocol)
            except EndpointError as exc:
                problems.append(document.problem(where + (protocol,), f"route {route!r}: {exc}"))
                return None
            connections.setdefault(default.name, default)
            wanted = default.name
    connection = connections.get(wanted)
    if connection is None:
        problems.append(document.problem(where + (protocol, "connection"), f"route {route!r}: unknown connection {wanted!r}"))
        return None
    if connection.protocol != protocol:
        problems.append(document.problem(where + (protocol, "connection"), f"route {route!r}: connection {wanted!r} is {connection.protocol}, not {protocol}"))
        return None
    return EndpointSpec(protocol, wanted, options)


def _endpoint_checks(
    document: _Document,
    where: Path_,
    route: str,
    source: EndpointSpec,
    sink: EndpointSpec,
    mapping: str | None,
    sink_mapping: str | None,
    problems: list[Problem],
) -> None:
    for side, spec, expression in (("source", source, mapping), ("sink", sink, sink_mapping)):
        base = where + (side, spec.protocol)
        try:
            transport = endpoints.transport(spec.protocol)
            check = transport.check_source if side == "source" else transport.check_sink
            results = list(check(spec.options, expression))
        except EndpointError as exc:
            results = [(None, str(exc))]
        for key, message in results:
            problems.append(document.problem(base + ((key,) if key else ()), f"route {route!r}: {side}: {message}"))
