"""Several sinks for one route (``sinks:``), each with its own mapping and ``when:``, and a
sink's ``fallback:``: one :class:`~engine.endpoints.base.Sink` to the route's runner, so the
runner's one delivery policy (engine/running/delivery.py) settles each message once.

A route with one plain ``sink:`` never comes here (no per-message cost: its pipeline and
runner are as before). A route with several sinks, a sink ``when:`` or a ``fallback:`` is
converted once (decode, mapping, schema, the route's ``when:``); then:

* **choosing and mapping** (in the pipeline's sink-mapping stage, :class:`SinkChoice`): each
  sink's ``when:`` says whether it gets the message, and its own mapping and field check make
  what it is given. The outbound's ``fields`` is then ``{sink name: its fields}`` of the sinks
  chosen (plain JSON: a buffer spills it as it is). A message no sink chose is settled and
  counted ``filtered``; one whose every chosen sink's mapping failed is one dead letter (stage
  ``sink mapping``, naming the sinks); one that only some sinks' mappings refuse goes to the
  others, and the refusals wait in its meta (``sinks_refused``) for the end below.
* **sending** (:class:`FanOutSink`): each sink gets its copy, the sinks concurrently; a message
  is accepted once every chosen sink settled it. What each sink settled is kept in the
  message's meta (``sinks_settled``: it survives the buffer's spill files), so a retry (after a
  transient failure of one sink) goes only to the sinks that have not: **an accepted copy is
  never sent again**. A sink that refuses a message for good (or whose mapping did) makes the
  message one dead letter once the other sinks settled it, naming the sink and its error
  (stage ``sink``, or ``sink mapping``); the copies the other sinks accepted stay accepted
  (its dead letter names the sinks that did not take it, ``x-source-sinks_unsent``, and
  ``dead-letters replay`` sends it to those only). A message the buffer held across a reload
  that changed the route's sinks (``sink:`` to ``sinks:``, back, or other names) has fields
  for sinks the route no longer has: the new pipeline maps it again before it is sent
  (:func:`mapped_for`, engine/running/held.py), so no copy is lost or sent in the old shape.
* **fallback**: what a sink refuses for good, or the broker returns unroutable (an
  exchange with no queue bound), goes to its fallback at once. While the sink cannot take
  messages (its connection down or not open, or not ready: :meth:`Slot.can_take`), the route
  waits as it waits for one sink (no attempt spent) for ``after`` seconds, then sends to the
  fallback until the sink can take messages again: then new messages go to it again (the
  fallback gives back); an outage counts only while it lasts (a sink seen able again starts the
  next one's ``after`` afresh, though no message reached it between). A send that fails while
  the sink says it can take messages (a publish timed out, a negative confirm) goes to the
  fallback at once, as a refusal does: the route's runner spends an attempt on each such
  failure, and its ``max_attempts`` (5, about 1.5 s of backoff) would dead-letter the message
  well before an ``after`` of seconds let the fallback take it; the next message tries the sink
  first again. Every message is accepted by the sink or by its fallback, once. No
  clock or retry loop of its own: the route's runner waits (``ready``) and retries with the
  engine's one backoff, and every failure is classified by the one delivery policy
  (engine/running/delivery.py ``classify``).
* **counts**: each sink's and fallback's (delivered, refused, to_fallback, unroutable) are in
  the route's one set of counters (engine/running/observe.py :class:`SinkCounts`, kept across
  reloads), read by the status' ``sinks`` and ``/metrics`` (``rabbitros_sink_messages_total``).

A down sink without a fallback makes the whole route wait (as one sink does), whatever the
others could take: a message is acknowledged at its source only once every chosen sink has it.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

from engine.common.placeholders import MappingError
from engine.endpoints import transport
from engine.endpoints.base import Connection, EndpointError, MessageRejected, NotSent, Outbound, Sink, Unroutable
from engine.language.mapping import Mapper, compile_mapping
from engine.language.specs import RouteSpec, SinkSpec
from engine.running.delivery import classify
from engine.running.observe import RouteObserver, SinkCounts

SETTLED = "sinks_settled"
"""Meta key: the names of the sinks that settled the message (accepted, or settled unsent)."""
REFUSED = "sinks_refused"
"""Meta key: sink name -> ``stage: error`` of the sinks that refused it for good."""
CHOSEN = "sinks_chosen"
"""Meta key: the names of every sink of the fan-out whose choice made the message's ``fields``
(the :class:`SinkChoice`'s own tuple, no copy): a message the buffer held across a reload that
changed the route's sinks is mapped again by the new pipeline (:func:`mapped_for`)."""
UNSENT = "sinks_unsent"
"""Meta key: the sinks a message that failed was not accepted by, comma-separated (text, so its
dead letter keeps it: ``x-source-sinks_unsent``); ``dead-letters replay`` sends it to those only."""


class NoSinkChosen(Exception):
    """No sink's ``when:`` chose the message (the pipeline settles it as ``filtered``)."""


@dataclass(frozen=True)
class Mapped:
    """A sink's own mapping and field check, compiled."""

    name: str
    mapper: Mapper | None
    check: Callable[[Any], None] | None

    @classmethod
    def compile(cls, spec: SinkSpec, compile_: Callable[[str | None], Mapper | None]) -> Mapped:
        end = spec.endpoint
        return cls(spec.name, compile_(spec.mapping), transport(end.protocol).sink_field_check(end.options, spec.mapping))

    def fields(self, data: Any, meta: dict[str, Any]) -> Any:
        """What this sink is given (MappingError, MessageRejected when it cannot be made)."""
        fields = data if self.mapper is None else self.mapper(data, meta)
        if self.check is not None:
            self.check(fields)
        return fields


class SinkChoice:
    """The sink-mapping stage of a route with several sinks (see the module docstring): the
    pipeline calls it as its sink mapper, ``(canonical, meta) -> {sink name: fields}``."""

    def __init__(self, sinks: Sequence[SinkSpec], compile_: Callable[[str | None], Mapper | None]) -> None:
        self.sinks = [(Mapped.compile(spec, compile_), compile_(spec.when)) for spec in sinks]
        self.names = tuple(spec.name for spec in sinks)

    def __call__(self, data: Any, meta: dict[str, Any]) -> dict[str, Any]:
        chosen: dict[str, Any] = {}
        refused: dict[str, str] = {}
        unsent = meta.get(UNSENT)  # a dead letter sent again: only to the sinks that did not take it
        for mapped, condition in self.sinks:
            if unsent is not None and mapped.name not in str(unsent).split(","):
                continue
            if condition is not None:
                try:
                    if not passes(condition(data, meta)):
                        continue
                except Exception as error:  # a condition that cannot be evaluated is that sink's refusal
                    refused[mapped.name] = f"when: {error}"
                    continue
            try:
                chosen[mapped.name] = mapped.fields(data, meta)
            except (MappingError, MessageRejected) as error:
                refused[mapped.name] = f"sink mapping: {error}"
            except Exception as error:
                refused[mapped.name] = f"sink mapping: {type(error).__name__}: {error}"
        if refused:
            if not chosen:
                raise MessageRejected("; ".join(f"sink {name!r}: {error}" for name, error in refused.items()), stage="sink mapping")
            meta[REFUSED] = refused
        elif not chosen:
            raise NoSinkChosen("no sink's when: chose the message")
        meta[CHOSEN] = self.names
        return chosen


def mapped_for(meta: Mapping[str, Any], names: tuple[str, ...] | None) -> bool:
    """Whether a message's ``fields`` were made for a route whose sinks are ``names`` (None: one
    plain sink): False for one the buffer held across a reload from ``sink:`` to ``sinks:``,
    back, or to other sinks (its fields are for sinks the route no longer has: sent as they are,
    the fan-out would send it nowhere and count it delivered). One look and an identity test
    for a message this pipeline mapped."""
    chosen = meta.get(CHOSEN)
    if chosen is names:
        return True
    return chosen is not None and names is not None and tuple(chosen) == names


def passes(value: Any) -> bool:
    """JMESPath's truth (the specification's "false-like" values), for the route's ``when:`` and
    each sink's: false, null, an empty string, list or object say no; any number, 0 included,
    says yes (unlike Python's ``bool``)."""
    if value is None or value is False:
        return False
    if isinstance(value, (str, list, dict)):
        return len(value) > 0
    return True


@dataclass(eq=False)
class Slot:
    """One sink of the route (or a sink's fallback) with its connection."""

    name: str
    sink: Sink
    connection: Connection
    is_open: Callable[[Connection], bool]
    counts: SinkCounts
    """Its counts in the route's one set (engine/running/observe.py), kept across reloads."""
    fallback: Slot | None = None
    after: float = 5.0
    mapped: Mapped | None = None
    """A fallback's own mapping (a primary's ran in the pipeline: :class:`SinkChoice`)."""
    unable_since: float | None = None
    """Monotonic time the sink was first seen unable to take messages, until it is seen able
    again (so an outage long past never counts toward the next one's ``after``)."""

    def can_take(self) -> bool:
        """Its connection is open and healthy, and the sink is ready (as the runner asks of one sink)."""
        connection = self.connection
        return connection.healthy and self.is_open(connection) and self.sink.ready

    def down_since(self) -> float | None:
        """Since when the sink has been unable to take messages (None: it can take them)."""
        if self.can_take():
            self.unable_since = None
        elif self.unable_since is None:
            self.unable_since = time.monotonic()
        return self.unable_since

    def fallback_due(self) -> bool:
        """Whether messages for this sink go to its fallback now: it has one that can take
        them, and this sink has been unable to take them for ``after`` seconds."""
        if self.fallback is None:
            return False
        since = self.down_since()
        return since is not None and time.monotonic() - since >= self.after and self.fallback.can_take()

    def able(self) -> bool:
        return self.can_take() or self.fallback_due()

    def reason(self) -> str | None:
        if self.able():
            return None
        why = self.sink.not_ready_reason() or f"connection {self.connection.name!r} {'down' if self.is_open(self.connection) else 'not open'}"
        since = self.down_since()
        if self.fallback is not None and since is not None:
            why += f" (fallback {self.fallback.name!r} in {max(0.0, self.after - (time.monotonic() - since)):.1f} s)"
        return f"sink {self.name!r}: {why}"


class _Progress:
    """One message's state across the sinks during one :meth:`FanOutSink.send_batch`."""

    __slots__ = ("message", "settled", "refused", "pending", "delivered", "not_sent")

    def __init__(self, message: Outbound) -> None:
        meta: dict[str, Any] = message.meta  # type: ignore[assignment]  # the source's own dict
        self.message = message
        self.settled: list[str] = meta.setdefault(SETTLED, [])
        self.refused: dict[str, str] = meta.setdefault(REFUSED, {})
        self.pending: BaseException | None = None
        self.delivered = False
        self.not_sent: NotSent | None = None

    def wanted(self, name: str) -> bool:
        fields = self.message.fields
        return isinstance(fields, dict) and name in fields and name not in self.settled and name not in self.refused

    def copy_for(self, name: str, fields: Any) -> Outbound:
        m = self.message
        return Outbound(m.body, m.canonical, fields, m.message_id, m.meta, m.reply, m.received_ns, m.captured)

    def result(self) -> BaseException | None:
        if self.pending is not None or self.refused:
            fields = self.message.fields
            unsent = [name for name in fields if name not in self.settled] + [name for name in self.refused if name not in fields]
            self.message.meta[UNSENT] = ",".join(unsent)  # type: ignore[index]  # the source's own dict
        if self.pending is not None:
            return self.pending
        if self.refused:
            stage = "sink mapping" if all(error.startswith("sink mapping: ") for error in self.refused.values()) else "sink"
            return MessageRejected("; ".join(f"sink {name!r}: {error.removeprefix('sink mapping: ')}" if stage == "sink mapping"
                                             else f"sink {name!r}: {error}" for name, error in self.refused.items()), stage=stage)
        if self.delivered or self.not_sent is None:
            return None
        return self.not_sent


class FanOutSink(Sink):
    """The route's sinks as one (see the module docstring)."""

    def __init__(self, slots: list[Slot], observer: RouteObserver) -> None:
        self.slots = slots
        self.observer = observer
        """The route's counters: returns that end a message's send here (a fallback took it, or
        the sink refused it for good) count ``unroutable`` here; the runner counts the rest."""
        self.batches_in_flight = min(slot.sink.batches_in_flight for slot in slots)  # type: ignore[misc]  # a ClassVar on Sink; a fan-out's is its sinks' least, known per instance

    @property
    def ready(self) -> bool:
        for slot in self.slots:
            if not slot.able():
                return False
        return True

    def not_ready_reason(self) -> str | None:
        reasons = [reason for slot in self.slots if (reason := slot.reason()) is not None]
        return "; ".join(reasons) or None

    def status(self) -> dict[str, Any]:
        """Each sink's counts and whether it can take messages now (the route's status ``sinks``)."""
        out: dict[str, Any] = {}
        for slot in self.slots:
            out[slot.name] = {**slot.counts.as_dict(), "can_take": slot.can_take()}
            if slot.fallback is not None:
                out[slot.fallback.name] = {**slot.fallback.counts.as_dict(), "can_take": slot.fallback.can_take(),
                                           "taking_over": slot.down_since() is not None and not slot.can_take()}
        return out

    async def send(self, message: Outbound) -> None:
        error = (await self.send_batch((message,)))[0]
        if error is not None:
            raise error

    async def send_batch(self, messages: Sequence[Outbound]) -> list[BaseException | None]:
        progress = [_Progress(message) for message in messages]
        await asyncio.gather(*(self._send_slot(slot, progress) for slot in self.slots))
        return [p.result() for p in progress]

    async def _send_slot(self, slot: Slot, progress: list[_Progress]) -> None:
        mine = [p for p in progress if p.wanted(slot.name)]
        if not mine:
            return
        if not slot.can_take():
            if slot.fallback_due():
                await self._to_fallback(slot, mine)
            else:
                waiting = EndpointError(f"sink {slot.name!r} cannot take messages now")
                for p in mine:
                    p.pending = waiting
            return
        results = await slot.sink.send_batch([p.copy_for(slot.name, p.message.fields[slot.name]) for p in mine])
        diverted = self._settle(slot, mine, results)
        if diverted:
            await self._to_fallback(slot, diverted)

    def _settle(self, slot: Slot, mine: list[_Progress], results: list[BaseException | None],
                primary: Slot | None = None) -> list[_Progress]:
        """Record what ``slot`` (``primary``'s fallback, when given) did with each message, by the
        engine's one classification (engine/running/delivery.py); return what goes on to its
        fallback: whatever it did not take (refused for good, returned, or a transient failure:
        see the module docstring)."""
        diverted: list[_Progress] = []
        counts = slot.counts
        for p, error in zip(mine, results):
            if error is None or isinstance(error, NotSent):
                p.settled.append(slot.name)
                if primary is not None:
                    p.settled.append(primary.name)
                if error is None:
                    p.delivered = True
                    counts.delivered += 1
                else:
                    p.not_sent = error
                continue
            returned = isinstance(error, Unroutable)
            counts.unroutable += returned
            if slot.fallback is not None:
                self.observer.unroutable += returned  # the runner never sees this return
                diverted.append(p)
                continue
            failure = classify(error)
            if failure.permanent:
                self.observer.unroutable += returned
                p.refused[slot.name] = f"{failure.stage}: {failure.error}"
                counts.refused += 1
            else:
                p.pending = _named(slot.name, error)
        return diverted

    async def _to_fallback(self, slot: Slot, mine: list[_Progress]) -> None:
        """Send what ``slot`` cannot take to its fallback; settled there counts as settled by ``slot``."""
        fallback = slot.fallback
        assert fallback is not None and fallback.mapped is not None
        ready: list[_Progress] = []
        copies: list[Outbound] = []
        for p in mine:
            try:
                fields = fallback.mapped.fields(p.message.canonical, p.message.meta)  # type: ignore[arg-type]  # the source's own dict
            except Exception as problem:
                p.refused[fallback.name] = f"sink mapping: {problem}"
                continue
            ready.append(p)
            copies.append(p.copy_for(fallback.name, fields))
        if not copies:
            return
        slot.counts.to_fallback += len(copies)
        self._settle(fallback, ready, await fallback.sink.send_batch(copies), slot)

    async def close(self) -> None:
        await asyncio.gather(*(sink.close() for sink in self.sinks()), return_exceptions=True)

    def sinks(self) -> list[Sink]:
        return [s.sink for slot in self.slots for s in (slot, slot.fallback) if s is not None]


def _named(name: str, error: BaseException) -> BaseException:
    """A transient error of one sink, saying which (the route's retry reports and dead letters name it)."""
    if isinstance(error, Unroutable):
        return Unroutable(f"sink {name!r}: {error}")
    return EndpointError(f"sink {name!r}: {error}")


async def open_fan_out(sinks: Sequence[SinkSpec], route: str, connection_of: Callable[[Any], Any],
                       is_open: Callable[[Connection], bool], observer: RouteObserver,
                       compile_: Callable[[str | None], Mapper | None]) -> tuple[FanOutSink, list[Connection]]:
    """The route's sinks (and fallbacks) on their connections (``connection_of(endpoint)``
    awaits the engine's pooled connection), as one :class:`FanOutSink`, and those connections."""
    slots: list[Slot] = []
    connections: list[Connection] = []
    for spec in sinks:
        connection = await connection_of(spec.endpoint)
        connections.append(connection)
        fallback = None
        if spec.fallback is not None:
            fallback_connection = await connection_of(spec.fallback.endpoint)
            connections.append(fallback_connection)
            fallback = Slot(spec.fallback.name, fallback_connection.sink(route, spec.fallback.endpoint.options), fallback_connection,
                            is_open, observer.sink(spec.fallback.name), mapped=Mapped.compile(spec.fallback, compile_))
        slots.append(Slot(spec.name, connection.sink(route, spec.endpoint.options), connection, is_open, observer.sink(spec.name),
                          fallback, spec.after))
    return FanOutSink(slots, observer), connections


async def open_sinks(spec: RouteSpec, connection_of: Callable[[Any], Any], is_open: Callable[[Connection], bool],
                     stores: Any, observer: RouteObserver | None = None) -> tuple[Sink, list[Connection], Connection | None]:
    """``(sink, connections, one)``: the route's one sink on its connection (``one``), or its
    several sinks as a :class:`FanOutSink` (``one`` None: it asks its sinks' connections
    itself); ``observer``: the route's counters (None: counts nobody reads, as a replay's)."""
    if not spec.sinks:
        connection = await connection_of(spec.sink)
        return connection.sink(spec.name, spec.sink.options), [connection], connection
    sink, connections = await open_fan_out(spec.sinks, spec.name, connection_of, is_open,
                                           observer if observer is not None else RouteObserver(spec.name), compiler(spec, stores))
    return sink, connections, None


def compiler(spec: Any, stores: Any) -> Callable[[str | None], Mapper | None]:
    """How a route's sink mappings and conditions compile (its variables and stores)."""
    return lambda expression: compile_mapping(expression, spec.variables, stores, spec.name)


def fan_out_of(sink: Sink) -> Mapping[str, Any] | None:
    """The per-sink status of a fan-out route's sink (None for one plain sink)."""
    return sink.status() if isinstance(sink, FanOutSink) else None
