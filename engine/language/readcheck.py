"""``check`` reads every read of the canonical message: what the sink mapping (each sink's, on
a route with ``sinks:``, and its fallback's), each sink's ``when:``, the route's ``when:``, the
``dedupe`` key, a ``window``'s ``per`` and aggregates' arguments, ``remember``'s ``value``
mappings, the throttle's, ``remember``'s and ``latest_only``'s ``per`` and the sink's templates
(routing key, topic, MAVLink target) read, against what the route's canonical schema can hold
(with a ``window:``, what its sinks read against the fields the window emits).

Before, ``check`` warned about keys a mapping *sets* that the schema lacks, never about fields
a mapping *reads* that its input cannot have: a sink mapping ``{temperature: temperatur_c}``
passed ``check``, then every message was dead-lettered (``field temperature: null``), and the
VDA 5050 example read ``nodePosition.allowedDeviationXy`` (the standard: ``allowedDeviationXY``)
unnoticed. A read path is walked down the schema (:class:`engine.common.schemas.Declared`:
properties through ``$ref``, ``allOf``/``anyOf``/``oneOf``, list elements): a field the schema
does not declare where it allows no other keys (``additionalProperties: false``) is always
null, an error; where it allows others (most canonical schemas), a warning. Where the route's
mapping says exactly what it makes (``{a: x, b: y}``: those keys, whatever the schema), a read of
another key is always null too: an error. Both name the file and line and the field meant. The reads of typed inputs (a ROS 2 or MAVLink source's message,
a call's answer) are the transports' (engine/language/fieldcheck.py): errors, as a typed
message has no other fields.
"""

from __future__ import annotations

from typing import Any, Iterator

from engine import endpoints
from engine.common.schemas import SchemaRegistry
from engine.common.suggest import closest
from engine.endpoints.base import ELEMENT, FieldPath
from engine.language.fieldcheck import mapping_reads, mapping_writes, undeclared_keys
from engine.language.mapping import parsed
from engine.language.route_yaml import Document, Path_, Problem
from engine.language.stores import remember_entries
from engine.language.window_options import emitted_fields, window_expressions


def read_problem(path: FieldPath, declared: Any, label: str) -> tuple[str, bool] | None:
    """``('agent_idd', which schema 'position' does not declare; did you mean 'agent_id'?``,
    error)`` for a path the schema ``declared`` cannot hold, error true where it allows no
    other keys; None when it declares the path, or allows anything there."""
    for depth, step in enumerate(path):
        if step == ELEMENT:
            declared = declared.items()
            continue
        if step not in declared.keys:
            if declared.open:
                return None  # any key goes here: nothing known of this one
            guess = closest(step, declared.keys)
            hint = f"; did you mean {_dotted(path[:depth] + (guess,))!r}?" if guess else f" (it declares: {', '.join(declared.keys)})"
            if declared.closed:
                return f"{_dotted(path[:depth + 1])!r}, which schema {label!r} does not declare and allows no other key there (always null){hint}", True
            return f"{_dotted(path[:depth + 1])!r}, which schema {label!r} does not declare{hint}", False
        declared = declared.child(step)
    return None


def schema_checks(document: Document, where: Path_, route: Any, sink: Any, schemas: SchemaRegistry,
                  captured: tuple[str, ...] = (), sink_path: Path_ = ("sink",)) -> Iterator[tuple[Problem, bool]]:
    """``(problem, error)`` for each canonical field name the schema does not declare: keys the
    mapping sets (warnings: the schema validates what is set), and fields the sink mapping, the
    ``per`` keys and the sink's templates read (:func:`read_problem`). A sink template's
    ``{name}`` that the source captures (``captured``) is no field; where the schema declares a
    field of that name too, the captured value wins, which is said."""
    name, schema_name = route.name, route.schema
    declared = schemas.declared(schema_name) if schema_name else None
    if declared is None:
        return
    for message in undeclared_keys(mapping_writes(route.mapping), declared, schema_name):
        yield document.problem(where + ("mapping",), f"route {name!r}: {message}"), False
    reads: list[tuple[Path_, str, FieldPath]] = []
    emitted_reads: list[tuple[Path_, str, FieldPath]] = []
    """With a ``window:``, the sink mapping and templates read the window's message, not the canonical one."""
    window = getattr(route, "window", None)
    sink_reads = emitted_reads if window is not None else reads
    sink_body = route.sink or {}
    for key, what in (("mapping", "sink mapping"), ("when", "sink when")):
        if isinstance(sink_body.get(key), str):
            sink_reads += [(where + sink_path + (key,), what, path) for path in _leaves(mapping_reads(sink_body[key]))]
    canonical_reads: tuple[tuple[Path_, str, str | None], ...] = (
        (("when",), "when", route.when), (("dedupe", "key"), "dedupe key", route.dedupe.key if getattr(route, "dedupe", None) else None))
    for key_path, what, text in canonical_reads:
        if isinstance(text, str):  # they read the canonical message, a window's inputs
            reads += [(where + key_path, what, path) for path in _leaves(mapping_reads(text))]
    for window_key, text in window_expressions(window):
        reads += [(where + ("window",) + window_key, f"window {'.'.join(window_key)}", path)
                  for path in _leaves(mapping_reads(text))]
    for index, entry in enumerate(remember_entries(route.remember)):
        if isinstance(entry.value, str):
            reads += [(where + _remembered_at(route, index) + ("value",), "remember value", path)
                      for path in _leaves(mapping_reads(entry.value))]
    for key_path, what, per in _per_keys(route):
        reads.append((where + key_path, what, tuple(per.split("."))))
    if sink is not None:
        transport = endpoints.transport(sink.protocol)
        for key, field_path in transport.canonical_fields(sink.options):
            key_path = where + sink_path + (sink.protocol, key)
            if field_path not in captured:
                sink_reads.append((key_path, f"sink {key}", tuple(field_path.split("."))))
            elif read_problem(tuple(field_path.split(".")), declared, schema_name) is None and not declared.open:
                yield document.problem(key_path, (
                    f"route {name!r}: {{{field_path}}} in sink {key} is the value the source captures from each topic, not the "
                    f"canonical field {field_path!r} of {schema_name}: the captured value wins (rename the topic's variable "
                    "to read the field at send time)")), False
    produced = mapping_output(route.mapping)
    for key_path, what, path in reads:
        found = read_problem(path, declared, schema_name)
        if found is None and produced is not None:
            found = unproduced(path, produced)
        if found is not None:
            yield document.problem(key_path, f"route {name!r}: {what} reads {found[0]}"), found[1]
    if window is not None:
        shape: Shape = dict.fromkeys(emitted_fields(window))
        for key_path, what, path in emitted_reads:
            found = unproduced(path, shape, "the route's window")
            if found is not None:
                yield document.problem(key_path, f"route {name!r}: {what} reads {found[0]}"), True


