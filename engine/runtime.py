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
import random
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

from engine import endpoints
from engine.buffer import HoldingBuffer, stats_dict
from engine.delivery import HEALTH_POLL, DeadLetters, Failure, classify, dead_letter_message, settle
from engine.endpoints.base import Connection, EndpointError, Inbound, Outbound, Source
from engine.pipeline import Pipeline
from engine.routes import ConnectionSpec, RouteSpec, RoutesConfig, RoutesInvalid, load_routes
from engine.schemas import SchemaRegistry
from engine.logs import Throttle
from engine.redaction import json_default

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
        self.buffer: HoldingBuffer | None = engine.buffer_for(self)
        """Holds the route's messages while its sink is down (``buffer:``; engine/buffer.py)."""
        self.state = "created"
        """created, waiting (for a connection that is not open yet), running, stopped."""
        self._starter: asyncio.Task[None] | None = None

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

    # -- starting when the connections are open

    async def start(self) -> None:
        """Start the source now if the connections it needs are open, else in the background
        once they are (a buffered route needs only its source's: the buffer holds the rest)."""
        if self.buffer is not None:
            self.buffer.start()
        missing = self.missing_connections()
        if not missing:
            await self.source.start(self)
            self.state = "running"
            return
        self.state = "waiting"
        log.warning("route waits for its connections", extra={"route": self.spec.name, "connections": missing})
        self._starter = asyncio.create_task(self._start_when_open(), name=f"start-{self.spec.name}")

    def _needed(self) -> list[Connection]:
        return self.connections if self.buffer is None else self.connections[:1]

    def missing_connections(self) -> list[str]:
        return [c.name for c in self._needed() if not self.engine.is_open(c)]

    async def _start_when_open(self) -> None:
        delay = 0.5
        while True:
            await self.engine.wait_open(self._needed())
            try:
                await self.source.start(self)
            except EndpointError as error:  # the connection went down again meanwhile
                log.warning("route could not start; retrying", extra={"route": self.spec.name, "error": str(error)})
                await asyncio.sleep(delay)
                delay = min(delay * 2, 10.0)
                continue
            self.state = "running"
            log.info("route started", extra={"route": self.spec.name})
            return

    # -- the buffer (engine/buffer.py): what the delivery policy hands it, and its way out

    def should_hold(self) -> bool:
        """True when a buffered route must hold new messages rather than try the sink: the
        buffer already holds some (order), or the sink's connection is down."""
        buffer = self.buffer
        if buffer is None:
            return False
        sink_connection = self.connections[-1]
        return buffer.holding or not (sink_connection.healthy and self.engine.is_open(sink_connection))

    async def hold(self, outbounds: Sequence[Outbound]) -> None:
        """Hand messages to the buffer, in order; each is settled for its source once held."""
        assert self.buffer is not None
        for outbound in outbounds:
            await self.buffer.hold(outbound)

    async def send_held(self, messages: list[Outbound]) -> list[BaseException | None]:
        pipeline = self.pipeline
        pipeline.enter()
        try:
            return await pipeline.sink.send_batch(messages)
        finally:
            pipeline.leave()

    def held_delivered(self, count: int) -> None:
        self.stats.delivered += count

    async def held_rejected(self, message: Outbound, error: BaseException, attempts: int) -> None:
        """A held message the sink rejected, or kept failing while healthy: dead-letter it."""
        inbound = Inbound(body=message.body, meta={k: v for k, v in message.meta.items() if k not in ("route", "generation")})
        failure = classify(error, "sink")
        letter = dead_letter_message(self, inbound, failure, attempts, self.spec.delivery.max_message_bytes)
        await self.engine.dead_letters_for(self).put(self.spec.name, [letter])
        self.stats.failed += 1
        self.stats.dead_lettered[failure.stage] = self.stats.dead_lettered.get(failure.stage, 0) + 1
        self.report_failure(failure)

    async def stop(self, drain_timeout: float = 0.0) -> None:
        self._stopping.set()
        self.state = "stopped"
        if self._starter is not None:
            self._starter.cancel()
            await asyncio.gather(self._starter, return_exceptions=True)
        await self.source.stop()
        if self.buffer is not None and self.engine.release_buffer(self):
            await self.buffer.close(drain_timeout)
        await self.retire_pipeline(self.pipeline)


