"""The route-file key reference (``docs/route-keys.md``), rendered from the route-file schema.

The schema (engine/language/route_schema.py) is itself generated from the option declarations, so
rendering the reference from the schema, rather than walking the declarations a second way,
documents exactly the keys the loader accepts: a key that is declared is in both, at the same
path, with the same type, bounds and default, whatever module declared it. Every object of the
schema becomes one section (``connections.<name>.amqp``, ``routes[].sink.mavlink``...), one row
per key: the key, its value (type, bounds, enum), its default (or "required") and its
description.

A page of its own rather than a generated section of docs/route-language.md: some 130 rows
would bury that page's explanations, and a file that is generated whole is compared byte for
byte (no markers to keep) and, after a merge that touched declarations, regenerated instead of
merged by hand. route-language.md explains and links to its sections (``anchor``).

    python -m engine.language.route_schema --write     # regenerates the schema and this reference
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from typing import Any

KEYS_HEADER = """# Route file keys

<!-- Generated from the option declarations by `python -m engine.language.route_schema --write`; do not edit.
     tests/language/test_route_schema.py fails while this file differs from what the declarations give. -->

Every key a route file accepts, at every level, with its value, default and meaning. This page
is generated from the same option declarations as the route-file JSON Schema
(`engine/language/route_file.schema.json`), so it lists exactly what the loader accepts. How the pieces
fit together (defaults of connections, delivery, throttling, route tests, functions) is in
[route-language.md](route-language.md).

A key path like `routes[].sink` is the one an error message names
(`routes[0].max_attempts: 0 is less than the minimum of 1`).
"""


@dataclass
class Section:
    """One object of the schema: its key path and the rows of its keys."""

    path: str
    description: str = ""
    rows: list[tuple[str, str, str, str]] = field(default_factory=list)


def anchor(path: str) -> str:
    """A stable HTML id for a key path (``routes[].source.amqp`` -> ``routes-source-amqp``)."""
    return re.sub(r"[^a-z0-9]+", "-", path.lower()).strip("-") or "top-level"


def _code(value: Any) -> str:
    return f"`{json.dumps(value, ensure_ascii=False)}`" if not isinstance(value, str) else f"`{value}`" if value else "`''`"


def _is_object(node: dict[str, Any]) -> bool:
    return "properties" in node or isinstance(node.get("additionalProperties"), dict)


def _bounds(node: dict[str, Any]) -> list[str]:
    """Bounds in words: ``1..65535``, ``>= 0``, ``> 0``, ``at least 1 item``, ``matches ^..$``."""
    out = []
    low, high, above = node.get("minimum"), node.get("maximum"), node.get("exclusiveMinimum")
    if low is not None and high is not None:
        out.append(f"{low}..{high}")
    elif low is not None:
        out.append(f">= {low}")
    elif high is not None:
        out.append(f"<= {high}")
    if above is not None:
        out.append(f"> {above}")
    if node.get("minItems"):
        out.append(f"at least {node['minItems']} item{'s' if node['minItems'] > 1 else ''}")
    if node.get("minProperties"):
        out.append(f"at least {node['minProperties']} key{'s' if node['minProperties'] > 1 else ''}")
    if node.get("pattern"):
        out.append(f"matching `{node['pattern']}`")
    return out


class _Renderer:
    def __init__(self) -> None:
        self.sections: list[Section] = []

    def value(self, node: dict[str, Any], path: str) -> str:
        """The value column of ``node`` (at key path ``path``); objects get their own section."""
        if "const" in node:
            text = _code(node["const"])
        elif "enum" in node:
            text = "one of " + ", ".join(_code(choice) for choice in node["enum"])
        elif "anyOf" in node:
            text = " or ".join(self.value(alternative, path) for alternative in node["anyOf"])
        elif _is_object(node):
            self.section(node, path)
            text = f"[object](#{anchor(path)})"
        else:
            types = node.get("type", "any")
            types = types if isinstance(types, list) else [types]
            words = []
            kind: str
            for kind in types:
                if kind == "array":
                    item = node.get("items") or {}
                    words.append(f"list of {self.value(item, path + '[]') if item else 'any'}")
                else:
                    words.append({"object": "mapping", "null": "`null`"}.get(kind, kind))
            text = " or ".join(words)
        bounds = _bounds(node)
        return f"{text}, {', '.join(bounds)}" if bounds else text

    def section(self, node: dict[str, Any], path: str) -> None:
        section = Section(path, node.get("description", ""))
        self.sections.append(section)
        required = set(node.get("required", ()))
        for key, prop in node.get("properties", {}).items():
            value = self.value(prop, f"{path}.{key}" if path else key)
            default = "**required**" if key in required else _code(prop["default"]) if "default" in prop else ""
            section.rows.append((f"`{key}`", value, default, _description(prop)))
        extra = node.get("additionalProperties")
        if isinstance(extra, dict):
            names = (node.get("propertyNames") or {}).get("pattern")
            key = "`<name>`" + (f" (matching `{names}`)" if names else "")
            value = self.value(extra, f"{path}.<name>")
            section.rows.append((key, value, "", _description(extra)))


def _description(node: dict[str, Any]) -> str:
    """A key's own description, or the one of its object alternative (``amqp: URL | {...}``)."""
    text = node.get("description") or next(
        (a["description"] for a in node.get("anyOf", ()) if isinstance(a, dict) and a.get("description")), "")
    return text.replace("|", "\\|").replace("\n", " ")


def render_keys(route_file_schema: dict[str, Any]) -> str:
    """The markdown key reference of a route-file schema."""
    renderer = _Renderer()
    renderer.section(route_file_schema, "")
    out = [KEYS_HEADER]
    for section in renderer.sections:
        title = f"`{section.path}`" if section.path else "Top level"
        out.append(f'<a id="{anchor(section.path)}"></a>\n\n## {title}\n')
        if section.description:
            out.append(section.description.replace("\n", " ") + "\n")
        out.append("| key | value | default | meaning |\n|---|---|---|---|")
        out.extend(f"| {' | '.join(row)} |" for row in section.rows)
        out.append("")
    return "\n".join(out)
