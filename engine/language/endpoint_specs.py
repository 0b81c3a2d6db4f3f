"""A route's two ends compiled: the protocol key's options parsed (leniently, so the rest of the
route is still checked), agents' names resolved, the connection chosen, the route-wide keys a
sink uses handed to it, and where the route runs (its placement)."""

from __future__ import annotations

from dataclasses import MISSING
from typing import Any, Callable, Mapping

from engine import endpoints
from engine.common.options import OptionError, describe, evolve, fields_of, given, parse
from engine.common.suggest import did_you_mean
from engine.endpoints.base import EndpointError, Transport
from engine.language import agents as agents_table
from engine.language.connection_loading import capable_connections, default_connection, incapable_reason
from engine.language.mapping import meta_names
from engine.language.route_options import LeaseOptions, OrderedOptions, RouteOptions
from engine.language.route_yaml import Document, Path_, Problem
from engine.language.specs import ConnectionSpec, EndpointSpec, Placement


def parse_leniently(
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


def placement_of(
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
    route, active_standby = options.name, options.active_standby
    partitioned = options.ordered if isinstance(options.ordered, OrderedOptions) else None
    ordered = bool(options.ordered)
    lease = options.lease if options.lease is not None and given(options.lease) else None
    source_transport = endpoints.transport(source.protocol)
    if ordered and not source_transport.supports_ordered:
        problems.append(document.problem(where + ("ordered",), f"route {route!r}: ordered does not apply to a {source.protocol} source (it is carried by one instance: use instances or active_standby)"))
    elif partitioned is not None:
        for key, message in source_transport.partition_problems(source.options, partitioned.partitions, partitioned.key):
            problems.append(document.problem(where + ("ordered",) + ((key,) if key else ()), f"route {route!r}: ordered: {message}"))
    if active_standby and source_transport.shares_sources:
        problems.append(document.problem(where + ("active_standby",), f"route {route!r}: a {source.protocol} source is shared by competing consumers; use ordered: true for one instance at a time"))
    if lease and not active_standby:
        problems.append(document.problem(where + ("lease",), f"route {route!r}: lease needs active_standby: true"))
    lease_connection = None
    if active_standby:
        lease_connection = lease.connection if lease is not None else None
        holders = capable_connections(connections, "holds_leases")
        if lease_connection is None:
            if sink.connection in holders:
                lease_connection = sink.connection
            elif len(holders) != 1:
                problems.append(document.problem(where + ("active_standby",), f"route {route!r}: active_standby needs a connection that holds leases (a broker) for its lease; name one with lease: {{connection: NAME}}" + (f" ({', '.join(holders)})" if holders else "")))
            else:
                lease_connection = holders[0]
        elif lease_connection not in holders:
            problems.append(document.problem(where + ("lease", "connection"), f"route {route!r}: lease: {incapable_reason(lease_connection, 'holds leases', holders, connections)}"))
    if len(problems) > before:
        return None
    lease = lease or LeaseOptions()
    return Placement(
        instances=options.instances,
        active_standby=active_standby,
        ordered=ordered,
        partitions=partitioned.partitions if partitioned is not None else 1,
        partition_key=partitioned.key if partitioned is not None else None,
        lease_name=lease.name or route,
        lease_connection=lease_connection,
        lease_heartbeat=float(lease.heartbeat),
    )


def endpoint_spec(
    document: Document,
    where: Path_,
    route: str,
    body: Mapping[str, Any],
    connections: dict[str, ConnectionSpec],
    problems: list[Problem],
    table: agents_table.Table,
    used: dict[str, Any] | None = None,
    side: str | None = None,
) -> tuple[EndpointSpec | None, bool]:
    """``(spec, complete)`` of a route's source or sink (``side``: ``source`` or ``sink``,
    default the last key of ``where``: a ``sinks:`` item or a fallback says ``sink``); an
    incomplete spec (an option at fault left out) serves only to check the rest of the route."""
    side = side or str(where[-1])
    protocols = [p for p in endpoints.PROTOCOLS if p in body]
    if len(protocols) != 1:
        if not document.reported(where):
            problems.append(document.problem(where, f"route {route!r}: {_written(where)} must name exactly one of {', '.join(endpoints.PROTOCOLS)}"))
        return None, False
    protocol = protocols[0]
    try:
        transport = endpoints.transport(protocol)
    except EndpointError as exc:
        problems.append(document.problem(where + (protocol,), f"route {route!r}: {side}: {exc}"))
        return None, False
    named = _agent_names(document, where + (protocol,), route, transport, body[protocol], table, problems, used, side)
    if named is None:
        return None, False
    options, complete = parse_leniently(
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
                default = default_connection(protocol)
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


def _written(where: Path_) -> str:
    """``sink``, ``sinks[1]``, ``sinks[1].fallback``: the key as a route file writes it."""
    at = where[2:] if where[:1] == ("routes",) and len(where) > 2 else where[-1:]
    return ".".join(f"[{step}]" if isinstance(step, int) else str(step) for step in at).replace(".[", "[")


def _agent_names(document: Document, where: Path_, route: str, transport: Transport, body: Any,
                 table: agents_table.Table, problems: list[Problem], used: dict[str, Any] | None, side: str) -> Any:
    """The endpoint's options with each agent's name (``target_system: uav2``) replaced by the
    entry's value the transport reads for that option (``Transport.agent_options``), and its
    connection the agent's when it names none; None after a problem (an unknown agent, with a
    did-you-mean; an agent on another connection than the endpoint's)."""
    if not isinstance(body, Mapping) or not transport.agent_options:
        return body
    out = dict(body)
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


def hand_agents(source: EndpointSpec | None, sink: EndpointSpec | None, route: RouteOptions,
                 variables: Mapping[str, Any], table: agents_table.Table,
                 used: dict[str, Any]) -> tuple[EndpointSpec | None, EndpointSpec | None]:
    """Give the agents on its connection to an endpoint that looks them up per message: a sink
    whose transport says so (a ``{field}`` target that may hold a name), a source whose route
    reads ``meta('agent')`` (not a template variable). Each table handed is one the route uses."""
    if not table:
        return source, sink
    reads_agent = agents_table.AGENT not in variables and any(
        agents_table.AGENT in meta_names(expression) for expression in (route.mapping, (route.sink or {}).get("mapping")))
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


def route_to_sink(options: Any, route: RouteOptions) -> Any:
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
