"""What a routes directory compiles to: the values the running engine reads (connections,
routes, their endpoints and placement, the whole directory), and the error listing every
problem when it does not compile. Plain frozen values: nothing here reads files or checks."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from engine.language.route_yaml import Problem
from engine.language.stage_options import (DEFAULT_MAX_MESSAGE_BYTES, BufferSpec, DeadLetterSpec, DedupeSpec, FairOptions, ReplyOptions, RouteDelivery,
                                           ThrottleOptions)
from engine.language.stores import RememberOptions
from engine.language.window_options import WindowOptions


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
class SinkSpec:
    """One sink of a route with several (``sinks:``, a sink ``when:`` or ``fallback:``;
    engine/running/fanout.py sends to them): its name (dead letters, status, route tests),
    its endpoint, its own sink mapping and condition, and its fallback."""

    name: str
    endpoint: EndpointSpec
    mapping: str | None = None
    when: str | None = None
    fallback: SinkSpec | None = None
    after: float = 5.0
    """Seconds the sink may be unable to take messages before they go to its ``fallback``."""


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
    window: WindowOptions | None = field(default=None, compare=False)
    """The route's ``window:`` (engine/running/windows.py): what the sink receives is its aggregates."""
    record: bool = field(default=True, compare=False)
    """Recorded under ``--record`` (engine/running/record.py); a change needs no restart of the route."""
    sinks: tuple[SinkSpec, ...] = ()
    """The route's sinks when it fans out (several, a sink ``when:`` or a ``fallback:``;
    engine/running/fanout.py); empty for a route with one plain ``sink:`` (then ``sink`` and
    ``sink_mapping`` are it, and nothing of the fan-out runs). With sinks, ``sink`` is the
    first one's endpoint and ``sink_mapping`` None (each sink maps for itself)."""

    def endpoints(self) -> tuple[EndpointSpec, ...]:
        """The source, then every sink and fallback: the connections the route uses."""
        if not self.sinks:
            return (self.source, self.sink)
        ends = [self.source]
        for sink in self.sinks:
            ends.append(sink.endpoint)
            if sink.fallback is not None:
                ends.append(sink.fallback.endpoint)
        return tuple(ends)


@dataclass(frozen=True)
class Placement:
    """Where a route runs when several engine instances share a routes directory.

    ``instances``: only on these instances (by ``--instance`` name). ``active_standby``:
    on every instance that can see the source, but only the holder of the broker lease
    ``lease_name`` (on AMQP connection ``lease_connection``) forwards. ``ordered`` (AMQP
    sources): single active consumer, one instance at a time, in order; with ``partitions``,
    one such queue per partition, the partitions spread over the instances."""

    instances: tuple[str, ...] | None = None
    active_standby: bool = False
    ordered: bool = False
    partitions: int = 1
    """``ordered: {partitions: N}``: N partitions of the source, each ordered, spread over the instances."""
    partition_key: str | None = None
    """What the broker hashes to choose a message's partition (``ordered.key``)."""
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
