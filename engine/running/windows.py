"""Tumbling windows (``window:``): a route's canonical messages aggregated per window and key.

``window: {seconds: 1, per: agent_id, emit: {speed: "avg(speed)", top: "max(speed)"}}`` turns
10 Hz telemetry into one message per agent and second: what a thin link (a SiK radio's ~5 kB/s, a
link billed by the byte) can carry, and a 1 s average where a throttle would keep only the last
sample. Measured (tests/running/test_windows.py, 20 agents at 10 Hz, avg/min/max/last, AMQP -> AMQP):
the sink side received 81 % fewer bytes over a 3 s run (partial windows at its edges), 86 % in
steady state: 4.2 kB/s instead of 30.7 kB/s.

Where it sits: the pipeline (engine/running/pipeline.py) converts and checks a message, then
evaluates the window's ``per`` key and each aggregate's argument (``x`` of ``avg(x)``) and raises
:class:`Windowed` instead of running the sink mapping; the runner (engine/running/runner.py) adds
it to the open window (:meth:`Window.add`) and settles it at once, counted ``windowed``. When the
window closes, each key's aggregates become a message, the "canonical" message of the sink stage:
it goes through the sink mapping and the sink as any converted message would
(``RouteRunner.window_closed``).

Windows are tumbling and aligned to the clock: ``[k * seconds, (k + 1) * seconds)`` in Unix time,
by the time the engine adds the message (its receive time: the engine's clock, not a field of
the message, so a vehicle's wrong clock cannot scatter windows). A window closes at its end (a
timer armed only while a window holds messages: an idle route costs nothing), or on a clean stop
or reload (a pipeline retiring), then with what it has.

The emitted message holds each ``emit`` field, the ``per`` value under its field name
(:func:`engine.language.window_options.per_field`) and ``window_start``/``window_end`` (RFC 3339,
UTC, milliseconds). Aggregates: ``count()`` the window's messages for the key; ``sum``/``avg``
numbers only, summed exactly (``math.fsum`` of the values, so the result does not depend on the
order of arrival; an all-integer sum stays an integer); ``min``/``max`` numbers or strings (ISO
times compare as time); ``first``/``last`` in arrival order. A null ``x`` is skipped (``count()``
still counts the message); a window where every ``x`` was null gives null. A value an aggregate
cannot take (a string to ``avg``, a string after numbers to ``min``) makes that input a dead
letter (stage ``window``), not the window.

Delivery: inputs are acknowledged at the source when they are added (the window holds no source
message): holding a second of 200 messages unsettled would need the source to keep that many
unacknowledged (AMQP prefetch, MQTT's receive maximum, a ROS 2 or MAVLink source that cannot be
asked again), and stalls every source that awaits its batch. The price, stated in
docs/route-language.md: an engine killed (kill -9) loses the open windows, that is the inputs it
added since the last window boundary, at most ``seconds`` of input per key, plus the emitted
messages the sink had not accepted yet (a window's output is being sent for the milliseconds a
publish takes). tests/running/test_windows.py kills an engine and checks that bound.
"""

from __future__ import annotations

import asyncio
import math
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any, Callable, Mapping

from engine.language.mapping import Mapper, compile_mapping
from engine.language.window_options import WINDOW_END, WINDOW_START, WindowOptions, parse_aggregate, per_field

DROPPED_META = ("message_id", "reply_to", "correlation_id")
"""Of the last input's metadata, what a window's message does not inherit: it is a new message
(a new id), and no caller waits for an answer to it."""


class Windowed(Exception):
    """The pipeline's answer for a message of a window route: its key and aggregate inputs."""

    def __init__(self, canonical: Any, key: Any, values: tuple[Any, ...]) -> None:
        super().__init__("windowed")
        self.canonical = canonical
        self.key = key
        self.values = values


Outputs = list[tuple[dict[str, Any], dict[str, Any]]]
"""Each closed key's message and the metadata it carries (the last input's, less :data:`DROPPED_META`)."""


