"""Static checks of MAVLink route options: every problem with the option it belongs to, so
``check`` and a reload name the file, route and field before anything connects."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

import jmespath
from jmespath import exceptions as jmespath_errors

from engine.common.options import given
from engine.common.placeholders import TemplateError, whole_field
from engine.common.suggest import did_you_mean
from engine.endpoints.base import EndpointError, typed_or_problem
from engine.endpoints.mavlink.codec import MESSAGES, NEVER_GUESSED
from engine.endpoints.mavlink.enums import mav_enum_value
from engine.endpoints.mavlink.options import MavlinkSinkOptions, MavlinkSourceOptions
from engine.endpoints.mavlink.transaction import TransactionOptions

_SENDER = {"system_id", "component_id"}
_TARGET = {"target_system", "target_component"}
_TRANSACTION_OPTIONS = {"timeout", "retries", "vehicle_timeout", "command_timeout"}
_MISSION_ONLY = {"mission", "home_placeholder", "mission_type"}
_MISSION_OPTIONS = {*_MISSION_ONLY, *_TARGET, *_TRANSACTION_OPTIONS}
_COMMAND_OPTIONS = {"acknowledged", "in_progress_timeout", "retry_delay", "refusals", *_TRANSACTION_OPTIONS}

# What each kind of endpoint reads: any other option would be silently ignored, so it is an error.
_MESSAGE_SOURCE = {"message", "json_tunnel", *_SENDER}
_TUNNEL_SOURCE = {"json_tunnel", "payload_type", *_SENDER}
_MESSAGE_SINK = {"message", "json_tunnel", "acknowledged", *_TARGET}
_COMMAND_SINK = {*_MESSAGE_SINK, *_COMMAND_OPTIONS}
_TUNNEL_SINK = {"json_tunnel", "payload_type", *_TARGET}

_APPLIES_TO = {
    "message": "message sources and sinks (not json_tunnel)",
    "payload_type": "json_tunnel sources and sinks",
    "system_id": "sources (the sender to accept); a sink names its receiver with target_system",
    "component_id": "sources (the sender to accept); a sink names its receiver with target_component",
    "target_system": "sinks (the receiver); a source filters senders with system_id",
    "target_component": "sinks (the receiver); a source filters senders with component_id",
    "acknowledged": "COMMAND_LONG and COMMAND_INT sinks",
    "in_progress_timeout": "acknowledged commands (acknowledged: true)",
    "retry_delay": "acknowledged commands (acknowledged: true)",
    "refusals": "acknowledged commands (acknowledged: true)",
    **{key: "acknowledged commands (acknowledged: true) and missions (mission: upload)" for key in _TRANSACTION_OPTIONS},
    **{key: "mission sinks (mission: upload)" for key in _MISSION_ONLY},
}
ACKNOWLEDGED_MESSAGES = ("COMMAND_LONG", "COMMAND_INT")


def _common_problems(options: MavlinkSourceOptions, used: set[str], kind: str) -> Iterator[tuple[str | None, str]]:
    yield from _unused(options, used, kind)
    name = options.message
    if name is not None and name not in MESSAGES:
        yield "message", f"unknown MAVLink message {name!r} (dialect: common)"


def _unused(options: MavlinkSourceOptions, used: set[str], kind: str) -> Iterator[tuple[str | None, str]]:
    """Every option written that this kind of endpoint does not read (meant for another kind)."""
    for key in sorted(given(options) - used - {"connection"}):
        if key in _APPLIES_TO:
            yield key, f"{key!r} is not used by a {kind}: it applies to {_APPLIES_TO[key]}"
        else:
            yield key, f"unknown option {key!r}"


def _agent_problems(options: MavlinkSourceOptions, keys: tuple[str, ...]) -> list[tuple[str | None, str]]:
    """A name where an id is wanted that the route loader did not resolve (an endpoint built
    without it), and agents the link cannot tell apart: never a guessed vehicle."""
    problems: list[tuple[str | None, str]] = [
        (key, f"{key}: {value!r} names an agent, which only a route file's agents table resolves")
        for key in keys if isinstance(value := getattr(options, key), str) and not value.startswith("{")]
    by_id: dict[Any, list[str]] = {}
    for name, entry in (options.agents or {}).items():
        if "system_id" in entry:
            by_id.setdefault(entry["system_id"], []).append(name)
    problems.extend((None, f"agents {', '.join(names)} have one system_id ({system_id}) on one connection: a message "
                           "from it could not be told apart") for system_id, names in by_id.items() if len(names) > 1)
    return problems


def source_problems(options: MavlinkSourceOptions) -> list[tuple[str | None, str]]:
    if options.json_tunnel:
        problems = list(_common_problems(options, _TUNNEL_SOURCE, "json_tunnel source"))
        return [("message", "a json_tunnel source reads TUNNEL frames; drop 'message'") if key == "message" else (key, text)
                for key, text in problems] + _agent_problems(options, ("system_id",))
    return list(_common_problems(options, _MESSAGE_SOURCE, "message source")) + _agent_problems(options, ("system_id",))


def _target_field_problems(options: MavlinkSinkOptions) -> list[tuple[str | None, str]]:
    """A ``"{field}"`` target the engine's one template grammar does not read as one whole field
    (a format spec, text around it, a bad path): what messages.target_fields would refuse."""
    problems: list[tuple[str | None, str]] = []
    for key in ("target_system", "target_component"):
        value = getattr(options, key)
        if isinstance(value, str) and value.startswith("{"):
            try:
                whole_field(value, key)
            except TemplateError as exc:
                problems.append((key, f"{key}: {exc}"))
    return problems


def sink_problems(options: MavlinkSinkOptions, mapping: str | None) -> list[tuple[str | None, str]]:
    unresolved = _target_field_problems(options) or _agent_problems(options, ("target_system", "target_component"))
    if unresolved:
        return unresolved
    templated = [key for key in ("target_system", "target_component") if isinstance(getattr(options, key), str)]
    if templated and options.json_tunnel:
        return [(key, f"{key}: a \"{{field}}\" target is read per message by message, command and mission sinks; a "
                      "json_tunnel sink names its receiver with a number (a route per vehicle: for_each)") for key in templated]
    if "mission" in given(options):
        return _mission_problems(options, mapping)
    if options.json_tunnel:
        return list(_common_problems(options, _TUNNEL_SINK, "json_tunnel sink"))
    acknowledged = options.acknowledged
    problems = list(_common_problems(options, _COMMAND_SINK if acknowledged else _MESSAGE_SINK,
                                     "acknowledged command sink" if acknowledged else "message sink"))
    if "acknowledged" in given(options):
        if options.acknowledged and options.message not in ACKNOWLEDGED_MESSAGES:
            problems.append(("acknowledged", "acknowledged applies to COMMAND_LONG and COMMAND_INT sinks"))
        problems += TransactionOptions.parse(options)[1]
    name = options.message
    if name is None:
        problems.append((None, "a mavlink sink needs 'message' (or json_tunnel: true)"))
        return problems
    cls = MESSAGES.get(name)
    if cls is None:
        return problems
    for key in ("target_system", "target_component"):
        if key in given(options) and key not in cls.fieldnames:
            problems.append((key, f"{name} has no field {key!r}"))
    for key, value in _mapping_pairs(mapping):
        if key not in cls.fieldnames:
            fields = ", ".join(cls.fieldnames)
            problems.append((None, f"sink mapping sets {key!r}, which {name} does not have"
                                   f"{did_you_mean(key, cls.fieldnames)} (fields: {fields})"))
        elif _is_null_literal(value):
            problems.append((None, f"sink mapping sets {key!r} to `null`: every message would be refused; {NEVER_GUESSED}"))
        else:
            problems.extend((None, f"sink mapping {key!r}: {problem}")
                            for problem in _enum_name_problems(value, cls.fieldenums_by_name.get(key)))
    return problems


_MISSION_MAPPING_KEYS = ("items", "waypoints")
"""What a mission sink reads of its mapping's output: explicit MISSION_ITEM_INT items, or waypoints."""


