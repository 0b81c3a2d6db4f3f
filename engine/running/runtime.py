"""The running engine: one runner per route, and reloads that lose nothing.

A reload compiles the whole directory first; if anything is wrong the running routes are
left exactly as they are. Otherwise only what changed is touched: an unchanged route keeps
its pipeline and its consumer; a route whose source is unchanged keeps its source (its AMQP
consumer, ROS subscription or MAVLink reader) and gets a new pipeline swapped in before the
old one drains (make-before-break); a route whose source changed gets a new source started
before the old one stops and drains. Messages in flight finish on the pipeline that took
them, so each is converted by exactly one configuration generation.

The reload plan (engine/running/plan.py, a pure value) is carried out in named phases, as Vector's
topology reload is: **prepare** (the dead-letter destination, new runners and pipelines,
nothing started), **start new** (make-before-break), **hand over** (exclusive resources,
break-before-make), then **commit** (swap pipelines, stop what was replaced or removed, the
new configuration becomes the live one) and **retire** (undo retired sources' setup later,
release leases and connections nobody uses). A failure before commit **undoes** what the
reload prepared, and the running routes are untouched. The engine's collaborators hold the
rest: the connection pool (engine/running/connections.py), the route buffers (engine/running/buffer.py),
the leases (engine/running/leases.py), the counters (engine/running/observe.py); a message's life is
engine/running/runner.py.
"""

from __future__ import annotations

import asyncio
import gc
import logging
import os
import socket
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

from engine import endpoints
from engine.common.schemas import SchemaRegistry
from engine.endpoints.base import Connection, EndpointError
from engine.language.route_yaml import Problem
from engine.language.routes import RoutesInvalid, load_routes
from engine.language.specs import RoutesConfig, RouteSpec
from engine.language.stores import Stores
from engine.running.buffer import Buffers
from engine.running.record import Recorder
from engine.running.connections import ConnectionPool
from engine.running.dead_letters import DeadLetters
from engine.running.dedupe import DedupeKeys
from engine.running.fanout import open_sinks
from engine.running.leases import Leases
from engine.running.observe import Observers
from engine.running.pipeline import Pipeline
from engine.running.plan import ReloadPlan, plan_reload
from engine.running.reload_stats import ReloadStats
from engine.running.runner import RouteRunner
from engine.running.shutdown import stop_routes
from engine.running.engine_status import engine_status

log = logging.getLogger("engine.running.runtime")

RETIRE_AFTER_S = 2.0
"""How long a retired source's setup (AMQP bindings, an auto-named queue) outlives it. A save
that is not atomic can be read half-written, as a file without routes, and fixed a moment
later: undoing at once would unbind a queue that should keep buffering, and drop what is
published meanwhile. After the delay, only what the live configuration no longer wants goes."""

EMPTIED_SETTLE_S = 0.1
"""How long a reload waits to read again a route file found empty (see Engine._emptied)."""


@dataclass
class _Reload:
    """One reload being applied: the plan and what its phases made so far."""

    config: RoutesConfig
    everywhere: RoutesConfig
    schemas: SchemaRegistry
    plan: ReloadPlan
    generation: int
    absent: tuple[str, ...]
    """Routes the plan keeps that do not run: lost by an earlier failed handover, started again."""
    dead_letters: DeadLetters | None
    """The dead-letter destination before this reload (restored if it fails)."""
    fresh: list[RouteRunner] = field(default_factory=list)
    swaps: list[tuple[RouteRunner, Pipeline, list[Connection]]] = field(default_factory=list)
    handed: list[RouteRunner] = field(default_factory=list)
    """Runners started on the other side of a handover."""
    handed_over: list[RouteRunner] = field(default_factory=list)
    """Runners a handover stopped (their source setup is retired later)."""


