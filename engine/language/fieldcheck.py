"""Static checks of what a mapping reads from a typed source, before anything flows.

A typed source (a ROS 2 message type, a MAVLink message) has known fields, so a mapping that
reads ``longitud`` from a ``sensor_msgs/msg/NavSatFix`` can only ever produce null: ``check``
reports it with a did-you-mean instead of letting the schema reject every message in the
field. The mapping's JMESPath tree is walked for the field paths it reads from the source
message (through sub-expressions, indexes, projections and filters; what follows a pipe or
a function's result is not the source message and is left alone); each path is resolved
against the type by its transport (``Transport.field_problem``: ROS 2 by rosidl introspection,
MAVLink from pymavlink's generated message classes).

The other direction, for every route: the keys a mapping *sets* (:func:`mapping_writes`,
read from the same tree: multi-select hashes, projections, ``merge``) against the properties
its canonical schema declares (:class:`engine.common.schemas.Declared`); ``check`` warns about the
ones the schema does not name, since the schemas allow extra keys and a misspelt optional
field would otherwise pass every message unnoticed. What the sink mapping, ``per`` keys and
templates read of the canonical message is checked in engine/language/readcheck.py.

Also here: did-you-mean hints for a misspelt type or message name (``Transport.suggest``).
"""

from __future__ import annotations

from typing import Any, Iterator

from engine import endpoints
from engine.common.suggest import closest
from engine.endpoints.base import ELEMENT, EndpointError, FieldPath, FieldProblem
from engine.language.mapping import parsed

_BARE_LITERALS = frozenset({"null", "true", "false"})
"""JMESPath reads bare ``null`` as a field that is never there, which gives null: the idiom
``x || null`` works, so it is not reported as a missing field."""


def mapping_reads(expression: str | None) -> list[FieldPath]:
    """The source-message field paths a mapping reads, in order, without duplicates."""
    found: list[FieldPath] = []
    _walk(parsed(expression), (), found)
    return list(dict.fromkeys(found))


def _walk(node: dict[str, Any], context: FieldPath | None, found: list[FieldPath]) -> FieldPath | None:
    """Record the paths ``node`` reads when evaluated on the value at ``context`` (None:
    not the source message); return the path of the value it evaluates to, if known."""
    kind = node.get("type")
    children = node.get("children", [])
    if kind == "field":
        if context is None or node["value"] in _BARE_LITERALS:
            return None
        path = context + (node["value"],)
        found.append(path)
        return path
    if kind in ("current", "identity"):
        return context
    if kind == "subexpression":
        value = context
        for child in children:
            value = _walk(child, value, found)
        return value
    if kind == "index_expression":
        value = _walk(children[0], context, found)
        return None if value is None else value + (ELEMENT,)
    if kind == "flatten":
        return _walk(children[0], context, found)
    if kind in ("projection", "filter_projection"):
        value = _walk(children[0], context, found)
        element = None if value is None else value + (ELEMENT,)
        for child in children[1:]:
            _walk(child, element, found)
        return None
    if kind == "value_projection":
        _walk(children[0], context, found)
        _walk(children[1], None, found)
        return None
    if kind == "pipe":
        _walk(children[1], _walk(children[0], context, found), found)
        return None
    if kind == "key_val_pair":
        return _walk(children[0], context, found)
    if kind == "expref":
        _walk(children[0], None, found)
        return None
    for child in children:  # multi-selects, functions, comparisons, and/or/not
        _walk(child, context, found)
    return None


Written = dict[str, Any]
"""The keys a mapping's result is known to have: key -> what is known of its value (another
``Written``, or None); :data:`ELEMENT` -> what is known of each element of a list result."""


def mapping_writes(expression: str | None) -> Written | None:
    """The keys a mapping sets, read from its JMESPath tree: ``{a: x, b: {c: y}}`` (multi-select
    hashes), ``l[].{e: f}`` (projections), ``merge(@, {h: ...})``, ``a || {m: n}``, JSON
    literals and the right side of a pipe; None when nothing is known (a bare field, identity)."""
    return _writes(parsed(expression))


