"""Route and test files read from YAML: line numbers, ``${VAR}``, validation against a schema.

One file becomes a :class:`Document`: the data as Python values, the line of every key (so
each later problem is ``file:line: message``), and the key paths the file's JSON Schema
rejected. A document the schema rejects is still returned when the caller asks
(``keep_invalid``): the route loader goes on checking the rest of it (mapping fields,
connections, schemas), so ``check`` shows every problem of a file in one run, and drops its
own option errors where the schema already reported the key (:meth:`Document.reported`).

``${VAR}`` and ``${VAR:-default}`` are replaced by the variable's text (``$$`` is ``$``); the
result then takes the type the key expects (:func:`_fit_substitutions`): a number or boolean
where the schema wants one, read as YAML reads an unquoted value (``"${ROS_DOMAIN_ID:-0}"``
is the integer 0), the text where it wants a string (``node: ${NAME}`` with ``NAME=42`` is
``"42"``). Where any value goes (a free mapping), an unquoted ``${VAR}`` takes the YAML type of
its value and a quoted one stays a string. Inside a flow mapping or list (``{...}``, ``[...]``)
YAML itself reads ``{`` as the start of a mapping, so an unquoted ``${VAR}`` there is invalid
YAML; the error says to quote it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

import jsonschema
import yaml

from engine.common.options import dotted, unknown_key
from engine.common.redaction import MASK, Secret, has_url_password, is_secret_name, redact_urls, shown
from engine.common.suggest import did_you_mean
from engine.language.yaml_bounds import bound_problem

Path_ = tuple[str | int, ...]
_ENV_REFERENCE = re.compile(r"\$\$|\$\{([A-Za-z_][A-Za-z0-9_]*)(?::-([^}]*))?\}|\$\{file:([^}]+)\}")


class SecretFileError(Exception):
    """A ``${file:...}`` secret that cannot be read; the message names the file, never content."""


@dataclass(frozen=True, order=True)
class Problem:
    file: str
    line: int
    message: str

    def __str__(self) -> str:
        return f"{self.file}:{self.line}: {self.message}"


@dataclass
class Document:
    file: str
    data: dict[str, Any]
    lines: dict[Path_, int]
    schema_paths: frozenset[Path_] = field(default=frozenset())
    """Key paths the file's schema rejected (each already reported as a problem)."""
    expansions: dict[int, Any] = field(default_factory=dict)
    """What the ``expand`` step of :func:`parse_document` made, by item (route templates:
    engine/language/templates.py's ``Expansion`` of each expanded route, by its index)."""

    def line(self, path: Path_) -> int:
        while path not in self.lines and path:
            path = path[:-1]
        return self.lines.get(path, 1)

    def problem(self, path: Path_, message: str) -> Problem:
        return Problem(self.file, self.line(path), message)

    def reported(self, path: Path_) -> bool:
        """Whether the schema rejected ``path``, a key inside it, or a key it is inside: the
        option parser checks the same declarations, so its problem there is a repeat."""
        return any(path[:len(known)] == known or known[:len(path)] == path for known in self.schema_paths)


_Loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
"""libyaml's parser where PyYAML was built with it (the wheels are): the same nodes and line
marks, parsed several times faster (1,000 routes: check 0.85 s -> 0.27 s here)."""


def parse_document(
    file: str, text: str, env: Mapping[str, str], problems: list[Problem],
    validator: jsonschema.protocols.Validator, keep_invalid: bool = False,
    expand: Callable[[Any, dict[Path_, int], dict[Path_, str], list[Problem]], dict[int, Any]] | None = None,
) -> Document | None:
    """``text`` as a :class:`Document`, its problems appended to ``problems``; None when it is
    not YAML, or when the schema rejects it and ``keep_invalid`` is false. ``expand`` rewrites
    the data as read, before it is validated (route templates), moving key lines with it.
    A file past the bounds of engine/language/yaml_bounds.py (size, nodes, alias copies,
    depth) is refused before it is composed."""
    bound = bound_problem(text)
    if bound is not None:
        problems.append(Problem(file, *bound))
        return None
    loader = _Loader(text)
    try:
        root = loader.get_single_node()
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark else 1
        problems.append(Problem(file, line, f"invalid YAML: {exc.problem or exc.context}{_flow_hint(text, exc)}"))
        return None
    except yaml.YAMLError as exc:
        problems.append(Problem(file, 1, f"invalid YAML: {exc}"))
        return None
    finally:
        loader.dispose()
    if root is None:
        return Document(file, {}, {})
    reader = _Reader(loader, env, file, problems)
    data = reader.value(root, ())  # no recursion past MAX_DEPTH, no recursive alias: bound_problem refused those
    data = data if data is not None else {}
    expansions = expand(data, reader.lines, reader.substituted, problems) if expand is not None else {}
    errors = list(validator.iter_errors(shown(data)))
    if errors and _fit_substitutions(data, reader.substituted, validator, errors):
        errors = list(validator.iter_errors(shown(data)))
    document = Document(file, data, reader.lines, expansions=expansions)
    rejected = [found for error in errors for found in _schema_problems(error)]
    problems.extend(document.problem(path, message) for path, message in rejected)
    if not rejected:
        return document
    if not keep_invalid or not isinstance(data, dict):
        return None
    document.schema_paths = frozenset(path for path, _ in rejected)
    return document


