"""One pipelined publish per loop turn for every route of an AMQP connection.

Every AMQP sink of a connection publishes on the connection's one confirm channel. At a
fleet's pace (200 telemetry routes at 10 Hz each) every route's batch is one message, and
publishing each through ``aiormq.Channel.basic_publish`` cost per message: the channel lock,
a timeout scope, a frame of its own through aiormq's ten-frame write queue (a writer task
wake-up and one socket write each) and a confirm wait of its own.

Measured on bench/fleet.py (bench/results/2026-11-23/fleet-v2/, the machine shared, load
average 4-9): 25 robots and 25 vehicles, before / after in interleaved runs, telemetry end to
end p50 229-1,446 ms / 4-6 ms, p99 1.8-2.9 s / 0.14-0.34 s (after: with the ROS 2 waiter's
kept wait set, engine/endpoints/ros2/waiter.py); the full fleet (2,100 msg/s) 335-351 µs / 193-196 µs of engine CPU per message.

So a route's ``publish`` only queues its messages and its future; the first one queued in a
loop turn schedules a *round* for the next turn, which takes everything queued meanwhile
(every route that published in this turn): it allocates the delivery tags under the
channel's lock, writes every message's frames as ONE write, awaits the round's confirms
together, and answers each route with its own per-message results (``None`` once the
broker took the message, else the error). A route still learns the outcome of exactly its
own messages: a message the broker nacks, or one that cannot be framed (a routing key over
255 bytes), fails alone; the runner (engine/running/runner.py) and engine/running/delivery.py decide what
that failure means, as before. Rounds overlap: the next turn's round is written while the
last one's confirms are still on their way.

A round is written in the callback that starts it, without a task, whenever nothing would
make it wait (:meth:`SharedPublisher._write_now`), and its routes are answered from the
confirmations' callbacks; its frames are encoded with ``struct`` (:func:`_frames`), byte for
byte pamqp's; the broker's confirms settle the front of the channel's table
(:func:`_confirm_in_order`). A round still carries few messages at a fleet's pace: 1.2-1.6 on
average with 25 robots and 25 vehicles (bench/fleet.py's "publishes per round"), so what a
round costs is paid nearly per message.

Publishing goes below aiormq's ``basic_publish`` to its channel's delivery-tag counter,
confirmation table and write queue (what ``basic_publish`` itself does, once per round
instead of once per message); each round also holds one future of the channel's own, which
aiormq rejects when the channel or connection closes (``FutureStore``), so every route in
flight then sees a failure, never a silent loss. A sink's ``mandatory`` message the broker
returns (no queue bound for it) is answered :class:`~engine.endpoints.base.Unroutable`:
returns.py matches the return, which comes before the message's confirm, to its round.
"""

from __future__ import annotations

import asyncio
import logging
import struct
import weakref
from typing import Any, Sequence

import aio_pika.abc
import aiormq.abc
import aiormq.exceptions
from aiormq import spec
from pamqp import encode

from engine.endpoints.amqp.errors import LIBRARY_ERRORS, edge_error
from engine.endpoints.amqp.returns import Awaiting, Returns
from engine.endpoints.base import EndpointError, Unroutable

log = logging.getLogger("engine.amqp")

Message = tuple[str, bytes, spec.Basic.Properties]
"""(routing key, body, properties)"""


class _Part:
    """One caller's messages in a round, and the future that answers it."""

    __slots__ = ("exchange", "messages", "answer", "mandatory")

    def __init__(self, exchange: str, messages: Sequence[Message], answer: asyncio.Future[list[BaseException | None]],
                 mandatory: bool = False) -> None:
        self.exchange = exchange
        self.messages = messages
        self.answer = answer
        self.mandatory = mandatory


