"""A schema a test names, looked up so that a missing one fails with its name (not an
AttributeError on None) and types as present."""

from __future__ import annotations

from engine.common.schemas import CanonicalSchema, SchemaRegistry


def known_schema(registry: SchemaRegistry, name: str) -> CanonicalSchema:
    """``registry.get(name)``, asserted present: the test relies on the schema existing."""
    schema = registry.get(name)
    assert schema is not None, f"no schema {name!r} in the registry"
    return schema