class _Reader:
    """Builds a node's Python value, recording each key's line and each ``${VAR}`` substituted."""

    def __init__(self, loader: Any, env: Mapping[str, str], file: str, problems: list[Problem]) -> None:
        self.loader = loader
        self.env = env
        self.file = file
        self.problems = problems
        self.lines: dict[Path_, int] = {}
        self.substituted: dict[Path_, str] = {}
        """Key path -> the substituted text of a value that held ``${VAR}`` (secrets excluded)."""

    def value(self, node: yaml.Node, path: Path_) -> Any:
        self.lines.setdefault(path, node.start_mark.line + 1)
        if isinstance(node, yaml.MappingNode):
            out: dict[str, Any] = {}
            for key_node, value_node in node.value:
                key = self.loader.construct_object(key_node)
                if not isinstance(key, str):
                    self.problems.append(Problem(self.file, key_node.start_mark.line + 1, f"key {key!r} must be a string"))
                    continue
                if key in out:
                    self.problems.append(Problem(self.file, key_node.start_mark.line + 1, f"duplicate key {key!r}"))
                    continue
                self.lines[path + (key,)] = key_node.start_mark.line + 1
                out[key] = self.value(value_node, path + (key,))
            return out
        if isinstance(node, yaml.SequenceNode):
            return [self.value(item, path + (index,)) for index, item in enumerate(node.value)]
        value = self.loader.construct_object(node)
        if isinstance(value, str) and "$" in value:
            return self._substituted(value, node, path)
        if isinstance(value, str) and has_url_password(value):
            return Secret(value)
        return value

    def _substituted(self, value: str, node: yaml.Node, path: Path_) -> Any:
        try:
            substituted, masked = _substitute_masked(value, self.env)
        except KeyError as exc:
            name = exc.args[0]
            self.problems.append(Problem(self.file, node.start_mark.line + 1,
                                         f"environment variable {name} is not set (use ${{{name}:-default}} for a default)"))
            return value
        except SecretFileError as exc:
            self.problems.append(Problem(self.file, node.start_mark.line + 1, str(exc)))
            return Secret(value, MASK)
        if masked != substituted or has_url_password(substituted):
            return Secret(substituted, redact_urls(masked) if MASK in masked or has_url_password(masked) else MASK)
        if substituted != value:
            self.substituted[path] = substituted
        return _yaml_scalar(substituted) if not node.style else substituted  # plain: None (Python) or "" (libyaml)


def _yaml_scalar(text: str) -> Any:
    """``text`` as YAML reads an unquoted value, when that is a number or a boolean; else the text."""
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        return text
    return value if isinstance(value, (int, float, bool)) else text


def _fit_substitutions(
    data: Any, substituted: Mapping[Path_, str], validator: jsonschema.protocols.Validator,
    errors: list[jsonschema.ValidationError],
) -> bool:
    """Give each substituted value the schema rejected the type its key expects: its other
    reading (the text, or the text read as a YAML number/boolean) replaces it if the schema
    accepts that there. Guided by the schema's errors, so a file the schema accepts costs
    nothing more, and a value the schema accepts is never changed. True if one changed."""
    changed = False
    for _ in range(len(substituted)):
        fitted = False
        for error in errors:
            for leaf in _with_context(error):
                path = tuple(leaf.absolute_path)
                if path not in substituted:
                    continue
                current = _at(data, path)
                other = _yaml_scalar(substituted[path]) if isinstance(current, str) else substituted[path]
                if type(other) is not type(current) and validator.evolve(schema=leaf.schema).is_valid(other):
                    _put(data, path, other)
                    fitted = True
                    break
        if not fitted:
            return changed
        changed = True
        errors = list(validator.iter_errors(shown(data)))
    return changed