class SharedPublisher:
    """The publishes of one connection's routes, coalesced per loop turn (module docstring)."""

    def __init__(self, channel: aio_pika.abc.AbstractChannel | None, connection: str) -> None:
        self._channel = channel
        self._connection = connection
        self._queued: list[_Part] = []
        self._rounds: set[asyncio.Task[None]] = set()
        self._writing: dict[aiormq.Channel, int] = {}
        """Per aiormq channel: rounds of :meth:`_write` between asking for its lock and queuing
        their frames. Per channel, so a round stuck on a channel that closed can never keep the
        fast path off on the next one (and :func:`_put_frame` does not stay stuck: it gives up
        when its channel closes)."""
        self._underlay: aiormq.Channel | None = None
        """The confirm channel's aiormq channel as last fetched (a reconnect replaces it, and
        the closed one sends rounds back the way that fetches it again)."""
        self._refused: weakref.WeakSet[aiormq.Channel] = weakref.WeakSet()
        """Channels the broker closed (:meth:`_watch_close`), from its ``Channel.Close`` on:
        nothing more may be written on them."""
        self.rounds = 0
        """Rounds written so far (each one socket write and one confirm wait)."""
        self.messages = 0
        """Messages written so far: ``messages / rounds`` is the mean round."""
        self._returns = Returns(connection)
        """The broker's returns of mandatory messages, matched to their rounds (returns.py)."""

    @property
    def returned(self) -> int:
        """Mandatory messages the broker returned (unroutable)."""
        return self._returns.count

    def replace(self, channel: aio_pika.abc.AbstractChannel | None) -> None:
        """Publish on ``channel`` from the next round on (the connection reopened its publish
        channel; None while it reopens: rounds fail at once, transiently). Rounds in flight on
        the old one fail with it (its futures), none waits."""
        self._channel = channel
        self._underlay = None

    async def publish(self, exchange: str, messages: Sequence[Message], mandatory: bool = False) -> list[BaseException | None]:
        """``result[i]`` is None once the broker took ``messages[i]``, else why not;
        ``mandatory``: a message the broker routes to no queue is returned, and its result is
        :class:`Unroutable` (needs publisher confirms: the return arrives before the confirm)."""
        loop = asyncio.get_running_loop()
        answer: asyncio.Future[list[BaseException | None]] = loop.create_future()
        if not self._queued:
            loop.call_soon(self._start_round)
        self._queued.append(_Part(exchange, messages, answer, mandatory))
        return await answer

    def _start_round(self) -> None:
        parts, self._queued = self._queued, []
        try:
            if self._write_now(parts):
                return
        except Exception as exc:  # a bug: every caller still hears of it
            self._fail(parts, exc)
            return
        task = asyncio.get_running_loop().create_task(self._round(parts))
        self._rounds.add(task)
        task.add_done_callback(self._rounds.discard)

    def _write_now(self, parts: list[_Part]) -> bool:
        """The round written in this callback, without a task of its own, where nothing would
        make it wait: the confirm channel last seen is still open, no round of the other way
        is between taking its tags on that channel (under its lock) and queuing its frames, and the
        connection's write queue has room. Nothing else uses this channel (exchanges are declared
        on one of their own: ``AmqpConnection.declare_exchange``), so no one else holds its lock.
        The broker's confirms then answer the routes from their futures' callbacks
        (:class:`_Confirming`). False (nothing done): the round goes the way that can wait
        (:meth:`_round`).

        Delivery tags stay in the order the broker numbers the frames: this connection's
        publisher is the only one that publishes on its channel, tags are allocated in the
        same step that queues the frames, and no round is written here while one of the other
        way is between taking its tags and queuing its frames (``_writing``: it may wait for
        the channel's lock or for room in the write queue, and must not be overtaken).

        At a fleet's pace a round carries one or two messages (300 routes at 10 Hz, staggered),
        so the round's own machinery was paid per message: a task, its two steps, and
        ``asyncio.wait`` with its waiter future, a chain of four callbacks from the broker's
        confirm to the route. Measured in-process (300 sinks of one connection, each publishing
        200 one-message batches, staggered, to a private broker; five interleaved runs), with
        :func:`_frames`: 46-63 (median 50) -> 36-43 (median 40) us of CPU per message."""
        channel = self._underlay
        if channel is None or channel.is_closed or not channel.publisher_confirms \
                or channel.write_queue.full() or channel in self._writing:
            return False
        results, payloads, slots = self._encode(parts, channel)
        if not payloads:
            self._answer(parts, results)
            return True
        loop = asyncio.get_running_loop()
        first = channel.delivery_tag + 1
        table = channel.confirmations
        confirmations: list[asyncio.Future[Any]] = []
        for tag in range(first, first + len(payloads)):
            future = loop.create_future()
            table[tag] = future
            confirmations.append(future)
        channel.delivery_tag += len(payloads)
        channel.write_queue.put_nowait(aiormq.abc.ChannelFrame(
            payload=b"".join(payloads), should_close=False, drain_future=None))
        self.rounds += 1
        self.messages += len(payloads)
        _Confirming(self, parts, results, slots, channel, confirmations, self._returns.enter(parts, slots, confirmations))
        return True

    async def _round(self, parts: list[_Part]) -> None:
        try:
            await self._publish(parts)
        except BaseException as exc:  # a bug or a cancel: every caller still hears of it
            self._fail(parts, exc)
            if not isinstance(exc, Exception):
                raise

    @staticmethod
    def _fail(parts: list[_Part], exc: BaseException) -> None:
        for part in parts:
            if not part.answer.done():
                part.answer.set_exception(exc if isinstance(exc, Exception) else EndpointError(f"publish cancelled: {exc!r}"))

    async def _publish(self, parts: list[_Part]) -> None:
        try:
            if self._channel is None:
                raise aiormq.exceptions.ChannelInvalidStateError("the publish channel is being reopened")
            channel = await self._channel.get_underlay_channel()
            assert isinstance(channel, aiormq.Channel)  # aio_pika's underlay: the publisher uses its internals
            if channel.is_closed:  # nothing would ever write (or confirm) this round's frames
                raise aiormq.exceptions.ChannelInvalidStateError("the publish channel is closed")
        except LIBRARY_ERRORS as exc:
            failed: list[list[BaseException | None]] = [[edge_error(exc, self._describe(part.exchange, ""))] * len(part.messages)
                                                        for part in parts]
            return self._answer(parts, failed)
        if channel is not self._underlay:  # (the hook below unsets a channel the broker closed)
            if channel in self._refused:
                refused: list[list[BaseException | None]] = [
                    [EndpointError(f"{self._describe(part.exchange, '')}: the broker closed the publish channel")] * len(part.messages)
                    for part in parts]
                return self._answer(parts, refused)
            _confirm_in_order(channel)
            self._watch_close(channel)
            self._returns.watch(channel)
            self._underlay = channel
        results, payloads, slots = self._encode(parts, channel)
        if payloads:
            awaiting = self._returns.enter(parts, slots)
            try:
                outcomes = await self._write(channel, payloads, awaiting)
            finally:
                returned = self._returns.done(awaiting)
            self._settle(parts, results, slots, outcomes, returned)
        self._answer(parts, results)

    def _watch_close(self, channel: aiormq.Channel) -> None:
        """Stop writing on ``channel`` the moment the broker's ``Channel.Close`` arrives.
        aiormq answers it with ``Channel.CloseOk`` at once (the broker then knows the channel
        number no more) but marks the channel closed only a few loop turns later, after its
        close task ran; a round written in between reached the broker after the CloseOk,
        which closed the whole CONNECTION (504 CHANNEL_ERROR "expected 'channel.open'",
        measured in tests/endpoints/amqp/test_amqp_publish_channel.py: every source's channel went with it).
        aiormq checks its own private close event for that in ``basic_publish``'s callers; the
        publisher hooks the frame's handler as it hooks the confirms' (:func:`_confirm_in_order`)."""
        on_close_frame = getattr(channel, "_on_close_frame", None)  # aiormq 7.2's (pinned ~=7.2.4)
        if on_close_frame is None:  # another aiormq: its own handler; the race above stays open
            return
        refused = self._refused

        async def close_frame(frame: Any) -> None:
            refused.add(channel)
            if self._underlay is channel:
                self._underlay = None  # the fast path: not this channel any more
            await on_close_frame(frame)

        channel._on_close_frame = close_frame  # type: ignore[method-assign]  # the hook above: aiormq has no public one

    def _encode(self, parts: list[_Part], channel: aiormq.Channel) -> tuple[
            list[list[BaseException | None]], list[bytes], list[tuple[int, int]]]:
        """Every message's frames; a message that cannot be framed (e.g. a routing key over 255
        bytes) fails alone. Returns (results so far, payloads, (part, message) of each payload)."""
        results = [[None] * len(part.messages) for part in parts]  # type: list[list[BaseException | None]]
        number, frame_max = channel.number, channel.max_content_size
        payloads: list[bytes] = []
        slots: list[tuple[int, int]] = []
        for p, part in enumerate(parts):
            exchange, mandatory = part.exchange, part.mandatory
            for m, (key, body, properties) in enumerate(part.messages):
                try:
                    payloads.append(_frames(number, frame_max, exchange, key, body, properties, mandatory))
                except Exception as exc:
                    results[p][m] = EndpointError(f"{self._describe(exchange, key)}: {exc}")
                    continue
                slots.append((p, m))
        return results, payloads, slots

    def _settle(self, parts: list[_Part], results: list[list[BaseException | None]], slots: list[tuple[int, int]],
                outcomes: list[Any], returned: dict[int, str]) -> None:
        """Each written message's outcome (the broker's Ack, Nack, or a failure) into its result;
        a message the broker returned (``returned``: by payload index) is :class:`Unroutable`."""
        for (p, m), outcome in zip(slots, outcomes):
            if isinstance(outcome, BaseException) or isinstance(outcome, (spec.Basic.Nack, spec.Basic.Reject)):
                reason = outcome if isinstance(outcome, BaseException) else "the broker nacked it"
                key = parts[p].messages[m][0]
                results[p][m] = EndpointError(f"{self._describe(parts[p].exchange, key)}: {reason}")
        for index, reply_text in returned.items():
            p, m = slots[index]
            if results[p][m] is None:
                key = parts[p].messages[m][0]
                results[p][m] = Unroutable(f"exchange {parts[p].exchange!r}, routing key {key!r}: the broker returned it "
                                           f"({reply_text}: no queue is bound for it)")

    async def _write(self, channel: aiormq.Channel, payloads: list[bytes],
                     awaiting: Awaiting | None = None) -> list[Any]:
        """Write the round's messages as one frame sequence; their outcomes, in order
        (``awaiting``: the round where its returns are matched, given its confirmations)."""
        confirms = channel.publisher_confirms
        loop = asyncio.get_running_loop()
        confirmations: list[asyncio.Future[Any]] = []
        drained = None if confirms else channel.create_future()  # the channel's: rejected if it closes
        writing = self._writing
        writing[channel] = writing.get(channel, 0) + 1
        try:
            async with channel.lock:  # the broker numbers publishes in the order they arrive
                if channel in self._refused:  # closed by the broker while this round waited
                    raise aiormq.exceptions.ChannelInvalidStateError("the broker closed the publish channel")
                first = channel.delivery_tag + 1
                if confirms:
                    table = channel.confirmations
                    for tag in range(first, first + len(payloads)):
                        future = loop.create_future()
                        table[tag] = future
                        confirmations.append(future)
                    if awaiting is not None:
                        awaiting.confirmations = confirmations
                channel.delivery_tag += len(payloads)
                try:
                    await _put_frame(channel, aiormq.abc.ChannelFrame(
                        payload=b"".join(payloads), should_close=False, drain_future=drained))
                except BaseException:  # not written: the broker never saw these tags
                    channel.delivery_tag = first - 1
                    for tag in range(first, first + len(confirmations)):
                        unsent = channel.confirmations.pop(tag, None)
                        if unsent is not None:
                            unsent.cancel()
                    raise
        except LIBRARY_ERRORS as exc:
            return [exc] * len(payloads)
        finally:
            left = writing[channel] - 1
            if left:
                writing[channel] = left
            else:
                del writing[channel]
        self.rounds += 1
        self.messages += len(payloads)
        if confirms:
            return await _confirmed(channel, confirmations)
        assert drained is not None  # made above for a channel without confirms
        try:
            await drained
        except LIBRARY_ERRORS as exc:
            return [exc] * len(payloads)
        return [None] * len(payloads)

    def _describe(self, exchange: str, key: str) -> str:
        return f"amqp publish to {exchange!r}/{key!r} on {self._connection!r}"

    @staticmethod
    def _answer(parts: list[_Part], results: list[list[BaseException | None]]) -> None:
        for part, part_results in zip(parts, results):
            if not part.answer.done():  # its caller may have been cancelled meanwhile
                part.answer.set_result(part_results)