class Engine:
    def __init__(
        self, routes_dir: Path, schemas_dirs: Path | Sequence[Path], require_connections: bool = False,
        instance: str | None = None, vet: Callable[[RoutesConfig, SchemaRegistry], list[Problem]] | None = None,
        recorder: Recorder | None = None,
    ) -> None:
        self.routes_dir = routes_dir
        self.vet = vet
        """Asked of every compiled generation before it runs, at start and at each reload: its
        problems refuse the generation as the loader's do (``run --test-on-reload``: the
        directory's route tests, engine/ops/route_tests.py; the engine itself names no test)."""
        self.schemas_dirs: tuple[Path, ...] = (schemas_dirs,) if isinstance(schemas_dirs, Path) else tuple(schemas_dirs)
        """The schema directories, a later one over the earlier (engine/common/schema_files.py)."""
        self.instance = instance or socket.gethostname()
        """This engine's name among the instances sharing the routes (``--instance``)."""
        self.elsewhere: list[str] = []
        """Routes pinned to other instances (``instances:``), not run here."""
        self.config: RoutesConfig | None = None
        self.generation = 0
        self.runners: dict[str, RouteRunner] = {}
        self.reloads = ReloadStats()
        self.started_at = time.time()
        self.connections = ConnectionPool(require_connections, on_opened=self._connection_opened)
        self.buffers = Buffers()
        self.leases = Leases(self.instance)
        self.observers = Observers()
        """Per-route counters for the log, status, metrics and taps, kept across reloads."""
        self.recorder = recorder
        """``--record``: what the routes receive and send, in MCAP files (engine/running/record.py)."""
        self.stores = Stores()
        """The latest-value stores and sequences mappings read (engine/language/stores.py), kept across reloads."""
        self.dedupe = DedupeKeys()
        """Each ``dedupe:`` route's accepted keys (engine/running/dedupe.py), kept across reloads."""
        self.dead_letters: DeadLetters | None = None
        self.retire_after_s = RETIRE_AFTER_S
        self._schemas: SchemaRegistry | None = None
        self._lock = asyncio.Lock()
        self._retiring: list[RouteRunner] = []
        """Stopped runners whose source setup is undone later; their connections stay open."""
        self._retirement: asyncio.Task[None] | None = None

    # -- what a route needs of the engine (engine/running/runner.py RouteHost)

    def is_open(self, connection: Connection) -> bool:
        return self.connections.is_open(connection)

    async def wait_open(self, connections: Sequence[Connection]) -> None:
        await self.connections.wait_open(connections)

    def key_files(self) -> frozenset[Path]:
        """The files outside the route files the running configuration reads (connections' key
        files, for_each files): watched, as an edit of one is a configuration change."""
        return self.config.watched_files if self.config is not None else frozenset()

    def open_connections(self) -> list[tuple[str, Connection]]:
        """``(protocol, connection)`` of every connection the engine holds (open or being retried)."""
        specs = self.config.connections if self.config is not None else {}
        return [(specs[c.name].protocol if c.name in specs else endpoints.protocol_of(c) or type(c).__name__, c)
                for _, c in self.connections.items()]

    def compile(self) -> tuple[RoutesConfig, SchemaRegistry]:
        """Load both directories; blocking (files, imports): called in a worker thread."""
        schemas = SchemaRegistry(self.schemas_dirs)
        config = load_routes(self.routes_dir, schemas)
        if self.vet is not None:
            problems = self.vet(config, schemas)
            if problems:
                raise RoutesInvalid(problems, list(config.warnings))
        return config, schemas

    async def start(self) -> None:
        """Load and start every route; raises RoutesInvalid or EndpointError.

        The collector is off while loading and what was loaded is then frozen (``gc.freeze``):
        1,000 routes are some 250,000 long-lived objects, and collecting while they are built
        took a third of the load; once loaded, each full collection traversed them all, which
        made a message cost up to 3x what it does with one route. A reload or a stop unfreezes
        them, so the routes they replace are collected as usual."""
        collecting = gc.isenabled()
        gc.disable()
        try:
            config, schemas = await asyncio.to_thread(self.compile)
            async with self._lock:
                await self._apply(config, schemas)
        finally:
            if collecting:
                gc.enable()
        gc.freeze()

    async def reload(self) -> bool:
        """Apply the directories as they are now; on any problem keep the running routes."""
        gc.unfreeze()  # what this reload replaces must be collectable (see start)
        async with self._lock:
            began = time.monotonic()
            try:
                config, schemas = await self._compile_settled()
            except RoutesInvalid as invalid:
                return self._rejected([str(p) for p in invalid.problems])
            except Exception as error:  # whatever the loader did not foresee: a rejected reload, not a dead reloader
                log.exception("loading the routes failed")
                return self._rejected([f"{self.routes_dir}: cannot load: {type(error).__name__}: {error}"])
            if self.config is not None and config.content_hash == self.config.content_hash:
                self._error_cleared("the files are back to what runs")
                return True
            try:
                await self._apply(config, schemas)
            except EndpointError as error:
                return self._rejected([str(error)])
            except Exception as error:  # a reload must never take the running engine down
                log.exception("reload failed")
                return self._rejected([f"{type(error).__name__}: {error}"])
            self.reloads.succeeded += 1
            self._error_cleared("a reload applied")
            self.reloads.last_reload_s = time.monotonic() - began
            return True

    async def _compile_settled(self) -> tuple[RoutesConfig, SchemaRegistry]:
        config, schemas = await asyncio.to_thread(self.compile)
        if self._emptied(config):
            await asyncio.sleep(EMPTIED_SETTLE_S)
            config, schemas = await asyncio.to_thread(self.compile)
        return config, schemas

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

    def _error_cleared(self, how: str) -> None:
        """Forget the last rejection, saying so in the log: the status stops showing it."""
        if self.reloads.last_error:
            log.info("reload error cleared", extra={"by": how, "generation": self.generation, "was": self.reloads.last_error})
        self.reloads.last_error = []

    def _rejected(self, problems: list[str]) -> bool:
        """Count and report a rejected reload, once per rejection (ReloadStats.reject)."""
        if not self.reloads.reject(problems):
            return False
        log.error(
            "reload rejected; previous routes keep running",
            extra={"generation": self.generation, "problems": problems},
        )
        return False

    # -- making routes

    async def _pipeline(
        self, config: RoutesConfig, schemas: SchemaRegistry, spec: RouteSpec, generation: int
    ) -> tuple[Pipeline, list[Connection]]:
        """The route's pipeline on its sink or sinks (engine/running/fanout.py), and their connections."""
        schema = schemas.get(spec.schema)
        assert schema is not None
        reply_schema = schemas.get(spec.reply.schema) if spec.reply is not None and spec.reply.schema else None
        seen_keys = await self.dedupe.get(spec.name, spec.dedupe)
        sink, connections, one = await open_sinks(spec, lambda end: self.connections.get(config.connections[end.connection]),
                                                  self.is_open, self.stores, self.observers.get(spec.name))
        pipeline = Pipeline.compile(spec, generation, schema, sink, reply_schema, self.stores, seen_keys)
        pipeline.sink_connection = one
        return pipeline, connections

    async def _runner(self, config: RoutesConfig, schemas: SchemaRegistry, spec: RouteSpec, generation: int) -> RouteRunner:
        """A route's pipeline and source, not started yet."""
        pipeline, sink_connections = await self._pipeline(config, schemas, spec, generation)
        try:
            source_connection = await self.connections.get(config.connections[spec.source.connection])
            source = source_connection.source(spec.name, spec.source.options)
        except BaseException:
            await pipeline.sink.close()
            raise
        runner = RouteRunner(self, spec, pipeline, source, [source_connection, *sink_connections])
        self._record(spec, schemas)  # before its source starts: every message it takes is recorded
        if spec.placement.active_standby:
            await self._take_lease(runner, config)
        return runner

    async def _take_lease(self, runner: RouteRunner, config: RoutesConfig) -> None:
        """Share one lease per (connection, lease name) among this instance's routes, so
        the routes of one robot fail over together."""
        placement = runner.spec.placement
        assert placement.lease_connection is not None
        connection = await self.connections.get(config.connections[placement.lease_connection])
        runner.connections.insert(1, connection)  # the sinks' connections stay last
        runner.lease = await self.leases.take(connection, placement.lease_name, placement.lease_heartbeat)

    async def _dead_letters(self, config: RoutesConfig) -> DeadLetters:
        """The engine's one dead-letter destination, kept when the configuration did not change it."""
        spec = config.dead_letters
        current = self.dead_letters
        connection = None
        if spec.connection is not None:
            connection = await self.connections.get(config.connections[spec.connection])
        if current is not None and current.spec == spec and current.connection is connection:
            return current
        dead_letters = DeadLetters(spec, connection)
        if connection is None or self.is_open(connection):  # else once it opens (_connection_opened)
            await dead_letters.prepare()
        return dead_letters

    async def _connection_opened(self, connection: Connection) -> None:
        """A connection retried in the background opened: declare the dead letters' queue on it."""
        dead_letters = self.dead_letters
        if dead_letters is not None and dead_letters.connection is connection:
            try:
                await dead_letters.prepare()
            except EndpointError as error:  # they go to the spool meanwhile
                log.error("dead-letter queue not declared", extra={"connection": connection.name, "error": str(error)})

    # -- applying a configuration, in phases

    async def _apply(self, everywhere: RoutesConfig, schemas: SchemaRegistry) -> None:
        """Carry out the plan: prepare, start new, hand over; then commit and retire (see the
        module docstring). Only the routes that run on this instance (``instances:``) are
        planned; the others are listed as ``elsewhere``."""
        change = self._plan(everywhere, schemas)
        try:
            await self._prepare(change)
            await _start_runners(change.fresh)
            await self._hand_over(change)
        except BaseException:
            await self._undo(change)
            raise
        stopped = await self._commit(change)
        for spec in change.config.routes.values():  # a kept route's record: or schema may have changed
            self._record(spec, change.schemas)
        await self._retire(change, stopped)

    def _record(self, spec: RouteSpec, schemas: SchemaRegistry) -> None:
        """Give the route's observer its recording (``--record``), or none (``record: false``)."""
        if self.recorder is None:
            return
        schema = schemas.bundled(spec.schema) if spec.record else None
        observer = self.observers.get(spec.name)
        observer.recording = None if schema is None else self.recorder.route(spec.name, spec.schema, schema)

    def _plan(self, everywhere: RoutesConfig, schemas: SchemaRegistry) -> _Reload:
        config = replace(everywhere, routes={
            name: spec for name, spec in everywhere.routes.items() if spec.placement.runs_on(self.instance)
        })
        plan = plan_reload(self.config, config)
        absent = tuple(n for n in plan.keep + plan.swap_pipeline if n not in self.runners)
        return _Reload(config, everywhere, schemas, plan, self.generation + 1, absent, self.dead_letters)

    async def _prepare(self, change: _Reload) -> None:
        """Phase 1: the dead-letter destination, the new runners and the swapped-in pipelines,
        nothing started yet."""
        config, plan, later = change.config, change.plan, change.plan.break_before_make
        self.dead_letters = await self._dead_letters(config)
        for name in plan.add + plan.replace_source + change.absent:
            if name not in later:
                change.fresh.append(await self._runner(config, change.schemas, config.routes[name], change.generation))
        for name in plan.swap_pipeline:
            if name not in change.absent:
                pipeline, sink_connections = await self._pipeline(config, change.schemas, config.routes[name], change.generation)
                change.swaps.append((self.runners[name], pipeline, sink_connections))

    async def _undo(self, change: _Reload) -> None:
        """A phase before commit failed: stop and close what this reload made."""
        self.dead_letters = change.dead_letters
        await asyncio.gather(
            *(runner.stop() for runner in change.fresh),
            *(pipeline.sink.close() for pipeline in [r.pipeline for r in change.fresh] + [p for _, p, _ in change.swaps]),
            return_exceptions=True,
        )
        await self._release_unused(self.runners.values())

    async def _commit(self, change: _Reload) -> list[RouteRunner]:
        """Phase 4: swap pipelines in, stop what was replaced or removed; the new configuration
        is the live one. Returns the runners stopped for good."""
        later = change.plan.break_before_make
        change.handed_over = [self.runners[name] for name in later if name in self.runners]
        keep = {name: self.runners[name] for name in change.plan.keep if name not in change.absent}
        retired = []
        for runner, pipeline, sink_connections in change.swaps:
            retired.append(runner.retire_pipeline(runner.pipeline))
            runner.spec, runner.pipeline = pipeline.spec, pipeline
            runner.observer.carries(pipeline.spec.schema)
            kept = len(runner.connections) - runner.sink_count  # the source's (and the lease's)
            runner.connections, runner.sink_count = [*runner.connections[:kept], *sink_connections], len(sink_connections)
            keep[runner.spec.name] = runner
        for runner in change.fresh + change.handed:
            keep[runner.spec.name] = runner
            runner.give_buffer_to_self()
        stopped = [runner for name, runner in self.runners.items() if keep.get(name) is not runner and name not in later]
        retired.extend(runner.stop() for runner in stopped)
        if retired:
            await asyncio.gather(*retired)
        self.runners = keep
        self.config, self._schemas, self.generation = change.config, change.schemas, change.generation
        return stopped

    async def _retire(self, change: _Reload, stopped: list[RouteRunner]) -> None:
        """Phase 5: what the old configuration used and the new one does not goes (sources'
        setup after a delay, see RETIRE_AFTER_S)."""
        self._retire_later(stopped + change.handed_over)
        self.elsewhere = sorted(set(change.everywhere.routes) - set(change.config.routes))
        await self._release_unused(self.runners.values())
        for warning in change.config.warnings:
            log.warning("route warning", extra={"problem": str(warning)})
        log.info(
            "routes applied",
            extra={"generation": change.generation, "config_hash": change.config.content_hash,
                   "routes": len(self.runners), **change.plan.summary()},
        )

    # -- phase 3: exclusive resources, break-before-make

    async def _hand_over(self, change: _Reload) -> None:
        """Stop the routes on the old connections, close those, then open the new ones and
        start the routes. If that fails, the old routes are restored (their connections
        reopened) and the error propagates."""
        plan = change.plan
        if not plan.handovers:
            self.reloads.last_handovers = []
            return
        began = time.monotonic()
        old = [self.runners[name] for name in sorted(plan.break_before_make) if name in self.runners]
        await asyncio.gather(*(runner.stop() for runner in old))
        for handover in plan.handovers:
            await self.connections.close(handover.close)
        try:
            await self._start_handed_over(change)
        except BaseException:
            await asyncio.gather(*(runner.stop() for runner in change.handed), return_exceptions=True)
            for handover in plan.handovers:
                await self.connections.close(handover.open)
            await self._restore(old, [h.close[0] for h in plan.handovers])
            raise
        self._record_handovers(plan, round((time.monotonic() - began) * 1e3, 1))

    async def _start_handed_over(self, change: _Reload) -> None:
        config = change.config
        for handover in change.plan.handovers:
            await self.connections.open_exclusive(config.connections[handover.open[0]])
        for name in sorted(change.plan.break_before_make):
            if name in config.routes:
                runner = await self._runner(config, change.schemas, config.routes[name], change.generation)
                change.handed.append(runner)
                await runner.start()

    def _record_handovers(self, plan: ReloadPlan, gap_ms: float) -> None:
        self.reloads.last_handovers = [
            {"resource": h.resource, "connection": h.open[0], "gap_ms": gap_ms, "routes": list(h.routes)}
            for h in plan.handovers
        ]
        for handover in self.reloads.last_handovers:
            log.info("exclusive resource replaced break-before-make", extra=handover)

    async def _restore(self, runners: list[RouteRunner], connections: list[str]) -> None:
        """Start again, on the running configuration, routes a failed handover had stopped."""
        assert self.config is not None and self._schemas is not None  # set together, by the first load
        for name in connections:
            try:
                await self.connections.open_exclusive(self.config.connections[name])
            except EndpointError as error:
                log.error("connection could not be reopened after a failed reload", extra={"connection": name, "error": str(error)})
        for runner in runners:
            try:
                again = await self._runner(self.config, self._schemas, runner.spec, runner.pipeline.generation)
                await again.start()
            except Exception as error:
                log.error("route could not be restored after a failed reload", extra={"route": runner.spec.name, "error": str(error)})
                del self.runners[runner.spec.name]
                continue
            again.give_buffer_to_self()
            self.runners[runner.spec.name] = again

    # -- retiring

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
            await self._release_unused(self.runners.values())

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

    async def _release_unused(self, runners: Iterable[RouteRunner]) -> None:
        """Stop the leases and close the connections that no running or retiring route (nor
        the dead letters) uses."""
        runners = list(runners)
        await self.leases.release_unused(runner.lease for runner in runners)
        used = {id(connection) for runner in [*runners, *self._retiring] for connection in runner.connections}
        if self.dead_letters is not None and self.dead_letters.connection is not None:
            used.add(id(self.dead_letters.connection))
        await self.connections.close_unused(used)

    # -- stopping and the status (engine/running/shutdown.py, engine/running/engine_status.py)

    async def stop(self, drain_timeout: float = 10.0) -> None:
        """Graceful stop, in the order engine/running/shutdown.py gives and explains."""
        gc.unfreeze()
        if self._retirement is not None:  # a stopped engine keeps its topology: its queues buffer
            self._retirement.cancel()
        async with self._lock:
            await stop_routes(self, drain_timeout)

    def status(self) -> dict[str, Any]:
        return engine_status(self)


SOURCE_START_CONCURRENCY = 64


async def _start_runners(runners: list[RouteRunner]) -> None:
    """Start routes concurrently, a bounded number at a time: each start is a few broker
    (or DDS) round trips, so one after another 1,000 routes took 11 s to load, together 2.
    Every start of a group finishes before the first error is raised, so the caller stops
    exactly the sources that may have started."""
    for first in range(0, len(runners), SOURCE_START_CONCURRENCY):
        group = runners[first:first + SOURCE_START_CONCURRENCY]
        outcomes = await asyncio.gather(*(runner.start() for runner in group), return_exceptions=True)
        for outcome in outcomes:
            if isinstance(outcome, BaseException):
                raise outcome
