"""Topic names with ``{placeholders}``: their check, and the renderer a sink names its topic
with. A sink's ``{field}`` (``/robot_{id:03d}/cmd``: a format spec too) is filled from the
canonical message, a source's ``{var}`` segments are discovery variables (discovery.py); rcl's
own substitutions (``{node}``, ``{ns}``, ``{namespace}``) are left to rcl. The braces are read
by the engine's one template grammar (engine/common/placeholders.py), so ``check`` and the run
read each one alike."""

from __future__ import annotations

from typing import Any, Callable, Iterator, Literal

from rclpy.expand_topic_name import expand_topic_name
from rclpy.validate_full_topic_name import validate_full_topic_name

from engine.common.placeholders import MappingError, compile_template, parse_template, template_fields, template_problem
from engine.endpoints.base import MessageRejected
from engine.endpoints.ros2 import discovery
from engine.endpoints.ros2.errors import rcl_reason

_RCL_SUBSTITUTIONS = discovery.RCL_SUBSTITUTIONS


def check_topic(topic: Any, placeholders: Literal["none", "fields", "variables"]) -> Iterator[str]:
    """A topic name valid by rcl's rules; ``placeholders``: what a ``{name}`` in it may be (a
    sink's canonical fields, a source's discovery variables, or nothing: a service's name)."""
    if not isinstance(topic, str) or not topic:
        yield "topic is required (a ROS topic name such as /uav1/weeds)"
        return
    names = discovery.topic_variables(topic)
    if names and placeholders == "none":
        yield f"topic {topic!r}: placeholders ({{{names[0]}}}) are not allowed here"
        return
    problem = discovery.pattern_problem(topic) if placeholders == "variables" else template_problem(topic, _RCL_SUBSTITUTIONS)
    if problem:
        yield problem if placeholders == "variables" else f"topic {problem}"
        return
    sample = "x".join(parse_template(topic, _RCL_SUBSTITUTIONS).literals)  # each placeholder as one name token
    try:
        validate_full_topic_name(expand_topic_name(sample, "node", "/"))
    except Exception as exc:  # rcl raises ValueError or InvalidTopicNameException
        yield f"invalid topic name {topic!r}: {rcl_reason(exc)}"


def topic_fields(topic: str | None) -> list[str]:
    """The canonical fields a sink's topic is rendered from (not rcl's substitutions)."""
    return template_fields(topic or "", _RCL_SUBSTITUTIONS)


def topic_template(topic: str) -> Callable[[Any, str], str] | None:
    """``/{agent_id}/weeds`` or ``/robot_{id:03d}/cmd`` -> a function of the canonical dict;
    None for a fixed topic. A value must be a string or an integer (a float's dot, a dict's
    braces are no name); rcl's own substitutions are left in the name for rcl."""
    if not template_fields(topic, _RCL_SUBSTITUTIONS):
        return None
    render = compile_template(topic, _RCL_SUBSTITUTIONS, kinds=(str, int))

    def resolve(canonical: Any, where: str) -> str:
        try:
            return render(canonical)
        except MappingError as exc:
            raise MessageRejected(f"{where}: {exc}") from None

    return resolve
