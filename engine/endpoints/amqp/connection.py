"""An AMQP connection as the engine sees it: the link (link.py) that makes sources and sinks."""

from __future__ import annotations

from typing import Any, Mapping

from engine.endpoints.amqp.link import AmqpLink
from engine.endpoints.amqp.options import AmqpSinkOptions, AmqpSourceOptions
from engine.endpoints.amqp.partitions import PartitionedSource
from engine.endpoints.amqp.sink import AmqpSink
from engine.endpoints.amqp.source import AmqpSource
from engine.endpoints.base import Sink, Source, typed


class AmqpConnection(AmqpLink):
    def source(self, route: str, options: AmqpSourceOptions | Mapping[str, Any]) -> Source:
        typed_options = typed(AmqpSourceOptions, options, f"route {route!r}: amqp source")
        if typed_options.partitions > 1:
            return PartitionedSource(self, route, typed_options)
        return AmqpSource(self, route, typed_options)

    def sink(self, route: str, options: AmqpSinkOptions | Mapping[str, Any]) -> Sink:
        return AmqpSink(self, route, typed(AmqpSinkOptions, options, f"route {route!r}: amqp sink"))
