"""Static checks of MAVLink route options: every problem with the option it belongs to, so
``check`` and a reload name the file, route and field before anything connects."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

import jmespath
from jmespath import exceptions as jmespath_errors

from engine.endpoints.base import EndpointError
from engine.endpoints.mavlink.codec import MESSAGES

_SOURCE_OPTIONS = {"message", "json_tunnel", "system_id", "component_id", "payload_type", "target_system", "target_component"}
_SINK_OPTIONS = _SOURCE_OPTIONS


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
    problems = list(_common_problems(options, _SINK_OPTIONS))
    if options.get("json_tunnel"):
        return problems
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


