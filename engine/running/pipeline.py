"""A route compiled into a chain of small callables: decode, map, validate, encode, sink-map.

The sink-mapping stage ends with the sink's field check (``Transport.sink_field_check``): a typed
sink refuses a field set to null there, so the message is dead-lettered as a ``sink mapping``
error before the throttle, the buffer or the sink see it, and ``rabbitros-engine test`` (which
compiles this same pipeline) reports the same error.

Everything that can be prepared is prepared here once (JMESPath expressions, the schema
validator, the sink); per message only the compiled steps run. A pipeline is immutable
and belongs to one configuration generation: a reload builds a new one and swaps it in,
so every message is converted by exactly one generation.
"""

from __future__ import annotations

import asyncio
import os
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable

from engine.common.placeholders import MappingError
from engine.common.schemas import CanonicalSchema, SchemaError, canonical_bytes, parse_json
from engine.endpoints import transport
from engine.endpoints.base import Inbound, MessageRejected, Outbound, Sink
from engine.language.mapping import Mapper, compile_mapping
from engine.language.stores import Remembers, Stores
from engine.running.dedupe import Dedupe, SeenKeys
from engine.running.delivery import ConversionError
from engine.running.fanout import NoSinkChosen, SinkChoice, compiler, passes
from engine.running.replies import ReplyShape
from engine.running.throttle import Throttle
from engine.running.windows import Window, Windowed

if TYPE_CHECKING:
    from engine.language.specs import RouteSpec

__all__ = ["ConversionError", "Filtered", "Pipeline", "Windowed", "passes"]


class Filtered(Exception):
    """The route's ``when:`` rejected the message: it is settled unsent, counted ``filtered``,
    never dead-lettered (a condition that says no is the route working, not failing).
    ``canonical``: the message the condition read (for the tap)."""

    def __init__(self, canonical: Any) -> None:
        super().__init__("filtered")
        self.canonical = canonical


