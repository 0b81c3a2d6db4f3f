"""Route templates: one route written once, expanded into one route per item of ``for_each``.

A route with ``for_each:`` (a list of objects, or the name of a YAML file holding one, beside
the route file) becomes one ordinary route per item: every ``{var}`` naming a key of the item,
in the route's name and in any string value below it, takes the item's value. A value that is
exactly ``{var}`` takes the value as it is (``system_id: "{sysid}"`` is the integer 3); inside
a longer text the value is written in (``/{agent}/fix``), through a format spec if it has one
(``/robot_{id:03d}`` with id 7 is ``/robot_007``, as a sink would render it: the braces are read
by the engine's one template grammar, engine/common/placeholders.py). A ``{name}`` that is no
variable of the item stays as it is, for the sink to fill from the canonical message at send
time.
Mappings (``mapping``, ``sink.mapping``) are JMESPath, where braces are syntax: they read the
item with ``meta('var')`` instead, a constant folded at compile time (engine/language/mapping.py).

Expansion happens on the document as read, before it is validated, so each expanded route is
checked, compiled, fingerprinted, tested and reloaded as if written by hand; its problems name
the template's line (and the route by its expanded name). A file in the routes directory
whose top level is a list is a ``for_each`` file, never a route file (:func:`is_items_text`).
"""

from __future__ import annotations

import copy
import re
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

from engine.common.placeholders import MappingError, scan_placeholders
from engine.common.suggest import did_you_mean
from engine.language.agents import AGENTS
from engine.language.route_yaml import Path_, Problem

FOR_EACH = "for_each"
_VARIABLE_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_JMESPATH_KEYS = frozenset({"mapping"})
"""Keys whose values are JMESPath, never substituted (they read variables with meta())."""

Items = list[dict[str, Any]]
ReadItems = Callable[[str, Path_], "tuple[Items | None, str | None]"]
"""``(items, problem)`` of a ``for_each`` file named in a route at a key path."""


@dataclass(frozen=True)
class Expansion:
    """Where an expanded route came from."""

    template: int
    """The template's index in the file's ``routes`` list (its lines are the route's)."""
    variables: Mapping[str, Any]
    placeholders: Mapping[Path_, tuple[str, ...]] = field(default_factory=dict)
    """Key path (inside the route) -> the variables substituted in its value."""
    source_file: str | None = None
    """The ``for_each`` file the item came from, if any."""


def is_items_text(text: str) -> bool:
    """Whether a YAML text's top level is a list (a ``for_each`` file), judged from its first
    line of content: route files are mappings, so a list there is never a route file."""
    for line in text.splitlines():
        stripped = line.strip()
        if not stripped or stripped.startswith("#") or stripped.startswith("%") or stripped == "---":
            continue
        return stripped.startswith("- ") or stripped == "-" or stripped.startswith("[")
    return False


def expand_routes(
    file: str, data: Any, lines: dict[Path_, int], substituted: dict[Path_, str],
    problems: list[Problem], read_items: ReadItems,
) -> dict[int, Expansion]:
    """Replace each templated item of ``data['routes']`` by its expansions, in place, with the
    key lines (and ``${VAR}`` records) of every route moved to its new index; returns the
    expanded routes' origins by their new index."""
    routes = data.get("routes") if isinstance(data, dict) else None
    if not isinstance(routes, list) or not any(isinstance(r, dict) and FOR_EACH in r for r in routes):
        return {}
    expanded: list[Any] = []
    origins: dict[int, Expansion] = {}
    moved: dict[int, list[int]] = {}
    typed_texts: dict[Path_, str] = {}
    for index, body in enumerate(routes):
        if not (isinstance(body, dict) and FOR_EACH in body):
            moved[index] = [len(expanded)]
            expanded.append(body)
            continue
        where: Path_ = ("routes", index, FOR_EACH)
        line = lines.get(where, lines.get(("routes", index), 1))
        items, source_file = _items(body[FOR_EACH], where, read_items, file, line, problems)
        moved[index] = []
        template = {key: value for key, value in body.items() if key != FOR_EACH}
        if items and isinstance(template.get("name"), str):
            problems.extend(_name_problems(file, lines.get(("routes", index, "name"), line), template["name"], items[0]))
        items = _complete_items(file, line, where, template, items, problems, source_file)
        for item in items:
            placeholders: dict[Path_, tuple[str, ...]] = {}
            substituted_at: dict[Path_, str] = {}
            try:
                copy_ = _substitute(template, item, (), placeholders, substituted_at)
            except MappingError as exc:  # a format spec the item's value does not take ({id:03d} with id "seven")
                problems.append(Problem(file, line, f"{_dotted(where)} item {item!r}: {exc}"))
                continue
            moved[index].append(len(expanded))
            origins[len(expanded)] = Expansion(index, dict(item), placeholders, source_file)
            typed_texts.update({("routes", len(expanded)) + path: text for path, text in substituted_at.items()})
            expanded.append(copy_)
    _move(lines, moved)
    _move(substituted, moved)
    substituted.update(typed_texts)
    data["routes"] = expanded
    return origins


