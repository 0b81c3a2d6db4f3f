"""Typed options: one declaration per endpoint (and per route-level key), parsed once.

An option class is a ``@dataclass(frozen=True, kw_only=True)`` whose fields say what the
route file may hold; :func:`option` adds what a user sees in an editor and what bounds the
value (description, minimum, pattern...). From that one declaration:

- :func:`parse` turns a mapping from a route file into an instance, once, at load. It checks
  types, bounds, enums (``Literal[...]``) and nesting, fills defaults, and raises a single
  error type, :class:`OptionError`, carrying the key path (``("routes", 0, "source",
  "amqp", "prefetch")``) the loader turns into ``file:line``.
- :func:`schema` produces the JSON Schema (draft 2020-12) fragment of the class, from which
  ``engine/language/route_schema.py`` builds the whole route-file schema (shipped as
  ``engine/language/route_file.schema.json``, kept fresh by ``tests/language/test_route_schema.py``).

Supported field types: ``bool``, ``int``, ``float`` (an int is accepted), ``str``,
``Literal[...]`` (an enum; one value is a ``const``), another option class (nested),
``tuple[X, ...]`` (a YAML list), ``dict[str, Any]`` (a free mapping), unions of those
(``str | int``), and ``X | None`` with a ``None`` default: the key may be absent (None means
"not given"; ``option(nullable=True)`` also lets a YAML ``null`` through).

Hand-written rather than pydantic/msgspec (neither is installed; adding one for ~200 lines
would not pay): the schema must keep today's exact shape and messages (the loader validates
with jsonschema first, so every existing ``file:line`` error stays as it was), secrets
(:class:`engine.common.redaction.Secret`) must pass through untouched, and the parse must know
which keys were written (:func:`given`) because an option given where it is not used is an
error in ``check``.
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from collections.abc import Mapping
from functools import cache
from typing import TYPE_CHECKING, Any, Literal, TypeVar, Union

from engine.common.redaction import Secret
from engine.common.suggest import did_you_mean

KeyPath = tuple[str | int, ...]
if TYPE_CHECKING:
    from _typeshed import DataclassInstance

T = TypeVar("T", bound="DataclassInstance")
"""An option class: a dataclass."""

_GIVEN = "_given_keys"


class OptionError(ValueError):
    """Option values the declaration does not allow. ``path`` and ``message`` name the
    first; ``problems`` lists every ``(path, message)`` found in the same parse, so a check
    reports them all at once."""

    def __init__(self, path: KeyPath, message: str, problems: tuple[tuple[KeyPath, str], ...] = ()) -> None:
        super().__init__(describe(path, message))
        self.path = path
        self.message = message
        self.problems = problems or ((path, message),)


def describe(path: KeyPath, message: str) -> str:
    """One problem as the loader shows it: ``routes[0].rate: 0 is less than ...`` (an unknown
    key's message names its place already)."""
    return message if message.startswith("unknown key") else f"{dotted(path)}: {message}"


def option(
    default: Any = dataclasses.MISSING,
    *,
    description: str | None = None,
    minimum: float | None = None,
    maximum: float | None = None,
    exclusive_minimum: float | None = None,
    pattern: str | None = None,
    min_items: int | None = None,
    show_default: bool = True,
    nullable: bool = False,
    secret: bool = False,
    internal: bool = False,
    schema: Mapping[str, Any] | None = None,
) -> Any:
    """A dataclass field with what the schema and the parser need.

    ``show_default=False`` keeps a default out of the schema (and docs/route-keys.md) where the
    declared value is not what applies: the description then says what does. ``secret``: a
    :class:`Secret` passes as a string. ``internal``: set by the engine, never by a route file
    (not parsed, not in the schema). ``description``: what the key does, shown in editors and
    in docs/route-keys.md (tests/language/test_route_schema.py requires one for every key). ``schema``:
    JSON Schema keywords for the schema only, merged as they are: bounds a check reports in
    its own words (the parser does not read them; the loader validates with the schema)."""
    metadata = {
        "description": description, "minimum": minimum, "maximum": maximum,
        "exclusiveMinimum": exclusive_minimum, "pattern": pattern, "minItems": min_items,
        "show_default": show_default, "nullable": nullable, "secret": secret, "internal": internal,
        "schema": dict(schema or {}),
    }
    if isinstance(default, (list, dict, set)):
        raise TypeError("option defaults must be immutable (use a tuple)")
    return dataclasses.field(default=default, metadata=metadata)


def evolve(value: T, **changes: Any) -> T:
    """``dataclasses.replace`` that keeps what :func:`given` says (the keys written)."""
    out = dataclasses.replace(value, **changes)
    object.__setattr__(out, _GIVEN, given(value))
    return out


def given(value: Any) -> frozenset[str]:
    """The keys the route file wrote for ``value`` (an instance :func:`parse` returned)."""
    return getattr(value, _GIVEN, frozenset())


def unknown_key(key: Any, path: KeyPath, allowed: list[str]) -> str:
    """The message for a key the declaration does not have (the schema's wording too)."""
    return f"unknown key {key!r} at {dotted(path)} (allowed: {', '.join(allowed)}){did_you_mean(str(key), allowed)}"


def dotted(path: KeyPath) -> str:
    """``routes[0].source.amqp`` (the loader's way of naming a key path)."""
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "top level"


def fields_of(cls: type) -> list[dataclasses.Field[Any]]:
    """The fields a route file may set (internal ones excluded), in declaration order."""
    return [f for f in dataclasses.fields(cls) if not f.metadata.get("internal")]


@cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


# --- parsing ---------------------------------------------------------------------------------


def parse(cls: type[T], data: Any, path: KeyPath = ()) -> T:
    """``data`` (a mapping from a route file) as an instance of the option class ``cls``;
    raises :class:`OptionError` naming every key path that does not fit."""
    if isinstance(data, cls):
        return data
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise OptionError(path, f"{_shown(data)} is not of type 'object'")
    known = {f.name: f for f in fields_of(cls)}
    problems: list[tuple[KeyPath, str]] = []
    for key in data:
        if key not in known:
            allowed = sorted(known)
            problems.append((path + (key,), unknown_key(key, path, allowed)))
    hints = _hints(cls)
    values: dict[str, Any] = {}
    for name, f in known.items():
        if name in data:
            try:
                values[name] = _value(hints[name], f.metadata, data[name], path + (name,))
            except OptionError as exc:
                problems.extend(exc.problems)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            problems.append((path + (name,), f"{name!r} is a required property"))
    if problems:
        raise OptionError(*problems[0], problems=tuple(problems))
    instance = cls(**values)
    object.__setattr__(instance, _GIVEN, frozenset(data))
    return instance


def _value(hint: Any, meta: Mapping[str, Any], value: Any, path: KeyPath) -> Any:
    if value is None and meta.get("nullable"):
        return None
    checked = _typed(hint, meta, value, path)
    _bounds(meta, checked, path)
    return checked


def _typed(hint: Any, meta: Mapping[str, Any], value: Any, path: KeyPath) -> Any:
    origin = typing.get_origin(hint)
    if origin in (Union, types.UnionType):
        alternatives = [a for a in typing.get_args(hint) if a is not type(None)]
        errors = []
        for alternative in alternatives:
            try:
                return _typed(alternative, meta, value, path)
            except OptionError as exc:
                errors.append(exc)
        if len(alternatives) == 1:
            raise errors[0]
        raise OptionError(path, f"{_shown(value)} is not valid under any of the given schemas")
    if origin is Literal:
        choices = typing.get_args(hint)
        if not any(value == choice and type(value) is type(choice) for choice in choices):
            hint = did_you_mean(value, [str(choice) for choice in choices]) if isinstance(value, str) else ""
            raise OptionError(path, f"{_shown(value)} is not one of {list(choices)!r}{hint}")
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise OptionError(path, f"{_shown(value)} is not of type 'array'")
        item = typing.get_args(hint)[0]
        return tuple(_value(item, {"secret": meta.get("secret")}, v, path + (i,)) for i, v in enumerate(value))
    if origin is dict or hint is dict:
        if not isinstance(value, Mapping):
            raise OptionError(path, f"{_shown(value)} is not of type 'object'")
        return dict(value)
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        return parse(hint, value, path)
    if hint is Any:
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise OptionError(path, f"{_shown(value)} is not of type 'boolean'")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise OptionError(path, f"{_shown(value)} is not of type 'integer'")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise OptionError(path, f"{_shown(value)} is not of type 'number'")
        return value
    if hint is str:
        if isinstance(value, Secret) and meta.get("secret"):
            return value
        if not isinstance(value, str):
            raise OptionError(path, f"{_shown(value)} is not of type 'string'")
        return value
    raise TypeError(f"option type {hint!r} is not supported")


def _bounds(meta: Mapping[str, Any], value: Any, path: KeyPath) -> None:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if meta.get("minimum") is not None and value < meta["minimum"]:
            raise OptionError(path, f"{value!r} is less than the minimum of {meta['minimum']!r}")
        if meta.get("maximum") is not None and value > meta["maximum"]:
            raise OptionError(path, f"{value!r} is greater than the maximum of {meta['maximum']!r}")
        if meta.get("exclusiveMinimum") is not None and value <= meta["exclusiveMinimum"]:
            raise OptionError(path, f"{value!r} is less than or equal to the minimum of {meta['exclusiveMinimum']!r}")
    if isinstance(value, str) and meta.get("pattern") and not re.search(meta["pattern"], value):
        raise OptionError(path, f"{value!r} does not match {meta['pattern']!r}")
    if isinstance(value, tuple) and meta.get("minItems") is not None and len(value) < meta["minItems"]:
        raise OptionError(path, f"{list(value)!r} should be non-empty" if meta["minItems"] == 1 else f"{list(value)!r} is too short")


def _shown(value: Any) -> str:
    return repr(str(value)) if isinstance(value, Secret) else repr(value)


# --- schema ----------------------------------------------------------------------------------


def schema(cls: type) -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) fragment of the option class ``cls``: an object with
    exactly the declared keys (``additionalProperties: false``)."""
    hints = _hints(cls)
    out: dict[str, Any] = {"type": "object", "additionalProperties": False}
    doc = getattr(cls, "__schema_description__", None)
    if doc:
        out["description"] = doc
    required = [f.name for f in fields_of(cls)
                if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
    if required:
        out["required"] = required
    out["properties"] = {f.name: field_schema(hints[f.name], f) for f in fields_of(cls)}
    return out


def property_schema(cls: type, name: str) -> dict[str, Any]:
    """The schema of one field of ``cls``."""
    f = next(f for f in fields_of(cls) if f.name == name)
    return field_schema(_hints(cls)[name], f)


def field_schema(hint: Any, f: dataclasses.Field[Any]) -> dict[str, Any]:
    """One property's schema: its type, bounds, default (unless None or hidden), description."""
    meta = f.metadata
    out = _type_schema(hint)
    if meta.get("nullable"):
        out["type"] = [out["type"], "null"] if isinstance(out.get("type"), str) else out["type"]
    for key in ("minimum", "maximum", "exclusiveMinimum", "pattern", "minItems"):
        if meta.get(key) is not None:
            out[key] = meta[key]
    if meta.get("show_default", True) and f.default is not dataclasses.MISSING and f.default is not None \
            and not dataclasses.is_dataclass(f.default):
        out["default"] = list(f.default) if isinstance(f.default, tuple) else f.default
    if meta.get("description"):
        out["description"] = meta["description"]
    extra = meta.get("schema") or {}
    if "enum" in extra or "const" in extra:
        out.pop("type", None)  # the values say the type
    out.update(extra)
    return out


_SIMPLE = {bool: "boolean", int: "integer", float: "number", str: "string"}


def _type_schema(hint: Any) -> dict[str, Any]:
    origin = typing.get_origin(hint)
    if origin in (Union, types.UnionType):
        alternatives = [a for a in typing.get_args(hint) if a is not type(None)]
        if len(alternatives) == 1:
            return _type_schema(alternatives[0])
        if all(a in _SIMPLE for a in alternatives):
            return {"type": [_SIMPLE[a] for a in alternatives]}
        return {"anyOf": [_type_schema(a) for a in alternatives]}
    if origin is Literal:
        choices = list(typing.get_args(hint))
        return {"const": choices[0]} if len(choices) == 1 else {"enum": choices}
    if origin is tuple:
        return {"type": "array", "items": _type_schema(typing.get_args(hint)[0])}
    if origin is dict or hint is dict:
        return {"type": "object"}
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        return schema(hint)
    if hint in _SIMPLE:
        return {"type": _SIMPLE[hint]}
    raise TypeError(f"option type {hint!r} is not supported")