async def _put_frame(channel: aiormq.Channel, frame: aiormq.abc.ChannelFrame) -> None:
    """Queue ``frame`` for the connection's writer; when the queue is full, wait for room or
    for the channel to close, whichever comes first (then raise the channel's failure). aiormq
    drains the write queue only while its connection lives and wakes no ``put`` waiting on it
    when the connection dies: a round waiting there waited for ever, holding the channel's
    lock and keeping the fast path (:meth:`SharedPublisher._write_now`) off. The room is
    there nearly always: ``put_nowait`` first, no future nor task."""
    queue = channel.write_queue
    try:
        queue.put_nowait(frame)
        return
    except asyncio.QueueFull:
        pass
    put = asyncio.ensure_future(queue.put(frame))
    closed = channel.create_future()  # the channel's own: rejected when it (or its connection) closes
    try:
        await asyncio.wait((put, closed), return_when=asyncio.FIRST_COMPLETED)
    except BaseException:  # cancelled: the caller takes its tags back
        put.cancel()
        closed.cancel()
        raise
    if not closed.done():
        closed.cancel()
    if not put.done():
        put.cancel()  # a put cancelled while it waits queues nothing; it ends in one step
        await asyncio.wait((put,))
    failure = None if closed.cancelled() else closed.exception()  # (retrieved either way)
    if put.cancelled():
        raise failure or aiormq.exceptions.ChannelInvalidStateError("the publish channel closed before the round was written")
    put.result()


