"""Static checks of what a mapping reads from a typed source, before anything flows.

A typed source (a ROS 2 message type, a MAVLink message) has known fields, so a mapping that
reads ``longitud`` from a ``sensor_msgs/msg/NavSatFix`` can only ever produce null: ``check``
reports it with a did-you-mean instead of letting the schema reject every message in the
field. The mapping's JMESPath tree is walked for the field paths it reads from the source
message (through sub-expressions, indexes, projections and filters; what follows a pipe or
a function's result is not the source message and is left alone); each path is resolved
against the type: ROS 2 by rosidl introspection (nested and sequence-of-message fields),
MAVLink from pymavlink's generated message classes.

The other direction, for every route: the keys a mapping *sets* (:func:`mapping_writes`,
read from the same tree: multi-select hashes, projections, ``merge``) against the properties
its canonical schema declares (:class:`engine.schemas.Declared`); ``check`` warns about the
ones the schema does not name, since the schemas allow extra keys and a misspelt optional
field would otherwise pass every message unnoticed.

Also here: did-you-mean hints for a misspelt ROS 2 type or MAVLink message name.
"""

from __future__ import annotations

import re
import sys
from functools import lru_cache
from pathlib import Path
from typing import Any, Iterator

import jmespath
from jmespath import exceptions as jmespath_errors

from engine.suggest import closest

FieldPath = tuple[str, ...]
ELEMENT = "[]"
"""A path step into the elements of a list."""
_BARE_LITERALS = frozenset({"null", "true", "false"})
"""JMESPath reads bare ``null`` as a field that is never there, which gives null: the idiom
``x || null`` works, so it is not reported as a missing field."""


