"""Topic filters and topic templates: validated at load, compiled once, cheap per message.

A source subscribes to one filter (``farm/+/weather``), or with ``shared: GROUP`` to the
shared subscription ``$share/GROUP/farm/+/weather``. A sink's topic may interpolate
canonical fields (``farm/{agent_id}/cmd``) with the same template helper the AMQP routing
keys use (engine.common.placeholders.compile_template); a value that would change the topic's shape
(a ``/`` adding a level, a wildcard, a NUL) refuses the message instead of publishing
somewhere nobody meant.
"""

from __future__ import annotations

import zlib
from typing import Any, Callable, Iterator

from aiomqtt import Topic, Wildcard

from engine.common.placeholders import MappingError, compile_template, template_fields, template_problem
from engine.endpoints.base import MessageRejected

SHARED_PREFIX = "$share"
MAX_SUBSCRIPTION_ID = 268_435_455
"""MQTT 5 subscription identifiers are variable byte integers from 1 to 2^28 - 1."""


def subscription(topic: str, shared: str | None) -> str:
    """What the source subscribes to: the filter, or ``$share/GROUP/filter``."""
    return f"{SHARED_PREFIX}/{shared}/{topic}" if shared else topic


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
        Wildcard(topic)
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
    literal = "".join(part for part in _literals(template))
    refused = template_problem(template)  # fields only: engine/common/placeholders.py parse_template
    if refused:
        yield f"topic {refused}"
    elif not template:
        yield "topic is empty"
    elif "+" in literal or "#" in literal:
        yield f"topic {template!r}: a message is published on one topic, never on a filter (+ and # are for sources)"
    elif "\0" in literal:
        yield f"topic {template!r} contains a NUL character"


def _literals(template: str) -> list[str]:
    out, rest = [], template
    for field in template_fields(template):
        head, _, rest = rest.partition("{" + field + "}")
        out.append(head)
    return out + [rest]


def topic_renderer(template: str, where: str) -> Callable[[Any], str]:
    """``canonical -> topic``; MessageRejected names the field when a value is missing or would
    add a level or a wildcard (``agent_id: "a/#"`` must not reach ``farm/a/#/cmd``)."""
    render = compile_template(template)
    if not template_fields(template):
        return render
    levels = template.count("/")  # placeholders name fields with dots, never slashes

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