async def _confirmed(channel: aiormq.Channel, confirmations: list[asyncio.Future[Any]]) -> list[Any]:
    """Each confirmation's outcome (the broker's Ack or Nack) once all arrived, or the channel's
    failure for those still open when it closes. The confirmations are plain futures and the
    round holds one of the channel's own (which aiormq rejects when the channel or connection
    closes): registering every message's future with the channel cost three callbacks each.
    """
    loop = asyncio.get_running_loop()
    confirmed = loop.create_future()
    remaining = len(confirmations)

    def arrived(_: asyncio.Future[Any]) -> None:
        nonlocal remaining
        remaining -= 1
        if not remaining and not confirmed.done():
            confirmed.set_result(None)

    for future in confirmations:
        future.add_done_callback(arrived)
    closed = channel.create_future()
    try:
        await asyncio.wait((confirmed, closed), return_when=asyncio.FIRST_COMPLETED)
    finally:
        if not closed.done():
            closed.cancel()
    return _outcomes(confirmations, None if confirmed.done() else closed)


def _outcomes(confirmations: list[asyncio.Future[Any]], closed: asyncio.Future[Any] | None) -> list[Any]:
    """The confirmations' outcomes; ``closed``: the channel's future that ended the wait
    before all arrived (its failure is theirs), None when all arrived."""
    failure: BaseException | None = None
    if closed is not None:
        failure = closed.exception() if not closed.cancelled() else None
        failure = failure or aiormq.exceptions.ChannelInvalidStateError("the publish channel closed before confirming")
    outcomes: list[Any] = []
    for future in confirmations:
        if not future.done():
            outcomes.append(failure)
        elif future.cancelled():
            outcomes.append(aiormq.exceptions.ChannelInvalidStateError("the confirmation was cancelled"))
        else:
            outcomes.append(future.exception() or future.result())
    return outcomes