@dataclass
class _Open:
    """One key's aggregates in the open window."""

    count: int = 0
    values: list[list[Any]] = field(default_factory=list)
    """Per aggregate: the numbers (sum, avg: summed at close), or [result] (min, max, first, last)."""
    meta: Mapping[str, Any] = field(default_factory=dict)


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _timestamp(seconds: float) -> str:
    return datetime.fromtimestamp(seconds, timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


@dataclass(eq=False)
class Window:
    """A route's open window (one per pipeline generation): see the module docstring."""

    seconds: float
    per: Mapper | None
    per_name: str | None
    fields: tuple[str, ...]
    functions: tuple[str, ...]
    arguments: tuple[Mapper | None, ...]
    stage: Callable[[Outputs], None] | None = None
    """Where closed windows go (the route's runner, set when it adds the first message)."""
    start: float = 0.0
    open: dict[Any, _Open] = field(default_factory=dict)
    _timer: asyncio.TimerHandle | None = None
    clock: Callable[[], float] = time.time

    @classmethod
    def compile(cls, options: WindowOptions | None, variables: Mapping[str, Any], stores: Any, route: str) -> Window | None:
        """The window of ``options`` (checked at load: an aggregate that does not parse cannot reach here)."""
        if options is None:
            return None
        aggregates = [parse_aggregate(name, text) for name, text in options.emit.items()]
        return cls(
            seconds=float(options.seconds),
            per=compile_mapping(options.per, variables, stores, route),
            per_name=per_field(options.per),
            fields=tuple(a.field for a in aggregates),
            functions=tuple(a.function for a in aggregates),
            arguments=tuple(compile_mapping(a.argument, variables, stores, route) for a in aggregates),
        )

    def evaluate(self, canonical: Any, meta: dict[str, Any]) -> Windowed:
        """The message's key and aggregate inputs (MappingError propagates: a ``window`` error)."""
        key = self.per(canonical, meta) if self.per is not None else None
        if not (key is None or isinstance(key, (str, int, float, bool))):
            raise TypeError(f"per gives {type(key).__name__} {str(key)[:80]}, not a string or number")
        return Windowed(canonical, key, tuple(None if a is None else a(canonical, meta) for a in self.arguments))

    def add(self, windowed: Windowed, meta: Mapping[str, Any]) -> str | None:
        """Add a message to its key's open window; the reason it cannot be (a dead letter), or None."""
        now = self.clock()
        if self.open and now >= self.start + self.seconds:  # the timer is late: that window is over
            self.close_now()
        slot = self.open.get(windowed.key)
        if slot is None:
            problem = self._refused(windowed.values, None)
            if problem is not None:
                return problem
            if not self.open:
                self.start = math.floor(now / self.seconds) * self.seconds
                self._arm()
            slot = self.open[windowed.key] = _Open(values=[[] for _ in self.functions])
        else:
            problem = self._refused(windowed.values, slot)
            if problem is not None:
                return problem
        slot.count += 1
        slot.meta = meta
        for function, value, held in zip(self.functions, windowed.values, slot.values):
            if value is None or function == "count":
                continue
            if function in ("sum", "avg"):
                held.append(value)
            elif not held or function == "last":
                held[:] = [value]
            elif (function == "min" and value < held[0]) or (function == "max" and value > held[0]):
                held[0] = value
        return None

    def _refused(self, values: tuple[Any, ...], slot: _Open | None) -> str | None:
        for name, function, value, index in zip(self.fields, self.functions, values, range(len(values))):
            if value is None or function in ("count", "first", "last"):
                continue
            if function in ("sum", "avg") and not _number(value):
                return f"{name}: {function}() takes numbers, got {type(value).__name__} {str(value)[:80]!r}"
            if function in ("min", "max"):
                if not (_number(value) or isinstance(value, str)):
                    return f"{name}: {function}() takes numbers or strings, got {type(value).__name__}"
                held = slot.values[index] if slot is not None else ()
                if held and _number(held[0]) != _number(value):
                    return f"{name}: {function}() of {type(held[0]).__name__} and {type(value).__name__} values"
        return None

    def _arm(self) -> None:
        if self._timer is not None or self.stage is None:
            return
        loop = asyncio.get_running_loop()
        self._timer = loop.call_at(loop.time() + max(0.0, self.start + self.seconds - self.clock()), self._due)

    def _due(self) -> None:
        self._timer = None
        if not self.open:
            return
        if self.clock() < self.start + self.seconds:  # the loop's clock ran ahead of the wall clock
            self._arm()
            return
        self.close_now()

    def close_now(self) -> Outputs:
        """Emit every key's message of the open window (to the stage, and returned)."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        start, end = _timestamp(self.start), _timestamp(self.start + self.seconds)
        outputs = []
        for key, slot in self.open.items():
            emitted: dict[str, Any] = {}
            for name, function, held in zip(self.fields, self.functions, slot.values):
                emitted[name] = _result(function, held, slot.count)
            if self.per_name is not None:
                emitted[self.per_name] = key
            emitted[WINDOW_START], emitted[WINDOW_END] = start, end
            meta = {k: v for k, v in slot.meta.items() if k not in DROPPED_META}
            outputs.append((emitted, meta))
        self.open = {}
        if outputs and self.stage is not None:
            self.stage(outputs)
        return outputs

    def close(self) -> None:
        """The pipeline retires (a clean stop, a reload): the open window is emitted now."""
        if self.open:
            self.close_now()
        elif self._timer is not None:
            self._timer.cancel()
            self._timer = None


def _result(function: str, held: list[Any], count: int) -> Any:
    if function == "count":
        return count
    if not held:
        return None
    if function in ("sum", "avg"):
        total: Any = sum(held) if all(isinstance(v, int) for v in held) else math.fsum(held)
        return total if function == "sum" else total / len(held)
    return held[0]