def mapping_reads(expression: str | None) -> list[FieldPath]:
    """The source-message field paths a mapping reads, in order, without duplicates."""
    if not expression:
        return []
    try:
        tree = jmespath.compile(expression).parsed
    except jmespath_errors.JMESPathError:
        return []
    found: list[FieldPath] = []
    _walk(tree, (), found)
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
    if not expression:
        return None
    try:
        tree = jmespath.compile(expression).parsed
    except jmespath_errors.JMESPathError:
        return None
    return _writes(tree)


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
    :class:`engine.schemas.Declared`) does not name, nested keys included."""
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


def undeclared_path(path: str, declared: Any, label: str) -> str | None:
    """``'agent_idd', which schema position does not declare; did you mean 'agent_id'?`` for
    a dotted canonical field path (a template placeholder, throttle's ``per``), or None."""
    steps = tuple(path.split("."))
    for depth, step in enumerate(steps):
        if declared.open:
            return None
        if step not in declared.keys:
            guess = closest(step, declared.keys)
            hint = f"; did you mean {_dotted(steps[:depth] + (guess,))!r}?" if guess else f" (it declares: {', '.join(declared.keys)})"
            return f"{_dotted(steps[:depth + 1])!r}, which schema {label!r} does not declare{hint}"
        declared = declared.child(step)
    return None


def mapping_field_problems(protocol: str, options: Any, mapping: str | None) -> Iterator[str]:
    """``mapping reads 'x', which T does not have; did you mean 'y'?`` for a typed source."""
    if not mapping:
        return
    resolve = _resolver(protocol, options)
    if resolve is None:
        return
    for path in mapping_reads(mapping):
        problem = resolve(path)
        if problem is not None:
            yield problem


def _resolver(protocol: str, options: Any) -> Any:
    """``options``: the source's typed options (engine/options.py)."""
    if protocol == "ros2":
        type_name = options.type
        try:
            from engine.endpoints import rosmsg

            cls = rosmsg.resolve_type(type_name)
        except Exception:  # not installed or misspelt: reported by the type check
            return None
        if rosmsg.type_name(cls) == "std_msgs/msg/String":
            return None  # a byte source: the mapping reads the JSON inside
        return lambda path: _resolve_ros(cls, path)
    if protocol == "mavlink" and not options.json_tunnel and options.message:
        fields = mavlink_fields(options.message)
        if fields is None:
            return None
        return lambda path: _resolve_flat(f"MAVLink {options.message}", fields, path)
    return None


def _dotted(path: FieldPath) -> str:
    return ".".join(path).replace(f".{ELEMENT}", ELEMENT)


def _resolve_ros(cls: type, path: FieldPath) -> str | None:
    from engine.endpoints import rosmsg

    current: type | None = cls
    in_list = False
    for depth, step in enumerate(path):
        if current is None:
            return None  # a primitive or an array of them: nothing more to check
        if step == ELEMENT:
            if not in_list:
                return None  # indexing a message: JMESPath gives null, not ours to judge
            in_list = False
            continue
        if in_list:
            return None
        fields = _ros_fields(current)
        if step not in fields:
            return (f"mapping reads {_dotted(path[:depth + 1])!r}, which {rosmsg.type_name(current)} does not have"
                    f"{_ros_hint(current, path, depth)}")
        current, in_list = fields[step]
    return None


NESTED_SEARCH_DEPTH = 3
"""How many message levels below a missing field ``check`` looks for it: Odometry's
``pose.pose.orientation`` is two below ``pose``; deeper guesses would be guesses."""


def _ros_hint(cls: type, path: FieldPath, depth: int) -> str:
    """Where the field ``path[depth]`` is: in a message nested below ``cls`` (a level left
    out: ``pose.orientation`` of a nav_msgs/Odometry is ``pose.pose.orientation``), else a
    field of ``cls`` spelt alike, else the list of its fields."""
    step, rest = path[depth], path[depth + 1:]
    found = _nested_paths(cls, step, rest)
    if found:
        shown = [_dotted(path[:depth] + prefix + (step,)) for prefix in found[:3]]
        return f"; did you mean {shown[0]!r}?" if len(shown) == 1 else f"; did you mean one of {', '.join(map(repr, shown))}?"
    fields = _ros_fields(cls)
    guess = closest(step, fields)
    return f"; did you mean {_dotted(path[:depth] + (guess,))!r}?" if guess else f" (fields: {', '.join(fields)})"


def _nested_paths(cls: type, step: str, rest: FieldPath) -> list[FieldPath]:
    """The shortest field paths ``p`` below ``cls`` (through nested messages, not sequences)
    such that ``p + (step,) + rest`` is a path of ``cls``."""
    level: list[tuple[FieldPath, type]] = [((), cls)]
    for _ in range(NESTED_SEARCH_DEPTH):
        level = [(prefix + (name,), nested) for prefix, message in level
                 for name, (nested, in_list) in _ros_fields(message).items() if nested is not None and not in_list]
        found = [prefix for prefix, message in level if step in _ros_fields(message)
                 and _resolve_ros(message, (step,) + rest) is None]
        if found:
            return found
    return []


@lru_cache(maxsize=None)
def _ros_fields(cls: type) -> dict[str, tuple[type | None, bool]]:
    """field -> (message class of the field or of its elements, is a sequence of messages)."""
    from rosidl_parser import definition as idl

    from engine.endpoints import rosmsg

    out: dict[str, tuple[type | None, bool]] = {}
    for name, slot in zip(cls.get_fields_and_field_types(), cls.SLOT_TYPES):
        if isinstance(slot, idl.NamespacedType):
            out[name] = (rosmsg.resolve_type(f"{slot.namespaces[0]}/{slot.name}"), False)
        elif isinstance(slot, idl.AbstractNestedType) and isinstance(slot.value_type, idl.NamespacedType):
            value = slot.value_type
            out[name] = (rosmsg.resolve_type(f"{value.namespaces[0]}/{value.name}"), True)
        else:
            out[name] = (None, False)
    return out


def _resolve_flat(label: str, fields: tuple[str, ...], path: FieldPath) -> str | None:
    if not path or path[0] == ELEMENT or path[0] in fields:
        return None
    guess = closest(path[0], fields)
    hint = f"; did you mean {guess!r}?" if guess else f" (fields: {', '.join(fields)})"
    return f"mapping reads {path[0]!r}, which {label} does not have{hint}"


# ---------------------------------------------------------------- MAVLink and ROS 2 names
# MAVLink knowledge is read from pymavlink's tables, plus the fields the MAVLink source adds.

@lru_cache(maxsize=1)
def _mavlink_messages() -> dict[str, tuple[str, ...]]:
    from pymavlink.dialects.v20 import common

    from engine.endpoints.mavlink.codec import ADDED_FIELDS

    return {cls.msgname: tuple(cls.fieldnames) + ADDED_FIELDS.get(cls.msgname, ()) for cls in common.mavlink_map.values()}


def mavlink_fields(message: str) -> tuple[str, ...] | None:
    try:
        return _mavlink_messages().get(message)
    except ImportError:
        return None


@lru_cache(maxsize=1)
def installed_ros_types() -> tuple[str, ...]:
    """``pkg/msg/Type`` of every installed message package, read from the generated
    ``msg/__init__.py`` files without importing them (only used to suggest a name)."""
    names: set[str] = set()
    pattern = re.compile(r"^from \S+ import (\w+)", re.M)
    for entry in sys.path:
        base = Path(entry or ".")
        if not base.is_dir():
            continue
        for init in base.glob("*/msg/__init__.py"):
            try:
                text = init.read_text(encoding="utf-8", errors="replace")
            except OSError:
                continue
            names.update(f"{init.parent.parent.name}/msg/{cls}" for cls in pattern.findall(text))
    return tuple(sorted(names))


def option_hint(protocol: str, key: str | None, options: Any) -> str:
    """A did-you-mean for a misspelt ``type`` (ROS 2) or ``message`` (MAVLink) option."""
    value = getattr(options, key, None) if key else None
    if not isinstance(value, str):
        return ""
    if protocol == "ros2" and key == "type":
        full = re.sub(r"^([a-z][a-z0-9_]*)/(?!msg/)", r"\1/msg/", value.strip())
        guess = closest(full, installed_ros_types())
    elif protocol == "mavlink" and key == "message":
        try:
            guess = closest(value, _mavlink_messages())
        except ImportError:
            return ""
    else:
        return ""
    return f"; did you mean {guess!r}?" if guess and guess != value else ""