def _confirm_in_order(channel: aiormq.Channel) -> None:
    """The broker's confirms on this publisher's channel settled from the front of its table.

    aiormq answers a confirm for several messages (``multiple``) by walking its whole table of
    unconfirmed publishes, each newer tag included, and scheduling one callback per settled
    one: O(unconfirmed) per confirm. When the broker falls behind, thousands are unconfirmed
    and each confirm walks them all, so the engine slows down exactly when the broker does. This
    publisher is the only one on its channel and enters tags in increasing order (its own
    return handler, :meth:`.returns.Returns.watch`, leaves the table alone; aiormq's
    puts a returned tag back out of order), so the settled
    tags are the table's prefix: they are taken from its front and settled at once, each with
    aiormq's own ``_confirm_delivery`` (an Ack's result, a Nack's ``DeliveryError``).
    Measured (see the commit) in-process at 300 routes and in bench/fleet.py's profile, where
    aiormq's walk was 5 % of the engine's GIL-holding samples under load.

    Both names are aiormq 7.2's own (pyproject pins ``aiormq~=7.2.4``); an aiormq without them
    keeps its own handler, which is correct, only slower."""
    table = getattr(channel, "confirmations", None)
    settle = getattr(channel, "_confirm_delivery", None)
    if not isinstance(table, dict) or settle is None or not hasattr(channel, "_on_confirm_frame"):
        return

    async def on_confirm_frame(frame: Any) -> None:
        if not channel.publisher_confirms:
            return
        tag = frame.delivery_tag
        if tag not in table:
            log.error("Unexpected confirmation frame %r from broker", frame)
            return
        if not getattr(frame, "multiple", False):
            settle(tag, frame)
            return
        while table:
            first = next(iter(table))
            if first > tag:
                break
            settle(first, frame)

    channel._on_confirm_frame = on_confirm_frame  # type: ignore[method-assign]  # the hook above: aiormq has no public one


