"""The memory sink: a route whose only outcome is what it remembers (``remember:``, engine/language/stores.py).

``sink: {memory: {}}`` accepts every message at once and sends it nowhere, so the route's
``remember`` keeps it: a vehicle's mission progress that no topic carries but a VDA 5050
``state`` reads with ``recall()``. Redpanda Connect writes a cache with its ``cache`` output,
Vector fills its memory enrichment table as a sink: the same shape. It has no source, no
library and no failure (nothing here can fail, so it has no table of errors), and its one
connection, ``default-memory``, is always up.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

from engine.endpoints.base import CheckResult, Connection, EndpointError, EndpointOptions, Outbound, Sink, Source, Transport


@dataclass(frozen=True, kw_only=True)
class MemoryConnectionOptions:
    """``connections.<name>.memory``: nothing to configure (the stores are the engine's)."""

    __schema_description__ = "the engine's own memory: nothing to configure"


@dataclass(frozen=True, kw_only=True)
class MemorySourceOptions(EndpointOptions):
    __schema_description__ = "not a source: memory is read by recall() in mappings"


@dataclass(frozen=True, kw_only=True)
class MemorySinkOptions(EndpointOptions):
    __schema_description__ = ("delivers nowhere, at once: the route only remembers (give it remember: {store: NAME}); "
                              "mappings read the store with recall()")


class MemorySink(Sink):
    async def send(self, message: Outbound) -> None:
        return None

    async def send_batch(self, messages: Sequence[Outbound]) -> list[BaseException | None]:
        return [None] * len(messages)


class MemoryConnection(Connection):
    async def open(self) -> None:
        return None

    def source(self, route: str, options: Any) -> Source:
        raise EndpointError(f"route {route!r}: memory is not a source (mappings read it with recall())")

    def sink(self, route: str, options: Any) -> Sink:
        return MemorySink()

    async def close(self) -> None:
        return None


class MemoryTransport(Transport):
    name = "memory"
    connection_type = MemoryConnection
    default_settings = {}
    connection_options = MemoryConnectionOptions
    source_options = MemorySourceOptions
    sink_options = MemorySinkOptions
    delivers = False

    def source_problems(self, options: MemorySourceOptions, mapping: str | None) -> CheckResult:
        yield None, "memory is not a source: a mapping reads what a route remembered with recall('STORE', key)"

    def connect(self, name: str, settings: Any) -> Connection:
        return MemoryConnection(name, settings)


TRANSPORT = MemoryTransport()

__all__ = ["TRANSPORT"]
