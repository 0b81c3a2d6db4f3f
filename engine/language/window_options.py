"""A route's ``window:`` as written, and what ``check`` says about it.

``window: {seconds: 1, per: agent_id, emit: {speed: "avg(speed)", n: "count()"}}`` turns the
route's canonical messages into one message per window (and per ``per`` key) holding the
aggregates ``emit`` names; engine/running/windows.py acts on it. The route language parses and
checks it here, so the language never imports the running engine (tests/project/test_import_graph.py).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, Iterator

from engine.common.suggest import did_you_mean
from engine.common.options import option

AGGREGATES = ("count", "sum", "avg", "min", "max", "first", "last")
"""The functions ``emit`` may call; ``count()`` alone takes no argument."""
WINDOW_START, WINDOW_END = "window_start", "window_end"
"""The emitted message's window bounds (RFC 3339, UTC, milliseconds): the start included, the end not."""
DEFAULT_PER_FIELD = "key"
"""The field holding the ``per`` value when ``per`` is not a plain field path (``a.b`` gives ``b``)."""

_CALL = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*\((.*)\)\s*$", re.S)
_FIELD_PATH = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")


@dataclass(frozen=True, kw_only=True)
class WindowOptions:
    """A route's ``window:`` (tumbling windows aligned to the clock)."""

    __schema_description__ = (
        "aggregate the route's canonical messages over tumbling windows aligned to the clock (multiples of seconds since "
        "the epoch, by the engine's receive time): one message per window and per key, holding the emit aggregates, the per "
        "value and window_start/window_end, goes through the sink mapping to the sink when the window closes (and on a clean "
        "stop). Inputs are acknowledged at the source when aggregated: an engine killed (kill -9) loses the open window")

    seconds: float = option(exclusive_minimum=0, description="the window's length; windows start at multiples of it since the epoch (UTC)")
    per: str | None = option(None, description=(
        "JMESPath on the canonical message giving the key windows are kept per (agent_id); its value is emitted under the "
        "path's last name (agent_id, or b for a.b; key for any other expression); absent: one window for the route"))
    emit: dict[str, Any] = option(description=(
        "the emitted fields: name -> count(), sum(x), avg(x), min(x), max(x), first(x) or last(x), x a JMESPath on the "
        "canonical message (a null x is skipped; sum and avg take numbers only)"),
        schema={"additionalProperties": {"type": "string", "description": "an aggregate: count(), sum(x), avg(x), min(x), max(x), first(x) or last(x)"},
                "minProperties": 1})


@dataclass(frozen=True)
class Aggregate:
    """One ``emit`` entry, parsed: the output field, the function, its argument (None for ``count()``)."""

    field: str
    function: str
    argument: str | None


def parse_aggregate(field: str, text: str) -> Aggregate:
    """``"avg(speed)"`` as an :class:`Aggregate`; ValueError saying what is wrong. The argument
    is not compiled here (the caller compiles it with the route's variables and stores)."""
    match = _CALL.match(text) if isinstance(text, str) else None
    if match is None:
        raise ValueError(f"{text!r} is not a call of one of {', '.join(a + '()' for a in AGGREGATES)}")
    function, argument = match.group(1), match.group(2).strip()
    if function not in AGGREGATES:
        raise ValueError(f"unknown aggregate function {function}(){did_you_mean(function, AGGREGATES)} "
                         f"(known: {', '.join(a + '()' for a in AGGREGATES)})")
    if function == "count":
        if argument:
            raise ValueError(f"count() takes no argument (it counts the window's messages), got {text!r}")
        return Aggregate(field, function, None)
    if not argument:
        raise ValueError(f"{function}() needs a JMESPath argument, as in {function}(speed)")
    return Aggregate(field, function, argument)


def per_field(per: str | None) -> str | None:
    """The emitted field holding the ``per`` value: a field path's last name, else ``key``."""
    if per is None:
        return None
    return per.strip().rsplit(".", 1)[-1] if _FIELD_PATH.match(per.strip()) else DEFAULT_PER_FIELD


def window_expressions(options: WindowOptions | None) -> Iterator[tuple[tuple[str, ...], str]]:
    """Every JMESPath the window evaluates, with its key path under ``window``: ``per`` and each
    aggregate's argument (those that parse), for ``check``'s expression and read checks."""
    if options is None:
        return
    if options.per is not None:
        yield ("per",), options.per
    for name, text in options.emit.items():
        try:
            aggregate = parse_aggregate(name, text)
        except ValueError:
            continue
        if aggregate.argument is not None:
            yield ("emit", name), aggregate.argument


def window_problems(options: WindowOptions | None) -> Iterator[tuple[tuple[str, ...], str]]:
    """What is wrong with a ``window:`` beside its expressions (checked by the caller with
    :func:`window_expressions`): unknown functions, a missing argument, a field emitted twice."""
    if options is None:
        return
    reserved = {WINDOW_START, WINDOW_END}
    key = per_field(options.per)
    for name, text in options.emit.items():
        try:
            parse_aggregate(name, text)
        except ValueError as error:
            yield ("emit", name), str(error)
        if name in reserved:
            yield ("emit", name), f"{name!r} is the window's own field (window_start, window_end): name it otherwise"
        elif name == key:
            yield ("emit", name), f"{name!r} holds the per value ({options.per!r}): name the aggregate otherwise"


def emitted_fields(options: WindowOptions) -> tuple[str, ...]:
    """The keys of every message the window emits (what the sink mapping and templates may read)."""
    key = per_field(options.per)
    return (*options.emit, *((key,) if key else ()), WINDOW_START, WINDOW_END)
