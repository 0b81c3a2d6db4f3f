"""Named latest-value stores and per-route sequences: what a mapping may know beyond its message.

A route converts one message at a time, and some outputs need the latest values of several
messages: a VDA 5050 ``state`` takes the battery from one message, the position from another,
the order from a third. A route with ``remember: {store: NAME, per: FIELD}`` keeps its
canonical message, once the sink accepted it, as the latest value of store NAME under the key
its field FIELD holds; any route's mapping reads it with ``recall('NAME', key)`` (null when
nothing is known yet, or when the value is older than the store's ``max_age``). This is the
shape of Redpanda Connect's cache resources (a cache output or processor writes, the
``cache`` processor's ``get`` reads) and Vector's memory enrichment table (fed as a sink, read
by ``get_enrichment_table_record``), kept to what routes need: in memory, latest value only.

Remembered on acceptance, not on conversion, so a store holds what actually went on: an order
the vehicle refused (a dead letter) is never the order a ``state`` reports. ``sequence()``
counts the messages a route's mapping converted, 1, 2, 3... (VDA 5050's ``headerId``).

Keyed state several routes update (a VDA 5050 action's state: RUNNING when the engine took
the action, FINISHED once the vehicle acknowledged it, FAILED when it refused) is the same
store written at other moments and with a computed value: ``remember`` takes a list, and an
entry may say ``when`` (``converted``: the mapping gave the canonical message; ``accepted``,
the default; ``failed``: the message became a dead letter once its mapping had given the
canonical message, refused by the schema, ``when:`` or the sink mapping or failed at the sink;
``meta('failure')`` then says why, as ``stage: error``) and ``value`` (a mapping from the canonical message to what is kept, which
may ``recall()`` the value so far to append to it or merge into it; null forgets the key).
Nothing here knows a protocol: the routes say what the states are. Each update is applied at
once, on the event loop, so two routes updating one key never interleave within an update.

One :class:`Stores` per engine, so both survive reloads (a route restarted by an edit keeps
counting; a state route reloaded keeps knowing the order); a restart starts them empty. Per
message a write is one dict store and a read one or two dict lookups: the store and the
counter a mapping uses are resolved when it compiles.
"""

from __future__ import annotations

import itertools
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Iterator, Literal, Mapping

from engine.common.field_keys import FIELD_PATH, slot_key
from engine.common.options import option

log = logging.getLogger(__name__)

RECALL_FUNCTION = "recall"
SEQUENCE_FUNCTION = "sequence"
FAILURE_META = "failure"
"""What ``meta()`` names in a ``remember`` value applied ``when: failed``: the dead letter's stage and error."""


@dataclass(frozen=True, kw_only=True)
class RememberOptions:
    """A route's ``remember:`` (see the module docstring)."""

    __schema_description__ = ("keep the route's canonical message, once its sink accepted it, as the latest value of a "
                              "named store, per value of the canonical field 'per'; mappings read it with recall('STORE', key)")

    store: str = option(pattern=r"^[A-Za-z_][A-Za-z0-9_]*$", description="the store's name, read by recall('NAME', key)")
    per: str | None = option(None, pattern=FIELD_PATH, description="canonical field (a.b) whose value is the key; "
                             "none: one value for the store, read by recall('NAME')")
    max_age: float | None = option(None, exclusive_minimum=0, description="seconds after which a remembered value is "
                                   "no longer given (recall answers null): a position stops being reported once stale")
    when: Literal["converted", "accepted", "failed"] = option(
        "accepted", description="when it is kept: converted (the mapping gave the canonical message), accepted (the sink "
                                "took it), failed (it became a dead letter once the mapping gave it: refused by the schema, "
                                "when: or the sink mapping, or failed at the sink; meta('failure') says why, 'stage: error')")
    value: str | None = option(None, description="JMESPath from the canonical message to the value kept (recall() reads "
                               "the value so far: append to it, merge into it); null forgets the key; none: the message")


WHEN = ("converted", "accepted", "failed")
"""The moments a route's message may be remembered, in the order they happen."""


def remember_entries(options: RememberOptions | tuple[RememberOptions, ...] | None) -> tuple[RememberOptions, ...]:
    """A route's ``remember:`` as a tuple of entries (one entry or a list in the route file)."""
    if options is None:
        return ()
    return options if isinstance(options, tuple) else (options,)


class Store:
    """One named store: the latest canonical message per key, with when it was remembered."""

    __slots__ = ("name", "values", "max_age_ns")

    def __init__(self, name: str) -> None:
        self.name = name
        self.values: dict[Any, tuple[Any, int]] = {}
        self.max_age_ns: int | None = None

    def put(self, key: Any, value: Any) -> None:
        self.values[key] = (value, time.monotonic_ns())

    def forget(self, key: Any) -> None:
        self.values.pop(key, None)

    def get(self, key: Any) -> Any:
        found = self.values.get(_hashable(key))
        if found is None:
            return None
        if self.max_age_ns is not None and time.monotonic_ns() - found[1] > self.max_age_ns:
            return None
        return found[0]


