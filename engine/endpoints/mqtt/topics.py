"""Topic filters and topic templates: validated at load, compiled once, cheap per message.

A source subscribes to one filter (``farm/+/weather``), or with ``shared: GROUP`` to the
shared subscription ``$share/GROUP/farm/+/weather``. A ``{name}`` level in a source's topic
(``farm/{station}/weather``) is a capture, as in a ROS 2 source's discovery: the source
subscribes with ``+`` there and gives each message that level as ``meta('station')`` and to
the sink's templates (``weather.{station}``). The braces are read by the engine's one template
grammar (engine/common/placeholders.py capture_levels): ``check`` refuses a capture that is
not a whole level, has a format spec or a dotted path, is named twice (the broker's filter
cannot ask two levels to be equal, so the engine would get messages it must drop) or takes a
name the source's metadata already gives; ``#`` after captures is fine (their levels come
before it). A sink's topic may interpolate
canonical fields (``farm/{agent_id}/cmd``) with the same template helper the AMQP routing
keys use (engine.common.placeholders.compile_template); a value that would change the topic's shape
(a ``/`` adding a level, a wildcard, a NUL) refuses the message instead of publishing
somewhere nobody meant.
"""

from __future__ import annotations

import zlib
from typing import Any, Callable, Iterator

from aiomqtt import Topic, Wildcard

from engine.common.placeholders import (
    MappingError, Placeholder, TemplateError, capture_levels, compile_template, parse_template, template_problem,
)
from engine.endpoints.base import MessageRejected

SHARED_PREFIX = "$share"
MAX_SUBSCRIPTION_ID = 268_435_455
"""MQTT 5 subscription identifiers are variable byte integers from 1 to 2^28 - 1."""


SOURCE_META = ("topic", "qos", "retain", "redelivered", "content_type", "headers")
"""What the source gives each message (source.py); a capture may not take these names."""
CORE_META = ("route", "generation", "test")
"""Metadata the engine adds to every message (the route, its generation, a route test's mark)."""


def subscription(topic: str, shared: str | None) -> str:
    """What the source subscribes to: the filter (captures as ``+``), or ``$share/GROUP/filter``."""
    filter_ = source_filter(topic)
    return f"{SHARED_PREFIX}/{shared}/{filter_}" if shared else filter_


def source_filter(topic: str) -> str:
    """``farm/{station}/weather`` -> ``farm/+/weather``; a topic without captures as written
    (one ``check`` refuses is returned as it is, for messages that name it)."""
    try:
        levels = capture_levels(topic)
    except TemplateError:
        return topic
    return "/".join("+" if isinstance(level, Placeholder) else level for level in levels)


def capture_names(topic: str) -> tuple[str, ...]:
    """The names a source topic captures, in order (none for one ``check`` refuses)."""
    try:
        return tuple(level.name for level in capture_levels(topic) if isinstance(level, Placeholder))
    except TemplateError:
        return ()


def capture_reader(topic: str) -> Callable[[str], dict[str, str]] | None:
    """``received topic -> {name: level}`` for a source topic with captures; None without.
    The broker sent the message for the filter with ``+`` at each capture, so each capture's
    level is there (a ``#`` after them only adds levels behind)."""
    try:
        levels = capture_levels(topic)
    except TemplateError:
        return None
    positions = [(index, level.name) for index, level in enumerate(levels) if isinstance(level, Placeholder)]
    if not positions:
        return None

    def read(received: str) -> dict[str, str]:
        parts = received.split("/")
        return {name: parts[index] for index, name in positions}

    return read


def subscription_id(filter_: str) -> int:
    """A stable MQTT 5 subscription identifier for ``filter_``: the same in every run of the
    engine, so messages a persistent session queued while the engine was away (they carry
    the identifier of the subscription that matched) reach the route that subscribed."""
    return zlib.crc32(filter_.encode()) % MAX_SUBSCRIPTION_ID + 1


def filter_problems(topic: str) -> Iterator[str]:
    """Why ``topic`` is not a filter a source can subscribe to (nothing when it is)."""
    if topic.startswith(SHARED_PREFIX + "/"):
        yield f"topic {topic!r}: write the filter alone and the group as shared: GROUP"
        return
    if "\0" in topic:
        yield f"topic {topic!r} contains a NUL character"
        return
    try:
        names = [level.name for level in capture_levels(topic) if isinstance(level, Placeholder)]
    except TemplateError as exc:
        yield str(exc)
        return
    for name in dict.fromkeys(name for name in names if names.count(name) > 1):
        yield (f"topic {topic!r}: {{{name}}} is captured twice: an MQTT filter cannot ask two levels to be equal "
               "(name each capture once, and compare them in a filter if needed)")
    for name in dict.fromkeys(name for name in names if name in SOURCE_META + CORE_META):
        yield (f"topic {topic!r}: capture {{{name}}} would hide the message's own meta({name!r}); name it otherwise "
               f"(taken: {', '.join(SOURCE_META + CORE_META)})")
    try:
        Wildcard(source_filter(topic))
    except ValueError:
        yield (f"topic {topic!r} is not an MQTT topic filter: + stands for one whole level, "
               "# for all remaining levels and must come last (farm/+/weather, farm/#)")


def matcher(filter_: str) -> Callable[[str], bool]:
    """``topic -> bool`` for a (possibly shared) filter; exact filters compare strings."""
    plain = filter_.split("/", 2)[2] if filter_.startswith(SHARED_PREFIX + "/") else filter_
    if "+" not in plain and "#" not in plain:
        return plain.__eq__
    wildcard = Wildcard(plain)
    return lambda topic: Topic(topic).matches(wildcard)


def template_problems(template: str) -> Iterator[str]:
    """Why a sink's topic template can never give a topic one may publish on."""
    refused = template_problem(template)  # the one grammar: engine/common/placeholders.py parse_template
    if refused:
        yield f"topic {refused}"
        return
    literal = "".join(parse_template(template).literals)
    if not template:
        yield "topic is empty"
    elif "+" in literal or "#" in literal:
        yield f"topic {template!r}: a message is published on one topic, never on a filter (+ and # are for sources)"
    elif "\0" in literal:
        yield f"topic {template!r} contains a NUL character"


def topic_renderer(template: str, where: str) -> Callable[[Any], str]:
    """``canonical -> topic``; MessageRejected names the field when a value is missing or would
    add a level or a wildcard (``agent_id: "a/#"`` must not reach ``farm/a/#/cmd``)."""
    render = compile_template(template)
    parsed = parse_template(template)
    if not parsed.placeholders:
        return render
    levels = sum(literal.count("/") for literal in parsed.literals)  # a rendered value must add none

    def topic(canonical: Any) -> str:
        try:
            rendered = render(canonical)
        except MappingError as exc:
            raise MessageRejected(f"{where}: {exc}") from None
        if rendered.count("/") != levels or "+" in rendered or "#" in rendered or "\0" in rendered or not rendered:
            raise MessageRejected(f"{where}: topic {rendered!r} from template {template!r}: "
                                  "a field put /, +, # or NUL into the topic")
        return rendered

    return topic