def _items(value: Any, where: Path_, read_items: ReadItems, file: str, line: int,
           problems: list[Problem]) -> tuple[Items, str | None]:
    source_file = None
    if isinstance(value, str):
        items, problem = read_items(value, where)
        if problem is not None:
            problems.append(Problem(file, line, problem))
            return [], None
        source_file = value
        value = items
    if not isinstance(value, list):
        problems.append(Problem(file, line, f"{_dotted(where)}: a list of objects, or the name of a YAML file holding one"))
        return [], None
    good: Items = []
    for number, item in enumerate(value):
        named = f"{_dotted(where)}[{number}]" + (f" (in {source_file})" if source_file else "")
        if not isinstance(item, dict):
            problems.append(Problem(file, line, f"{named}: {item!r} is not an object of template variables"))
            continue
        bad = [key for key in item if not isinstance(key, str) or not _VARIABLE_NAME.match(key)]
        if bad:
            problems.append(Problem(file, line, f"{named}: variable name {bad[0]!r} must be a letter or _ then letters, digits, _"))
            continue
        good.append(item)
    return good, source_file


def _complete_items(file: str, line: int, where: Path_, template: Any, items: Items, problems: list[Problem],
                    source_file: str | None) -> Items:
    """The items that give every variable the template uses that some item gives: an item
    without one would leave its ``{var}`` to be read from the canonical message (or in its
    route's name), which is never what a list of robots means. Over the agents table
    (``for_each: agents``) such an agent is left out instead: a MAVLink route is for the agents
    with a ``system_id``, a ROS 2 one for those with its own keys."""
    given = {key for item in items for key in item}
    used = {name for name in _placeholders(template) if name in given}
    complete = []
    for number, item in enumerate(items):
        missing = sorted(used - set(item))
        if missing and source_file == AGENTS:
            continue  # the agents table: the route is for the agents that have what it uses (UAVs, not robots)
        if missing:
            named = f"{_dotted(where)}[{number}]" + (f" (in {source_file})" if source_file else "")
            problems.append(Problem(file, line, f"{named}: no {', '.join(missing)} (the route uses "
                                                f"{', '.join('{' + name + '}' for name in missing)}, which other items give)"))
        else:
            complete.append(item)
    return complete


def _placeholders(value: Any) -> set[str]:
    if isinstance(value, dict):
        return {name for key, child in value.items() if key not in _JMESPATH_KEYS for name in _placeholders(child)}
    if isinstance(value, list):
        return {name for child in value for name in _placeholders(child)}
    return set(_variables(value)) if isinstance(value, str) else set()


def _variables(text: str) -> list[str]:
    """The one-word placeholders of a text, read by the engine's one grammar
    (engine/common/placeholders.py): a variable is a name, never a dotted path."""
    return [found.name for found in scan_placeholders(text) if len(found.path) == 1]


def _name_problems(file: str, line: int, name: str, item: Mapping[str, Any]) -> list[Problem]:
    """A route's name is fixed at load, so each ``{...}`` in it must be a variable."""
    return [Problem(file, line, f"route name {name!r}: {{{placeholder}}} is not a for_each variable (variables: "
                                f"{', '.join(item)}){did_you_mean(placeholder, item)}")
            for placeholder in dict.fromkeys(found.name for found in scan_placeholders(name)) if placeholder not in item]


def _substitute(value: Any, item: Mapping[str, Any], path: Path_,
                placeholders: dict[Path_, tuple[str, ...]], substituted: dict[Path_, str]) -> Any:
    if isinstance(value, dict):
        return {key: value[key] if key in _JMESPATH_KEYS else _substitute(value[key], item, path + (key,), placeholders, substituted)
                for key in value}
    if isinstance(value, list):
        return [_substitute(element, item, path + (number,), placeholders, substituted) for number, element in enumerate(value)]
    if not isinstance(value, str) or "{" not in value:
        return value
    used = [found for found in scan_placeholders(value) if len(found.path) == 1 and found.name in item]
    if not used:
        return value
    placeholders[path] = tuple(found.name for found in used)
    if len(used) == 1 and (used[0].start, used[0].end) == (0, len(value)) and not used[0].spec:
        found = item[used[0].name]
        if isinstance(found, (int, float, bool)):
            substituted[path] = _text(found)  # the text, should the key want a string (engine/language/route_yaml.py fits it)
        return copy.deepcopy(found)
    out, last = [], 0
    for found in used:  # a spec is honoured as the sink would (``{id:03d}``: 7 -> 007); MappingError if it cannot be
        try:
            out += [value[last:found.start], found.render(value, item[found.name]) if found.spec else _text(item[found.name])]
        except MappingError as exc:
            raise MappingError(f"{_dotted(path)}: {exc}") from None
        last = found.end
    return "".join(out) + value[last:]


def _text(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def _move(paths: dict[Path_, Any], moved: Mapping[int, list[int]]) -> None:
    """Re-key ``("routes", old, ...)`` entries to each new index of route ``old``."""
    old_entries = {path: value for path, value in paths.items() if len(path) >= 2 and path[0] == "routes" and isinstance(path[1], int)}
    for path in old_entries:
        del paths[path]
    for path, value in old_entries.items():
        old = path[1]
        assert isinstance(old, int)  # old_entries holds route indices only (above)
        for new in moved.get(old, ()):
            paths[("routes", new) + path[2:]] = value


def _dotted(path: Path_) -> str:
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out

