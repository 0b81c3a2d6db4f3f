"""``{name}`` placeholders: the one grammar of templates that name fields of a message.

AMQP routing keys, MQTT topics, ROS 2 topics and ``format()`` in mappings all render
``canonical.weeds.{agent_id}`` the same way, so the grammar is parsed here, below both the
protocol packages (engine/endpoints/) and the route language (engine/language/mapping.py),
which import it.
"""

from __future__ import annotations

import re
from typing import Any, Callable


class MappingError(ValueError):
    """A mapping expression does not compile, or failed on a message."""


class TemplateError(MappingError):
    """A template that is not literal text and ``{field.path}`` placeholders."""


_FIELD_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
# Python's format-spec mini-language without nested fields: [[fill]align][sign][z][#][0][width][,_][.precision][type]
_FORMAT_SPEC = re.compile(r"(?:[^{}]?[<>=^])?[-+ ]?z?#?0?\d*[,_]?(?:\.\d+)?[bcdeEfFgGnosxX%]?\Z")
Template = tuple[list[str], list[tuple[tuple[str, ...], str]]]


def parse_template(template: str) -> Template:
    """Split ``canonical.weeds.{agent_id}`` into literals and ``(field path, format spec)``.

    The whole grammar, shared by ``format()``, AMQP routing keys and ROS 2 topics: literal
    text, ``{{``/``}}`` for a brace, and ``{name}`` or ``{name.name...}`` naming a field
    path into the canonical message, optionally ``{name:spec}`` with a plain format spec
    (``{lat:.6f}``, ``{n:04d}``) applied only to numbers and strings. A field name is an
    identifier that is not a ``__dunder__``; indexing, conversions (``!r``), nested fields
    and attribute access do not exist, so a template taken from a message can only read
    that message's fields.
    """
    literals: list[str] = []
    fields: list[tuple[tuple[str, ...], str]] = []
    text: list[str] = []
    index, length = 0, len(template)
    while index < length:
        char = template[index]
        if char in "{}" and template[index + 1:index + 2] == char:
            text.append(char)
            index += 2
        elif char == "}":
            raise TemplateError(f"template {template!r}: single '}}' at {index} (write '}}}}' for a brace)")
        elif char == "{":
            close = template.find("}", index)
            if close < 0:
                raise TemplateError(f"template {template!r}: '{{' at {index} is never closed")
            fields.append(_placeholder(template, template[index + 1:close]))
            literals.append("".join(text))
            text = []
            index = close + 1
        else:
            text.append(char)
            index += 1
    literals.append("".join(text))
    return literals, fields


def _placeholder(template: str, body: str) -> tuple[tuple[str, ...], str]:
    name, _, spec = body.partition(":")
    path = tuple(name.split("."))
    for part in path:
        if not _FIELD_NAME.match(part) or (part.startswith("__") and part.endswith("__")):
            raise TemplateError(f"template {template!r}: {{{body}}} is not a field path "
                                "(names and dots only: {agent_id}, {pose.frame})")
    if "{" in body or not _FORMAT_SPEC.match(spec):
        raise TemplateError(f"template {template!r}: {{{body}}}: {spec!r} is not a plain format spec")
    return path, spec


def template_problem(template: str) -> str | None:
    """Why ``template`` is refused, for ``check``; None when it is fine."""
    try:
        parse_template(template)
    except TemplateError as exc:
        return str(exc)
    return None


def compile_template(template: str) -> Callable[[Any], str]:
    """Compile ``canonical.weeds.{agent_id}`` into a function of the canonical message.

    Raises :class:`TemplateError` for anything :func:`parse_template` refuses. Templates
    without placeholders return the constant string, so the common case costs nothing per
    message.
    """
    literals, fields = parse_template(template)
    if not fields:
        constant = literals[0]
        return lambda _data: constant

    def render(data: Any) -> str:
        out = [literals[0]]
        for (path, spec), literal in zip(fields, literals[1:]):
            value = data
            for key in path:
                if not isinstance(value, dict) or key not in value:
                    raise MappingError(f"template {template!r}: field {'.'.join(path)!r} is missing")
                value = value[key]
            out.append(_render_value(template, value, spec))
            out.append(literal)
        return "".join(out)

    return render


def _render_value(template: str, value: Any, spec: str) -> str:
    if not spec:
        return str(value)
    if type(value) not in (int, float, str):
        raise MappingError(f"template {template!r}: format spec {spec!r} applies to numbers and strings, not {value!r}")
    try:
        return format(value, spec)
    except ValueError as exc:
        raise MappingError(f"template {template!r}: {exc}") from None


def template_fields(template: str) -> list[str]:
    """Dotted field paths a template reads; [] for a template :func:`parse_template` refuses
    (``check`` reports that separately)."""
    try:
        return [".".join(path) for path, _spec in parse_template(template)[1]]
    except TemplateError:
        return []