Shape = dict[str, Any]
"""The keys a mapping's result has, exactly: key -> the shape of its value (None: unknown);
:data:`ELEMENT` -> the shape of each element of a list result."""


def mapping_output(expression: str | None) -> Shape | None:
    """The exact shape of what a mapping makes, where its JMESPath says it: a multi-select hash
    ``{a: x, b: {c: y}}`` has exactly those keys (null where ``x`` is missing), a projection
    ``l[].{e: f}`` a list of such, a JSON literal its own; None when not known exactly (a
    field, ``merge()``, ``||``, no mapping: the source's message as it came)."""
    return _exact(parsed(expression)) if expression else None


def _exact(node: dict[str, Any]) -> Shape | None:
    kind = node.get("type")
    children = node.get("children", [])
    if kind == "multi_select_dict":
        return {child["value"]: _exact(child["children"][0]) for child in children}
    if kind == "literal":
        return _literal_shape(node.get("value"))
    if kind in ("projection", "filter_projection"):
        element = _exact(children[1])
        return None if element is None else {ELEMENT: element}
    return None


def _literal_shape(value: Any) -> Shape | None:
    if isinstance(value, dict):
        return {str(key): _literal_shape(item) for key, item in value.items()}
    return None


def unproduced(path: FieldPath, shape: Shape, maker: str = "the route's mapping") -> tuple[str, bool] | None:
    """``('temp', which the route's mapping never sets (it sets: ...); did you mean ...?',
    True)`` for a read of a key the route's mapping does not make: always null, an error."""
    for depth, step in enumerate(path):
        if step not in shape:
            if step == ELEMENT:
                return None  # a list read of a value not known to be one: left to the schema
            keys = sorted(key for key in shape if key != ELEMENT)
            guess = closest(step, keys)
            hint = f"; did you mean {_dotted(path[:depth] + (guess,))!r}?" if guess else f" (it sets: {', '.join(keys)})"
            return f"{_dotted(path[:depth + 1])!r}, which {maker} never sets (always null){hint}", True
        shape = shape[step]
        if shape is None:
            return None
    return None


def _per_keys(route: Any) -> Iterator[tuple[Path_, str, str]]:
    """The canonical field paths that key a route's state: throttle, remember, latest_only."""
    if route.throttle is not None and route.throttle.per:
        yield ("throttle", "per"), "throttle per", route.throttle.per
    for index, entry in enumerate(remember_entries(route.remember)):
        if entry.per:
            yield _remembered_at(route, index) + ("per",), "remember per", entry.per
    latest_only = route.buffer.latest_only if route.buffer else None
    if latest_only is not None and latest_only.per:
        yield ("buffer", "latest_only", "per"), "buffer latest_only per", latest_only.per


def _remembered_at(route: Any, index: int) -> Path_:
    """Where a ``remember`` entry is written: the mapping itself, or an item of the list."""
    return ("remember", index) if isinstance(route.remember, tuple) else ("remember",)


def _leaves(paths: list[FieldPath]) -> list[FieldPath]:
    """The paths not continued by another (``a.b.c`` says all ``a``, ``a.b`` would): one
    problem per read, at the first step the schema lacks."""
    return [path for path in paths if not any(len(other) > len(path) and other[:len(path)] == path for other in paths)]


def _dotted(path: FieldPath) -> str:
    return ".".join(path).replace(f".{ELEMENT}", ELEMENT)
