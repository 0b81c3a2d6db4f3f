"""A ROS 2 connection as the engine sees it: the node (node.py) that makes sources and sinks,
of a topic (source.py, sink.py) or of a service or an action (calls.py)."""

from __future__ import annotations

from typing import Any, Mapping

from engine.endpoints.base import Sink, Source, typed
from engine.endpoints.ros2 import calls as ros2_calls
from engine.endpoints.ros2.node import Ros2Node
from engine.endpoints.ros2.options import Ros2EndpointOptions, Ros2SinkOptions, Ros2SourceOptions
from engine.endpoints.ros2.sink import Ros2Sink
from engine.endpoints.ros2.source import Ros2Source


class Ros2Connection(Ros2Node):
    def source(self, route: str, options: Ros2EndpointOptions | Mapping[str, Any]) -> Source:
        typed_options = typed(Ros2SourceOptions, options, f"route {route!r}: ros2 source")
        if typed_options.service is not None:
            return ros2_calls.ServiceSource(self.calls(), route, typed_options.service, typed_options.type,
                                            typed_options.max_in_flight)
        return Ros2Source(self, route, typed_options)

    def sink(self, route: str, options: Ros2SinkOptions | Mapping[str, Any]) -> Sink:
        typed_options = typed(Ros2SinkOptions, options, f"route {route!r}: ros2 sink")
        if typed_options.service is not None:
            return ros2_calls.ServiceSink(self.calls(), route, typed_options.service, typed_options.type,
                                          typed_options.timeout, typed_options.max_in_flight)
        if typed_options.action is not None:
            return ros2_calls.ActionSink(self.calls(), route, typed_options.action, typed_options.type, typed_options.timeout)
        sink = Ros2Sink(self, route, options)
        self.sink_opened(sink)
        return sink
