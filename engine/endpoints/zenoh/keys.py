"""Key expressions: a source's pattern with ``{name}`` captures, a sink's key template.

Both are read by the engine's one template parser (engine.common.placeholders.parse_template), so
``check`` and the run agree on every form. A source key ``farm/{robot}/weather`` subscribes
to ``farm/*/weather`` and gives each message the chunk in that place as ``meta('robot')``; a
capture is one whole chunk, takes no format spec (``{id:03d}`` is refused: a received key is
read, not formatted), and must have a place one can count: from the start when no ``**``
comes before it, else from the end when none comes after it. A sink key may interpolate
canonical fields and captures with format specs (``robot_{n:03d}/cmd``); a value that would
change the key's shape (a ``/``, a wildcard, a ``$``) refuses the message instead of putting
somewhere nobody meant.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Iterator

import zenoh

from engine.common.placeholders import (
    MappingError, Placeholder, TemplateError, capture_levels, compile_template, parse_template, template_fields,
)
from engine.endpoints.base import MessageRejected
from engine.endpoints.zenoh.errors import describe, rejected

RESERVED = frozenset({"key", "encoding", "parameters", "route", "generation", "test", "reply_to", "correlation_id",
                      "cancel", "message_id"})
"""Metadata names a message already carries: a capture of that name would overwrite them."""
_SHAPE = ("/", "*", "$", "?", "#")
"""What a value written into a key must not hold: each would add a chunk or a wildcard."""


@dataclass(frozen=True)
class Pattern:
    """A source key: what to subscribe to, and where each capture sits in a received key."""

    subscription: str
    captures: tuple[tuple[str, int], ...]
    """``(name, chunk index)``; a negative index counts from the end (after a ``**``)."""

    def captured(self, key: str) -> dict[str, str]:
        """The captures' values in a received key (one the subscription matched)."""
        if not self.captures:
            return {}
        chunks = key.split("/")
        return {name: chunks[index] for name, index in self.captures}


def parse_pattern(key: str) -> Pattern:
    """The source pattern of ``key``; ValueError says why it is none (check reports it). The
    captures are read by placeholders.capture_levels, as MQTT's and ROS 2's are."""
    try:
        levels = capture_levels(key, level="chunk")
    except TemplateError as exc:
        raise ValueError(f"key {str(exc).removeprefix('topic ')}") from None
    names: list[str] = []
    for level in levels:
        if not isinstance(level, Placeholder):
            continue
        if level.name in RESERVED:
            raise ValueError(f"key {key!r}: {{{level.name}}} would overwrite the message's meta({level.name!r}); name it otherwise")
        if level.name in names:
            raise ValueError(f"key {key!r}: {{{level.name}}} is captured twice")
        names.append(level.name)
    chunks = ["*" if isinstance(level, Placeholder) else level for level in levels]
    written = "/".join(chunks)
    try:
        subscription = str(zenoh.KeyExpr.autocanonize(written))  # **/* is written */** in canon form
    except zenoh.ZError as exc:
        raise ValueError(f"key {key!r} is no Zenoh key expression: {describe(exc)}") from None
    captures = []
    for place, level in enumerate(levels):
        if not isinstance(level, Placeholder):
            continue
        if "**" not in chunks[:place]:
            captures.append((level.name, place))
        elif "**" not in chunks[place + 1:]:
            captures.append((level.name, place - len(chunks)))
        else:
            raise ValueError(f"key {key!r}: {{{level.name}}} sits between two **, so its place in a key is unknown")
    return Pattern(subscription, tuple(captures))


def pattern_problems(key: str) -> Iterator[str]:
    try:
        parse_pattern(key)
    except ValueError as exc:
        yield str(exc)


def key_variables(key: str) -> tuple[str, ...]:
    """The names a source key captures, in order ([] for a key check refuses)."""
    try:
        return tuple(name for name, _ in parse_pattern(key).captures)
    except ValueError:
        return ()


def template_problems(template: str) -> Iterator[str]:
    """Why a sink's key template can never give a key one may put on."""
    try:
        literals = parse_template(template).literals
    except TemplateError as exc:
        yield f"key {exc}"
        return
    sample = "x".join(literals)
    try:
        zenoh.KeyExpr.autocanonize(sample)
    except zenoh.ZError as exc:
        yield f"key {template!r} is no Zenoh key expression: {describe(exc)}"


def key_renderer(template: str, where: str) -> Callable[[Any], str]:
    """``template data -> key``; MessageRejected names the field when a value is missing or
    would change the key's shape, or the key is no key expression Zenoh accepts."""
    render = compile_template(template)
    if not template_fields(template):
        return render
    literals = "".join(parse_template(template).literals)
    shape = tuple((mark, literals.count(mark)) for mark in _SHAPE)

    def key(data: Any) -> str:
        try:
            rendered = render(data)
        except MappingError as exc:
            raise MessageRejected(f"{where}: {exc}") from None
        if any(rendered.count(mark) != count for mark, count in shape):
            raise MessageRejected(f"{where}: key {rendered!r} from template {template!r}: "
                                  "a field put /, *, $, ? or # into the key")
        try:
            return str(zenoh.KeyExpr.autocanonize(rendered))
        except zenoh.ZError as exc:
            raise rejected(exc, f"{where}: key {rendered!r} from template {template!r}") from None

    return key
