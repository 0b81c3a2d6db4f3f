"""What an MQTT connection publishes by itself (its last will, its ``on_stop``), filled when set.

The payload's strings ``{now}`` (ISO 8601 UTC, ms) and ``{now_ms}`` (ms since 1970) are the time
it is set, and ``{next}`` is one more than the messages this connection has published on the
message's topic, so a counter the routes keep on that topic (VDA 5050's ``headerId`` on the
``connection`` topic: a route publishes ONLINE 1, 2, 3..., the clean stop says OFFLINE with the
next number) goes on without a jump. A string that is exactly one placeholder of a number
(``"{now_ms}"``, ``"{next}"``) becomes that number in a mapping payload (a JSON integer).

A will is fixed when the client connects (MQTT sets it in CONNECT): its ``{now}`` is the time of
connecting and its ``{next}`` the count then. Only the topics a will or ``on_stop`` names are
counted: one set lookup per published message elsewhere.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from engine.endpoints.mqtt.options import MqttMessageOptions


class PublishedCounts:
    """Messages the connection published (acknowledged) per topic, for the topics its will or
    ``on_stop`` names."""

    def __init__(self, messages: Iterable[MqttMessageOptions | None]) -> None:
        self.counts: dict[str, int] = {message.topic: 0 for message in messages if message is not None}

    def count(self, messages: Sequence[tuple[str, bytes]], results: Sequence[BaseException | None]) -> None:
        counts = self.counts
        if not counts:
            return
        for (topic, _), error in zip(messages, results):
            if error is None and topic in counts:
                counts[topic] += 1

    def next(self, topic: str) -> int:
        return self.counts.get(topic, 0) + 1


def rendered(message: MqttMessageOptions, next_number: int = 1, now_ns: int | None = None) -> bytes:
    """``message``'s payload with ``{now}``, ``{now_ms}`` and ``{next}`` filled (the module
    docstring); a mapping is sent as JSON."""
    now_ns = time.time_ns() if now_ns is None else now_ns
    millis = now_ns // 1_000_000
    iso = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(millis // 1000)) + f".{millis % 1000:03d}Z"
    numbers = {"{now_ms}": millis, "{next}": next_number}

    def text(value: str) -> str:
        return value.replace("{now_ms}", str(millis)).replace("{next}", str(next_number)).replace("{now}", iso)

    def fill(value: Any) -> Any:
        if isinstance(value, str):
            return numbers[value] if value in numbers else text(value)
        if isinstance(value, Mapping):
            return {key: fill(item) for key, item in value.items()}
        if isinstance(value, list | tuple):
            return [fill(item) for item in value]
        return value

    payload = message.payload
    if isinstance(payload, str):
        return text(payload).encode()
    return json.dumps(fill(payload), separators=(",", ":")).encode()
