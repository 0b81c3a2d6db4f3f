"""An MQTT connection as the engine sees it: the link (link.py) that makes sources and sinks."""

from __future__ import annotations

from typing import Any, Mapping

from engine.endpoints.base import Sink, Source, typed
from engine.endpoints.mqtt.link import MqttLink
from engine.endpoints.mqtt.options import MqttSinkOptions, MqttSourceOptions
from engine.endpoints.mqtt.sink import MqttSink
from engine.endpoints.mqtt.source import MqttSource


class MqttConnection(MqttLink):
    def source(self, route: str, options: MqttSourceOptions | Mapping[str, Any]) -> Source:
        return MqttSource(self, route, typed(MqttSourceOptions, options, f"route {route!r}: mqtt source"))

    def sink(self, route: str, options: MqttSinkOptions | Mapping[str, Any]) -> Sink:
        return MqttSink(self, route, typed(MqttSinkOptions, options, f"route {route!r}: mqtt sink"))
