"""What each route carried: per-route counters, a latency histogram, and live taps.

A :class:`RouteRunner` calls its route's :class:`RouteObserver` once per settled message with
``(inbound, outbound | None, outcome, error)``. The call is the whole cost on the hot path:
a few integer increments and, for delivered messages, a bisect into the latency buckets.
Nothing is formatted or logged per message; the Prometheus collector and ``/status`` read
these counters when asked. A tap (``GET /tap/{route}``) costs one JSON serialisation per
message while at least one is attached, and nothing otherwise; each tap client has a
bounded buffer, and what a slow client cannot take is dropped and counted, never waited for.

Observers are kept per route name across reloads, so counters stay monotonic for Prometheus
while a route's pipeline or source is swapped.
"""

from __future__ import annotations

import asyncio
import time
from bisect import bisect_left
from collections import deque
from typing import Any, Callable

import orjson

from engine.endpoints.base import Inbound, Outbound

RECEIVED, DELIVERED, DEAD_LETTERED, REDELIVERED, CONFLATED = (
    "received", "delivered", "dead_lettered", "redelivered", "conflated")
OUTCOMES = (RECEIVED, DELIVERED, DEAD_LETTERED, REDELIVERED, CONFLATED)
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


class RouteObserver:
    """The counters of one route; called by the runner once per settled message."""

    def __init__(self, route: str) -> None:
        self.route = route
        self.counts = dict.fromkeys(OUTCOMES, 0)
        self.dead_letters: dict[str, int] = {}
        self.latency_buckets = [0] * (len(LATENCY_BUCKETS) + 1)
        self.latency_sum = 0.0
        self.last_error: str | None = None
        self.last_error_at: float | None = None
        self.last_canonical: Any = None
        self.last_at: float | None = None
        self.taps: list[Tap] = []
        self.tap_dropped = 0
        self.generation: Callable[[], int] = lambda: 0
        """Set by the runner: the generation of the pipeline converting now."""

    def __call__(self, inbound: Inbound, outbound: Outbound | None, outcome: str, error: BaseException | None) -> None:
        counts = self.counts
        counts[RECEIVED] += 1
        counts[outcome] += 1
        if outcome == DELIVERED:
            latency = (time.monotonic_ns() - inbound.received_ns) / 1e9
            self.latency_buckets[bisect_left(LATENCY_BUCKETS, latency)] += 1
            self.latency_sum += latency
            self.last_canonical = outbound.canonical if outbound is not None else None
            self.last_at = time.time()
        elif error is not None:
            if outcome == DEAD_LETTERED:
                stage = getattr(error, "stage", "sink")
                self.dead_letters[stage] = self.dead_letters.get(stage, 0) + 1
            self.last_error = str(error)
            self.last_error_at = time.time()
        if self.taps:
            self._tap(inbound, outbound, outcome, error)

    def _tap(self, inbound: Inbound, outbound: Outbound | None, outcome: str, error: BaseException | None) -> None:
        taps = self.taps
        if all(tap.full for tap in taps):  # nobody can take it: count, do not serialise
            for tap in taps:
                tap.dropped += 1
            return
        record = {
            "ts": time.time(),
            "route": self.route,
            "generation": outbound.meta.get("generation") if outbound is not None else self.generation(),
            "source": source_view(inbound),
            "canonical": outbound.canonical if outbound is not None else None,
            "outcome": outcome,
            "error": None if error is None else str(error),
        }
        line = orjson.dumps(record, default=str, option=_ORJSON_OPTIONS)
        for tap in taps:
            tap.offer(line)

    def attach(self, tap: Tap) -> None:
        self.taps = [*self.taps, tap]

    def detach(self, tap: Tap) -> None:
        self.taps = [t for t in self.taps if t is not tap]
        self.tap_dropped += tap.dropped

    def snapshot(self) -> dict[str, Any]:
        """The counters for ``/status``."""
        return {
            "messages": dict(self.counts),
            "dead_letters": dict(self.dead_letters),
            "latency_mean_s": self.latency_sum / self.counts[DELIVERED] if self.counts[DELIVERED] else None,
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
        self._samples: dict[str, deque[tuple[float, int, int]]] = {}

    def get(self, route: str) -> RouteObserver:
        observer = self.routes.get(route)
        if observer is None:
            observer = self.routes[route] = RouteObserver(route)
        return observer

    def sample(self, now: float | None = None, window: int = 5) -> None:
        """Record the counts now; rates are over the last ``window`` samples (call every second)."""
        now = time.monotonic() if now is None else now
        for name, observer in self.routes.items():
            samples = self._samples.setdefault(name, deque(maxlen=window + 1))
            samples.append((now, observer.counts[RECEIVED], observer.counts[DELIVERED]))

    def rates(self, route: str) -> dict[str, float]:
        samples = self._samples.get(route)
        if not samples or len(samples) < 2:
            return {"received_per_s": 0.0, "delivered_per_s": 0.0}
        (t0, r0, d0), (t1, r1, d1) = samples[0], samples[-1]
        span = max(t1 - t0, 1e-9)
        return {"received_per_s": round((r1 - r0) / span, 3), "delivered_per_s": round((d1 - d0) / span, 3)}