class _Confirming:
    """A round written by :meth:`SharedPublisher._write_now`, answered from callbacks: when its
    last confirmation arrives, or when the channel closes first (its own future, which aiormq
    rejects then: the rest fail with that), exactly as :func:`_confirmed` decides."""

    __slots__ = ("publisher", "parts", "results", "slots", "confirmations", "remaining", "closed", "awaiting")

    def __init__(self, publisher: SharedPublisher, parts: list[_Part], results: list[list[BaseException | None]],
                 slots: list[tuple[int, int]], channel: aiormq.Channel,
                 confirmations: list[asyncio.Future[Any]], awaiting: Awaiting | None) -> None:
        self.publisher, self.parts, self.results, self.slots = publisher, parts, results, slots
        self.awaiting = awaiting
        self.confirmations = confirmations
        self.remaining = len(confirmations)
        self.closed: asyncio.Future[Any] | None = channel.create_future()
        self.closed.add_done_callback(self._closed)
        for future in confirmations:
            future.add_done_callback(self._arrived)

    def _arrived(self, _: asyncio.Future[Any]) -> None:
        self.remaining -= 1
        if not self.remaining and self.closed is not None:
            closed, self.closed = self.closed, None
            closed.cancel()  # out of the channel's store
            self._finish(None)

    def _closed(self, closed: asyncio.Future[Any]) -> None:
        if self.closed is None:  # answered already (we cancelled it)
            return
        self.closed = None
        self._finish(closed)

    def _finish(self, closed: asyncio.Future[Any] | None) -> None:
        try:
            returned = self.publisher._returns.done(self.awaiting)
            self.publisher._settle(self.parts, self.results, self.slots, _outcomes(self.confirmations, closed), returned)
            self.publisher._answer(self.parts, self.results)
        except Exception as exc:  # a bug: every caller still hears of it
            self.publisher._fail(self.parts, exc)


