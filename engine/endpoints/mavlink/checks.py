"""Static checks of MAVLink route options: every problem with the option it belongs to, so
``check`` and a reload name the file, route and field before anything connects."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

import jmespath
from jmespath import exceptions as jmespath_errors

from engine.endpoints.base import EndpointError
from engine.endpoints.mavlink.codec import MESSAGES
from engine.endpoints.mavlink.transaction import TransactionOptions

_SOURCE_OPTIONS = {"message", "json_tunnel", "system_id", "component_id", "payload_type", "target_system", "target_component"}
_TRANSACTION_OPTIONS = {"timeout", "retries", "vehicle_timeout"}
_MISSION_OPTIONS = {"mission", "target_system", "target_component", "home_placeholder", "default_alt", "mission_type",
                    *_TRANSACTION_OPTIONS}
_COMMAND_OPTIONS = {"acknowledged", "in_progress_timeout", "retry_delay", *_TRANSACTION_OPTIONS}
_SINK_OPTIONS = _SOURCE_OPTIONS | _COMMAND_OPTIONS
ACKNOWLEDGED_MESSAGES = ("COMMAND_LONG", "COMMAND_INT")


def _int_option(options: Mapping[str, Any], key: str, low: int, high: int) -> Iterator[tuple[str, str]]:
    if key in options:
        value = options[key]
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            yield key, f"{key} must be an integer {low}..{high}"


def _common_problems(options: Mapping[str, Any], allowed: set[str]) -> Iterator[tuple[str | None, str]]:
    for key in sorted(set(options) - allowed - {"connection"}):
        yield key, f"unknown option {key!r}"
    for key in ("system_id", "component_id", "target_system", "target_component"):
        yield from _int_option(options, key, 0, 255)
    yield from _int_option(options, "payload_type", 32768, 65535)
    name = options.get("message")
    if name is not None and name not in MESSAGES:
        yield "message", f"unknown MAVLink message {name!r} (dialect: common)"


def check_source_options(options: Mapping[str, Any], mapping: str | None) -> list[tuple[str | None, str]]:
    problems = list(_common_problems(options, _SOURCE_OPTIONS))
    if options.get("json_tunnel") and options.get("message") not in (None, "TUNNEL"):
        problems.append(("message", "a json_tunnel source reads TUNNEL frames; drop 'message'"))
    return problems


def check_sink_options(options: Mapping[str, Any], mapping: str | None) -> list[tuple[str | None, str]]:
    if "mission" in options:
        return _mission_problems(options, mapping)
    problems = list(_common_problems(options, _SINK_OPTIONS))
    if options.get("json_tunnel"):
        return problems
    if "acknowledged" in options:
        if not isinstance(options["acknowledged"], bool):
            problems.append(("acknowledged", "acknowledged must be true or false"))
        elif options["acknowledged"] and options.get("message") not in ACKNOWLEDGED_MESSAGES:
            problems.append(("acknowledged", "acknowledged applies to COMMAND_LONG and COMMAND_INT sinks"))
        problems += TransactionOptions.parse(options)[1]
    elif set(options) & (_COMMAND_OPTIONS - {"acknowledged"}):
        key = sorted(set(options) & _COMMAND_OPTIONS)[0]
        problems.append((key, f"{key!r} applies to acknowledged commands (acknowledged: true) and missions"))
    name = options.get("message")
    if name is None:
        problems.append((None, "a mavlink sink needs 'message' (or json_tunnel: true)"))
        return problems
    cls = MESSAGES.get(name)
    if cls is None:
        return problems
    for key in ("target_system", "target_component"):
        if key in options and key not in cls.fieldnames:
            problems.append((key, f"{name} has no field {key!r}"))
    for key in _mapping_keys(mapping):
        if key not in cls.fieldnames:
            fields = ", ".join(cls.fieldnames)
            problems.append((None, f"sink mapping sets {key!r}, which {name} does not have (fields: {fields})"))
    return problems


def _mission_problems(options: Mapping[str, Any], mapping: str | None) -> list[tuple[str | None, str]]:
    problems: list[tuple[str | None, str]] = [
        (key, f"unknown option {key!r} for a mission sink") for key in sorted(set(options) - _MISSION_OPTIONS - {"connection"})]
    if options["mission"] != "upload":
        problems.append(("mission", "mission must be 'upload'"))
    problems += TransactionOptions.parse(options)[1]
    for key in _mapping_keys(mapping):
        if key != "items":
            problems.append((None, f"a mission sink mapping produces {{items: [...]}} (or a canonical mission); "
                                   f"{key!r} is not used"))
    return problems


def _mapping_keys(mapping: str | None) -> list[str]:
    if not mapping:
        return []
    try:
        node = jmespath.compile(mapping).parsed
    except jmespath_errors.JMESPathError:
        return []
    if node.get("type") != "multi_select_dict":
        return []
    return [child["value"] for child in node["children"] if child.get("type") == "key_val_pair"]


def raise_problems(route: str, side: str, problems: list[tuple[str | None, str]]) -> None:
    if problems:
        raise EndpointError(f"route {route!r}: mavlink {side}: " + "; ".join(m for _, m in problems))


