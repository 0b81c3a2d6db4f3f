"""A message's life in a route, from its source's batch to settling, in one place.

A :class:`RouteRunner` is what a route's source hands its messages to (the
:class:`~engine.endpoints.base.Deliver` contract). Each message goes through these stages,
in order, and is settled for its source once it leaves them:

1. **received**: counted once (engine/running/observe.py keeps the route's one set of counters);
2. **converted** by the route's pipeline (engine/running/pipeline.py); a message that cannot be
   decoded, converted, or that is too large, or that already used its attempts, is a dead
   letter; one the route's ``when:`` rejects is settled unsent (``filtered``), and one whose
   ``dedupe:`` key the sink accepted within its ttl too (``duplicates``, engine/running/dedupe.py);
   one of a ``window:`` route is added to its window and settled (``windowed``); each closed
   window's message then takes steps 4 and 5 (engine/running/windows.py);
3. **throttled** (``throttle:``, engine/running/throttle.py): parked and settled; the slot releases
   the converted message to step 4, or a newer one conflates it;
4. **sent**: while the sink cannot take messages the route waits (or, with a buffer, holds
   them: engine/running/buffer.py); transient failures are retried with the engine's backoff up to
   ``max_attempts`` (engine/running/delivery.py decides what is transient), then dead-lettered. A
   message older than the route's ``max_age`` when it would be sent (at once, from a throttle
   slot, on a retry, from the buffer) is expired instead: :meth:`RouteRunner.too_old` is the
   one place that decides it;
5. **dead-lettered** together at the end of the batch (engine/running/dead_letters.py).

A batch is settled as a whole: one pipelined ``send_batch``, the failures retried together,
all dead letters of the batch stored together (AMQP: one confirm round), so a batch costs a
constant number of round trips however large it is. No message is logged on its own: a
:class:`~engine.common.logs.ReportLimiter` reports at most once per second per route, with the count
it held back.

The runner needs only what :class:`~engine.running.route_state.RouteHost` declares of the
engine that runs it. Its roles apart: starting, stopping and the status in its base class
(engine/running/route_lifecycle.py); dead letters, failure reports and the replies of calls
that end unsent (engine/running/dead_lettering.py); the buffer's callbacks
(engine/running/held.py). What stays here is the per-message path (stages 1 to 4), in one
class so a message pays no extra indirection (measured in the commit that split it).
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import TYPE_CHECKING, Any, Sequence

from engine.common.schemas import canonical_bytes

from engine.endpoints.base import (Connection, Conflated, EndpointError, Inbound, Inbox, MessageRejected, NotSent, Outbound, Refused, Source,
                                   Unroutable)
from engine.running.buffer import HoldingBuffer
from engine.running.dead_lettering import DeadLettering
from engine.running.delivery import HEALTH_POLL, Failure, classify, given_up, prior_attempts, retry_delay
from engine.running.fairness import route_inbox
from engine.running.held import HeldMessages
from engine.running.pipeline import ConversionError, Filtered, Pipeline, Windowed
from engine.running.replies import Replies
from engine.running.route_lifecycle import RouteLifecycle
from engine.running.route_state import Converted, Dead, RouteHost

if TYPE_CHECKING:
    from engine.language.specs import RouteSpec

log = logging.getLogger("engine.running.runtime")


class RouteRunner(RouteLifecycle):
    """A route's live source and its current pipeline (swapped by a reload); the source's
    :class:`~engine.endpoints.base.Deliver` (see the module docstring)."""

    def __init__(self, host: RouteHost, spec: RouteSpec, pipeline: Pipeline, source: Source,
                 connections: list[Connection]) -> None:
        self.host = host
        self.spec = spec
        self.pipeline = pipeline
        self.source = source
        self.connections = connections
        """The source's then the sinks' connections: kept open while the runner lives."""
        self.sink_count = len(connections) - 1
        """How many of ``connections`` are the sinks' (the last ones; a reload may change them)."""
        self.lease: Any = None
        """The broker lease of an ``active_standby`` route: only its holder forwards."""
        self.observer = host.observers.get(spec.name)
        """The route's one set of counters, and its taps (engine/running/observe.py)."""
        self.observer.generation = lambda: self.pipeline.generation
        self.observer.carries(spec.schema)
        self.replies = Replies(spec.name, source)
        """The route's replies to requests (engine/running/replies.py), through this runner's source."""
        self.dead_lettering = DeadLettering(self)
        """Stage 5, failure reports, and the one reply of a call that ends unsent."""
        self.held = HeldMessages(self, self.dead_lettering)
        """What the route's buffer calls back (engine/running/held.py)."""
        self.buffer: HoldingBuffer | None = None if spec.buffer is None else host.buffers.acquire(
            spec.name, spec.buffer, spec.delivery.max_attempts, self.held)
        """Holds the route's messages while its sink is down (``buffer:``; engine/running/buffer.py)."""
        self.state = "created"
        """created, waiting (for a connection that is not open yet), running, stopped."""
        self._starter: asyncio.Task[None] | None = None
        self._stopping = asyncio.Event()
        self._released: set[asyncio.Task[None]] = set()
        """Messages the throttle released from their slot, on their way to the sink."""

    # -- the Deliver contract a source sees

    @property
    def overflow(self) -> str:
        return self.spec.delivery.overflow

    @property
    def queue_limit(self) -> int:
        return self.spec.delivery.queue_limit

    @property
    def batches_in_flight(self) -> int:
        """The one decision of how many batches the source may have in flight (the
        ``Deliver`` contract): what the sink declares, but one at a time where the route
        keeps order (``ordered``) or its buffer does (held messages go out in order)."""
        if self.spec.placement.ordered or self.buffer is not None:
            return 1
        return max(1, self.pipeline.sink.batches_in_flight)

    async def __call__(self, inbound: Inbound) -> None:
        if not (await self.batch((inbound,)))[0]:
            raise EndpointError(f"route {self.spec.name!r}: message not settled (route stopping)")

    deliver = __call__

    def dropped(self, count: int = 1) -> None:
        self.observer.dropped += count

    def inbox(self, overflow: str) -> Inbox[Inbound]:
        """The route's queue in its source: its ``fair:`` decides which (engine/running/fairness.py)."""
        return route_inbox(self.spec.fair, self.queue_limit, overflow, self.observer.agent_dropped)

    async def batch(self, inbounds: Sequence[Inbound]) -> list[bool]:
        """Take a batch through the stages; ``result[i]`` is True once ``inbounds[i]`` was
        accepted by the sink, parked by the throttle, held, or stored as a dead letter."""
        pipeline = self.pipeline
        settled = [False] * len(inbounds)
        pipeline.enter()
        try:
            self.observer.took(len(inbounds), inbounds)
            dead: list[Dead] = []
            pending = self._convert(pipeline, inbounds, settled, dead)
            if pending:
                await self._send(pipeline, pending, settled, dead)
            if dead:
                await self.dead_lettering.store(dead, settled)
        finally:
            pipeline.leave()
        return settled

    # -- stages 2 and 3: conversion, checks, the throttle

    def _convert(self, pipeline: Pipeline, inbounds: Sequence[Inbound], settled: list[bool],
                 dead: list[Dead]) -> list[Converted]:
        """Convert every message; what cannot be sent goes to ``dead``, what the throttle
        parks is settled; the rest is returned, in order."""
        pending: list[Converted] = []
        throttle, dedupe, remember = pipeline.throttle, pipeline.dedupe, pipeline.remember
        for index, inbound in enumerate(inbounds):
            message = self._converted(pipeline, index, inbound)
            if isinstance(message, Filtered):  # the route's when: said no
                settled[index] = True
                self.observer.filter(inbound, message.canonical)
                self.dead_lettering.filtered_call(inbound)
                continue
            if isinstance(message, Windowed):
                settled[index] = self._windowed(pipeline, index, inbound, message, dead)
                continue
            if remember is not None and message.outbound is not None and message.outbound.canonical is not None:
                remember.on_converted(message.outbound.canonical, message.outbound.meta)
            if isinstance(message, Dead):
                dead.append(message)
            elif dedupe is not None and self._duplicate(dedupe, message):
                settled[index] = True
            elif throttle is not None and not throttle.admit(message, message.outbound.canonical, self):
                settled[index] = True  # parked: sent when its slot opens, or conflated by a newer one
            else:
                pending.append(message)
        return pending

    def _duplicate(self, dedupe: Any, message: Converted) -> bool:
        """Whether ``message``'s key was accepted within the ttl (then it is counted, and a call
        told); else its key is kept on it, to be recorded once the sink accepts it."""
        outbound = message.outbound
        assert outbound is not None
        key = dedupe.key(outbound.canonical, outbound.meta)
        if key is not None and dedupe.keys.seen(key):
            self.observer.duplicate(message.inbound, outbound)
            self.dead_lettering.ended_call(outbound, "dedupe", "duplicate: a message with its key was accepted within the route's dedupe ttl")
            return True
        message.dedupe_key = key
        return False

    def _windowed(self, pipeline: Pipeline, index: int, inbound: Inbound, windowed: Windowed, dead: list[Dead]) -> bool:
        """Add a message to the route's open window: settled (True), or a dead letter (stage ``window``)."""
        window = pipeline.window
        assert window is not None  # only a window route's pipeline raises Windowed
        if window.stage is None:
            window.stage = lambda outputs: self.window_closed(pipeline, outputs)
        problem = window.add(windowed, inbound.meta)
        if problem is None:
            self.observer.window(inbound, windowed.canonical)
            return True
        dead.append(Dead(index, inbound, None, prior_attempts(inbound.meta) + 1, pipeline, Failure("window", problem, True)))
        return False

    def window_closed(self, pipeline: Pipeline, outputs: list[tuple[dict[str, Any], dict[str, Any]]]) -> None:
        """Each closed window's message goes through the sink mapping and to the sink, together."""
        messages: list[Converted] = []
        dead: list[Dead] = []
        settled = [False] * len(outputs)
        for index, (emitted, meta) in enumerate(outputs):
            inbound = Inbound(body=canonical_bytes(emitted), meta=meta)
            try:
                outbound = pipeline.window_output(emitted, meta)
            except ConversionError as error:
                dead.append(Dead(index, inbound, None, 1, pipeline, classify(error, "sink mapping")))
                continue
            except Filtered:  # several sinks, none of whose when: chose it
                self.observer.filter(inbound, emitted)
                settled[index] = True
                continue
            outbound.received_ns = inbound.received_ns
            messages.append(Converted(index, inbound, outbound, 0, pipeline))
        self.observer.emitted += len(outputs)
        pipeline.enter()  # before the pipeline can be seen drained
        task = asyncio.create_task(self._send_window(pipeline, messages, dead, settled))
        self._released.add(task)
        task.add_done_callback(self._released_done)

    async def _send_window(self, pipeline: Pipeline, messages: list[Converted], dead: list[Dead], settled: list[bool]) -> None:
        try:
            if messages:
                await self._send(pipeline, messages, settled, dead)
            if dead:
                await self.dead_lettering.store(dead, settled)
            self.observer.dropped += settled.count(False)  # the route stopped meanwhile
        finally:
            pipeline.leave()

    def _converted(self, pipeline: Pipeline, index: int, inbound: Inbound) -> Converted | Dead | Filtered | Windowed:
        """The message converted, or with the failure that makes it a dead letter; the
        :class:`Filtered` raised when the route's ``when:`` rejected it."""
        delivery = pipeline.spec.delivery
        prior = prior_attempts(inbound.meta)
        body = inbound.body
        if inbound.undecodable is not None:
            return Dead(index, inbound, None, prior + 1, pipeline, Failure("decode", inbound.undecodable, True))
        if body is not None and len(body) > delivery.max_message_bytes:
            failure = Failure("size", f"{len(body)} bytes exceed max_message_bytes {delivery.max_message_bytes}", True)
            return Dead(index, inbound, None, prior + 1, pipeline, failure)
        try:
            if pipeline.sink.cancels and inbound.meta.get("cancel") is not None:
                outbound = pipeline.cancel_request(inbound)
            else:
                outbound = pipeline.convert(inbound)
        except (Filtered, Windowed) as shaped:
            return shaped
        except Exception as error:  # ConversionError, or anything the pipeline did not foresee
            return Dead(index, inbound, None, prior + 1, pipeline, classify(error, "convert"),
                        error.canonical if isinstance(error, ConversionError) else None)
        if len(outbound.body) > delivery.sink_max_message_bytes:
            failure = Failure("size", f"canonical message of {len(outbound.body)} bytes exceeds the sink "
                              f"connection's max_message_bytes {delivery.sink_max_message_bytes}", True)
            return Dead(index, inbound, outbound, prior + 1, pipeline, failure)
        outbound.reply = self.replies.bind(pipeline.reply_shape, inbound.meta)
        outbound.received_ns = inbound.received_ns
        if prior >= delivery.max_attempts:
            failure = Failure("sink", f"already attempted {prior} times (max_attempts {delivery.max_attempts})", False)
            return Dead(index, inbound, outbound, prior, pipeline, failure)
        return Converted(index, inbound, outbound, prior, pipeline)

    def released(self, message: Converted) -> None:
        """The throttle released a parked message: it goes to the sink on the pipeline that
        converted it (its source was answered when it was parked, so ``settled`` is its own)."""
        pipeline = message.pipeline
        pipeline.enter()  # before the pipeline can be seen drained
        message.index = 0
        task = asyncio.create_task(self._send_released(pipeline, message))
        self._released.add(task)
        task.add_done_callback(self._released_done)

    def conflated(self, message: Converted) -> None:
        self.observer.conflate(message.inbound, message.outbound)
        self.dead_lettering.ended_call(message.outbound, "throttle", "conflated: a newer message took its throttle slot before it was sent")

    async def _send_released(self, pipeline: Pipeline, message: Converted) -> None:
        try:
            dead: list[Dead] = []
            settled = [False]
            await self._send(pipeline, [message], settled, dead)
            if dead:
                await self.dead_lettering.store(dead, settled)
            if not settled[0]:  # the route stopped meanwhile; its source cannot have it again
                self.observer.dropped += 1
        finally:
            pipeline.leave()

    def _released_done(self, task: asyncio.Task[None]) -> None:
        self._released.discard(task)
        error = None if task.cancelled() else task.exception()
        if error is not None:
            log.error("throttled message failed", extra={"route": self.spec.name, "error": repr(error)})

    # -- stage 4: the sink

    def sink_can_take(self, pipeline: Pipeline | None = None) -> bool:
        """The one place the route asks whether its sink can take messages now: its
        connection is open and does not report itself down, and the sink is ready (a ROS 2
        topic some subscriber has matched). Everything that waits for the sink, holds
        messages instead of trying it, or lets the buffer try it asks this."""
        pipeline = pipeline or self.pipeline
        connection = pipeline.sink_connection  # None: several sinks, each asked by the sink itself (engine/running/fanout.py)
        return (connection is None or (connection.healthy and self.host.is_open(connection))) and pipeline.sink.ready

    async def _send(self, pipeline: Pipeline, pending: list[Converted], settled: list[bool],
                    dead: list[Dead]) -> None:
        """Send, retry while transient (or hand to the buffer), until each is settled, dead
        (appended to ``dead``) or the route stops (left unsettled)."""
        buffer = self.buffer
        while pending:
            if buffer is not None and (buffer.holding or not self.sink_can_take(pipeline)):
                await self._hold(pending, settled)  # behind what the buffer holds, in order
                return
            if not self._ready_now(pipeline) and not await self._sink_ready(pipeline):
                if buffer is not None:  # kept: spilled, or delivered by the runner replacing this one
                    await self._hold(pending, settled)
                return  # the route is stopping: what is left stays unsettled
            pending = self._fresh(pending, settled)
            if not pending:
                return
            if pipeline.dedupe is not None:  # in doubt until the sink answers (engine/running/dedupe.py)
                pipeline.dedupe.keys.send([m.dedupe_key for m in pending if m.dedupe_key is not None])
            results = await pipeline.sink.send_batch([message.outbound for message in pending])
            # whether the sink can take messages now matters only for a failure (see _sent): a
            # batch that all went out does not ask again (a ROS 2 sink's readiness is an rcl
            # call, 2.8 us, and a drain's batches are 3 messages long: measured 3,960 batches
            # for 13,200 messages)
            failed = results.count(None) != len(results)
            pending = self._sent(pending, results, settled, dead, waiting=failed and not self.sink_can_take(pipeline))
            if pending and buffer is not None:  # transient: the buffer retries them, the source moves on
                await self._hold(pending, settled)
                return
            if pending:
                failure = pending[0].failure
                assert failure is not None  # _sent returns only messages it set a failure on
                self.dead_lettering.report_retry(failure, len(pending))
                if not await self.pause(retry_delay(min(message.attempts for message in pending))):
                    return

    def too_old(self, age_ns: int) -> bool:
        """The one decision of freshness: a message received ``age_ns`` ago is not sent any
        more but expired (``max_age``; telemetry is worthless once stale, events have none)."""
        max_age_ns = self.spec.delivery.max_age_ns
        return max_age_ns is not None and age_ns > max_age_ns

    def _fresh(self, pending: list[Converted], settled: list[bool]) -> list[Converted]:
        """``pending`` without the messages too old to send, which are settled as expired."""
        if self.spec.delivery.max_age_ns is None:
            return pending
        now_ns = time.monotonic_ns()
        fresh = []
        for message in pending:
            if self.too_old(now_ns - message.inbound.received_ns):
                settled[message.index] = True
                self.observer.expire(message.inbound, message.outbound)
                self.dead_lettering.expired_call(message.outbound)
            else:
                fresh.append(message)
        return fresh

    def _sent(self, pending: list[Converted], results: list[BaseException | None], settled: list[bool],
              dead: list[Dead], waiting: bool = False) -> list[Converted]:
        """Settle what the sink accepted, move what failed for good to ``dead``; return what
        is to be tried again. ``waiting``: the sink says now that it cannot take messages (a
        ROS 2 topic a message named has no subscriber yet), so a transient failure is the
        route waiting, not an attempt (as the buffer counts it)."""
        retry: list[Converted] = []
        max_attempts = self.spec.delivery.max_attempts
        keys: list[str] = []
        unsent: list[str] = []
        for message, error in zip(pending, results):
            if not (waiting and isinstance(error, EndpointError) and not isinstance(error, MessageRejected)):
                message.attempts += 1
            if error is None:
                settled[message.index] = True
                self._accepted(message.inbound, message.outbound)
                if message.pipeline.remember is not None:
                    message.pipeline.remember.on_accepted(message.outbound.canonical, message.outbound.meta)
                if message.dedupe_key is not None:
                    keys.append(message.dedupe_key)
                continue
            if message.dedupe_key is not None:  # a refusal is an answer: its key is remembered as an acceptance's
                (keys if isinstance(error, Refused) else unsent).append(message.dedupe_key)
            if isinstance(error, NotSent):  # the sink settled it undelivered: refused, conflated, or expired while it tried
                settled[message.index] = True
                self._not_sent(error, message.inbound, message.outbound)
                continue
            failure = classify(error, "sink")
            if isinstance(error, Unroutable):
                self.observer.unroutable += 1
            if not failure.permanent:
                self.observer.sink_errors += 1
            if failure.permanent or message.attempts >= max_attempts:
                dead.append(Dead(message.index, message.inbound, message.outbound, message.attempts, message.pipeline,
                                  failure if failure.permanent else given_up(failure, message.attempts)))
            else:
                message.failure = failure
                retry.append(message)
                self.observer.retrying(message.inbound, message.outbound, error)
        if keys or unsent:  # one write for the batch, before its source is acknowledged (engine/running/dedupe.py)
            dedupe = pending[0].pipeline.dedupe
            assert dedupe is not None  # only a dedupe: route's messages have keys
            dedupe.keys.answered(keys, unsent)
        return retry

    def _not_sent(self, outcome: NotSent, inbound: Inbound | None, outbound: Outbound) -> None:
        """Count a message its sink settled without delivering it (engine/endpoints/base.py)."""
        if isinstance(outcome, Refused):  # the sink replied with the refusal itself
            self.observer.refuse(inbound, outbound)
        elif isinstance(outcome, Conflated):
            self.observer.conflate(inbound, outbound)
        else:
            self.observer.expire(inbound, outbound)
            self.dead_lettering.expired_call(outbound)

    def _accepted(self, inbound: Inbound, outbound: Outbound) -> None:
        self.observer.accepted(inbound, outbound, time.monotonic_ns() - inbound.received_ns)

    def _ready_now(self, pipeline: Pipeline) -> bool:
        """What :meth:`_sink_ready` answers when it need not wait: asked first, inline, as the
        ready sink is the common case and a coroutine per batch is not free."""
        return self.sink_can_take(pipeline) and not self._stopping.is_set()

    async def _sink_ready(self, pipeline: Pipeline) -> bool:
        """Wait while the sink cannot take messages; False once the route stops, or once a
        reload swapped ``pipeline`` out meanwhile (its messages go back to the source or to
        the buffer, for the new one: a reload must not wait for a subscriber)."""
        while not self.sink_can_take(pipeline):
            if not await self.pause(HEALTH_POLL) or self.pipeline is not pipeline:
                return False
        return not self._stopping.is_set()

    async def pause(self, seconds: float) -> bool:
        """Sleep between attempts; False (at once) when the route stops meanwhile."""
        try:
            await asyncio.wait_for(self._stopping.wait(), seconds)
        except asyncio.TimeoutError:
            return True
        return False

    # -- the buffer (engine/running/buffer.py): what the route hands it (its way out: engine/running/held.py)

    async def _hold(self, pending: list[Converted], settled: list[bool]) -> None:
        """Hand messages to the buffer, in order; each is settled for its source once held."""
        assert self.buffer is not None
        now_ns, wall_ns = time.monotonic_ns(), time.time_ns()
        for message in pending:
            await self.buffer.hold(message.outbound, wall_ns - (now_ns - message.inbound.received_ns))
            settled[message.index] = True

    # -- the lifecycle (engine/running/route_lifecycle.py) asks these of the runner

    def receiver(self) -> RouteRunner | StandbyGate:
        """What the source hands its messages to: this runner, or for an ``active_standby``
        route the gate that forwards only while this instance holds the lease."""
        return StandbyGate(self) if self.lease is not None else self

    def buffer_owner(self) -> HeldMessages:
        return self.held

    async def retire_pipeline(self, pipeline: Pipeline) -> None:
        if pipeline.throttle is not None:  # parked messages go out, not lost
            pipeline.throttle.close(self)
        if pipeline.window is not None:  # the open window is emitted with what it has
            pipeline.window.close()
        await pipeline.drained()
        await pipeline.sink.close()


class StandbyGate:
    """The :class:`~engine.endpoints.base.Deliver` an ``active_standby`` route's source is
    given: while another instance holds the route's lease, messages are settled by being
    dropped (and counted), because the active instance forwards its own copy."""

    def __init__(self, runner: RouteRunner) -> None:
        self.runner = runner

    @property
    def overflow(self) -> str:
        return self.runner.overflow

    @property
    def queue_limit(self) -> int:
        return self.runner.queue_limit

    @property
    def batches_in_flight(self) -> int:
        return self.runner.batches_in_flight

    def dropped(self, count: int = 1) -> None:
        self.runner.dropped(count)

    def inbox(self, overflow: str) -> Inbox[Inbound]:
        return self.runner.inbox(overflow)

    async def batch(self, inbounds: Sequence[Inbound]) -> list[bool]:
        if not self.runner.lease.active:
            self.runner.observer.standby_skipped += len(inbounds)
            return [True] * len(inbounds)
        return await self.runner.batch(inbounds)

    async def __call__(self, inbound: Inbound) -> None:
        if not self.runner.lease.active:
            self.runner.observer.standby_skipped += 1
            return
        await self.runner(inbound)
