"""Static checks of ROS 2 connections, sources and sinks (``rabbitros-engine check`` and the
endpoints' own constructors): what the typed options cannot say by themselves (a valid node
name, an installed type, options that contradict each other, a sink mapping's keys that are
not fields of the message)."""

from __future__ import annotations

from typing import Any, Iterator, Mapping

import jmespath
from rclpy.validate_namespace import validate_namespace
from rclpy.validate_node_name import validate_node_name

from engine.common.options import given
from engine.common.suggest import did_you_mean
from engine.endpoints.base import CheckResult, typed_or_problem
from engine.endpoints.ros2 import calls as ros2_calls, discovery, rosmsg
from engine.endpoints.ros2.errors import rcl_reason
from engine.endpoints.ros2.options import (
    STRING_TYPE, Ros2ConnectionOptions, Ros2EndpointOptions, Ros2SinkOptions, Ros2SourceOptions,
)
from engine.endpoints.ros2.topics import check_topic


def source_variables(options: Ros2SourceOptions) -> tuple[str, ...]:
    """A topic's ``{var}`` segments (engine/endpoints/ros2/discovery.py)."""
    return () if options.service is not None else discovery.topic_variables(options.topic)


def connection_problems(options: Ros2ConnectionOptions) -> CheckResult:
    node, namespace, domain_id = options.node, options.namespace, options.domain_id
    try:
        validate_node_name(node)
    except Exception as exc:
        yield "node", f"invalid node name {node!r}: {rcl_reason(exc)}"
    if namespace:
        try:
            validate_namespace(namespace if namespace.startswith("/") else "/" + namespace)
        except Exception as exc:
            yield "namespace", f"invalid namespace {namespace!r}: {rcl_reason(exc)}"
    if domain_id is not None and not 0 <= domain_id <= 232:
        yield "domain_id", f"domain_id must be an integer in 0..232, not {domain_id!r}"


def source_problems(options: Ros2SourceOptions, mapping: str | None) -> CheckResult:
    if "forget_after" in given(options) and not source_variables(options):
        yield "forget_after", "forget_after applies to a topic with {var} segments (discovered topics, as /{agent}/fix)"
    if options.service is None:
        yield from _check_endpoint(options, sink=False)
        if "max_in_flight" in given(options):
            yield "max_in_flight", "max_in_flight applies to a source that offers a service"
        return
    if options.topic is not None:
        yield "service", "a ros2 source names a topic or a service, not both"
    for message in check_topic(options.service, "none"):
        yield "service", message.replace("topic", "service")
    try:
        ros2_calls.resolve_service(options.type)
    except rosmsg.MessageError as exc:
        yield "type", str(exc)


def sink_problems(options: Ros2SinkOptions, mapping: str | None) -> CheckResult:
    if options.service is not None or options.action is not None:
        yield from _check_service(options)
    else:
        yield from _check_endpoint(options, sink=True)
        for key in ("timeout", "max_in_flight"):
            if key in given(options):
                yield key, f"{key} applies to a sink that calls a service"
    if not mapping or options.type == STRING_TYPE:
        return
    try:
        cls = sink_class(options)
        tree = jmespath.compile(mapping).parsed
    except (rosmsg.MessageError, jmespath.exceptions.JMESPathError):
        return  # reported by the type check and by the route loader
    if tree.get("type") == "multi_select_dict":
        for message in _check_mapping_keys(tree, cls, ""):
            yield "mapping", message


def checked_source(options: Ros2SourceOptions | Mapping[str, Any]) -> list[str]:
    """Every problem of a source's options (as ``check`` reports them), for its constructor."""
    parsed, problems = typed_or_problem(Ros2SourceOptions, options)
    return [message for _, message in (problems if parsed is None else source_problems(parsed, None))]


def checked_sink(options: Ros2SinkOptions | Mapping[str, Any]) -> list[str]:
    """Every problem of a sink's options (as ``check`` reports them), for its constructor."""
    parsed, problems = typed_or_problem(Ros2SinkOptions, options)
    return [message for _, message in (problems if parsed is None else sink_problems(parsed, None))]


def _check_type(name: Any) -> Iterator[tuple[str, str]]:
    try:
        rosmsg.resolve_type(name)
    except rosmsg.MessageError as exc:
        yield "type", str(exc)


def _check_endpoint(options: Ros2EndpointOptions, sink: bool) -> Iterator[tuple[str | None, str]]:
    for message in check_topic(options.topic, "fields" if sink else "variables"):
        yield "topic", message
    yield from _check_type(options.type)


def _check_service(options: Ros2SinkOptions) -> Iterator[tuple[str | None, str]]:
    """A service or action sink: one valid name, an installed pkg/srv/Type or pkg/action/Type."""
    key = "service" if options.service is not None else "action"
    if sum(value is not None for value in (options.topic, options.service, options.action)) > 1:
        yield key, "a ros2 sink names one of topic, service or action"
    if key == "action" and "max_in_flight" in given(options):
        yield "max_in_flight", "max_in_flight applies to a sink that calls a service (goals are bounded by the server)"
    for message in check_topic(getattr(options, key), "none"):
        yield key, message.replace("topic", key)
    try:
        (ros2_calls.resolve_service if key == "service" else ros2_calls.resolve_action)(options.type)
    except rosmsg.MessageError as exc:
        yield "type", str(exc)


def sink_class(options: Ros2SinkOptions) -> rosmsg.RosClass:
    """What a sink's mapping builds: the message of its topic, its service's request, its action's goal."""
    if options.service is not None:
        return ros2_calls.resolve_service(options.type).Request
    if options.action is not None:
        return ros2_calls.resolve_action(options.type).Goal
    return rosmsg.resolve_type(options.type)


def _check_mapping_keys(node: Mapping[str, Any], cls: rosmsg.RosClass, prefix: str) -> Iterator[str]:
    """Keys of a JMESPath multiselect hash (``{a: x, b: {c: y}}``) against message fields,
    descending into nested hashes for nested message fields."""
    fields = rosmsg.field_names(cls)
    for pair in node.get("children", ()):
        key = pair.get("value")
        if key not in fields:
            yield (f"mapping key {prefix}{key!r} is not a field of {rosmsg.type_name(cls)} "
                   f"(fields: {', '.join(fields)}){did_you_mean(key, fields)}")
            continue
        value = (pair.get("children") or [{}])[0]
        nested = rosmsg.nested_type(cls, key)
        if value.get("type") == "multi_select_dict" and nested is not None:
            yield from _check_mapping_keys(value, nested, f"{prefix}{key}.")