@dataclass(eq=False)
class Pipeline:
    route: str
    generation: int
    spec: RouteSpec
    schema: CanonicalSchema
    sink: Sink
    mapper: Mapper | None = None
    sink_mapper: Mapper | None = None
    sink_check: Callable[[Any], None] | None = None
    """What the sink refuses in the sink mapping's output (MessageRejected), or None."""
    throttle: Throttle[Any] | None = None
    """The route's throttle stage (engine/running/throttle.py): one per generation, closed when it retires."""
    reply_shape: ReplyShape = field(default_factory=lambda: ReplyShape(None, None))
    """The route's ``reply:`` mapping and schema (engine/running/replies.py), compiled with the rest."""
    captured: tuple[str, ...] = ()
    """The names the source captures (``Transport.source_variables``), handed to the sink's templates."""
    remember: Remembers | None = None
    """Where the route keeps its canonical messages, and when (``remember:``, engine/language/stores.py)."""
    condition: Mapper | None = None
    """The route's ``when:``, compiled: evaluated on the canonical message (and meta), a false-like
    result settles the message as ``filtered`` (:class:`Filtered`) before the sink mapping runs.
    Measured (bench/bench_convert.py's weeds route, 2 loaded cores): 1-2 us a message for a
    two-clause condition, beside the 4.5 us of the conversion."""
    dedupe: Dedupe | None = None
    """The route's ``dedupe:`` (engine/running/dedupe.py): its key, and the keys its sink accepted."""
    window: Window | None = None
    """The route's ``window:`` (engine/running/windows.py): its messages are aggregated, and what
    the sink mapping and the sink get is each closed window's message."""
    sink_connection: Any = None
    """The connection of the route's one sink, which the runner asks before sending (the
    engine sets it); None for a route with several sinks (engine/running/fanout.py), whose
    sink asks each of its own."""
    sink_names: tuple[str, ...] | None = None
    """The names of the route's several sinks (its :class:`SinkChoice`'s); None for one sink."""
    in_flight: int = 0
    _drained: asyncio.Event = field(default_factory=asyncio.Event)

    @classmethod
    def compile(cls, spec: RouteSpec, generation: int, schema: CanonicalSchema, sink: Sink,
                reply_schema: CanonicalSchema | None = None, stores: Stores | None = None,
                seen_keys: SeenKeys | None = None) -> Pipeline:
        """``stores``: the engine's (engine/language/stores.py), which ``recall()``, ``sequence()`` and
        ``remember:`` use; a fresh, empty set when None (a route test gives its own). ``seen_keys``:
        the keys the route's sink accepted (``dedupe:``; the engine's, kept across reloads)."""
        stores = stores if stores is not None else Stores()
        if spec.sinks:  # several sinks: each maps and checks its own (engine/running/fanout.py)
            sink_mapper: Any = SinkChoice(spec.sinks, compiler(spec, stores))
            sink_check, sink_names = None, sink_mapper.names
        else:
            sink_mapper = compile_mapping(spec.sink_mapping, spec.variables, stores, spec.name)
            sink_check = transport(spec.sink.protocol).sink_field_check(spec.sink.options, spec.sink_mapping)
            sink_names = None
        return cls(
            route=spec.name,
            generation=generation,
            spec=spec,
            schema=schema,
            sink=sink,
            mapper=compile_mapping(spec.mapping, spec.variables, stores, spec.name),
            sink_mapper=sink_mapper,
            sink_check=sink_check,
            sink_names=sink_names,
            throttle=Throttle.from_options(spec.throttle),
            reply_shape=ReplyShape(spec.reply, reply_schema),
            captured=transport(spec.source.protocol).source_variables(spec.source.options),
            remember=Remembers.compile(spec.remember, stores,
                                       lambda value: compile_mapping(value, spec.variables, stores, spec.name)),
            condition=compile_mapping(spec.when, spec.variables, stores, spec.name),
            dedupe=Dedupe.compile(spec.dedupe, seen_keys, spec.variables, stores, spec.name),
            window=Window.compile(spec.window, spec.variables, stores, spec.name),
        )

    def convert(self, inbound: Inbound) -> Outbound:
        """Raise ConversionError naming the stage for anything that goes wrong, expected or
        not (a RecursionError from deeply nested JSON is as permanent as a syntax error);
        :class:`Filtered` when the route's ``when:`` says no (after the schema, before the sink
        mapping: a condition reads the canonical message, and a filtered one costs no sink mapping)."""
        body = inbound.body
        if body is not None:
            try:
                data: Any = parse_json(body)
            except SchemaError as exc:
                raise ConversionError("decode", str(exc)) from None
            except Exception as exc:
                raise ConversionError("decode", _unexpected(exc)) from None
        else:
            data = inbound.fields
        if self.mapper is not None:
            try:
                data = self.mapper(data, inbound.meta)
            except MappingError as exc:
                raise ConversionError("mapping", str(exc)) from None
            except Exception as exc:
                raise ConversionError("mapping", _unexpected(exc)) from None
            body = None
        try:
            self.schema.validate(data)
            if body is None:
                body = canonical_bytes(data)
        except SchemaError as exc:
            raise ConversionError("schema", str(exc), data) from None
        except Exception as exc:
            raise ConversionError("schema", _unexpected(exc), data) from None
        if self.condition is not None:
            try:
                verdict = self.condition(data, inbound.meta)
            except MappingError as exc:
                raise ConversionError("when", str(exc), data) from None
            except Exception as exc:
                raise ConversionError("when", _unexpected(exc), data) from None
            if not passes(verdict):
                raise Filtered(data)
        if self.window is not None:  # aggregated: the sink mapping reads the window's message
            try:
                windowed = self.window.evaluate(data, inbound.meta)
            except MappingError as exc:
                raise ConversionError("window", str(exc)) from None
            except Exception as exc:
                raise ConversionError("window", _unexpected(exc)) from None
            raise windowed
        return self._outbound(body, data, inbound.meta)

    def window_output(self, emitted: dict[str, Any], meta: dict[str, Any]) -> Outbound:
        """A closed window's message, taken through the sink mapping as a canonical message is
        (ConversionError ``sink mapping`` when it fails)."""
        return self._outbound(canonical_bytes(emitted), emitted, meta)

    def _outbound(self, body: bytes, data: Any, meta: dict[str, Any]) -> Outbound:
        """The sink mapping and the sink's field check, then the message the sink is given."""
        fields = self._sink_fields(data, meta)
        # meta: the source's own dict for this message: extended, not copied
        meta["route"] = self.route
        meta["generation"] = self.generation
        return Outbound(
            body=body,
            canonical=data,
            fields=fields,
            message_id=meta.get("message_id") or new_message_id(),
            meta=meta,
            captured={name: meta[name] for name in self.captured if name in meta} if self.captured else None,
        )

    def remap(self, outbound: Outbound) -> None:
        """Make ``outbound``'s fields again with this pipeline's sink mapping (a message held
        across a reload that changed the route's sinks: engine/running/held.py); ConversionError
        ``sink mapping`` when it cannot (no sink's ``when:`` chooses it any more, too)."""
        meta: dict[str, Any] = outbound.meta  # type: ignore[assignment]  # the source's own dict
        try:
            outbound.fields = self._sink_fields(outbound.canonical, meta)
        except Filtered:
            raise ConversionError("sink mapping", "no sink's when: chooses it (held while a reload changed the route's sinks)",
                                  outbound.canonical) from None
        meta["generation"] = self.generation

    def _sink_fields(self, data: Any, meta: dict[str, Any]) -> Any:
        """What the sink (or each chosen sink) is given: the sink mapping's output, checked."""
        fields = data
        if self.sink_mapper is not None or self.sink_check is not None:
            try:
                if self.sink_mapper is not None:
                    fields = self.sink_mapper(data, meta)
                if self.sink_check is not None:
                    self.sink_check(fields)
            except (MappingError, MessageRejected) as exc:
                raise ConversionError("sink mapping", str(exc), data) from None
            except NoSinkChosen:  # several sinks, and no sink's when: chose it
                raise Filtered(data) from None
            except Exception as exc:
                raise ConversionError("sink mapping", _unexpected(exc), data) from None
        return fields

    def cancel_request(self, inbound: Inbound) -> Outbound:
        """A cancel for a sink that understands it (``Sink.cancels``): not converted, as its
        body is not a request (engine/endpoints/base.py)."""
        meta = inbound.meta
        meta["route"] = self.route
        meta["generation"] = self.generation
        return Outbound(body=b"", canonical=None, fields=None,
                        message_id=meta.get("message_id") or new_message_id(), meta=meta)

    def enter(self) -> None:
        self.in_flight += 1
        self._drained.clear()

    def leave(self) -> None:
        self.in_flight -= 1
        if self.in_flight == 0:
            self._drained.set()

    async def drained(self) -> None:
        """Wait until every message this pipeline started has been settled."""
        if self.in_flight:
            await self._drained.wait()


_IDS: list[str] = []
"""Random message ids drawn 256 at a time: ``os.urandom(16).hex()`` per message cost 0.9 us
(measured in the AMQP -> ROS 2 path, a getrandom call each), the pool's ``pop`` a few
hundredths of that. ``list.pop`` is atomic, so no two callers get one id; a forked child
starts with an empty pool, so it never repeats its parent's."""


def new_message_id() -> str:
    """A message id for a message that came without one: 128 random bits, 32 hex digits."""
    try:
        return _IDS.pop()
    except IndexError:
        pool = os.urandom(16 * 256).hex()
        _IDS.extend([pool[i:i + 32] for i in range(0, len(pool), 32)])
        return _IDS.pop()


os.register_at_fork(after_in_child=_IDS.clear)


def _unexpected(exc: BaseException) -> str:
    text = str(exc)
    return f"{type(exc).__name__}: {text[:200]}" if text else type(exc).__name__
