"""The running engine: connections, one runner per route, and reloads that lose nothing.

A reload compiles the routes and schemas directories first, off the event loop; if anything
is wrong the running routes are left exactly as they are. Otherwise :mod:`engine.plan` says
what changed and only that is touched: an unchanged route keeps its pipeline and its
consumer; a route whose source is unchanged keeps its source (its AMQP consumer, ROS
subscription or MAVLink reader) and gets a new pipeline swapped in before the old one
drains (make-before-break); a route whose source changed gets a new source started before
the old one stops and drains. A connection holding an exclusive resource (a listening
port, a serial device) is the exception: its routes stop, it closes, its successor opens
and the routes start again (break-before-make), and the gap is logged. Messages in flight
finish on the pipeline that took them, so each is converted by exactly one generation.
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
from engine.plan import ReloadPlan, connection_key, plan_reload
from engine.routes import ConnectionSpec, RouteSpec, RoutesConfig, RoutesInvalid, load_routes
from engine.schemas import SchemaRegistry
from engine.logs import Throttle
from engine.observe import DEAD_LETTERED, DELIVERED, REDELIVERED, Observers

log = logging.getLogger("engine.runtime")

EXCLUSIVE_RELEASE_S = 2.0
"""How long a handover waits for an exclusive resource the old connection released: the
operating system (or asyncio, which closes a socket on the next loop turn) may free it a
moment after ``close`` returns."""

RETIRE_AFTER_S = 2.0
"""How long a retired source's setup (AMQP bindings, an auto-named queue) outlives it. A save
that is not atomic can be read half-written, as a file without routes, and fixed a moment
later: undoing at once would unbind a queue that should keep buffering, and drop what is
published meanwhile. After the delay, only what the live configuration no longer wants goes."""

EMPTIED_SETTLE_S = 0.1
"""How long a reload waits to read again a route file found empty (see Engine._emptied)."""

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
    last_handovers: list[dict[str, Any]] = field(default_factory=list)
    """Exclusive resources the last reload handed over break-before-make, with the gap
    (ms from stopping the old routes to the new ones running) during which none was served."""


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
        self._schemas: SchemaRegistry | None = None
        self._lock = asyncio.Lock()
        self.observers = Observers()  # ops: per-route counters for metrics, status and taps
        self.retire_after_s = RETIRE_AFTER_S
        self._retiring: list[RouteRunner] = []
        """Stopped runners whose source setup is undone later; their connections stay open."""
        self._retirement: asyncio.Task[None] | None = None

    def open_connections(self) -> list[tuple[str, Connection]]:
        """ops: ``(protocol, connection)`` of every open connection, for health and metrics."""
        specs = self.config.connections if self.config is not None else {}
        return [(specs[c.name].protocol if c.name in specs else type(c).__module__.rsplit(".", 1)[-1], c)
                for c in self._connections.values()]

    def compile(self) -> tuple[RoutesConfig, SchemaRegistry]:
        """Load both directories; blocking (files, imports): called in a worker thread."""
        schemas = SchemaRegistry(self.schemas_dir)
        return load_routes(self.routes_dir, schemas), schemas

    async def start(self) -> None:
        """Load and start every route; raises RoutesInvalid or EndpointError."""
        config, schemas = await asyncio.to_thread(self.compile)
        async with self._lock:
            await self._apply(config, schemas)

    async def reload(self) -> bool:
        """Apply the directories as they are now; on any problem keep the running routes."""
        async with self._lock:
            began = time.monotonic()
            try:
                config, schemas = await asyncio.to_thread(self.compile)
                if self._emptied(config):
                    await asyncio.sleep(EMPTIED_SETTLE_S)
                    config, schemas = await asyncio.to_thread(self.compile)
            except RoutesInvalid as invalid:
                return self._rejected([str(p) for p in invalid.problems])
            except Exception as error:  # whatever the loader did not foresee: a rejected reload, not a dead reloader
                log.exception("loading the routes failed")
                return self._rejected([f"{self.routes_dir}: cannot load: {type(error).__name__}: {error}"])
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

    def _emptied(self, config: RoutesConfig) -> bool:
        """Whether a route file that defined routes is now empty: more often an editor
        half-way through a save (truncate, then write) than an operator's intent."""
        if self.config is None:
            return False
        before = {route.file for route in self.config.routes.values()}
        after = {route.file for route in config.routes.values()}
        for file in before - after:
            try:
                if os.stat(file).st_size == 0:
                    return True
            except OSError:
                pass
        return False

    def _rejected(self, problems: list[str]) -> bool:
        self.reloads.rejected += 1
        self.reloads.last_error = problems
        log.error(
            "reload rejected; previous routes keep running",
            extra={"generation": self.generation, "problems": problems},
        )
        return False

    async def _connection(self, spec: ConnectionSpec) -> Connection:
        key = connection_key(spec)
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

    async def _runner(self, config: RoutesConfig, schemas: SchemaRegistry, spec: RouteSpec, generation: int) -> RouteRunner:
        """A route's pipeline and source, not started yet."""
        pipeline, sink_connection = await self._pipeline(config, schemas, spec, generation)
        try:
            source_connection = await self._connection(config.connections[spec.source.connection])
            source = source_connection.source(spec.name, spec.source.options)
        except BaseException:
            await pipeline.sink.close()
            raise
        return RouteRunner(self, spec, pipeline, source, [source_connection, sink_connection])

    async def _apply(self, config: RoutesConfig, schemas: SchemaRegistry) -> None:
        """Carry out the plan: prepare everything make-before-break, hand exclusive resources
        over, then commit (swap pipelines, stop what was replaced or removed)."""
        plan = plan_reload(self.config, config)
        generation = self.generation + 1
        later = plan.break_before_make
        swaps: list[tuple[RouteRunner, Pipeline, Connection]] = []
        fresh: list[RouteRunner] = []
        handed: list[RouteRunner] = []
        absent = tuple(n for n in plan.keep + plan.swap_pipeline if n not in self.runners)  # lost by a failed handover
        try:
            for name in plan.add + plan.replace_source + absent:
                if name not in later:
                    fresh.append(await self._runner(config, schemas, config.routes[name], generation))
            for name in plan.swap_pipeline:
                if name in absent:
                    continue
                pipeline, sink_connection = await self._pipeline(config, schemas, config.routes[name], generation)
                swaps.append((self.runners[name], pipeline, sink_connection))
            for runner in fresh:
                await runner.source.start(runner.deliver)
            if plan.handovers:
                handed = await self._hand_over(plan, config, schemas, generation)
            else:
                self.reloads.last_handovers = []
        except BaseException:
            await asyncio.gather(
                *(runner.source.stop() for runner in fresh),
                *(pipeline.sink.close() for pipeline in [r.pipeline for r in fresh] + [p for _, p, _ in swaps]),
                return_exceptions=True,
            )
            await self._close_unused(self.runners.values())
            raise

        handed_over = [self.runners[name] for name in later if name in self.runners]
        keep = {name: self.runners[name] for name in plan.keep if name not in absent}
        retired = []
        for runner, pipeline, sink_connection in swaps:
            retired.append(runner.retire_pipeline(runner.pipeline))
            runner.spec, runner.pipeline = pipeline.spec, pipeline
            runner.connections = [runner.connections[0], sink_connection]
            keep[runner.spec.name] = runner
        for runner in fresh + handed:
            keep[runner.spec.name] = runner
        stopped = [runner for name, runner in self.runners.items() if keep.get(name) is not runner and name not in later]
        retired.extend(runner.stop() for runner in stopped)
        if retired:
            await asyncio.gather(*retired)
        self.runners = keep
        self.config, self._schemas = config, schemas
        self.generation = generation
        self._retire_later(stopped + handed_over)
        await self._close_unused(keep.values())
        for warning in config.warnings:
            log.warning("route warning", extra={"problem": str(warning)})
        log.info(
            "routes applied",
            extra={"generation": generation, "config_hash": config.content_hash, "routes": len(keep), **plan.summary()},
        )

    async def _hand_over(
        self, plan: ReloadPlan, config: RoutesConfig, schemas: SchemaRegistry, generation: int
    ) -> list[RouteRunner]:
        """Break-before-make for exclusive resources: stop the routes on the old connections,
        close those, then open the new ones and start the routes. If that fails, the old
        routes are restored (their connections reopened) and the error propagates."""
        names = sorted(plan.break_before_make)
        began = time.monotonic()
        old = [self.runners[name] for name in names if name in self.runners]
        await asyncio.gather(*(runner.stop() for runner in old))
        for handover in plan.handovers:
            connection = self._connections.pop(handover.close, None)
            if connection is not None:
                await connection.close()
        started: list[RouteRunner] = []
        try:
            for handover in plan.handovers:
                await self._open_exclusive(config.connections[handover.open[0]])
            for name in names:
                if name in config.routes:
                    runner = await self._runner(config, schemas, config.routes[name], generation)
                    started.append(runner)
                    await runner.source.start(runner.deliver)
        except BaseException:
            await asyncio.gather(*(runner.stop() for runner in started), return_exceptions=True)
            for handover in plan.handovers:
                connection = self._connections.pop(handover.open, None)
                if connection is not None:
                    await connection.close()
            await self._restore(old, [h.close[0] for h in plan.handovers])
            raise
        gap_ms = round((time.monotonic() - began) * 1e3, 1)
        self.reloads.last_handovers = [
            {"resource": h.resource, "connection": h.open[0], "gap_ms": gap_ms, "routes": list(h.routes)}
            for h in plan.handovers
        ]
        for handover in self.reloads.last_handovers:
            log.info("exclusive resource replaced break-before-make", extra=handover)
        return started

    def _retire_later(self, runners: list[RouteRunner]) -> None:
        self._retiring.extend(runners)
        if runners and (self._retirement is None or self._retirement.done()):
            self._retirement = asyncio.create_task(self._retire_pending(), name="retire-sources")

    async def _retire_pending(self) -> None:
        await asyncio.sleep(self.retire_after_s)
        async with self._lock:
            runners, self._retiring = self._retiring, []
            assert self.config is not None
            await self._retire_sources(self.config, runners)
            await self._close_unused(self.runners.values())

    async def topology_settled(self) -> None:
        """Wait until retired sources' setup has been undone (tests, orderly tools)."""
        while self._retirement is not None and not self._retirement.done():
            await asyncio.shield(self._retirement)

    async def _retire_sources(self, config: RoutesConfig, runners: list[RouteRunner]) -> None:
        """Let each protocol undo what a source that stopped for good had set up (AMQP
        bindings and auto-named queues) and the live configuration no longer wants."""
        for runner in runners:
            spec = runner.spec.source
            remaining = [
                (name, route.source.options) for name, route in config.routes.items()
                if route.source.protocol == spec.protocol and route.source.connection == spec.connection
            ]
            try:
                await endpoints.transport(spec.protocol).source_retired(runner.connections[0], runner.spec.name, spec.options, remaining)
            except Exception as error:  # the reload is done; leftovers are reported, not fatal
                log.warning("could not undo a retired source's setup", extra={"route": runner.spec.name, "error": f"{type(error).__name__}: {error}"})

    async def _open_exclusive(self, spec: ConnectionSpec) -> Connection:
        """Open a connection whose exclusive resource was just released, waiting briefly
        for the release to take effect."""
        deadline = time.monotonic() + EXCLUSIVE_RELEASE_S
        pause = 0.0
        while True:
            try:
                return await self._connection(spec)
            except EndpointError:
                if time.monotonic() + pause > deadline:
                    raise
            await asyncio.sleep(pause)
            pause = min(0.1, pause * 2 or 0.005)

    async def _restore(self, runners: list[RouteRunner], connections: list[str]) -> None:
        """Start again, on the running configuration, routes a failed handover had stopped."""
        assert self.config is not None
        for name in connections:
            try:
                await self._open_exclusive(self.config.connections[name])
            except EndpointError as error:
                log.error("connection could not be reopened after a failed reload", extra={"connection": name, "error": str(error)})
        for runner in runners:
            try:
                again = await self._runner(self.config, self._schemas, runner.spec, runner.pipeline.generation)
                await again.source.start(again.deliver)
            except Exception as error:
                log.error("route could not be restored after a failed reload", extra={"route": runner.spec.name, "error": str(error)})
                del self.runners[runner.spec.name]
                continue
            self.runners[runner.spec.name] = again

    async def _close_unused(self, runners: Any) -> None:
        used = {id(connection) for runner in [*runners, *self._retiring] for connection in runner.connections}
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
        if self._retirement is not None:  # a stopped engine keeps its topology: its queues buffer
            self._retirement.cancel()
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