class Stores:
    """The engine's stores and sequence counters, by name; created on first use, kept for the
    engine's life (reloads included)."""

    def __init__(self) -> None:
        self._stores: dict[str, Store] = {}
        self._sequences: dict[str, Iterator[int]] = {}

    def store(self, name: str) -> Store:
        store = self._stores.get(name)
        if store is None:
            store = self._stores[name] = Store(name)
        return store

    def sequence(self, route: str) -> Iterator[int]:
        """The counter of ``route`` (by name: a reload that restarts the route goes on counting)."""
        counter = self._sequences.get(route)
        if counter is None:
            counter = self._sequences[route] = itertools.count(1)
        return counter

    def status(self) -> dict[str, int]:
        """How many keys each store holds (the status file's ``stores``)."""
        return {name: len(store.values) for name, store in sorted(self._stores.items())}

    @classmethod
    def given(cls, remembered: Mapping[str, Any], keyed: Mapping[str, bool]) -> Stores:
        """Stores holding what a route test gives (``remembered: {NAME: {KEY: value}}``, or
        ``{NAME: value}`` for a store without ``per``)."""
        stores = cls()
        for name, values in remembered.items():
            store = stores.store(name)
            if keyed.get(name, True) and isinstance(values, Mapping):
                for key, value in values.items():
                    store.put(key, value)
            else:
                store.put(None, values)
        return stores


@dataclass
class Remember:
    """One compiled ``remember:`` entry: where a route's canonical messages go, and what of them."""

    store: Store
    per: tuple[str, ...] | None = field(default=None)
    value: Callable[..., Any] | None = field(default=None)
    """The compiled ``value`` mapping, called as ``value(canonical, meta)``; None: the message itself."""

    @classmethod
    def compile(cls, options: RememberOptions, stores: Stores,
                compile_value: Callable[[str], Callable[..., Any] | None]) -> Remember:
        store = stores.store(options.store)
        if options.max_age is not None:
            store.max_age_ns = int(options.max_age * 1e9)
        return cls(store, tuple(options.per.split(".")) if options.per else None,
                   compile_value(options.value) if options.value is not None else None)

    failed_once: bool = field(default=False)

    def __call__(self, canonical: Any, meta: Mapping[str, Any]) -> None:
        if canonical is None:
            return
        key = slot_key(canonical, self.per)
        try:
            kept = canonical if self.value is None else self.value(canonical, meta)
        except ValueError as error:  # a MappingError: the value so far stays; said once per entry
            if not self.failed_once:
                self.failed_once = True
                log.warning("remember: value failed; the store keeps its value", extra={
                    "store": self.store.name, "error": str(error)})
            return
        if kept is None:
            self.store.forget(key)
        else:
            self.store.put(key, kept)


@dataclass(frozen=True)
class Remembers:
    """A route's compiled ``remember:`` entries, by the moment they apply (``when``)."""

    converted: tuple[Remember, ...] = ()
    accepted: tuple[Remember, ...] = ()
    failed: tuple[Remember, ...] = ()

    @classmethod
    def compile(cls, options: RememberOptions | tuple[RememberOptions, ...] | None, stores: Stores,
                compile_value: Callable[[str], Callable[..., Any] | None]) -> Remembers | None:
        """``compile_value``: how a ``value`` expression becomes a mapper (engine/language/mapping.py's
        compile_mapping with the route's variables and the engine's stores, passed in so this
        module stays below the mapping language)."""
        entries = remember_entries(options)
        if not entries:
            return None
        compiled = [(entry.when, Remember.compile(entry, stores, compile_value)) for entry in entries]
        return cls(*(tuple(remember for when, remember in compiled if when == moment) for moment in WHEN))

    def on_converted(self, canonical: Any, meta: Mapping[str, Any]) -> None:
        for remember in self.converted:
            remember(canonical, meta)

    def on_accepted(self, canonical: Any, meta: Mapping[str, Any]) -> None:
        for remember in self.accepted:
            remember(canonical, meta)

    def on_failed(self, canonical: Any, meta: Mapping[str, Any], failure: str) -> None:
        if not self.failed:
            return
        meta = {**meta, FAILURE_META: failure}  # a dead letter is rare: a copy, read by meta('failure')
        for remember in self.failed:
            remember(canonical, meta)


def _hashable(key: Any) -> Any:
    """A recall key as the store keeps it (slot_key's rule: scalars as they are, else repr)."""
    return key if isinstance(key, (str, int, float, bool)) or key is None else repr(key)
