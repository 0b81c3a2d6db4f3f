"""The small contract every protocol endpoint implements.

The engine core (routes, pipeline, runtime) knows only these types. Each protocol lives in
one module of this package that subclasses them and translates its library's exceptions
into :class:`EndpointError` at the edge, so a new protocol means one new file.

Delivery contract: a :class:`Source` hands each message to ``deliver`` and waits for it.
``deliver`` returns once the message is settled (accepted by the sink, or dead-lettered);
only then may the source acknowledge it upstream. If ``deliver`` raises, the message was
not settled and the source must let it be redelivered (AMQP: nack with requeue).
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, Awaitable, Callable, ClassVar, Iterable, Mapping


class EndpointError(Exception):
    """A protocol library failed; the message names the connection or endpoint.

    Treated as transient: the message is handed back to its source for redelivery."""


class MessageRejected(EndpointError):
    """This message can never be accepted by this sink (a field the type lacks, a value out
    of range). Retrying cannot help, so the engine dead-letters it instead of redelivering."""


@dataclass(slots=True)
class Inbound:
    """One message as a source received it.

    Byte protocols (AMQP bodies, ROS ``std_msgs/String`` data, MAVLink JSON tunnels) fill
    ``body`` so an identity route can forward the bytes untouched; typed protocols (ROS
    messages, MAVLink telemetry) fill ``fields`` with a plain dict.
    """

    body: bytes | None = None
    fields: dict[str, Any] | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    received_ns: int = field(default_factory=time.monotonic_ns)


@dataclass(slots=True)
class Outbound:
    """What a sink is given.

    ``body`` is the canonical JSON (the original bytes when the route maps by identity),
    ``canonical`` the validated canonical dict, ``fields`` the result of ``sink.mapping``
    (``canonical`` itself when there is none); ``meta`` carries the source's metadata.
    """

    body: bytes
    canonical: Any
    fields: Any
    message_id: str
    meta: Mapping[str, Any]


Deliver = Callable[[Inbound], Awaitable[None]]


class Source(ABC):
    @abstractmethod
    async def start(self, deliver: Deliver) -> None:
        """Begin receiving; every message goes through ``deliver``."""

    @abstractmethod
    async def stop(self) -> None:
        """Stop taking messages and wait for those in flight; unsettled ones are redelivered."""


class Sink(ABC):
    @abstractmethod
    async def send(self, message: Outbound) -> None:
        """Return once the destination has accepted the message; raise EndpointError if not."""

    async def close(self) -> None:
        """Release what the sink holds (the connection itself stays open)."""


class Connection(ABC):
    """One named connection (a broker, a ROS 2 node, a MAVLink link) shared by routes."""

    keeps_dead_letters: ClassVar[bool] = False
    """True where :meth:`dead_letter` stores messages durably (a broker); the engine hands
    a route's unconvertible messages to the first of its connections that does."""

    def __init__(self, name: str, settings: Mapping[str, Any]) -> None:
        self.name = name
        self.settings = settings

    @property
    def healthy(self) -> bool:
        """True while the connection can carry messages (read by /healthz and the status);
        protocols that can tell override it."""
        return True

    @abstractmethod
    async def open(self) -> None: ...

    @abstractmethod
    def source(self, route: str, options: Mapping[str, Any]) -> Source: ...

    @abstractmethod
    def sink(self, route: str, options: Mapping[str, Any]) -> Sink: ...

    @abstractmethod
    async def close(self) -> None: ...

    async def dead_letter(self, route: str, body: bytes, headers: Mapping[str, Any]) -> None:
        raise NotImplementedError


CheckResult = Iterable[tuple[str | None, str]]
"""``(option key or None, message)`` pairs; the route loader attaches file and line."""


class Transport(ABC):
    """What the engine knows about a protocol before connecting: defaults and static checks."""

    name: ClassVar[str]
    default_settings: ClassVar[Mapping[str, Any]]

    def check_connection(self, settings: Mapping[str, Any]) -> CheckResult:
        return ()

    def check_source(self, options: Mapping[str, Any], mapping: str | None) -> CheckResult:
        return ()

    def check_sink(self, options: Mapping[str, Any], mapping: str | None) -> CheckResult:
        return ()

    def exclusive_resource(self, settings: Mapping[str, Any]) -> str | None:
        """The operating-system resource only one open connection can hold (a listening port,
        a serial device: two readers would split the bytes), as a key such as ``udp:14550``,
        or None. A reload that changes such a connection closes the old one before opening
        the new (break-before-make) instead of the usual make-before-break."""
        return None

    def key_files(self, settings: Mapping[str, Any]) -> Iterable[str]:
        """Files whose contents the connection reads when it opens (signing keys): a reload
        reopens the connection when their contents change."""
        return ()

    async def source_retired(
        self, connection: Connection, route: str, options: Mapping[str, Any],
        remaining: Iterable[tuple[str, Mapping[str, Any]]],
    ) -> None:
        """The source of ``route`` stopped for good (route removed, or source replaced):
        undo on ``connection`` what only it needed (AMQP: bindings, an auto-named queue).
        ``remaining`` are the (route, options) of the sources configured on that connection now."""

    def competing_consumers(self, route: str, options: Mapping[str, Any]) -> str | None:
        """For a source whose consumers compete for messages (an AMQP queue), the name of what
        it consumes; ``check`` warns when two routes name the same one."""
        return None

    @abstractmethod
    def connect(self, name: str, settings: Mapping[str, Any]) -> Connection: ...
