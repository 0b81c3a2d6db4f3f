"""A message's life in a route, from its source's batch to settling, in one place.

A :class:`RouteRunner` is what a route's source hands its messages to (the
:class:`~engine.endpoints.base.Deliver` contract). Each message goes through these stages,
in order, and is settled for its source once it leaves them:

1. **received**: counted once (engine/running/observe.py keeps the route's one set of counters);
2. **converted** by the route's pipeline (engine/running/pipeline.py); a message that cannot be
   decoded, converted, or that is too large, or that already used its attempts, is a dead
   letter; one the route's ``when:`` rejects is settled unsent (``filtered``), and one whose
   ``dedupe:`` key the sink accepted within its ttl too (``duplicates``, engine/running/dedupe.py);
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

The runner needs only what :class:`RouteHost` declares of the engine that runs it.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import TYPE_CHECKING, Any, Protocol, Sequence

from engine.common.backoff import Backoff
from engine.common.logs import ReportLimiter
from engine.endpoints.base import (Connection, Conflated, EndpointError, Inbound, Inbox, MessageRejected, NotSent, Outbound, Source,
                                   Unroutable)
from engine.running.buffer import Buffers, Held, HoldingBuffer, stats_dict
from engine.running.dead_letters import DeadLetters, dead_letter_message
from engine.running.delivery import HEALTH_POLL, Failure, classify, given_up, prior_attempts, retry_delay
from engine.running.fairness import route_inbox
from engine.running.observe import Observers
from engine.running.pipeline import Filtered, Pipeline
from engine.running.replies import Replies

if TYPE_CHECKING:
    from engine.language.routes import RouteSpec

log = logging.getLogger("engine.running.runtime")

START_RETRY_FIRST, START_RETRY_MAX = 0.5, 10.0
"""Backoff between attempts to start a source whose connection went down again meanwhile."""


class RouteHost(Protocol):
    """What a route needs of the engine that runs it (engine/running/runtime.py's ``Engine``)."""

    observers: Observers
    """Every route's counters, by route name, kept across reloads."""
    buffers: Buffers
    """Every route's buffer, shared across a reload by the runners of a route."""
    dead_letters: DeadLetters | None
    """The engine's one dead-letter destination (set before any route starts)."""

    def is_open(self, connection: Connection) -> bool:
        """Whether ``connection`` was opened (it may be reconnecting now)."""

    async def wait_open(self, connections: Sequence[Connection]) -> None:
        """Return once every one of ``connections`` is open."""


class _Message:
    """A message between its conversion and its settling: converted, so it has an outbound."""

    __slots__ = ("index", "inbound", "outbound", "attempts", "failure", "pipeline", "dedupe_key")

    def __init__(self, index: int, inbound: Inbound, outbound: Outbound, attempts: int,
                 pipeline: Pipeline, failure: Failure | None = None) -> None:
        self.index = index
        self.inbound = inbound
        self.outbound = outbound
        self.attempts = attempts
        self.pipeline = pipeline
        """The pipeline (generation) that converted it, whose sink sends it."""
        self.failure = failure
        """The sink's last transient failure while it is retried."""
        self.dedupe_key: str | None = None
        """Its ``dedupe:`` key, recorded once the sink accepted it."""


class _Dead:
    """A message that failed for good, to be stored as a dead letter: its ``failure`` is
    known, its ``outbound`` is None when it failed before or in its conversion."""

    __slots__ = ("index", "inbound", "outbound", "attempts", "failure", "pipeline")

    def __init__(self, index: int, inbound: Inbound, outbound: Outbound | None, attempts: int,
                 pipeline: Pipeline, failure: Failure) -> None:
        self.index = index
        self.inbound = inbound
        self.outbound = outbound
        self.attempts = attempts
        self.pipeline = pipeline
        self.failure = failure


class RouteRunner:
    """A route's live source and its current pipeline (swapped by a reload); the source's
    :class:`~engine.endpoints.base.Deliver` (see the module docstring)."""

    def __init__(self, host: RouteHost, spec: RouteSpec, pipeline: Pipeline, source: Source,
                 connections: list[Connection]) -> None:
        self.host = host
        self.spec = spec
        self.pipeline = pipeline
        self.source = source
        self.connections = connections
        """The source's then the sink's connection: kept open while the runner lives."""
        self.lease: Any = None
        """The broker lease of an ``active_standby`` route: only its holder forwards."""
        self.observer = host.observers.get(spec.name)
        """The route's one set of counters, and its taps (engine/running/observe.py)."""
        self.observer.generation = lambda: self.pipeline.generation
        self.observer.carries(spec.schema)
        self.buffer: HoldingBuffer | None = None if spec.buffer is None else host.buffers.acquire(
            spec.name, spec.buffer, spec.delivery.max_attempts, self)
        """Holds the route's messages while its sink is down (``buffer:``; engine/running/buffer.py)."""
        self.replies = Replies(spec.name, source)
        """The route's replies to requests (engine/running/replies.py), through this runner's source."""
        self.state = "created"
        """created, waiting (for a connection that is not open yet), running, stopped."""
        self._starter: asyncio.Task[None] | None = None
        self._stopping = asyncio.Event()
        self._report = ReportLimiter()
        self._retry_report = ReportLimiter()
        self._released: set[asyncio.Task[None]] = set()
        """Messages the throttle released from their slot, on their way to the sink."""
        self._replying: set[asyncio.Task[None]] = set()
        """Error replies to calls settled without being sent (expired, conflated), on their way."""

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
            dead: list[_Dead] = []
            pending = self._convert(pipeline, inbounds, settled, dead)
            if pending:
                await self._send(pipeline, pending, settled, dead)
            if dead:
                await self._dead_letter(dead, settled)
        finally:
            pipeline.leave()
        return settled

    # -- stages 2 and 3: conversion, checks, the throttle

    def _convert(self, pipeline: Pipeline, inbounds: Sequence[Inbound], settled: list[bool],
                 dead: list[_Dead]) -> list[_Message]:
        """Convert every message; what cannot be sent goes to ``dead``, what the throttle
        parks is settled; the rest is returned, in order."""
        pending: list[_Message] = []
        throttle, dedupe, remember = pipeline.throttle, pipeline.dedupe, pipeline.remember
        for index, inbound in enumerate(inbounds):
            message = self._converted(pipeline, index, inbound)
            if isinstance(message, Filtered):  # the route's when: said no
                settled[index] = True
                self.observer.filter(inbound, message.canonical)
                self._filtered_call(inbound)
                continue
            if remember is not None and message.outbound is not None and message.outbound.canonical is not None:
                remember.on_converted(message.outbound.canonical, message.outbound.meta)
            if isinstance(message, _Dead):
                dead.append(message)
            elif dedupe is not None and self._duplicate(dedupe, message):
                settled[index] = True
            elif throttle is not None and not throttle.admit(message, message.outbound.canonical, self):
                settled[index] = True  # parked: sent when its slot opens, or conflated by a newer one
            else:
                pending.append(message)
        return pending

    def _duplicate(self, dedupe: Any, message: _Message) -> bool:
        """Whether ``message``'s key was accepted within the ttl (then it is counted, and a call
        told); else its key is kept on it, to be recorded once the sink accepts it."""
        outbound = message.outbound
        assert outbound is not None
        key = dedupe.key(outbound.canonical, outbound.meta)
        if key is not None and dedupe.keys.seen(key):
            self.observer.duplicate(message.inbound, outbound)
            self._ended_call(outbound, "dedupe", "duplicate: a message with its key was accepted within the route's dedupe ttl")
            return True
        message.dedupe_key = key
        return False

    def _filtered_call(self, inbound: Inbound) -> None:
        """A request the route's ``when:`` rejected: its caller hears one ``error`` reply."""
        if inbound.meta.get("reply_to"):
            task = asyncio.create_task(self.replies.failed(None, inbound.meta, "when", "filtered: the route's when: condition is false"))
            self._replying.add(task)
            task.add_done_callback(self._replying.discard)

    def _converted(self, pipeline: Pipeline, index: int, inbound: Inbound) -> _Message | _Dead | Filtered:
        """The message converted, or with the failure that makes it a dead letter; the
        :class:`Filtered` raised when the route's ``when:`` rejected it."""
        delivery = pipeline.spec.delivery
        prior = prior_attempts(inbound.meta)
        body = inbound.body
        if inbound.undecodable is not None:
            return _Dead(index, inbound, None, prior + 1, pipeline, Failure("decode", inbound.undecodable, True))
        if body is not None and len(body) > delivery.max_message_bytes:
            failure = Failure("size", f"{len(body)} bytes exceed max_message_bytes {delivery.max_message_bytes}", True)
            return _Dead(index, inbound, None, prior + 1, pipeline, failure)
        try:
            if pipeline.sink.cancels and inbound.meta.get("cancel") is not None:
                outbound = pipeline.cancel_request(inbound)
            else:
                outbound = pipeline.convert(inbound)
        except Filtered as filtered:
            return filtered
        except Exception as error:  # ConversionError, or anything the pipeline did not foresee
            return _Dead(index, inbound, None, prior + 1, pipeline, classify(error, "convert"))
        if len(outbound.body) > delivery.sink_max_message_bytes:
            failure = Failure("size", f"canonical message of {len(outbound.body)} bytes exceeds the sink "
                              f"connection's max_message_bytes {delivery.sink_max_message_bytes}", True)
            return _Dead(index, inbound, outbound, prior + 1, pipeline, failure)
        outbound.reply = self.replies.bind(pipeline.reply_shape, inbound.meta)
        outbound.received_ns = inbound.received_ns
        if prior >= delivery.max_attempts:
            failure = Failure("sink", f"already attempted {prior} times (max_attempts {delivery.max_attempts})", False)
            return _Dead(index, inbound, outbound, prior, pipeline, failure)
        return _Message(index, inbound, outbound, prior, pipeline)

    def released(self, message: _Message) -> None:
        """The throttle released a parked message: it goes to the sink on the pipeline that
        converted it (its source was answered when it was parked, so ``settled`` is its own)."""
        pipeline = message.pipeline
        pipeline.enter()  # before the pipeline can be seen drained
        message.index = 0
        task = asyncio.create_task(self._send_released(pipeline, message))
        self._released.add(task)
        task.add_done_callback(self._released_done)

    def conflated(self, message: _Message) -> None:
        self.observer.conflate(message.inbound, message.outbound)
        self._ended_call(message.outbound, "throttle", "conflated: a newer message took its throttle slot before it was sent")

    async def _send_released(self, pipeline: Pipeline, message: _Message) -> None:
        try:
            dead: list[_Dead] = []
            settled = [False]
            await self._send(pipeline, [message], settled, dead)
            if dead:
                await self._dead_letter(dead, settled)
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
        connection = self.connections[-1]
        return connection.healthy and self.host.is_open(connection) and (pipeline or self.pipeline).sink.ready

    async def _send(self, pipeline: Pipeline, pending: list[_Message], settled: list[bool],
                    dead: list[_Dead]) -> None:
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
                self._report_retry(failure, len(pending))
                if not await self.pause(retry_delay(min(message.attempts for message in pending))):
                    return

    def too_old(self, age_ns: int) -> bool:
        """The one decision of freshness: a message received ``age_ns`` ago is not sent any
        more but expired (``max_age``; telemetry is worthless once stale, events have none)."""
        max_age_ns = self.spec.delivery.max_age_ns
        return max_age_ns is not None and age_ns > max_age_ns

    def _fresh(self, pending: list[_Message], settled: list[bool]) -> list[_Message]:
        """``pending`` without the messages too old to send, which are settled as expired."""
        if self.spec.delivery.max_age_ns is None:
            return pending
        now_ns = time.monotonic_ns()
        fresh = []
        for message in pending:
            if self.too_old(now_ns - message.inbound.received_ns):
                settled[message.index] = True
                self.observer.expire(message.inbound, message.outbound)
                self._expired_call(message.outbound)
            else:
                fresh.append(message)
        return fresh

    def _sent(self, pending: list[_Message], results: list[BaseException | None], settled: list[bool],
              dead: list[_Dead], waiting: bool = False) -> list[_Message]:
        """Settle what the sink accepted, move what failed for good to ``dead``; return what
        is to be tried again. ``waiting``: the sink says now that it cannot take messages (a
        ROS 2 topic a message named has no subscriber yet), so a transient failure is the
        route waiting, not an attempt (as the buffer counts it)."""
        retry: list[_Message] = []
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
            if message.dedupe_key is not None:
                unsent.append(message.dedupe_key)
            if isinstance(error, NotSent):  # the sink settled it unsent: conflated, or expired while it tried
                settled[message.index] = True
                self._not_sent(error, message.inbound, message.outbound)
                continue
            failure = classify(error, "sink")
            if isinstance(error, Unroutable):
                self.observer.unroutable += 1
            if not failure.permanent:
                self.observer.sink_errors += 1
            if failure.permanent or message.attempts >= max_attempts:
                dead.append(_Dead(message.index, message.inbound, message.outbound, message.attempts, message.pipeline,
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
        """Count a message its sink settled without sending it (engine/endpoints/base.py)."""
        if isinstance(outcome, Conflated):
            self.observer.conflate(inbound, outbound)
        else:
            self.observer.expire(inbound, outbound)
            self._expired_call(outbound)

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

    # -- the buffer (engine/running/buffer.py): what the route hands it, and its way out

    async def _hold(self, pending: list[_Message], settled: list[bool]) -> None:
        """Hand messages to the buffer, in order; each is settled for its source once held."""
        assert self.buffer is not None
        now_ns, wall_ns = time.monotonic_ns(), time.time_ns()
        for message in pending:
            await self.buffer.hold(message.outbound, wall_ns - (now_ns - message.inbound.received_ns))
            settled[message.index] = True

    async def send_held(self, messages: list[Outbound]) -> list[BaseException | None]:
        for message in messages:
            self._reply_of(message)
        pipeline = self.pipeline
        pipeline.enter()
        try:
            results = await pipeline.sink.send_batch(messages)
        finally:
            pipeline.leave()
        if results.count(None) != len(results):
            self.observer.unroutable += sum(isinstance(result, Unroutable) for result in results)
        return results

    def held_delivered(self, held: list[Held]) -> None:
        now_ns = time.time_ns()
        remember, dedupe = self.pipeline.remember, self.pipeline.dedupe
        keys = []
        for outbound, received_at_ns in held:
            self.observer.accepted(None, outbound, None if received_at_ns is None else now_ns - received_at_ns)
            if remember is not None:
                remember.on_accepted(outbound.canonical, outbound.meta)
            if dedupe is not None and (key := dedupe.key(outbound.canonical, outbound.meta)) is not None:
                keys.append(key)
        if keys and dedupe is not None:
            dedupe.keys.answered(keys)

    def held_stale(self, held: Held) -> bool:
        received_at_ns = held[1]
        return received_at_ns is not None and self.too_old(time.time_ns() - received_at_ns)

    def held_expired(self, held: list[Held]) -> None:
        for outbound, _ in held:
            self.observer.expire(None, outbound)
            self._expired_call(outbound)

    def _expired_call(self, outbound: Outbound) -> None:
        max_age_ns = self.spec.delivery.max_age_ns
        assert max_age_ns is not None  # only a route with a max_age expires messages (too_old)
        age = f"older than the route's max_age ({max_age_ns / 1e9:g} s) before it could be sent"
        self._ended_call(outbound, "max_age", age)

    def _ended_call(self, outbound: Outbound, stage: str, error: str) -> None:
        """A request settled without being sent and without a dead letter (expired under
        ``max_age``, conflated by the throttle or ``latest_only``): its caller still hears the
        end, one ``error`` reply naming the stage, sent beside the route's work."""
        if not outbound.meta.get("reply_to"):
            return
        task = asyncio.create_task(self.replies.failed(self._reply_of(outbound), outbound.meta, stage, error))
        self._replying.add(task)
        task.add_done_callback(self._replying.discard)

    def _reply_of(self, outbound: Outbound) -> Any:
        """The reply of a held message: a message read back from the buffer's spill files lost
        its ``Outbound.reply`` (an object, not JSON) but not its meta, so a call is bound again,
        through this runner's source (a reload's new runner included)."""
        if outbound.reply is None:
            outbound.reply = self.replies.bind(self.pipeline.reply_shape, outbound.meta)
        return outbound.reply

    def held_conflated(self, held: list[Held]) -> None:
        for outbound, _ in held:
            self.observer.conflate(None, outbound)
            self._ended_call(outbound, "latest_only", "conflated: a newer message with the same key was held while the "
                                                      "sink was down (buffer.latest_only)")

    async def held_lost(self, held: list[Held]) -> None:
        """The buffer closed (the route or the engine stopped) with calls held in memory only:
        they can no longer be delivered, so each caller gets its one ``error`` reply now."""
        error = "the route stopped before its sink could take it (held in memory, not spilled)"
        await asyncio.gather(*(self.replies.failed(self._reply_of(outbound), outbound.meta, "buffer", error)
                               for outbound, _ in held if outbound.meta.get("reply_to")))

    async def held_rejected(self, message: Outbound, error: BaseException, attempts: int) -> None:
        """A held message the sink rejected, or kept failing while it could take messages."""
        self._reply_of(message)
        inbound = Inbound(body=message.body, meta=dict(message.meta))
        await self._dead_letter([_Dead(0, inbound, message, attempts, self.pipeline, classify(error, "sink"))], [False])

    # -- stage 5: the dead letters

    async def _dead_letter(self, dead: list[_Dead], settled: list[bool]) -> None:
        """Store the batch's dead letters together; each is settled once stored."""
        dead.sort(key=lambda message: message.index)
        spec, host = self.spec, self.host
        limit = spec.delivery.max_message_bytes
        letters = [dead_letter_message(spec.name, f"{spec.file}:{spec.line}", m.inbound, m.failure, m.attempts, limit)
                   for m in dead]
        try:
            assert host.dead_letters is not None
            await host.dead_letters.put(spec.name, letters)
        except EndpointError as error:
            self.observer.dead_letter_errors += len(dead)
            self._report_failure(Failure("dead-letter", str(error), False))
            return
        for message in dead:
            settled[message.index] = True
            failure = message.failure
            self.observer.dead_letter(message.inbound, message.outbound, failure.stage, failure.error)
            remember = message.pipeline.remember
            if remember is not None and message.outbound is not None:
                remember.on_failed(message.outbound.canonical, message.outbound.meta, f"{failure.stage}: {failure.error}")
        self._report_failure(dead[-1].failure, len(dead))
        calls = [m for m in dead if m.inbound.meta.get("reply_to")]
        if calls:  # each request that failed for good: its caller gets one error reply, published together
            await asyncio.gather(*(self.replies.failed(m.outbound.reply if m.outbound is not None else None,
                                                       m.inbound.meta, m.failure.stage, m.failure.error)
                                   for m in calls))

    def _report_retry(self, failure: Failure, count: int) -> None:
        if self._retry_report.ready():
            log.warning(
                "sink failed; retrying with backoff",
                extra={"route": self.spec.name, "error": failure.error, "messages": count,
                       "suppressed": self._retry_report.take_suppressed()},
            )

    def _report_failure(self, failure: Failure, count: int = 1) -> None:
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

    # -- starting when the connections are open, stopping

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

    def receiver(self) -> RouteRunner | StandbyGate:
        """What the source hands its messages to: this runner, or for an ``active_standby``
        route the gate that forwards only while this instance holds the lease."""
        return StandbyGate(self) if self.lease is not None else self

    def _needed(self) -> list[Connection]:
        return self.connections if self.buffer is None else self.connections[:1]

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
            self.host.buffers.hand_to(self.spec.name, self.buffer, self)

    async def retire_pipeline(self, pipeline: Pipeline) -> None:
        if pipeline.throttle is not None:  # parked messages go out, not lost
            pipeline.throttle.close(self)
        await pipeline.drained()
        await pipeline.sink.close()

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
            "role": lease.role if lease else ("single-active-consumer" if spec.placement.ordered else "shared"),
            "lease_changes": lease.changes if lease else 0,
            **self.observer.counters(),
            "source": self.source.status(),
            "state": self.state,
            "waiting_for": self.missing_connections() if self.state == "waiting" else [],
            "sink_not_ready": self.pipeline.sink.not_ready_reason(),
            "source_degraded": self.source.degraded_reason(),
            "buffer": stats_dict(self.buffer) if self.buffer is not None else None,
            "replies": self.replies.counters(),
        }


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
