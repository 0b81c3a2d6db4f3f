"""What each route carried: the route's one set of counters, a latency histogram, and live taps.

A route's :class:`RouteObserver` is the only place its message counts are kept: the log's
``route counters`` line, the status (``engine status``, ``--status-file``, ``/status``),
``/metrics`` and the taps all read these fields, so they cannot disagree. The route counts
a message ``received`` once, when its source hands it over, and then exactly one of
``delivered`` (the sink took it, at once, after a throttle slot opened or from the buffer),
``refused`` (the destination answered no, a vehicle's DENIED: an answer, replied to the
caller, not a dead letter), ``dead_lettered`` (per stage), ``conflated`` (a newer one replaced it under ``throttle``, or
in the buffer under ``latest_only``), ``expired`` (older than the route's ``max_age`` when it
would have been sent: never delivered), ``filtered`` (the route's ``when:`` said no),
``duplicates`` (its ``dedupe:`` key was accepted within the ttl), ``windowed`` (added to its
``window:``'s open window: engine/running/windows.py), unless it is still in flight (parked, held in the buffer, being retried). Beside those:
``retries`` (a message tried again after a transient sink failure: the tap's and
Prometheus' ``redelivered`` outcome), ``sink_errors`` (transient sink failures, including
the last one before a message is dead-lettered), ``unroutable`` (sends the destination routed
to nobody, each attempt: an AMQP sink's returned messages), ``dropped`` (by a source: overflow, or
unsettled at stop), ``dropped_by_agent`` (the part of ``dropped`` a ``fair:`` route's
per-agent queues dropped, by agent: engine/running/fairness.py), ``standby_skipped`` and
``dead_letter_errors``, and ``emitted``: the messages a ``window:`` route's closed windows made,
each then counted ``delivered`` once its sink took it (or dead-lettered), so on such a route
``delivered`` counts windows, not inputs.

A recording (``--record``, engine/running/record.py) is one more observer of the same calls:
what ``took`` and ``accepted`` see is handed to its queue.

The calls are the whole cost on the hot path: a few integer increments and, for delivered
messages, a bisect into the latency buckets. Nothing is formatted or logged per message;
the Prometheus collector and ``/status`` read these counters when asked. A tap
(``GET /tap/{route}``) costs one JSON serialisation per message while at least one is
attached, and nothing otherwise; each tap client has a bounded buffer, and what a slow
client cannot take is dropped and counted, never waited for.

A watcher (``watchers``: the Foxglove view's channels, engine/ops/foxglove.py) is called with
each message the sink took; it is attached only while someone looks (a Foxglove client
subscribed), so with none the cost is the one truth test ``if self.watchers``.

A route with several sinks (``sinks:``, engine/running/fanout.py) also counts per sink, here
too (:class:`SinkCounts`, by sink name, kept across reloads like the rest): what each sink (or
fallback) took, refused for good, handed to its fallback, and had returned unroutable. They
say where the route's messages went; the route's own counts above stay one per message.

Observers are kept per route name across reloads, so counters stay monotonic for Prometheus
while a route's pipeline or source is swapped.

For the web console (engine/ops/console.py) the observers also keep, for every route together,
two small bounded views (engine/running/recent.py): the most recent dead letters (:class:`RecentDeadLetters`: route, stage,
reason, time; one deque append per dead letter) and the fleet (:class:`Fleet`: the last canonical
position of each ``agent_id`` from the routes whose schema is ``position``; one dict store per
delivered position, nothing on other routes). Neither logs nor formats anything per message.
"""

from __future__ import annotations

import asyncio
import time
from bisect import bisect_left
from collections import deque
from typing import TYPE_CHECKING, Any, Callable, Sequence

import orjson

from engine.common.json_bytes import json_bytes
from engine.endpoints.base import Inbound, Outbound
from engine.running.recent import Fleet, RecentDeadLetters, is_position_schema

if TYPE_CHECKING:
    from engine.running.record import RouteRecording