def _mission_problems(options: MavlinkSinkOptions, mapping: str | None) -> list[tuple[str | None, str]]:
    problems: list[tuple[str | None, str]] = list(_unused(options, _MISSION_OPTIONS, "mission sink"))
    if options.mission != "upload":
        problems.append(("mission", "mission must be 'upload'"))
    problems += TransactionOptions.parse(options)[1]
    keys = [key for key, _ in _mapping_pairs(mapping)]
    for key in keys:
        if key not in _MISSION_MAPPING_KEYS:
            problems.append((None, f"a mission sink mapping produces {{items: [...]}} or a canonical mission's "
                                   f"{{waypoints: [...]}}; {key!r} is not used{did_you_mean(key, _MISSION_MAPPING_KEYS)}"))
    if set(_MISSION_MAPPING_KEYS) <= set(keys):
        problems.append((None, "a mission sink mapping produces items or waypoints, not both (items would win)"))
    return problems


def _mapping_pairs(mapping: str | None) -> list[tuple[str, dict[str, Any]]]:
    """The (key, value expression) pairs of a ``{a: x, b: y}`` sink mapping; [] for another shape."""
    if not mapping:
        return []
    try:
        node = jmespath.compile(mapping).parsed
    except jmespath_errors.JMESPathError:
        return []
    if node.get("type") != "multi_select_dict":
        return []
    return [(child["value"], child["children"][0]) for child in node["children"] if child.get("type") == "key_val_pair"]


