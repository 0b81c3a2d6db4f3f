"""A route runner's life around its messages: starting its source once the connections it
needs are open (retrying with backoff), stopping (halt, drain, retire a pipeline), and the
route's status. :class:`RouteLifecycle` is the base of engine/running/runner.py's
``RouteRunner``, which adds the per-message stages: a base class, not a collaborator, so the
engine calls ``runner.start()`` and the message path pays no extra indirection.
"""

from __future__ import annotations

import asyncio
import logging
from typing import TYPE_CHECKING, Any

from engine.common.backoff import Backoff
from engine.endpoints.base import Connection, Deliver, EndpointError, Source
from engine.running.buffer import HoldingBuffer, stats_dict
from engine.running.fanout import fan_out_of
from engine.running.observe import RouteObserver
from engine.running.pipeline import Pipeline
from engine.running.replies import Replies
from engine.running.route_state import RouteHost

if TYPE_CHECKING:
    from engine.language.specs import RouteSpec

log = logging.getLogger("engine.running.runtime")

START_RETRY_FIRST, START_RETRY_MAX = 0.5, 10.0
"""Backoff between attempts to start a source whose connection went down again meanwhile."""


class RouteLifecycle:
    """Starting, stopping and the status of a route runner (see the module docstring); the
    runner's ``__init__`` sets what is declared here."""

    host: RouteHost
    spec: RouteSpec
    pipeline: Pipeline
    source: Source
    connections: list[Connection]
    """The source's then the sinks' connections: kept open while the runner lives."""
    sink_count: int
    lease: Any
    """The broker lease of an ``active_standby`` route: only its holder forwards."""
    observer: RouteObserver
    buffer: HoldingBuffer | None
    replies: Replies
    state: str
    """created, waiting (for a connection that is not open yet), running, stopped."""
    _starter: asyncio.Task[None] | None
    _stopping: asyncio.Event

    def receiver(self) -> Deliver:
        """What the source hands its messages to (the runner decides)."""
        raise NotImplementedError

    def buffer_owner(self) -> Any:
        """What the route's buffer calls back (engine/running/held.py)."""
        raise NotImplementedError

    async def start(self) -> None:
        """Start the source now if the connections it needs are open, else in the background
        once they are (a buffered route needs only its source's: the buffer holds the rest)."""
        if self.buffer is not None:
            self.buffer.start()
        missing = self.missing_connections()
        if not missing:
            await self.source.start(self.receiver())
            self.state = "running"
            return
        self.state = "waiting"
        log.warning("route waits for its connections", extra={"route": self.spec.name, "connections": missing})
        self._starter = asyncio.create_task(self._start_when_open(), name=f"start-{self.spec.name}")

    def _needed(self) -> list[Connection]:
        """What must be open before the source starts: all (the source's only, with a buffer
        that holds the rest); a route with several sinks waits for its sinks itself (a sink's
        fallback takes over while its connection cannot open: engine/running/fanout.py)."""
        if self.buffer is not None or self.pipeline.sink_connection is None:
            return self.connections[:len(self.connections) - self.sink_count]
        return self.connections

    def missing_connections(self) -> list[str]:
        return [c.name for c in self._needed() if not self.host.is_open(c)]

    async def _start_when_open(self) -> None:
        backoff = Backoff(START_RETRY_FIRST, START_RETRY_MAX)
        while True:
            await self.host.wait_open(self._needed())
            try:
                await self.source.start(self.receiver())
            except EndpointError as error:  # the connection went down again meanwhile
                log.warning("route could not start; retrying", extra={"route": self.spec.name, "error": str(error)})
                await asyncio.sleep(backoff.next())
                continue
            self.state = "running"
            log.info("route started", extra={"route": self.spec.name})
            return

    def give_buffer_to_self(self) -> None:
        """This runner is the route's live one: it sends what the route's buffer holds."""
        if self.buffer is not None:
            self.host.buffers.hand_to(self.spec.name, self.buffer, self.buffer_owner())

    async def retire_pipeline(self, pipeline: Pipeline) -> None:
        """Let ``pipeline`` go: what its throttle parks goes out, then its sink closes (the
        runner does it: it is the throttle's stage)."""
        raise NotImplementedError

    def halt(self) -> None:
        """Stop waiting to start, and stop retrying: what is not settled now stays unsettled."""
        self.state = "stopped"
        self._stopping.set()
        if self._starter is not None:
            self._starter.cancel()

    def stop_starting(self) -> None:
        """Do not start later (the engine stops): the source stops taking messages next. A
        route whose sink is not ready has nothing to drain into: it lets go of what it holds
        at once (measured: the whole drain timeout, 10 s, otherwise)."""
        self.state = "stopped"
        if self._starter is not None:
            self._starter.cancel()
        if not self.pipeline.sink.ready:
            self._stopping.set()

    async def stop(self, drain_timeout: float = 0.0) -> None:
        self.halt()
        if self._starter is not None:
            await asyncio.gather(self._starter, return_exceptions=True)
        await self.source.stop()
        if self.buffer is not None and self.host.buffers.release(self.spec.name, self.buffer):
            await self.buffer.close(drain_timeout)
        await self.retire_pipeline(self.pipeline)

    def status(self) -> dict[str, Any]:
        """The route in the engine's status: where it is defined, its role, its counters."""
        spec, lease = self.spec, self.lease
        return {
            "file": f"{spec.file}:{spec.line}",
            "fingerprint": spec.fingerprint,
            "generation": self.pipeline.generation,
            "role": lease.role if lease else ("partitioned" if spec.placement.partitions > 1 else
                                              "single-active-consumer" if spec.placement.ordered else "shared"),
            "lease_changes": lease.changes if lease else 0,
            **self.observer.counters(),
            "source": self.source.status(),
            "state": self.state,
            "waiting_for": self.missing_connections() if self.state == "waiting" else [],
            "sink_not_ready": self.pipeline.sink.not_ready_reason(),
            **({"sinks": sinks} if (sinks := fan_out_of(self.pipeline.sink)) is not None else {}),
            "source_degraded": self.source.degraded_reason(),
            "buffer": stats_dict(self.buffer) if self.buffer is not None else None,
            "replies": self.replies.counters(),
        }