RECEIVED, DELIVERED, REFUSED, DEAD_LETTERED, REDELIVERED, CONFLATED, EXPIRED, DROPPED, FILTERED, DUPLICATES, WINDOWED = (
    "received", "delivered", "refused", "dead_lettered", "redelivered", "conflated", "expired", "dropped", "filtered",
    "duplicates", "windowed")
OUTCOMES = (RECEIVED, DELIVERED, REFUSED, DEAD_LETTERED, REDELIVERED, CONFLATED, EXPIRED, DROPPED, FILTERED, DUPLICATES, WINDOWED)
"""The ``outcome`` label of ``rabbitros_messages_total`` and the keys of the status' ``messages``."""
COUNTERS = ("received", "delivered", "refused", "failed", "conflated", "expired", "filtered", "duplicates", "windowed", "emitted",
            "retries", "sink_errors", "unroutable", "dropped", "standby_skipped", "dead_letter_errors")
"""The integer counters, as the status and the log's ``route counters`` line name them."""
LATENCY_BUCKETS = (0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
"""Seconds from reception to the sink's acceptance: sub-millisecond conversion on a LAN up to
the seconds a SiK radio's tunnel takes."""
_ORJSON_OPTIONS = orjson.OPT_NON_STR_KEYS | orjson.OPT_SERIALIZE_NUMPY | orjson.OPT_APPEND_NEWLINE
TAP_BUFFER = 1000
"""Lines a tap client may fall behind before its lines are dropped (and counted)."""


class Tap:
    """One client of ``/tap/{route}``: a bounded queue of JSON lines."""

    def __init__(self, route: str, size: int = TAP_BUFFER) -> None:
        self.route = route
        self.lines: asyncio.Queue[bytes] = asyncio.Queue(size)
        self.dropped = 0

    @property
    def full(self) -> bool:
        return self.lines.full()

    def offer(self, line: bytes) -> None:
        try:
            self.lines.put_nowait(line)
        except asyncio.QueueFull:
            self.dropped += 1


SINK_OUTCOMES = ("delivered", "refused", "to_fallback", "unroutable")
"""The per-sink counts (:class:`SinkCounts`): the ``outcome`` label of ``rabbitros_sink_messages_total``."""


class SinkCounts:
    """One sink's counts on a route with several (engine/running/fanout.py increments them):
    ``delivered`` (it, or as a fallback it, took a copy), ``refused`` (refused for good: the
    message's dead letter names it), ``to_fallback`` (copies handed to its fallback: while it
    could not take them, or what it refused or had returned), ``unroutable`` (returns: sends
    the destination routed to nobody, each attempt)."""

    __slots__ = SINK_OUTCOMES

    def __init__(self) -> None:
        self.delivered = 0
        self.refused = 0
        self.to_fallback = 0
        self.unroutable = 0

    def as_dict(self) -> dict[str, int]:
        return {name: getattr(self, name) for name in SINK_OUTCOMES}


class RouteObserver:
    """The counters of one route (see the module docstring) and its taps."""

    def __init__(self, route: str, recent: RecentDeadLetters | None = None, fleet: Fleet | None = None) -> None:
        self.route = route
        self.recent_dead_letters = recent
        """Shared by every route (:class:`Observers`); None: not kept."""
        self.fleet: Fleet | None = None
        """The shared :class:`Fleet`, once :meth:`carries` is told this route's schema is a position's."""
        self._fleet = fleet
        self.received = 0
        self.delivered = 0
        self.refused = 0
        """Messages the destination answered with a refusal (engine/endpoints/base.py ``Refused``)."""
        self.conflated = 0
        self.expired = 0
        self.filtered = 0
        """Settled unsent because the route's ``when:`` said no."""
        self.duplicates = 0
        """Settled unsent because the route's ``dedupe:`` key was accepted within its ttl."""
        self.windowed = 0
        """Added to the route's open ``window:`` (settled at the source then)."""
        self.emitted = 0
        """Messages the route's closed windows made (each then delivered, or dead-lettered)."""
        self.retries = 0
        self.sink_errors = 0
        self.unroutable = 0
        """Sends the destination routed to nobody (an AMQP exchange without a queue bound for the
        routing key, published mandatory), each attempt: held or dead-lettered, never delivered."""
        self.dropped = 0
        self.standby_skipped = 0
        self.dead_letter_errors = 0
        self.dropped_by_agent: dict[str, int] = {}
        """Of ``dropped``: what a ``fair:`` route dropped from each agent's queue, by agent."""
        self.sinks: dict[str, SinkCounts] = {}
        """A route with several sinks: each sink's (and fallback's) counts, by name (:meth:`sink`)."""
        self.dead_lettered: dict[str, int] = {}
        """Dead-lettered messages by stage (decode, size, mapping, schema, sink mapping, sink)."""
        self.latency_buckets = [0] * (len(LATENCY_BUCKETS) + 1)
        self.latency_ns_total = 0
        """Sum over delivered messages of reception to the sink's acceptance (the paper's
        t2 - t1), so the mean is available without the histogram."""
        self.latency_ns_max = 0
        self.last_error: str | None = None
        self.last_error_at: float | None = None
        self.last_canonical: Any = None
        self.last_at: float | None = None
        self.taps: list[Tap] = []
        self.tap_dropped = 0
        self.generation: Callable[[], int] = lambda: 0
        """Set by the runner: the generation of the pipeline converting now."""
        self.recording: RouteRecording | None = None
        """Set by the engine under ``--record`` (engine/running/record.py), unless the route says
        ``record: false``: it gets what the route received and the canonical messages it sent."""
        self.watchers: tuple[Callable[[Outbound], None], ...] = ()
        """Called with every message the sink took, while attached (replaced whole, never
        mutated, so another thread may attach one: engine/ops/foxglove.py)."""

    @property
    def failed(self) -> int:
        return sum(self.dead_lettered.values())

    # -- the hot path: integer increments, and a tap line only while a tap is attached

    def took(self, count: int, inbounds: Sequence[Inbound] = ()) -> None:
        self.received += count
        if self.recording is not None:
            self.recording.received(inbounds)

    def agent_dropped(self, agent: Any, count: int = 1) -> None:
        """A fair route dropped ``count`` of ``agent``'s messages (counted in ``dropped`` too)."""
        key = str(agent)
        self.dropped_by_agent[key] = self.dropped_by_agent.get(key, 0) + count

    def accepted(self, inbound: Inbound | None, outbound: Outbound, latency_ns: int | None) -> None:
        """The sink took ``outbound``; ``latency_ns`` from its reception (None: unknown)."""
        self.delivered += 1
        if latency_ns is not None:
            self.latency_ns_total += latency_ns
            if latency_ns > self.latency_ns_max:
                self.latency_ns_max = latency_ns
            self.latency_buckets[bisect_left(LATENCY_BUCKETS, latency_ns / 1e9)] += 1
        self.last_canonical = outbound.canonical
        self.last_at = time.time()
        if self.fleet is not None:
            self.fleet.heard(outbound.canonical, self.route, self.last_at)
        if self.recording is not None:
            self.recording.sent(outbound)
        if self.taps:
            self._tap(inbound, outbound, DELIVERED, None)
        if self.watchers:
            for watcher in self.watchers:
                watcher(outbound)

    def retrying(self, inbound: Inbound | None, outbound: Outbound, error: BaseException) -> None:
        self.retries += 1
        self._error(error)
        if self.taps:
            self._tap(inbound, outbound, REDELIVERED, error)

    def refuse(self, inbound: Inbound | None, outbound: Outbound) -> None:
        """The destination refused ``outbound`` (its answer went back to the caller)."""
        self.refused += 1
        if self.taps:
            self._tap(inbound, outbound, REFUSED, None)

    def conflate(self, inbound: Inbound | None, outbound: Outbound) -> None:
        self.conflated += 1
        if self.taps:
            self._tap(inbound, outbound, CONFLATED, None)

    def expire(self, inbound: Inbound | None, outbound: Outbound) -> None:
        """``outbound`` was older than the route's ``max_age`` when it would have been sent."""
        self.expired += 1
        if self.taps:
            self._tap(inbound, outbound, EXPIRED, None)

    def filter(self, inbound: Inbound, canonical: Any = None) -> None:
        """The route's ``when:`` rejected ``inbound`` (``canonical``, what it read): settled unsent."""
        self.filtered += 1
        if self.taps:
            self._tap(inbound, None, FILTERED, None, canonical)

    def duplicate(self, inbound: Inbound | None, outbound: Outbound) -> None:
        """``outbound``'s ``dedupe:`` key was accepted within the ttl: settled unsent."""
        self.duplicates += 1
        if self.taps:
            self._tap(inbound, outbound, DUPLICATES, None)

    def window(self, inbound: Inbound, canonical: Any) -> None:
        """``inbound`` (``canonical``) was added to the route's open window: settled, aggregated."""
        self.windowed += 1
        if self.taps:
            self._tap(inbound, None, WINDOWED, None, canonical)

    def dead_letter(self, inbound: Inbound | None, outbound: Outbound | None, stage: str, error: str) -> None:
        self.dead_lettered[stage] = self.dead_lettered.get(stage, 0) + 1
        self.last_error = f"{stage}: {error}"
        self.last_error_at = time.time()
        if self.recent_dead_letters is not None:
            self.recent_dead_letters.add(self.route, stage, str(error))
        if self.taps:
            self._tap(inbound, outbound, DEAD_LETTERED, self.last_error)

    def sink(self, name: str) -> SinkCounts:
        """The counts of the route's sink ``name`` (made at its first use: a fan-out asks once,
        when it opens, and increments them on the hot path)."""
        counts = self.sinks.get(name)
        if counts is None:
            counts = self.sinks[name] = SinkCounts()
        return counts

    def carries(self, schema: str | None) -> None:
        """The route's canonical schema (set by the runner, again on a reload): a position's
        draws the fleet."""
        self.fleet = self._fleet if is_position_schema(schema) else None

    def _error(self, error: BaseException) -> None:
        self.last_error = str(error)
        self.last_error_at = time.time()

    def __call__(self, inbound: Inbound, outbound: Outbound | None, outcome: str, error: BaseException | None) -> None:
        """Record one outcome by name (tools and benchmarks; the route calls the methods)."""
        if outcome == DELIVERED and outbound is not None:
            self.accepted(inbound, outbound, time.monotonic_ns() - inbound.received_ns)
        elif outcome == REDELIVERED and outbound is not None and error is not None:
            self.retrying(inbound, outbound, error)
        elif outcome == REFUSED and outbound is not None:
            self.refuse(inbound, outbound)
        elif outcome == CONFLATED and outbound is not None:
            self.conflate(inbound, outbound)
        elif outcome == EXPIRED and outbound is not None:
            self.expire(inbound, outbound)
        elif outcome == FILTERED:
            self.filter(inbound)
        elif outcome == DUPLICATES and outbound is not None:
            self.duplicate(inbound, outbound)
        elif outcome == DEAD_LETTERED:
            self.dead_letter(inbound, outbound, getattr(error, "stage", "sink"), getattr(error, "detail", str(error)))
        else:
            raise ValueError(f"not an outcome of a message: {outcome!r}")

    def _tap(self, inbound: Inbound | None, outbound: Outbound | None, outcome: str, error: BaseException | str | None,
             canonical: Any = None) -> None:
        taps = self.taps
        if all(tap.full for tap in taps):  # nobody can take it: count, do not serialise
            for tap in taps:
                tap.dropped += 1
            return
        record = {
            "ts": time.time(),
            "route": self.route,
            "generation": outbound.meta.get("generation") if outbound is not None else self.generation(),
            "source": source_view(inbound) if inbound is not None else None,
            "canonical": outbound.canonical if outbound is not None else canonical,
            "outcome": outcome,
            "error": None if error is None else str(error),
        }
        line = json_bytes(record, _ORJSON_OPTIONS)  # not orjson alone: a value it refuses must not fail the route
        for tap in taps:
            tap.offer(line)

    def attach(self, tap: Tap) -> None:
        self.taps = [*self.taps, tap]

    def detach(self, tap: Tap) -> None:
        self.taps = [t for t in self.taps if t is not tap]
        self.tap_dropped += tap.dropped

    # -- the views: every one reads the fields above

    def counters(self) -> dict[str, Any]:
        """The counters by the names the status and the log line use."""
        return {**{name: getattr(self, name) for name in COUNTERS}, "dead_lettered": dict(self.dead_lettered),
                "dropped_by_agent": dict(self.dropped_by_agent),
                "latency_ns_total": self.latency_ns_total, "latency_ns_max": self.latency_ns_max}

    def outcomes(self) -> dict[str, int]:
        """The counters by outcome (``rabbitros_messages_total``, the status' ``messages``)."""
        return {RECEIVED: self.received, DELIVERED: self.delivered, REFUSED: self.refused, DEAD_LETTERED: self.failed,
                REDELIVERED: self.retries, CONFLATED: self.conflated, EXPIRED: self.expired,
                DROPPED: self.dropped, FILTERED: self.filtered, DUPLICATES: self.duplicates, WINDOWED: self.windowed}

    def snapshot(self) -> dict[str, Any]:
        """What ``/status`` shows beside the counters."""
        latency = sum(self.latency_buckets)
        return {
            "messages": self.outcomes(),
            "dead_letters": dict(self.dead_lettered),
            "latency_mean_s": self.latency_ns_total / latency / 1e9 if latency else None,
            "last_error": self.last_error,
            "last_error_at": self.last_error_at,
            "last_canonical": self.last_canonical,
            "last_at": self.last_at,
            "taps": len(self.taps),
            "tap_dropped": self.tap_dropped + sum(t.dropped for t in self.taps),
        }


def source_view(inbound: Inbound) -> Any:
    """The message as received, as JSON: the parsed body, its text if it is not JSON, or the
    typed source's fields."""
    if inbound.body is None:
        return inbound.fields
    try:
        return orjson.loads(inbound.body)
    except orjson.JSONDecodeError:
        return inbound.body.decode("utf-8", errors="replace")


class Observers:
    """Every route's observer, by route name, kept across reloads; and per-route rates."""

    def __init__(self) -> None:
        self.routes: dict[str, RouteObserver] = {}
        self.recent_dead_letters = RecentDeadLetters()
        self.fleet = Fleet()
        self._samples: dict[str, deque[tuple[float, int, int]]] = {}

    def get(self, route: str) -> RouteObserver:
        observer = self.routes.get(route)
        if observer is None:
            observer = self.routes[route] = RouteObserver(route, self.recent_dead_letters, self.fleet)
        return observer

    def sample(self, now: float | None = None, window: int = 5) -> None:
        """Record the counts now; rates are over the last ``window`` samples (call every second)."""
        now = time.monotonic() if now is None else now
        for name, observer in self.routes.items():
            samples = self._samples.setdefault(name, deque(maxlen=window + 1))
            samples.append((now, observer.received, observer.delivered))

    def rates(self, route: str) -> dict[str, float]:
        samples = self._samples.get(route)
        if not samples or len(samples) < 2:
            return {"received_per_s": 0.0, "delivered_per_s": 0.0}
        (t0, r0, d0), (t1, r1, d1) = samples[0], samples[-1]
        span = max(t1 - t0, 1e-9)
        return {"received_per_s": round((r1 - r0) / span, 3), "delivered_per_s": round((d1 - d0) / span, 3)}
