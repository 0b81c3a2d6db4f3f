"""Compiling ``connections:`` (each protocol's options parsed and checked once, identified by a
fingerprint of settings and key files) and the connection-wide choices made from them: the
dead-letter destination, the connections able to hold leases, ``--local-broker`` warnings."""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path
from typing import Any, Mapping

from engine import endpoints
from engine.common.options import OptionError, describe, fields_of, parse
from engine.common.processes import LOCAL_BROKER_ENV
from engine.common.redaction import Secret, revealed
from engine.common.suggest import did_you_mean
from engine.endpoints.base import EndpointError, Transport
from engine.language.identity import connection_fingerprint, connection_key_files, exclusive_resource
from engine.language.reading import document_items, together_hint
from engine.language.route_options import ConnectionLimits
from engine.language.route_yaml import Document, Path_, Problem
from engine.language.specs import ConnectionSpec
from engine.language.stage_options import DeadLettersOptions, DeadLetterSpec


def compile_connections(
    documents: list[Document], problems: list[Problem]
) -> dict[str, ConnectionSpec]:
    connections: dict[str, ConnectionSpec] = {}
    for document in documents:
        for name, body in document_items(document, "connections", dict):
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
                problems.append(document.problem(where, f"connection {name!r} is already defined at {first.file}:{first.line}{together_hint(document, first.file)}"))
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


def default_connection(protocol: str) -> ConnectionSpec:
    transport = endpoints.transport(protocol)
    settings = dict(transport.default_connection_settings(os.environ))
    try:
        options = parse(transport.connection_options, settings)
    except OptionError as exc:
        raise EndpointError(f"default {protocol} connection: {exc}") from None
    return _identified(ConnectionSpec(f"default-{protocol}", protocol, settings, options=options))


def private_broker_warnings(connections: Mapping[str, ConnectionSpec], env: Mapping[str, str]) -> list[Problem]:
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


def compile_dead_letters(
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
    keepers = capable_connections(connections, "keeps_dead_letters")
    name = options.connection
    spec = DeadLetterSpec(max_length=options.max_length, spool_dir=options.spool_dir, spool_max_bytes=options.spool_max_bytes)
    if name is not None:
        if name not in keepers:
            assert document is not None
            problems.append(document.problem(("dead_letters", "connection"), f"dead_letters: {incapable_reason(name, 'keeps dead letters', keepers, connections)}"))
        return DeadLetterSpec(name, spec.max_length, spec.spool_dir, spec.spool_max_bytes)
    if options.spool_dir is not None or not keepers:
        return spec
    if len(keepers) > 1:
        where = document or documents[0]
        problems.append(where.problem(("dead_letters",), f"several connections ({', '.join(keepers)}) could keep dead letters; name one with dead_letters: {{connection: ...}}"))
        return spec
    return DeadLetterSpec(keepers[0], spec.max_length, spec.spool_dir, spec.spool_max_bytes)


def capable_connections(connections: Mapping[str, ConnectionSpec], capability: str) -> list[str]:
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


def incapable_reason(wanted: str, doing: str, capable: list[str], connections: Mapping[str, ConnectionSpec]) -> str:
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
