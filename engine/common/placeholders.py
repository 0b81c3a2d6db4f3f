"""``{name}`` placeholders: the one grammar of every template that names a value.

AMQP routing keys, the topics of every protocol (MQTT, ROS 2, sinks and sources), ``format()``
in mappings, ``for_each`` variables (engine/language/templates.py) and the captures of a source
topic (``farm/{station}/weather``, ROS 2 discovery's ``/{agent}/fix``) are all read by
:func:`parse_template` (or, for ``for_each`` over free text, :func:`scan_placeholders`, the same
tokenizer that skips what is no placeholder), so ``check`` and the run read each ``{...}`` the
same way. The module sits below both the protocol packages (engine/endpoints/) and the route
language (engine/language/), which import it.

Format specs (``{id:03d}``). Where a template *renders* (a sink's topic or routing key,
``format()``, a ``for_each`` value written into text) a spec is honoured as ``str.format``
would (``{id:03d}`` renders 7 as ``007``): robot fleets number their topics ``/robot_007``,
the spec is already part of ``format()``, and refusing it where a field is rendered would make
one grammar two. Where a template *matches* (a source topic's capture) a spec is refused by
``check``: the inverse of a spec is not one value (``{id:03d}`` would have to match ``007``
and ``1234`` but not ``7``, and give ``meta('id')`` as the text ``007`` or the number 7), and a
capture that guessed would subscribe to what the operator did not mean. A capture takes one
whole level as text (:func:`capture_levels`); a mapping formats it if it must.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, Callable, Collection, Iterator


class MappingError(ValueError):
    """A mapping expression does not compile, or failed on a message."""


class TemplateError(MappingError):
    """A template that is not literal text and ``{field.path}`` placeholders."""


_FIELD_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
# Python's format-spec mini-language without nested fields: [[fill]align][sign][z][#][0][width][,_][.precision][type]
_FORMAT_SPEC = re.compile(r"(?:[^{}]?[<>=^])?[-+ ]?z?#?0?\d*[,_]?(?:\.\d+)?[bcdeEfFgGnosxX%]?\Z")


@dataclass(frozen=True)
class Placeholder:
    """One ``{path:spec}`` of a template, where it stands in the template's text."""

    path: tuple[str, ...]
    spec: str
    start: int
    end: int
    """``template[start:end]`` is the placeholder as written, braces included."""

    @property
    def name(self) -> str:
        """The dotted path (``pose.frame``)."""
        return ".".join(self.path)

    def render(self, template: str, value: Any) -> str:
        """``value`` as this placeholder writes it: ``str(value)``, or formatted by the spec
        (numbers and strings only: a spec on a dict would print Python's repr)."""
        if not self.spec:
            return str(value)
        if type(value) not in (int, float, str):
            raise MappingError(f"template {template!r}: format spec {self.spec!r} applies to numbers and strings, not {value!r}")
        try:
            return format(value, self.spec)
        except ValueError as exc:
            raise MappingError(f"template {template!r}: {{{self.name}:{self.spec}}}: {exc}") from None


@dataclass(frozen=True)
class ParsedTemplate:
    """Literal text around placeholders: ``literals[i]``, ``placeholders[i]``, ..., ``literals[-1]``."""

    text: str
    literals: list[str]
    placeholders: list[Placeholder]


def parse_template(template: str, keep: Collection[str] = ()) -> ParsedTemplate:
    """Split ``canonical.weeds.{agent_id}`` into literals and placeholders.

    The whole grammar: literal text, ``{{``/``}}`` for a brace, and ``{name}`` or
    ``{name.name...}`` naming a field path, optionally ``{name:spec}`` with a plain format spec
    (``{lat:.6f}``, ``{n:04d}``; see the module for where a spec applies). A field name is an
    identifier that is not a ``__dunder__``; indexing, conversions (``!r``), nested fields and
    attribute access do not exist, so a template taken from a message can only read that
    message's fields. ``keep``: names left in the text as written, for a library that fills them
    itself (rcl's ``{node}`` in a ROS 2 topic).
    """
    literals: list[str] = []
    placeholders: list[Placeholder] = []
    text: list[str] = []
    for token in _tokens(template, strict=True):
        if isinstance(token, str):
            text.append(token)
        elif token.name in keep and not token.spec:
            text.append(template[token.start:token.end])
        else:
            placeholders.append(token)
            literals.append("".join(text))
            text = []
    literals.append("".join(text))
    return ParsedTemplate(template, literals, placeholders)


def scan_placeholders(text: str) -> list[Placeholder]:
    """The well-formed placeholders of any text, skipping what is none (``{"a": 1}``, a lone
    brace): for ``for_each``, whose variables may sit in any string of a route, JSON included.
    The same tokenizer as :func:`parse_template`, which refuses instead of skipping."""
    return [token for token in _tokens(text, strict=False) if isinstance(token, Placeholder)]


def _tokens(template: str, strict: bool) -> Iterator[str | Placeholder]:
    index, length = 0, len(template)
    while index < length:
        char = template[index]
        if char in "{}" and template[index + 1:index + 2] == char:
            yield char
            index += 2
        elif char == "}":
            if strict:
                raise TemplateError(f"template {template!r}: single '}}' at {index} (write '}}}}' for a brace)")
            yield char
            index += 1
        elif char == "{":
            close = template.find("}", index)
            if close < 0:
                if strict:
                    raise TemplateError(f"template {template!r}: '{{' at {index} is never closed (write '{{{{' for a brace)")
                yield template[index:]
                return
            try:
                yield _placeholder(template, index, close + 1)
            except TemplateError:
                if strict:
                    raise
                yield char
                index += 1
                continue
            index = close + 1
        else:
            yield char
            index += 1


