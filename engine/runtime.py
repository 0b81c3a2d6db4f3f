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
from typing import Any

from engine import endpoints
from engine.endpoints.base import Connection, EndpointError, Inbound, MessageRejected, Source
from engine.pipeline import ConversionError, Pipeline
from engine.routes import ConnectionSpec, RouteSpec, RoutesConfig, RoutesInvalid, load_routes
from engine.schemas import SchemaRegistry
from engine.logs import Throttle
from engine.observe import DEAD_LETTERED, DELIVERED, REDELIVERED, Observers

log = logging.getLogger("engine.runtime")

SINK_RETRY_DELAY = 0.5
"""Pause before handing a message back for redelivery after a sink failure, so a
destination that is down is not hammered in a tight loop."""


@dataclass
class RouteStats:
    received: int = 0
    delivered: int = 0
    failed: int = 0
    sink_errors: int = 0
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
    """A route's live source and its current pipeline; the pipeline can be swapped."""

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
        self.observe = engine.observers.get(spec.name)  # ops: metrics, status and taps
        self.observe.generation = lambda: self.pipeline.generation
        self._parked_tasks: set[asyncio.Task[None]] = set()  # ops: throttle

    async def deliver(self, inbound: Inbound) -> None:
        pipeline = self.pipeline
        pipeline.enter()
        self.stats.received += 1
        try:
            try:
                outbound = pipeline.convert(inbound)
            except ConversionError as error:
                self.stats.failed += 1
                await self.engine.dead_letter(self, inbound, error)
                self.observe(inbound, None, DEAD_LETTERED, error)  # ops
                return
            if pipeline.throttle is not None and not pipeline.throttle.admit(inbound, outbound, self):  # ops: throttle
                return  # parked: delivered when its slot opens, or conflated by a newer message
            try:
                await pipeline.sink.send(outbound)
            except MessageRejected as error:
                self.stats.failed += 1
                rejected = ConversionError("sink", str(error))
                await self.engine.dead_letter(self, inbound, rejected)
                self.observe(inbound, outbound, DEAD_LETTERED, rejected)  # ops
                return
            except EndpointError as error:
                self.stats.sink_errors += 1
                self.observe(inbound, outbound, REDELIVERED, error)  # ops
                if self._report.ready():
                    log.error("sink failed; message will be redelivered", extra={"route": self.spec.name, "error": str(error)})
                await asyncio.sleep(SINK_RETRY_DELAY)
                raise
            stats = self.stats
            stats.delivered += 1
            latency = time.monotonic_ns() - inbound.received_ns
            stats.latency_ns_total += latency
            if latency > stats.latency_ns_max:
                stats.latency_ns_max = latency
            if self.latency_samples is not None:
                self.latency_samples.append(latency)
            self.observe(inbound, outbound, DELIVERED, None)  # ops
        finally:
            pipeline.leave()

    def redeliver(self, inbound: Inbound) -> None:
        """ops: a message the throttle parked goes through ``deliver`` again when its slot
        opens; its source was already answered, so a failure here is counted, not retried."""
        task = asyncio.create_task(self.deliver(inbound))
        self._parked_tasks.add(task)
        task.add_done_callback(self._parked_done)

    def _parked_done(self, task: asyncio.Task[None]) -> None:
        self._parked_tasks.discard(task)
        error = None if task.cancelled() else task.exception()
        if error is not None and not isinstance(error, EndpointError):  # EndpointError: counted as redelivered
            log.error("throttled message failed", extra={"route": self.spec.name, "error": repr(error)})

    def report_failure(self, error: ConversionError) -> None:
        if self._report.ready():
            log.warning(
                "message rejected",
                extra={
                    "route": self.spec.name,
                    "file": f"{self.spec.file}:{self.spec.line}",
                    "stage": error.stage,
                    "error": error.detail,
                    "suppressed": self._report.take_suppressed(),
                },
            )

    async def retire_pipeline(self, pipeline: Pipeline) -> None:
        if pipeline.throttle is not None:  # ops: parked messages go out, not lost
            pipeline.throttle.close(self)
            await asyncio.sleep(0)
        await pipeline.drained()
        await pipeline.sink.close()

    async def stop(self) -> None:
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
        self.observers = Observers()  # ops: per-route counters for metrics, status and taps

    def open_connections(self) -> list[tuple[str, Connection]]:
        """ops: ``(protocol, connection)`` of every open connection, for health and metrics."""
        specs = self.config.connections if self.config is not None else {}
        return [(specs[c.name].protocol if c.name in specs else type(c).__module__.rsplit(".", 1)[-1], c)
                for c in self._connections.values()]

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
        try:
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
            for runner in fresh:
                await runner.source.start(runner.deliver)
        except BaseException:
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
        for key, connection in list(self._connections.items()):
            if id(connection) not in used:
                del self._connections[key]
                await connection.close()

    async def dead_letter(self, runner: RouteRunner, inbound: Inbound, error: ConversionError) -> None:
        """Keep a message that cannot be converted: count it, report it, and hand it to the
        first of the route's connections that keeps dead letters (AMQP: a durable queue)."""
        runner.report_failure(error)
        connection = next((c for c in runner.connections if c.keeps_dead_letters), None)
        if connection is None:
            return
        spec = runner.spec
        body = inbound.body if inbound.body is not None else json.dumps(inbound.fields, default=str).encode()
        headers = {
            "x-rabbitros-route": spec.name,
            "x-rabbitros-stage": error.stage,
            "x-rabbitros-error": error.detail[:1000],
            "x-rabbitros-route-file": f"{spec.file}:{spec.line}",
        }
        headers.update(
            {f"x-source-{k}": v for k, v in inbound.meta.items() if isinstance(v, (str, int, float)) and k != "headers"}
        )
        await connection.dead_letter(spec.name, body, headers)

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
            "routes": {
                name: {
                    "file": f"{runner.spec.file}:{runner.spec.line}",
                    "fingerprint": runner.spec.fingerprint,
                    "generation": runner.pipeline.generation,
                    **asdict(runner.stats),
                }
                for name, runner in sorted(self.runners.items())
            },
        }


def _same_source(previous: RoutesConfig, old: RouteSpec, config: RoutesConfig, new: RouteSpec) -> bool:
    return old.source == new.source and previous.connections.get(old.source.connection) == config.connections.get(
        new.source.connection
    )

