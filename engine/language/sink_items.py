"""A route's sinks as written: ``sink:`` (one) or ``sinks:`` (several), each with its own
``mapping``, ``when:`` and ``fallback:`` beside its one protocol key; enumerated where each is
written (so every problem names its ``file:line``), named, and told apart from the plain one-sink
route, which runs exactly as before (no fan-out: engine/running/fanout.py is used only by a route
with several sinks, a sink ``when:`` or a ``fallback:``).

A sink's name is what dead letters, the status and route tests call it: its ``name:``, else its
protocol key, with its position when two sinks of the route have the same protocol (``PROTOCOL.1``);
a fallback is ``NAME.fallback``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterator, Mapping

from engine import endpoints
from engine.language.route_options import DEFAULT_FALLBACK_AFTER, RouteOptions

Path_ = tuple[str | int, ...]


@dataclass(frozen=True)
class SinkPart:
    """One end a route sends to: a sink or a sink's fallback, where it is written."""

    name: str
    path: Path_
    """From the route item: ``("sink",)``, ``("sinks", 1)``, ``("sinks", 1, "fallback")``."""
    body: Mapping[str, Any]
    fallback_of: str | None = None
    """The primary's name, for a fallback."""


@dataclass(frozen=True)
class SinkItem:
    """A sink of the route and its fallback, if any."""

    primary: SinkPart
    fallback: SinkPart | None
    when: str | None
    after: float

    def parts(self) -> Iterator[SinkPart]:
        yield self.primary
        if self.fallback is not None:
            yield self.fallback


def protocol_key(body: Any) -> str | None:
    """The one protocol key of a sink's body (None when it has none or several)."""
    if not isinstance(body, Mapping):
        return None
    keys = [key for key in endpoints.PROTOCOLS if key in body]
    return keys[0] if len(keys) == 1 else None


def sink_items(route: RouteOptions) -> list[SinkItem]:
    """The route's sinks, in order: ``sink:`` as one item, or each item of ``sinks:``."""
    if route.sinks is not None:
        bodies: list[tuple[Path_, Any]] = [(("sinks", index), body) for index, body in enumerate(route.sinks)]
    elif route.sink is not None:
        bodies = [(("sink",), route.sink)]
    else:
        return []
    protocols = [protocol_key(body) for _, body in bodies]
    items = []
    for index, (path, body) in enumerate(bodies):
        body = body if isinstance(body, Mapping) else {}
        name = body.get("name")
        if not isinstance(name, str):
            protocol = protocols[index] or "sink"
            name = f"{protocol}.{index}" if protocols.count(protocols[index]) > 1 else protocol
        primary = SinkPart(name, path, body)
        fallback_body = body.get("fallback")
        fallback = SinkPart(f"{name}.fallback", path + ("fallback",), fallback_body, name) \
            if isinstance(fallback_body, Mapping) else None
        after = fallback_body.get("after", DEFAULT_FALLBACK_AFTER) if isinstance(fallback_body, Mapping) else DEFAULT_FALLBACK_AFTER
        when = body.get("when")
        items.append(SinkItem(primary, fallback, when if isinstance(when, str) else None,
                              float(after) if isinstance(after, (int, float)) else DEFAULT_FALLBACK_AFTER))
    return items


def fans_out(route: RouteOptions) -> bool:
    """Whether the route needs the fan-out (engine/running/fanout.py): several sinks, a sink
    ``when:`` or a ``fallback:``; a plain ``sink:`` (or a ``sinks:`` of one such) does not."""
    items = sink_items(route)
    return len(items) > 1 or any(item.fallback is not None or item.when is not None for item in items)


def duplicate_names(items: list[SinkItem]) -> Iterator[tuple[Path_, str]]:
    """``(where, message)`` for each sink whose name another sink of the route has already."""
    seen: dict[str, Path_] = {}
    for item in items:
        for part in item.parts():
            if part.name in seen:
                yield part.path + (("name",) if "name" in part.body else ()), (
                    f"sink name {part.name!r} is used twice in the route (give each sink its own name:)")
            seen.setdefault(part.name, part.path)