def _with_context(error: jsonschema.ValidationError) -> Iterator[jsonschema.ValidationError]:
    yield error
    for child in error.context or ():
        yield from _with_context(child)


def _at(data: Any, path: Path_) -> Any:
    for key in path:
        data = data[key]
    return data


def _put(data: Any, path: Path_, value: Any) -> None:
    _at(data, path[:-1])[path[-1]] = value


def _flow_hint(text: str, exc: yaml.MarkedYAMLError) -> str:
    """What to do when an unquoted ``${VAR}`` sits inside ``{...}`` or ``[...]``: YAML reads its
    ``{`` as a nested mapping, so the parser stops right there (libyaml and PyYAML alike)."""
    mark = exc.problem_mark
    if mark is None:
        return ""
    lines = text.splitlines()
    line = lines[mark.line] if mark.line < len(lines) else ""
    if not line[mark.column - 1:mark.column + 1] == "${":
        return ""
    start = mark.column - 1
    while start > 0 and line[start - 1] not in " \t,[{":
        start -= 1
    end = line.find("}", mark.column)
    value = line[start:end + 1] if end >= 0 else line[start:]
    where = "flow mapping ({...})" if "mapping" in str(exc.context) else "flow list ([...])"
    return (f"; inside a {where} an unquoted ${{VAR}} is read as a nested mapping: quote the value, "
            f"\"{value}\" (a quoted ${{VAR}} still becomes a number or boolean where the key expects one)")


def substitute_env(text: str, env: Mapping[str, str]) -> str:
    """``${VAR}`` and ``${VAR:-default}``; ``$$`` is a literal ``$``. Unset without default raises."""
    return _substitute_masked(text, env)[0]


def read_secret_file(path: str) -> str:
    """The content of a ``${file:/run/credentials/amqp-password}`` secret (a systemd
    credential, a Docker or Kubernetes secret), one trailing newline stripped, as ``echo`` and
    most editors leave one. Always a secret: shown as ``***`` wherever it is printed."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else "not UTF-8 text"
        raise SecretFileError(f"secret file {path}: cannot read it ({reason})") from None
    return text[:-2] if text.endswith("\r\n") else text.removesuffix("\n")


def _substitute_masked(text: str, env: Mapping[str, str]) -> tuple[str, str]:
    """The substituted text, and the same with every secret-named variable's value as ``***``
    (see engine/common/redaction.py for the rule)."""

    def value(match: re.Match[str]) -> str:
        if match.group(0) == "$$":
            return "$"
        if match.group(3):
            return read_secret_file(match.group(3))
        name, default = match.group(1), match.group(2)
        if name in env:
            return env[name]
        if default is not None:
            return default
        raise KeyError(name)

    def masked(match: re.Match[str]) -> str:
        found = value(match)
        secret = match.group(3) or (match.group(1) and is_secret_name(match.group(1)))
        return MASK if secret and found else found

    return _ENV_REFERENCE.sub(value, text), _ENV_REFERENCE.sub(masked, text)


def _schema_problems(error: jsonschema.ValidationError) -> Iterator[tuple[Path_, str]]:
    """``(key path, message)`` of one schema error, in the option parser's words."""
    path = tuple(error.absolute_path)
    if error.validator == "additionalProperties" and isinstance(error.instance, dict):
        allowed = sorted(error.schema.get("properties", {}))
        for key in error.instance:
            if key not in allowed:
                yield path + (key,), unknown_key(key, path, allowed)
        return
    if error.context:
        # of a value several types are allowed for (ordered: true or {partitions: N}), what is
        # wrong within the alternative of its own type, not that it is not the other type
        within = [child for child in error.context if child.validator != "type"]
        error = jsonschema.exceptions.best_match(within or error.context)
        path = tuple(error.absolute_path)
    hint = ""
    if error.validator == "enum" and isinstance(error.instance, str):
        hint = did_you_mean(error.instance, [str(choice) for choice in error.validator_value])
    yield path, f"{dotted(path)}: {error.message}{hint}"
