"""A Zenoh connection as the engine sees it: the session (session.py) that makes sources and sinks."""

from __future__ import annotations

from typing import Any, Mapping

from engine.endpoints.base import Sink, Source, typed
from engine.endpoints.zenoh.calls import QuerySource
from engine.endpoints.zenoh.options import ZenohSinkOptions, ZenohSourceOptions
from engine.endpoints.zenoh.session import ZenohLink
from engine.endpoints.zenoh.sink import ZenohSink
from engine.endpoints.zenoh.source import ZenohSource


class ZenohConnection(ZenohLink):
    def source(self, route: str, options: ZenohSourceOptions | Mapping[str, Any]) -> Source:
        typed_options = typed(ZenohSourceOptions, options, f"route {route!r}: zenoh source")
        if typed_options.queryable:
            return QuerySource(self, route, typed_options)
        return ZenohSource(self, route, typed_options)

    def sink(self, route: str, options: ZenohSinkOptions | Mapping[str, Any]) -> Sink:
        return ZenohSink(self, route, typed(ZenohSinkOptions, options, f"route {route!r}: zenoh sink"))