def _enum_name_problems(node: dict[str, Any], enum: str | None) -> list[str]:
    """A misspelt enum name written in the mapping itself, found before any message: a name
    given to an enum field (``command: 'MAV_CMD_DO_REPOSITON'``) or to ``mav_enum_value`` with
    both arguments written out. Names that come from the message are checked as it arrives."""
    if node.get("type") == "literal" and isinstance(node.get("value"), str) and enum is not None:
        name = node["value"]
    elif node.get("type") == "function_expression" and node.get("value") == "mav_enum_value" \
            and [child.get("type") for child in node["children"]] == ["literal", "literal"]:
        name, enum = (child["value"] for child in node["children"])
    else:
        return []
    try:
        mav_enum_value(name, enum)
    except ValueError as exc:
        return [str(exc)]
    return []


def _is_null_literal(node: dict[str, Any]) -> bool:
    """A value written as `` `null` ``: every message would be refused at the sink mapping stage."""
    return node.get("type") == "literal" and node.get("value") is None


def source_options(route: str, options: MavlinkSourceOptions | Mapping[str, Any]) -> MavlinkSourceOptions:
    """The typed options of a source about to be built; EndpointError lists every problem."""
    parsed, problems = typed_or_problem(MavlinkSourceOptions, options)
    raise_problems(route, "source", problems if parsed is None else problems or source_problems(parsed))
    assert parsed is not None
    return parsed


def sink_options(route: str, options: MavlinkSinkOptions | Mapping[str, Any]) -> MavlinkSinkOptions:
    """The typed options of a sink about to be built; EndpointError lists every problem."""
    parsed, problems = typed_or_problem(MavlinkSinkOptions, options)
    raise_problems(route, "sink", problems if parsed is None else problems or sink_problems(parsed, None))
    assert parsed is not None
    return parsed


def raise_problems(route: str, side: str, problems: list[tuple[str | None, str]]) -> None:
    if problems:
        raise EndpointError(f"route {route!r}: mavlink {side}: " + "; ".join(m for _, m in problems))


