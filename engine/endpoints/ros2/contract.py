"""What the ROS 2 transport answers for the core's checks and dry runs: the message a typed
source gives for a test's input, what the sink would build, the fields a mapping may read
(with a did-you-mean), and the installed type closest to a misspelt one."""

from __future__ import annotations

import re
import sys
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Mapping

from engine.common.suggest import closest
from engine.endpoints.base import ELEMENT, FieldPath, FieldProblem, Outbound
from engine.endpoints.ros2 import rosmsg

STRING_TYPE = "std_msgs/msg/String"


def test_input(type_name: str) -> Callable[[Any], dict[str, Any]] | None:
    """The field dict a source of ``type_name`` hands over (None for a byte source)."""
    cls = rosmsg.resolve_type(type_name)
    if rosmsg.type_name(cls) == STRING_TYPE:
        return None

    def received(value: Any) -> dict[str, Any]:
        if not isinstance(value, Mapping):
            raise ValueError(f"{type_name} input must be a mapping of fields")
        return rosmsg.to_dict(rosmsg.from_dict(cls, value))

    return received


def sink_dry_run(route: str, topic: str, type_name: str, resolve: Callable[[Any, str], str] | None,
                 build: Callable[[type, Outbound, str], Any]) -> Callable[[Outbound], str | None]:
    """The topic the sink would publish on, and the message ``build`` makes from the fields as
    the sink does (raising MessageRejected where the sink would)."""
    cls = rosmsg.resolve_type(type_name)
    typed = rosmsg.type_name(cls) != STRING_TYPE
    where = f"route {route!r}, ros2 topic {topic!r}"  # as the sink names it

    def built(outbound: Outbound) -> str | None:
        rendered = topic if resolve is None else resolve(outbound.template_data, where)
        if typed:
            build(cls, outbound, where)
        return rendered

    return built


def field_problem(type_name: str) -> FieldProblem | None:
    try:
        cls = rosmsg.resolve_type(type_name)
    except Exception:  # not installed or misspelt: reported by the type check
        return None
    if rosmsg.type_name(cls) == STRING_TYPE:
        return None  # a byte source: the mapping reads the JSON inside
    return message_field_problem(cls)


def message_field_problem(cls: rosmsg.RosClass) -> FieldProblem:
    """The paths a mapping may read from a message of ``cls`` (a topic's message, a service's
    request or response)."""
    return lambda path: _resolve(cls, path)


ACTION_ANSWER = ("kind", "status", "feedback", "result")
"""The keys of an action sink's answers (engine/endpoints/ros2/calls.py): ``{kind, status?,
feedback?, result?}``; ``feedback`` and ``result`` hold the action's Feedback and Result."""


def action_answer_problem(action: rosmsg.RosClass) -> FieldProblem:
    """The paths a reply mapping may read from an action sink's answers: the keys of
    :data:`ACTION_ANSWER`, and below ``feedback.``/``result.`` the action's Feedback/Result."""
    parts = {"feedback": action.Feedback, "result": action.Result}

    def problem(path: FieldPath) -> str | None:
        head = path[0]
        if head in parts:
            return _resolve(parts[head], path, start=1)
        if head not in ACTION_ANSWER:
            guess = closest(head, ACTION_ANSWER)
            hint = f"; did you mean {guess!r}?" if guess else f" (it has: {', '.join(ACTION_ANSWER)})"
            return f"mapping reads {head!r}, which an action's answer does not have{hint}"
        return None  # kind, status: strings

    return problem


def _dotted(path: FieldPath) -> str:
    return ".".join(path).replace(f".{ELEMENT}", ELEMENT)


def _resolve(cls: rosmsg.RosClass, path: FieldPath, start: int = 0) -> str | None:
    """What is wrong with ``path[start:]`` read from a ``cls`` (messages name the whole ``path``)."""
    current: type | None = cls
    in_list = False
    for depth, step in enumerate(path[start:], start):
        if current is None:
            return None  # a primitive or an array of them: nothing more to check
        if step == ELEMENT:
            if not in_list:
                return None  # indexing a message: JMESPath gives null, not ours to judge
            in_list = False
            continue
        if in_list:
            return None
        fields = _fields(current)
        if step not in fields:
            return (f"mapping reads {_dotted(path[:depth + 1])!r}, which {rosmsg.type_name(current)} does not have"
                    f"{_hint(current, path, depth)}")
        current, in_list = fields[step]
    return None


NESTED_SEARCH_DEPTH = 3
"""How many message levels below a missing field ``check`` looks for it: Odometry's
``pose.pose.orientation`` is two below ``pose``; deeper guesses would be guesses."""


def _hint(cls: rosmsg.RosClass, path: FieldPath, depth: int) -> str:
    """Where the field ``path[depth]`` is: in a message nested below ``cls`` (a level left
    out: ``pose.orientation`` of a nav_msgs/Odometry is ``pose.pose.orientation``), else a
    field of ``cls`` spelt alike, else the list of its fields."""
    step, rest = path[depth], path[depth + 1:]
    found = _nested_paths(cls, step, rest)
    if found:
        shown = [_dotted(path[:depth] + prefix + (step,)) for prefix in found[:3]]
        return f"; did you mean {shown[0]!r}?" if len(shown) == 1 else f"; did you mean one of {', '.join(map(repr, shown))}?"
    fields = _fields(cls)
    guess = closest(step, fields)
    return f"; did you mean {_dotted(path[:depth] + (guess,))!r}?" if guess else f" (fields: {', '.join(fields)})"


def _nested_paths(cls: rosmsg.RosClass, step: str, rest: FieldPath) -> list[FieldPath]:
    """The shortest field paths ``p`` below ``cls`` (through nested messages, not sequences)
    such that ``p + (step,) + rest`` is a path of ``cls``."""
    level: list[tuple[FieldPath, type]] = [((), cls)]
    for _ in range(NESTED_SEARCH_DEPTH):
        level = [(prefix + (name,), nested) for prefix, message in level
                 for name, (nested, in_list) in _fields(message).items() if nested is not None and not in_list]
        found = [prefix for prefix, message in level if step in _fields(message)
                 and _resolve(message, (step,) + rest) is None]
        if found:
            return found
    return []


@lru_cache(maxsize=None)
def _fields(cls: rosmsg.RosClass) -> dict[str, tuple[type | None, bool]]:
    """field -> (message class of the field or of its elements, is a sequence of messages)."""
    from rosidl_parser import definition as idl

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


@lru_cache(maxsize=1)
def installed_types() -> tuple[str, ...]:
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


def suggest_type(value: str) -> str | None:
    """The installed type closest to ``value`` (``pkg/Type`` is read as ``pkg/msg/Type``)."""
    full = re.sub(r"^([a-z][a-z0-9_]*)/(?!msg/)", r"\1/msg/", value.strip())
    return closest(full, installed_types())
