"""The running engine: connections, one runner per route, and reloads that lose nothing.

A reload compiles the whole directory first; if anything is wrong the running routes are
left exactly as they are. Otherwise only what changed is touched: an unchanged route keeps
its pipeline and its consumer; a route whose source is unchanged keeps its source (its AMQP
consumer, ROS subscription or MAVLink reader) and gets a new pipeline swapped in before the
old one drains (make-before-break); a route whose source changed gets a new source started
before the old one stops and drains. Messages in flight finish on the pipeline that took
them, so each is converted by exactly one configuration generation.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

from engine import endpoints
from engine.delivery import HEALTH_POLL, DeadLetters, Failure, settle
from engine.endpoints.base import Connection, EndpointError, Inbound, Source
from engine.pipeline import Pipeline
from engine.routes import ConnectionSpec, RouteSpec, RoutesConfig, RoutesInvalid, load_routes
from engine.schemas import SchemaRegistry
from engine.logs import Throttle

log = logging.getLogger("engine.runtime")

@dataclass
class RouteStats:
    received: int = 0
    delivered: int = 0
    failed: int = 0
    """Messages dead-lettered (any stage); ``dead_lettered`` splits them by stage."""
    sink_errors: int = 0
    """Transient sink failures (each retried, or dead-lettered after max_attempts)."""
    retries: int = 0
    dropped: int = 0
    """Messages a source dropped: queue overflow, or unsettled at stop and not redeliverable."""
    dead_letter_errors: int = 0
    dead_lettered: dict[str, int] = field(default_factory=dict)
    latency_ns_total: int = 0
    """Sum over delivered messages of the time from reception to the sink's acceptance
    (the paper's t2 - t1), so the mean processing latency is available without a histogram."""
    latency_ns_max: int = 0


@dataclass
class ReloadStats:
    succeeded: int = 0
    rejected: int = 0
    last_error: list[str] = field(default_factory=list)
    last_reload_s: float = 0.0


class RouteRunner:
    """A route's live source and its current pipeline; the pipeline can be swapped.

    The runner is the source's :class:`~engine.endpoints.base.Deliver`: it settles what the
    source hands it with the one delivery policy (engine/delivery.py)."""

    def __init__(
        self, engine: Engine, spec: RouteSpec, pipeline: Pipeline, source: Source, connections: list[Connection]
    ) -> None:
        self.engine = engine
        self.spec = spec
        self.pipeline = pipeline
        self.source = source
        self.connections = connections
        """The source's then the sink's connection: kept open while the runner lives."""
        self.stats = RouteStats()
        self.latency_samples: list[int] | None = None
        """Set to a list to record every message's reception-to-acceptance time (benchmarks)."""
        self._report = Throttle()
        self._retry_report = Throttle()
        self._stopping = asyncio.Event()

    # -- the Deliver contract a source sees

    @property
    def overflow(self) -> str:
        return self.spec.delivery.overflow

    @property
    def queue_limit(self) -> int:
        return self.spec.delivery.queue_limit

    async def batch(self, inbounds: Sequence[Inbound]) -> list[bool]:
        return await settle(self, inbounds)

    async def __call__(self, inbound: Inbound) -> None:
        if not (await settle(self, (inbound,)))[0]:
            raise EndpointError(f"route {self.spec.name!r}: message not settled (route stopping)")

    deliver = __call__

    def dropped(self, count: int = 1) -> None:
        self.stats.dropped += count

    # -- what the delivery policy asks of the route

    def accepted(self, inbound: Inbound) -> None:
        stats = self.stats
        stats.delivered += 1
        latency = time.monotonic_ns() - inbound.received_ns
        stats.latency_ns_total += latency
        if latency > stats.latency_ns_max:
            stats.latency_ns_max = latency
        if self.latency_samples is not None:
            self.latency_samples.append(latency)

    async def sink_ready(self) -> bool:
        """Wait while the sink's connection is known to be down; False once the route stops."""
        sink_connection = self.connections[-1]
        while not self._stopping.is_set() and not sink_connection.healthy:
            await self.pause(HEALTH_POLL)
        return not self._stopping.is_set()

    async def pause(self, seconds: float) -> bool:
        """Sleep between attempts; False (at once) when the route stops meanwhile."""
        try:
            await asyncio.wait_for(self._stopping.wait(), seconds)
        except asyncio.TimeoutError:
            return True
        return False

    def report_retry(self, failure: Failure, count: int) -> None:
        if self._retry_report.ready():
            log.warning(
                "sink failed; retrying with backoff",
                extra={"route": self.spec.name, "error": failure.error, "messages": count,
                       "suppressed": self._retry_report.take_suppressed()},
            )

    def report_failure(self, failure: Failure, count: int = 1) -> None:
        if self._report.ready():
            log.warning(
                "message dead-lettered" if failure.stage != "dead-letter" else "dead letters could not be stored",
                extra={
                    "route": self.spec.name,
                    "file": f"{self.spec.file}:{self.spec.line}",
                    "stage": failure.stage,
                    "error": failure.error[:500],
                    "messages": count,
                    "suppressed": self._report.take_suppressed(),
                },
            )

    async def retire_pipeline(self, pipeline: Pipeline) -> None:
        await pipeline.drained()
        await pipeline.sink.close()

    async def stop(self) -> None:
        self._stopping.set()
        await self.source.stop()
        await self.retire_pipeline(self.pipeline)


class Engine:
    def __init__(self, routes_dir: Path, schemas_dir: Path) -> None:
        self.routes_dir = routes_dir
        self.schemas_dir = schemas_dir
        self.config: RoutesConfig | None = None
        self.generation = 0
        self.runners: dict[str, RouteRunner] = {}
        self.reloads = ReloadStats()
        self.started_at = time.time()
        self._connections: dict[tuple[str, str], Connection] = {}
        self._lock = asyncio.Lock()
        self.dead_letters: DeadLetters | None = None

    def compile(self) -> tuple[RoutesConfig, SchemaRegistry]:
        schemas = SchemaRegistry(self.schemas_dir)
        return load_routes(self.routes_dir, schemas), schemas

    async def start(self) -> None:
        """Load and start every route; raises RoutesInvalid or EndpointError."""
        config, schemas = self.compile()
        async with self._lock:
            await self._apply(config, schemas)

    async def reload(self) -> bool:
        """Apply the directory as it is now; on any problem keep the running routes."""
        async with self._lock:
            began = time.monotonic()
            try:
                config, schemas = self.compile()
            except RoutesInvalid as invalid:
                return self._rejected([str(p) for p in invalid.problems])
            if self.config is not None and config.content_hash == self.config.content_hash:
                return True
            try:
                await self._apply(config, schemas)
            except EndpointError as error:
                return self._rejected([str(error)])
            except Exception as error:  # a reload must never take the running engine down
                log.exception("reload failed")
                return self._rejected([f"{type(error).__name__}: {error}"])
            self.reloads.succeeded += 1
            self.reloads.last_error = []
            self.reloads.last_reload_s = time.monotonic() - began
            return True

    def _rejected(self, problems: list[str]) -> bool:
        self.reloads.rejected += 1
        self.reloads.last_error = problems
        log.error(
            "reload rejected; previous routes keep running",
            extra={"generation": self.generation, "problems": problems},
        )
        return False

    async def _connection(self, spec: ConnectionSpec) -> Connection:
        key = (spec.name, json.dumps(spec.settings, sort_keys=True, default=str))
        connection = self._connections.get(key)
        if connection is None:
            connection = endpoints.transport(spec.protocol).connect(spec.name, spec.settings)
            await connection.open()
            self._connections[key] = connection
        return connection

    async def _pipeline(
        self, config: RoutesConfig, schemas: SchemaRegistry, spec: RouteSpec, generation: int
    ) -> tuple[Pipeline, Connection]:
        connection = await self._connection(config.connections[spec.sink.connection])
        schema = schemas.get(spec.schema)
        assert schema is not None
        return Pipeline.compile(spec, generation, schema, connection.sink(spec.name, spec.sink.options)), connection

    async def _apply(self, config: RoutesConfig, schemas: SchemaRegistry) -> None:
        generation = self.generation + 1
        previous = self.config
        keep: dict[str, RouteRunner] = {}
        swaps: list[tuple[RouteRunner, Pipeline, Connection]] = []
        fresh: list[RouteRunner] = []
        dead_letters = self.dead_letters
        try:
            self.dead_letters = await self._dead_letters(config)
            for name, spec in config.routes.items():
                old = self.runners.get(name)
                if old is not None and old.spec.fingerprint == spec.fingerprint:
                    keep[name] = old
                    continue
                pipeline, sink_connection = await self._pipeline(config, schemas, spec, generation)
                if old is not None and previous is not None and _same_source(previous, old.spec, config, spec):
                    swaps.append((old, pipeline, sink_connection))
                    continue
                source_connection = await self._connection(config.connections[spec.source.connection])
                source = source_connection.source(name, spec.source.options)
                fresh.append(RouteRunner(self, spec, pipeline, source, [source_connection, sink_connection]))
            await _start_sources(fresh)
        except BaseException:
            self.dead_letters = dead_letters
            await asyncio.gather(
                *(runner.source.stop() for runner in fresh),
                *(pipeline.sink.close() for pipeline in [r.pipeline for r in fresh] + [p for _, p, _ in swaps]),
                return_exceptions=True,
            )
            await self._close_unused(self.runners.values())
            raise

        retired = []
        for runner, pipeline, sink_connection in swaps:
            retired.append(runner.retire_pipeline(runner.pipeline))
            runner.spec, runner.pipeline = pipeline.spec, pipeline
            runner.connections = [runner.connections[0], sink_connection]
            keep[runner.spec.name] = runner
        for runner in fresh:
            keep[runner.spec.name] = runner
        stopped = [runner for name, runner in self.runners.items() if keep.get(name) is not runner]
        retired.extend(runner.stop() for runner in stopped)
        if retired:
            await asyncio.gather(*retired)
        self.runners = keep
        self.config = config
        self.generation = generation
        await self._close_unused(keep.values())
        log.info(
            "routes applied",
            extra={
                "generation": generation,
                "config_hash": config.content_hash,
                "routes": len(keep),
                "started": [r.spec.name for r in fresh],
                "swapped": [r.spec.name for r, _, _ in swaps],
                "stopped": [r.spec.name for r in stopped],
            },
        )

    async def _close_unused(self, runners: Any) -> None:
        used = {id(connection) for runner in runners for connection in runner.connections}
        if self.dead_letters is not None and self.dead_letters.connection is not None:
            used.add(id(self.dead_letters.connection))
        for key, connection in list(self._connections.items()):
            if id(connection) not in used:
                del self._connections[key]
                await connection.close()

    async def _dead_letters(self, config: RoutesConfig) -> DeadLetters:
        """The engine's one dead-letter destination, kept when the configuration did not change it."""
        spec = config.dead_letters
        current = self.dead_letters
        connection = None
        if spec.connection is not None:
            connection = await self._connection(config.connections[spec.connection])
        if current is not None and current.spec == spec and current.connection is connection:
            return current
        dead_letters = DeadLetters(spec, connection)
        await dead_letters.prepare()
        return dead_letters

    def dead_letters_for(self, runner: RouteRunner) -> DeadLetters:
        assert self.dead_letters is not None
        return self.dead_letters

    async def stop(self) -> None:
        async with self._lock:
            await asyncio.gather(*(runner.stop() for runner in self.runners.values()), return_exceptions=True)
            for connection in self._connections.values():
                await connection.close()
            self._connections.clear()

    def status(self) -> dict[str, Any]:
        config = self.config
        return {
            "pid": os.getpid(),
            "routes_dir": str(self.routes_dir),
            "generation": self.generation,
            "config_hash": config.content_hash if config else None,
            "reloads": asdict(self.reloads),
            "dead_letters": None if self.dead_letters is None else {
                "destination": self.dead_letters.where,
                "stored": self.dead_letters.stored,
                "spooled": self.dead_letters.spooled,
            },
            "routes": {
                name: {
                    "file": f"{runner.spec.file}:{runner.spec.line}",
                    "fingerprint": runner.spec.fingerprint,
                    "generation": runner.pipeline.generation,
                    **asdict(runner.stats),
                    "source": runner.source.status(),
                }
                for name, runner in sorted(self.runners.items())
            },
        }


def _same_source(previous: RoutesConfig, old: RouteSpec, config: RoutesConfig, new: RouteSpec) -> bool:
    return old.source == new.source and previous.connections.get(old.source.connection) == config.connections.get(
        new.source.connection
    )


SOURCE_START_CONCURRENCY = 64


async def _start_sources(runners: list[RouteRunner]) -> None:
    """Start sources concurrently, a bounded number at a time: each start is a few broker
    (or DDS) round trips, so one after another 1,000 routes took 11 s to load, together 2.
    Every start of a group finishes before the first error is raised, so the caller stops
    exactly the sources that may have started."""
    for first in range(0, len(runners), SOURCE_START_CONCURRENCY):
        group = runners[first:first + SOURCE_START_CONCURRENCY]
        outcomes = await asyncio.gather(*(runner.source.start(runner) for runner in group), return_exceptions=True)
        for outcome in outcomes:
            if isinstance(outcome, BaseException):
                raise outcome