def _placeholder(template: str, start: int, end: int) -> Placeholder:
    body = template[start + 1:end - 1]
    name, _, spec = body.partition(":")
    path = tuple(name.split("."))
    for part in path:
        if not _FIELD_NAME.match(part) or (part.startswith("__") and part.endswith("__")):
            raise TemplateError(f"template {template!r}: {{{body}}} is not a field path "
                                "(names and dots only: {agent_id}, {pose.frame})")
    if "{" in body or not _FORMAT_SPEC.match(spec):
        raise TemplateError(f"template {template!r}: {{{body}}}: {spec!r} is not a plain format spec")
    return Placeholder(path, spec, start, end)


def template_problem(template: str, keep: Collection[str] = ()) -> str | None:
    """Why ``template`` is refused, for ``check``; None when it is fine."""
    try:
        parse_template(template, keep)
    except TemplateError as exc:
        return str(exc)
    return None


def compile_template(template: str, keep: Collection[str] = (),
                     kinds: tuple[type, ...] | None = None) -> Callable[[Any], str]:
    """Compile ``canonical.weeds.{agent_id}`` into a function of the canonical message.

    Raises :class:`TemplateError` for anything :func:`parse_template` refuses; the function
    raises :class:`MappingError` naming the field when a message lacks it, or (``kinds``) when
    its value is of another type (a ROS 2 topic takes strings and integers: a float's dot or a
    dict's braces are no name). Templates without placeholders return the constant string, so
    the common case costs nothing per message.
    """
    parsed = parse_template(template, keep)
    literals, fields = parsed.literals, parsed.placeholders
    if not fields:
        constant = literals[0]
        return lambda _data: constant

    def render(data: Any) -> str:
        out = [literals[0]]
        for field, literal in zip(fields, literals[1:]):
            value = data
            for key in field.path:
                if not isinstance(value, dict) or key not in value:
                    raise MappingError(f"template {template!r}: field {field.name!r} is missing")
                value = value[key]
            if kinds is not None and (type(value) not in kinds):
                raise MappingError(f"template {template!r}: field {field.name!r} is {value!r}, not "
                                   f"{' or '.join(kind.__name__ for kind in kinds)}")
            out.append(field.render(template, value))
            out.append(literal)
        return "".join(out)

    return render


def template_fields(template: str, keep: Collection[str] = ()) -> list[str]:
    """Dotted field paths a template reads; [] for a template :func:`parse_template` refuses
    (``check`` reports that separately)."""
    try:
        return [field.name for field in parse_template(template, keep).placeholders]
    except TemplateError:
        return []


def capture_levels(pattern: str, separator: str = "/", keep: Collection[str] = (), level: str = "level",
                   example: str = "farm/{name}/weather") -> list[str | Placeholder]:
    """A source topic's levels, each literal text or a capture (``farm/{station}/weather``:
    ``["farm", {station}, "weather"]``), for the protocols whose sources follow many topics.

    Raises :class:`TemplateError` for a brace a capture cannot honour: a placeholder that is
    not a whole level (``robot{n}``: a level is the unit a wildcard matches), one with a format
    spec (no single inverse: see the module), or a dotted path (a capture names one
    ``meta()`` key, not a field of a message). ``level`` and ``example`` word the refusal in the
    protocol's terms (a ROS 2 topic's "name segment", ``/{name}/fix``).
    """
    parsed = parse_template(pattern, keep)
    levels: list[list[str | Placeholder]] = [[]]
    for index, literal in enumerate(parsed.literals):
        first, *others = literal.split(separator)
        levels[-1].append(first)
        levels.extend([other] for other in others)
        if index < len(parsed.placeholders):
            levels[-1].append(parsed.placeholders[index])
    out: list[str | Placeholder] = []
    for parts in levels:
        fields = [part for part in parts if isinstance(part, Placeholder)]
        if not fields:
            out.append("".join(str(part) for part in parts))
            continue
        field = fields[0]
        written = pattern[field.start:field.end]
        if len(fields) > 1 or any(part for part in parts if isinstance(part, str)):
            raise TemplateError(f"topic {pattern!r}: {written} must be a whole {level}, as in "
                                f"{example.replace('{name}', written)} (a capture matches exactly one {level})")
        if field.spec:
            raise TemplateError(f"topic {pattern!r}: {written} has a format spec, which a source cannot match: a capture "
                                f"takes one whole {level} as it is (write {{{field.name}}}, and format it where it is written)")
        if len(field.path) > 1:
            raise TemplateError(f"topic {pattern!r}: {written}: a capture names one meta() key, not a field path "
                                "(one name, as in {station})")
        out.append(field)
    return out


def whole_field(text: str, what: str = "value") -> tuple[str, ...]:
    """The field path of a value that is exactly one placeholder (``"{vehicle}"``,
    ``"{target.system}"``): a MAVLink sink's target, read from each message as it is.

    Raises :class:`TemplateError` for anything else: text around the placeholder, or a format
    spec (a spec makes text, and a target is the number or agent's name the field holds).
    """
    parsed = parse_template(text)
    if len(parsed.placeholders) != 1 or any(parsed.literals):
        raise TemplateError(f"{text!r}: a {what} read from the message is one whole {{field}}, as \"{{vehicle}}\"")
    field = parsed.placeholders[0]
    if field.spec:
        raise TemplateError(f"{text!r}: a format spec makes text, and a {what} is the id or agent's name the field holds "
                            f"as it is (write \"{{{field.name}}}\")")
    return field.path