def _writes(node: dict[str, Any]) -> Written | None:
    kind = node.get("type")
    children = node.get("children", [])
    if kind == "multi_select_dict":
        return {child["value"]: _writes(child["children"][0]) for child in children}
    if kind == "literal":
        return _literal_writes(node.get("value"))
    if kind in ("projection", "filter_projection"):
        element = _writes(children[1])
        return None if element is None else {ELEMENT: element}
    if kind in ("pipe", "subexpression", "and_expression"):
        return _writes(children[-1])
    if kind == "or_expression" or (kind == "function_expression" and node.get("value") == "merge"):
        return _union([_writes(child) for child in children])
    return None


def _literal_writes(value: Any) -> Written | None:
    if isinstance(value, dict):
        return {str(key): _literal_writes(item) for key, item in value.items()}
    if isinstance(value, list):
        return _union([{ELEMENT: found} for found in map(_literal_writes, value) if found is not None])
    return None


def _union(shapes: list[Written | None]) -> Written | None:
    known = [shape for shape in shapes if shape is not None]
    if not known:
        return None
    out: Written = {}
    for shape in known:
        for key, value in shape.items():
            out[key] = _union([out.get(key), value])
    return out


def undeclared_keys(written: Written | None, declared: Any, label: str) -> Iterator[str]:
    """``mapping sets 'heding', which schema position does not declare; did you mean
    'heading'?`` for every key the mapping sets that the schema (``declared``, a
    :class:`engine.common.schemas.Declared`) does not name, nested keys included."""
    yield from _undeclared(written, declared, label, ())


def _undeclared(written: Written | None, declared: Any, label: str, path: FieldPath) -> Iterator[str]:
    if not written or declared.open and ELEMENT not in written:
        return
    for key, value in written.items():
        if key == ELEMENT:
            yield from _undeclared(value, declared.items(), label, path + (ELEMENT,))
        elif declared.open:
            continue
        elif key not in declared.keys:
            guess = closest(key, declared.keys)
            hint = f"; did you mean {_dotted(path + (guess,))!r}?" if guess else f" (it declares: {', '.join(declared.keys)})"
            yield f"mapping sets {_dotted(path + (key,))!r}, which schema {label!r} does not declare{hint}"
        else:
            yield from _undeclared(value, declared.child(key), label, path + (key,))


def mapping_field_problems(protocol: str, options: Any, mapping: str | None) -> Iterator[str]:
    """``mapping reads 'x', which T does not have; did you mean 'y'?`` for a typed source
    (``options``: its typed options, engine/common/options.py; its transport knows its fields)."""
    yield from _read_problems(_resolver(protocol, "field_problem", options), mapping)


def reply_field_problems(protocol: str, sink_options: Any, mapping: str | None) -> Iterator[str]:
    """The same for a route's ``reply.mapping``, whose input is the sink's answer: the sink's
    transport knows what a typed answer has (a service's response, an action's feedback and
    result: ``Transport.reply_field_problem``)."""
    yield from _read_problems(_resolver(protocol, "reply_field_problem", sink_options), mapping)


def _read_problems(resolve: FieldProblem | None, mapping: str | None) -> Iterator[str]:
    if resolve is None or not mapping:
        return
    for path in mapping_reads(mapping):
        problem = resolve(path)
        if problem is not None:
            yield problem


def _resolver(protocol: str, hook: str, options: Any) -> FieldProblem | None:
    """The transport's ``hook`` (``field_problem``, ``reply_field_problem``) for these options."""
    try:
        return getattr(endpoints.transport(protocol), hook)(options)
    except EndpointError:  # not installed: reported where the route's endpoints are checked
        return None


def _dotted(path: FieldPath) -> str:
    return ".".join(path).replace(f".{ELEMENT}", ELEMENT)


def option_hint(protocol: str, key: str | None, options: Any) -> str:
    """A did-you-mean for a misspelt name option (a type, a message) of an endpoint, from its transport."""
    value = getattr(options, key, None) if key else None
    if not isinstance(value, str) or key is None:
        return ""
    try:
        guess = endpoints.transport(protocol).suggest(key, value)
    except (EndpointError, ImportError):
        return ""
    return f"; did you mean {guess!r}?" if guess and guess != value else ""
