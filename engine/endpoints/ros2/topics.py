"""Topic names with ``{placeholders}``: their check, and the renderer a sink names its topic
with. A sink's ``{field}`` is filled from the canonical message, a source's ``{var}`` segments
are discovery variables (discovery.py); rcl's own substitutions (``{node}``, ``{ns}``,
``{namespace}``) are left to rcl."""

from __future__ import annotations

import re
from typing import Any, Callable, Iterator, Literal, Mapping

from rclpy.expand_topic_name import expand_topic_name
from rclpy.validate_full_topic_name import validate_full_topic_name

from engine.common.placeholders import template_problem
from engine.endpoints.base import MessageRejected
from engine.endpoints.ros2 import discovery
from engine.endpoints.ros2.errors import rcl_reason

_PLACEHOLDER = re.compile(r"\{([^{}]*)\}")
_RCL_SUBSTITUTIONS = frozenset({"node", "ns", "namespace"})


def check_topic(topic: Any, placeholders: Literal["none", "fields", "variables"]) -> Iterator[str]:
    """A topic name valid by rcl's rules; ``placeholders``: what a ``{name}`` in it may be (a
    sink's canonical fields, a source's discovery variables, or nothing: a service's name)."""
    if not isinstance(topic, str) or not topic:
        yield "topic is required (a ROS topic name such as /uav1/weeds)"
        return
    names = [n for n in _PLACEHOLDER.findall(topic) if n not in _RCL_SUBSTITUTIONS]
    if names and placeholders == "none":
        yield f"topic {topic!r}: placeholders ({{{names[0]}}}) are not allowed here"
        return
    problem = template_problem(topic) if placeholders == "fields" else discovery.pattern_problem(topic)
    if problem:
        yield problem if placeholders == "variables" else f"topic {problem}"
        return
    sample = _PLACEHOLDER.sub(lambda m: m.group(0) if m.group(1) in _RCL_SUBSTITUTIONS else "x", topic)
    try:
        validate_full_topic_name(expand_topic_name(sample, "node", "/"))
    except Exception as exc:  # rcl raises ValueError or InvalidTopicNameException
        yield f"invalid topic name {topic!r}: {rcl_reason(exc)}"



def topic_fields(topic: str | None) -> list[str]:
    """The canonical fields a sink's topic is rendered from (not rcl's substitutions)."""
    return [name for name in _PLACEHOLDER.findall(topic or "") if name not in _RCL_SUBSTITUTIONS]


def topic_template(topic: str) -> Callable[[Any, str], str] | None:
    """``/{agent_id}/weeds`` -> a function of the canonical dict; None for a fixed topic.
    rcl's own substitutions ({node}, {ns}, {namespace}) are left to rcl."""
    parts = _PLACEHOLDER.split(topic)
    literals, paths = parts[0::2], [p.split(".") for p in parts[1::2]]
    if all(".".join(p) in _RCL_SUBSTITUTIONS for p in paths):
        return None

    def resolve(canonical: Any, where: str) -> str:
        out = [literals[0]]
        for path, literal in zip(paths, literals[1:]):
            if ".".join(path) in _RCL_SUBSTITUTIONS:
                out.append("{" + path[0] + "}")
            else:
                value = canonical
                for key in path:
                    value = value.get(key) if isinstance(value, Mapping) else None
                if type(value) is not str and type(value) is not int:
                    raise MessageRejected(f"{where}: field {'.'.join(path)!r} for the topic is "
                                        f"missing or not a string ({value!r})")
                out.append(str(value))
            out.append(literal)
        return "".join(out)

    return resolve
