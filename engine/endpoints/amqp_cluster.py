"""AMQP on a RabbitMQ cluster: failover between nodes, replicated (quorum) queues.

aio-pika's robust connection reconnects to the one URL it was given, so a connection
that lists several nodes (``amqp: {urls: [...]}``) uses :class:`FailoverConnection`: the
same robust connection (its channels re-declare their exchanges, queues, bindings and
consumers on every reconnect), but each connection attempt after the first goes to the
next node of the list. Queues the engine declares follow the connection's default
``queue_type`` unless a source names its own; quorum queues are replicated by Raft, so a
node lost with -9 loses no acknowledged message.
"""

from __future__ import annotations

from typing import Any, Iterator, Mapping, Sequence
from urllib.parse import urlsplit

import aio_pika
from aio_pika.robust_connection import RobustConnection
from yarl import URL

QUEUE_TYPES = ("classic", "quorum")

QUORUM_REFUSED_ARGUMENTS = {
    "x-max-priority": "quorum queues have no priorities",
    "x-queue-mode": "quorum queues keep messages on disk anyway (no lazy mode)",
    "x-queue-master-locator": "use x-queue-leader-locator for quorum queues",
    "x-queue-version": "applies to classic queues only",
    "x-max-age": "applies to streams only",
    "x-stream-max-segment-size-bytes": "applies to streams only",
}
"""Arguments RabbitMQ 3.10 refuses on a quorum queue (measured: PRECONDITION_FAILED
'invalid arg'); besides these, a quorum queue cannot be non-durable, exclusive or auto-delete."""


class FailoverConnection(RobustConnection):
    """A robust connection over several nodes: each (re)connection attempt after the first
    goes to the next URL of the list, round robin, so losing the node in use moves the
    connection (and every channel's topology) to a node that is up.

    aio-pika's reconnect loop resets ``transport`` to None right before every attempt and
    then connects to ``self.url``; that moment is where the next URL is chosen.
    """

    def __init__(self, urls: Sequence[str], first: int = 0, **kwargs: Any) -> None:
        self._urls = [URL(url) for url in urls]
        self._index = first % len(self._urls)
        self._attempts = 0
        super().__init__(self._urls[self._index], **kwargs)

    @property  # type: ignore[override]
    def transport(self) -> Any:
        return self.__dict__.get("_transport")

    @transport.setter
    def transport(self, value: Any) -> None:
        if value is None and "_transport" in self.__dict__ and len(self._urls) > 1:
            self._attempts += 1
            if self._attempts > 1:  # the first attempt uses the URL we were given
                self._index = (self._index + 1) % len(self._urls)
                self.url = self._urls[self._index]
        self.__dict__["_transport"] = value

    @property
    def endpoint(self) -> str:
        """``host:port`` of the node this connection uses (or is trying)."""
        return f"{self.url.host}:{self.url.port}"


async def connect_failover(urls: Sequence[str], **kwargs: Any) -> FailoverConnection:
    """Connect to the first node of ``urls`` that answers; raise the last error if none does."""
    error: BaseException | None = None
    timeout = kwargs.pop("timeout", None)
    for index in range(len(urls)):
        connection = FailoverConnection(urls, first=index, **kwargs)
        try:
            await connection.connect(timeout)
            return connection
        except (ConnectionError, OSError, aio_pika.exceptions.AMQPError, TimeoutError) as exc:
            error = exc
            await connection.close()
    assert error is not None
    raise error


def connection_urls(settings: Mapping[str, Any]) -> list[str]:
    """Every node of a connection: ``urls`` (a cluster) or the single ``url``."""
    urls = settings.get("urls")
    if urls:
        return [str(url) for url in urls]
    return [str(settings["url"])]


def check_urls(settings: Mapping[str, Any], redact: Any) -> Iterator[tuple[str | None, str]]:
    """Static checks of a connection's URLs; passwords never appear in a problem."""
    if "url" in settings and "urls" in settings:
        yield "urls", "give either url or urls, not both"
        return
    if "url" not in settings and "urls" not in settings:
        yield None, "an amqp connection needs url (one node) or urls (the nodes of a cluster)"
        return
    if "urls" in settings:
        urls = settings["urls"]
        if not isinstance(urls, list) or not urls:
            yield "urls", "urls must be a non-empty list of amqp:// URLs"
            return
    else:
        urls = [settings.get("url", "")]
    seen: set[tuple[str, int | None, str]] = set()
    for index, url in enumerate(urls):
        where = "urls" if "urls" in settings else None
        try:
            parts = urlsplit(str(url))
            port = parts.port
        except ValueError as exc:
            yield where, f"URL {index + 1}: {redact(str(url))!r} is not a valid URL ({exc})"
            continue
        if parts.scheme not in ("amqp", "amqps") or not parts.hostname:
            label = f"URL {index + 1}: " if where else ""
            yield where, f"{label}not an amqp:// URL: {redact(str(url))!r}"
            continue
        key = (parts.hostname, port, parts.path or "/")
        if key in seen:
            yield where, f"URL {index + 1}: {redact(str(url))!r} names the same node twice"
        seen.add(key)


def queue_type(options: Mapping[str, Any], default: str | None) -> str | None:
    """The queue type a source declares: its own ``queue_type``, an explicit
    ``x-queue-type`` argument, or the connection's default."""
    arguments = options.get("queue_arguments") or {}
    return options.get("queue_type") or arguments.get("x-queue-type") or default


def queue_arguments(
    options: Mapping[str, Any], default_type: str | None, single_active: bool = False
) -> dict[str, Any] | None:
    """The ``queue.declare`` arguments of a source's queue."""
    arguments = dict(options.get("queue_arguments") or {})
    kind = queue_type(options, default_type)
    if kind and kind != "classic":
        arguments["x-queue-type"] = kind
    if single_active:
        arguments["x-single-active-consumer"] = True
    return arguments or None


def check_queue(options: Mapping[str, Any]) -> Iterator[tuple[str | None, str]]:
    """What a quorum queue refuses, said before RabbitMQ says PRECONDITION_FAILED."""
    arguments = options.get("queue_arguments") or {}
    declared = arguments.get("x-queue-type")
    if declared is not None and options.get("queue_type") and declared != options["queue_type"]:
        yield "queue_arguments", f"x-queue-type {declared!r} contradicts queue_type {options['queue_type']!r}"
    if queue_type(options, None) != "quorum":
        return
    if options.get("durable") is False:
        yield "durable", "a quorum queue is always durable (durable: false is refused)"
    for key in ("exclusive", "auto_delete"):
        if options.get(key):
            yield key, f"a quorum queue cannot be {key.replace('_', '-')}"
    for argument, why in QUORUM_REFUSED_ARGUMENTS.items():
        if argument in arguments:
            yield "queue_arguments", f"quorum queues refuse {argument} ({why})"
