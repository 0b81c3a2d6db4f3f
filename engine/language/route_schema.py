"""The route-file JSON Schema, generated from the option declarations (engine/common/options.py).

Every key a route file may hold is declared once, as a field of an option class: each
protocol's connection, source and sink options (``Transport.connection_options``,
``source_options``, ``sink_options``), and the route file's own keys (engine/language/route_options.py
``RouteOptions``, ``ConnectionLimits``, ``LeaseOptions``; ``BufferOptions``,
``ThrottleOptions``, ``DeadLettersOptions`` in the modules that use them). This module puts
them together into ``engine/language/route_file.schema.json``, which the loader validates with (so
editors and ``check`` agree) and which ships with the package, and into the key reference
``docs/route-keys.md`` (engine/language/route_keys.py renders it from this schema, so the docs list
exactly the keys the loader accepts); ``tests/language/test_route_schema.py`` fails when either file is
not what this module generates.

    python -m engine.language.route_schema --write     # regenerate the schema and docs/route-keys.md
    python -m engine.language.route_schema --check     # exit 1 if either is stale
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from engine import endpoints
from engine.common.options import property_schema, schema
from engine.endpoints.base import Transport
from engine.language.route_keys import render_keys
from engine.language.route_options import ENDPOINT_DESCRIPTION, NAME_PATTERN, ConnectionLimits, FallbackKeys, RouteOptions, SinkKeys
from engine.language.stage_options import DeadLettersOptions

SCHEMA_PATH = Path(__file__).with_name("route_file.schema.json")
KEYS_PATH = Path(__file__).resolve().parents[2] / "docs" / "route-keys.md"
"""The generated key reference; in a source checkout only (an installed package has no docs/)."""
REGENERATE = "python -m engine.language.route_schema --write"


def _connection_description(transports: list[Transport]) -> str:
    beside = [transport.name for transport in transports if transport.options_beside]
    return (f"exactly one protocol key ({' / '.join(transport.name for transport in transports)}); the keys of a protocol "
            f"whose options sit beside it ({', '.join(beside)}) and the limits every protocol has")


def _transports() -> list[Transport]:
    return [endpoints.transport(protocol) for protocol in endpoints.PROTOCOLS]


def _connection_entry(transports: list[Transport]) -> dict[str, Any]:
    """``connections.<name>``: one protocol key (its options, or the shorthand string) and
    the keys beside it (a protocol's ``options_beside``, and :class:`ConnectionLimits`)."""
    properties: dict[str, Any] = {}
    beside: dict[str, Any] = {}
    for transport in transports:
        cls = transport.connection_options
        if transport.options_beside:
            shorthand = transport.connection_shorthand or ""
            properties[transport.name] = property_schema(cls, shorthand)
            beside.update({name: _only(transport.name, prop) for name, prop in schema(cls)["properties"].items() if name != shorthand})
        elif transport.connection_shorthand:
            properties[transport.name] = {"anyOf": [{"type": "string"}, schema(cls)]}
        else:
            properties[transport.name] = schema(cls)
    properties.update(beside)
    properties.update(schema(ConnectionLimits)["properties"])
    return {
        "type": "object",
        "additionalProperties": False,
        "minProperties": 1,
        "description": _connection_description(transports),
        "properties": properties,
    }


def _only(protocol: str, prop: dict[str, Any]) -> dict[str, Any]:
    """A key beside a protocol's key applies to that protocol's connections only: say so."""
    return {**prop, "description": f"{protocol} connections: {prop.get('description', '')}".rstrip(": ")}


def _endpoint(transports: list[Transport], side: str) -> dict[str, Any]:
    """``source:`` or ``sink:``: exactly one protocol key with that protocol's options; a sink
    also has the keys of :class:`SinkKeys` (its mapping, name, when and fallback), a fallback
    (side ``fallback``) those of :class:`FallbackKeys`."""
    properties = {t.name: schema(t.source_options if side == "source" else t.sink_options) for t in transports}
    if side == "sink":
        properties.update(schema(SinkKeys)["properties"])
        properties["fallback"] = _endpoint(transports, "fallback")
    elif side == "fallback":
        fallback = schema(FallbackKeys)
        properties.update(fallback["properties"])
        return {"type": "object", "additionalProperties": False, "properties": properties, "description": fallback["description"]}
    return {"type": "object", "additionalProperties": False, "properties": properties,
            "description": ENDPOINT_DESCRIPTION}


def route_file_schema() -> dict[str, Any]:
    """The whole route-file schema (draft 2020-12)."""
    transports = _transports()
    route = schema(RouteOptions)
    route["properties"]["source"] = _endpoint(transports, "source")
    route["properties"]["sink"] = _endpoint(transports, "sink")
    route["properties"]["sinks"] = {**route["properties"]["sinks"], "items": _endpoint(transports, "sink")}
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "$id": "https://rabbitros.dev/schemas/route-file.json",
        "title": "RabbitROS engine route file",
        "type": ["object", "null"],
        "additionalProperties": False,
        "properties": {
            "connections": {
                "type": "object",
                "description": "named connections, shared by every file of the directory",
                "propertyNames": {"type": "string", "pattern": NAME_PATTERN},
                "additionalProperties": _connection_entry(transports),
            },
            "agents": {
                "type": "object",
                "description": "the fleet's members by name (engine/language/agents.py), names unique across the directory: "
                               "for_each: agents expands a route per agent, options that take an agent (system_id, "
                               "target_system) take its name, and meta('agent') names the agent heard",
                "propertyNames": {"type": "string", "pattern": NAME_PATTERN},
                "additionalProperties": {
                    "type": "object",
                    "description": "the agent's values, each a template variable of for_each: agents; connection: the "
                                   "connection it is reached over (the others mean what each protocol says: system_id)",
                    "propertyNames": {"type": "string", "pattern": "^[A-Za-z_][A-Za-z0-9_]*$"},
                    "additionalProperties": {"type": ["string", "number", "boolean"],
                                             "description": "one value (a text, a number or a boolean)"},
                },
            },
            "dead_letters": schema(DeadLettersOptions),
            "routes": {"type": "array", "items": route, "description": "the routes of this file; names unique across the directory"},
        },
    }


def render() -> str:
    return json.dumps(route_file_schema(), indent=2, ensure_ascii=False) + "\n"


def render_reference() -> str:
    """docs/route-keys.md: the key reference, from the same schema."""
    return render_keys(route_file_schema())


def generated() -> dict[Path, str]:
    """Each generated file and the text it must hold."""
    return {SCHEMA_PATH: render(), KEYS_PATH: render_reference()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m engine.language.route_schema", description=__doc__.split("\n\n")[0])
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--write", action="store_true", help=f"write {SCHEMA_PATH.name} and docs/{KEYS_PATH.name}")
    group.add_argument("--check", action="store_true", help="exit 1 if the shipped schema or the key reference is stale")
    args = parser.parse_args(argv)
    if args.write:
        for path, text in generated().items():
            path.write_text(text, encoding="utf-8")
            print(f"wrote {path}")
        return 0
    if args.check:
        stale = [path for path, text in generated().items() if not path.is_file() or path.read_text(encoding="utf-8") != text]
        for path in stale:
            print(f"{path} is stale; regenerate it with: {REGENERATE}", file=sys.stderr)
        return 1 if stale else 0
    sys.stdout.write(render())
    return 0


if __name__ == "__main__":
    sys.exit(main())