_METHOD_FRAME = struct.Struct(">BHI")
"""A frame's type, channel and payload size (a body frame's header too)."""
_HEADER_FRAME = struct.Struct(">BHIHHQ")
"""A content header frame up to its properties: type, channel, size, class, weight, body size."""
_PUBLISH_METHOD = struct.pack(">IH", spec.Basic.Publish.index, 0)
"""Basic.Publish's method index and its reserved ``ticket`` (0)."""
_FRAME_END = b"\xce"
_EXCHANGES: dict[str, bytes] = {}
"""Exchange name -> its encoded short string, once pamqp validated it (a sink's exchange is one
of a few names; bounded by :data:`_EXCHANGES_KEPT` all the same)."""
_EXCHANGES_KEPT = 4096


def _exchange(exchange: str) -> bytes:
    encoded = _EXCHANGES.get(exchange)
    if encoded is None:
        spec.Basic.Publish(exchange=exchange)  # pamqp's checks (length, characters): its ValueError as before
        encoded = encode.short_string(exchange)
        if len(_EXCHANGES) < _EXCHANGES_KEPT:
            _EXCHANGES[exchange] = encoded
    return encoded


def _frames(channel: int, frame_max: int, exchange: str, key: str, body: bytes, properties: spec.Basic.Properties,
            mandatory: bool = False) -> bytes:
    """One message's publish, content header and body frames, encoded: byte for byte what
    aiormq's ``basic_publish`` sends through pamqp (bodies split at the negotiated frame size;
    tests/endpoints/amqp/test_amqp_shared_publish.py compares the two), with the same refusals (an invalid
    exchange name, a routing key over 255 bytes).

    Written with ``struct`` rather than through pamqp's generic marshalling: pamqp builds a
    ``Basic.Publish``, validates the exchange against a regular expression and encodes every
    field by its declared type, for each message. In bench/fleet.py (300 routes, 2,100 msg/s)
    that was 5.9 % of the engine's samples (py-spy), for a frame whose only varying parts are
    the routing key and the sizes."""
    if len(key) > 255:
        raise ValueError("Routing key too long (max 255 bytes)")
    encoded_key = encode.short_string(key)  # its TypeError beyond 255 bytes, as pamqp's
    method = b"".join((_PUBLISH_METHOD, _exchange(exchange), encoded_key, b"\x01" if mandatory else b"\x00"))  # bits: mandatory, immediate
    props = properties.marshal()
    size = len(body)
    parts = [_METHOD_FRAME.pack(1, channel, len(method)), method, _FRAME_END,
             _HEADER_FRAME.pack(2, channel, 12 + len(props), spec.Basic.frame_id, 0, size), props, _FRAME_END]
    if frame_max <= 0 or size <= frame_max:  # frame_max 0 is the broker's "no limit" (aiormq: max_content_size -8)
        if size:
            parts += (_METHOD_FRAME.pack(3, channel, size), body, _FRAME_END)
    else:
        for start in range(0, size, frame_max):
            chunk = body[start:start + frame_max]
            parts += (_METHOD_FRAME.pack(3, channel, len(chunk)), chunk, _FRAME_END)
    return b"".join(parts)