OPEN_RETRY_FIRST, OPEN_RETRY_MAX = 0.25, 2.0
"""Backoff between attempts to open a connection that was unreachable at start."""
STOP_GRACE = 2.0
"""Seconds a stop gives sources to hand back what they hold once the drain timeout is over."""


class Engine:
    def __init__(self, routes_dir: Path, schemas_dir: Path, require_connections: bool = False) -> None:
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
        self.require_connections = require_connections
        """Fail (EndpointError) when a connection cannot be opened, instead of retrying it in
        the background while the routes that do not need it run."""
        self._opened: set[int] = set()
        self._openers: dict[int, asyncio.Task[None]] = {}
        self._open_changed = asyncio.Event()
        self._buffers: dict[str, list[Any]] = {}
        """route name -> [buffer, runners using it, newest runner]: a buffer outlives a reload."""

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
        key = (spec.name, json.dumps(spec.settings, sort_keys=True, default=json_default))
        connection = self._connections.get(key)
        if connection is None:
            connection = endpoints.transport(spec.protocol).connect(spec.name, spec.settings)
            try:
                await connection.open()
            except EndpointError as error:
                if self.require_connections:
                    raise
                log.warning("connection unreachable; retrying in the background", extra={"connection": spec.name, "error": str(error)})
                self._openers[id(connection)] = asyncio.create_task(self._keep_opening(connection), name=f"open-{spec.name}")
            else:
                self._opened.add(id(connection))
            self._connections[key] = connection
        return connection

    async def _keep_opening(self, connection: Connection) -> None:
        delay = OPEN_RETRY_FIRST
        while True:
            await asyncio.sleep(delay * (0.5 + random.random() / 2))
            delay = min(delay * 2, OPEN_RETRY_MAX)
            try:
                await connection.open()
            except EndpointError as error:
                log.debug("connection still unreachable", extra={"connection": connection.name, "error": str(error)})
                continue
            self._opened.add(id(connection))
            self._openers.pop(id(connection), None)
            dead_letters = self.dead_letters
            if dead_letters is not None and dead_letters.connection is connection:
                try:
                    await dead_letters.prepare()
                except EndpointError as error:  # they go to the spool meanwhile
                    log.error("dead-letter queue not declared", extra={"connection": connection.name, "error": str(error)})
            self._open_changed.set()
            self._open_changed = asyncio.Event()
            log.info("connection opened", extra={"connection": connection.name})
            return

    def is_open(self, connection: Connection) -> bool:
        """Opened once (it may be reconnecting now: its library takes care of that)."""
        return id(connection) in self._opened

    async def wait_open(self, connections: list[Connection]) -> None:
        while not all(self.is_open(c) for c in connections):
            await self._open_changed.wait()

    def buffer_for(self, runner: RouteRunner) -> HoldingBuffer | None:
        """The route's buffer, shared with the runner it replaces across a reload so held
        messages are not lost; its settings change at the next start."""
        spec = runner.spec.buffer
        name = runner.spec.name
        if spec is None:
            return None
        entry = self._buffers.get(name)
        if entry is None:
            sink_connection = runner.connections[-1]

            def current() -> RouteRunner:
                live = self.runners.get(name)
                return live if live is not None and live.buffer is entry[0] else entry[2]

            buffer = HoldingBuffer(
                name,
                lambda messages: current().send_held(messages),
                max_messages=spec.max_messages,
                spill_dir=spec.spill_dir,
                fsync_interval=spec.fsync_interval,
                max_attempts=runner.spec.delivery.max_attempts,
                ready=lambda: sink_connection.healthy and self.is_open(sink_connection),
                on_delivered=lambda count: current().held_delivered(count),
                on_rejected=lambda message, error, attempts: current().held_rejected(message, error, attempts),
            )
            entry = self._buffers[name] = [buffer, 0, runner]
        entry[1] += 1
        entry[2] = runner
        return entry[0]

    def release_buffer(self, runner: RouteRunner) -> bool:
        """True when no other runner uses the route's buffer any more (the caller closes it)."""
        entry = self._buffers.get(runner.spec.name)
        if entry is None or entry[0] is not runner.buffer:
            return False
        entry[1] -= 1
        if entry[1] > 0:
            return False
        del self._buffers[runner.spec.name]
        return True

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
            for runner in fresh:
                await runner.start()
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
                self._stop_opening(connection)
                await connection.close()

    def _stop_opening(self, connection: Connection) -> None:
        opener = self._openers.pop(id(connection), None)
        if opener is not None:
            opener.cancel()
        self._opened.discard(id(connection))

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
        if connection is None or self.is_open(connection):  # else once it opens (_keep_opening)
            await dead_letters.prepare()
        return dead_letters

    def dead_letters_for(self, runner: RouteRunner) -> DeadLetters:
        assert self.dead_letters is not None
        return self.dead_letters

    async def stop(self, drain_timeout: float = 10.0) -> None:
        """Graceful stop: sources stop taking messages; what is in flight is settled for at
        most ``drain_timeout`` seconds in all (buffers keep delivering meanwhile, then stay
        spilled on disk); then the connections close, which returns unacknowledged AMQP
        messages to their queues."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + drain_timeout
        async with self._lock:
            runners = list(self.runners.values())
            for connection in self._connections.values():
                self._stop_opening(connection)
            for runner in runners:
                runner.state = "stopped"
                if runner._starter is not None:
                    runner._starter.cancel()
            sources = asyncio.ensure_future(asyncio.gather(*(r.source.stop() for r in runners), return_exceptions=True))
            if not await _finished(sources, deadline):
                log.warning("drain timeout: what is not settled yet is requeued (AMQP) or dropped and counted (ROS 2, MAVLink)")
                for runner in runners:
                    runner._stopping.set()  # the delivery policy stops retrying; sources settle what they can
                if not await _finished(sources, loop.time() + STOP_GRACE):
                    sources.cancel()
                    await asyncio.gather(sources, return_exceptions=True)
            buffers = [entry[0] for entry in self._buffers.values()]
            self._buffers.clear()
            await asyncio.gather(*(b.close(max(0.0, deadline - loop.time())) for b in buffers), return_exceptions=True)
            pipelines = asyncio.ensure_future(asyncio.gather(*(r.retire_pipeline(r.pipeline) for r in runners), return_exceptions=True))
            if not await _finished(pipelines, max(deadline, loop.time() + STOP_GRACE)):
                pipelines.cancel()
                await asyncio.gather(pipelines, return_exceptions=True)
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
                    "state": runner.state,
                    "waiting_for": runner.missing_connections() if runner.state == "waiting" else [],
                    "buffer": stats_dict(runner.buffer) if runner.buffer is not None else None,
                }
                for name, runner in sorted(self.runners.items())
            },
            "connections": {
                connection.name: {
                    "protocol": type(connection).__module__.rsplit(".", 1)[-1],
                    "healthy": connection.healthy and self.is_open(connection),
                    **connection.health(),
                    **({} if self.is_open(connection) else {"state": "retrying"}),
                }
                for connection in self._connections.values()
            },
        }


async def _finished(work: asyncio.Future[Any], deadline: float) -> bool:
    """Wait for ``work`` until ``deadline`` (loop time) without cancelling it; True if done."""
    done, _ = await asyncio.wait({work}, timeout=max(0.0, deadline - asyncio.get_running_loop().time()))
    return bool(done)


def _same_source(previous: RoutesConfig, old: RouteSpec, config: RoutesConfig, new: RouteSpec) -> bool:
    return old.source == new.source and previous.connections.get(old.source.connection) == config.connections.get(
        new.source.connection
    )

