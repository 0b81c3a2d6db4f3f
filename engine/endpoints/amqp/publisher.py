"""One pipelined publish per loop turn for every route of an AMQP connection.

Every AMQP sink of a connection publishes on the connection's one confirm channel. At a
fleet's pace (200 telemetry routes at 10 Hz each) every route's batch is one message, and
publishing each through ``aiormq.Channel.basic_publish`` cost per message: the channel lock,
a timeout scope, a frame of its own through aiormq's ten-frame write queue (a writer task
wake-up and one socket write each) and a confirm wait of its own.

Measured on bench/fleet.py (bench/results/2026-11-23/fleet-v2/, the machine shared, load
average 4-9): 25 robots and 25 vehicles, before / after in interleaved runs, telemetry end to
end p50 229-1,446 ms / 4-6 ms, p99 1.8-2.9 s / 0.14-0.34 s (after: with the ROS 2 waiter's
kept wait set, engine/endpoints/ros2/transport.py); the full fleet (2,100 msg/s) 335-351 µs / 193-196 µs of engine CPU per message.

So a route's ``publish`` only queues its messages and its future; the first one queued in a
loop turn schedules a *round* for the next turn, which takes everything queued meanwhile
(every route that published in this turn): it allocates the delivery tags under the
channel's lock, writes every message's frames as ONE write, awaits the round's confirms
together, and answers each route with its own per-message results (``None`` once the
broker took the message, else the error). A route still learns the outcome of exactly its
own messages: a message the broker nacks, or one that cannot be framed (a routing key over
255 bytes), fails alone; the runner (engine/runner.py) and engine/delivery.py decide what
that failure means, as before. Rounds overlap: the next turn's round is written while the
last one's confirms are still on their way.

Publishing goes below aiormq's ``basic_publish`` to its channel's delivery-tag counter,
confirmation table and write queue (what ``basic_publish`` itself does, once per round
instead of once per message); each round also holds one future of the channel's own, which
aiormq rejects when the channel or connection closes (``FutureStore``), so every route in
flight then sees a failure, never a silent loss.
"""

from __future__ import annotations

import asyncio
from typing import Any, Sequence

import aio_pika.abc
import aiormq.abc
import aiormq.exceptions
from aiormq import spec
from pamqp import frame as pamqp_frame
from pamqp.body import ContentBody
from pamqp.header import ContentHeader

from engine.endpoints.amqp.errors import LIBRARY_ERRORS, edge_error
from engine.endpoints.base import EndpointError

Message = tuple[str, bytes, spec.Basic.Properties]
"""(routing key, body, properties)"""


class _Part:
    """One caller's messages in a round, and the future that answers it."""

    __slots__ = ("exchange", "messages", "answer")

    def __init__(self, exchange: str, messages: Sequence[Message], answer: asyncio.Future[list[BaseException | None]]) -> None:
        self.exchange = exchange
        self.messages = messages
        self.answer = answer


class SharedPublisher:
    """The publishes of one connection's routes, coalesced per loop turn (module docstring)."""

    def __init__(self, channel: aio_pika.abc.AbstractChannel, connection: str) -> None:
        self._channel = channel
        self._connection = connection
        self._queued: list[_Part] = []
        self._rounds: set[asyncio.Task[None]] = set()
        self.rounds = 0
        """Rounds written so far (each one socket write and one confirm wait)."""
        self.messages = 0
        """Messages written so far: ``messages / rounds`` is the mean round."""

    async def publish(self, exchange: str, messages: Sequence[Message]) -> list[BaseException | None]:
        """``result[i]`` is None once the broker took ``messages[i]``, else why not."""
        loop = asyncio.get_running_loop()
        answer: asyncio.Future[list[BaseException | None]] = loop.create_future()
        if not self._queued:
            loop.call_soon(self._start_round)
        self._queued.append(_Part(exchange, messages, answer))
        return await answer

    def _start_round(self) -> None:
        parts, self._queued = self._queued, []
        task = asyncio.get_running_loop().create_task(self._round(parts))
        self._rounds.add(task)
        task.add_done_callback(self._rounds.discard)

    async def _round(self, parts: list[_Part]) -> None:
        try:
            await self._publish(parts)
        except BaseException as exc:  # a bug or a cancel: every caller still hears of it
            for part in parts:
                if not part.answer.done():
                    part.answer.set_exception(exc if isinstance(exc, Exception) else EndpointError(f"publish cancelled: {exc!r}"))
            if not isinstance(exc, Exception):
                raise

    async def _publish(self, parts: list[_Part]) -> None:
        results = [[None] * len(part.messages) for part in parts]  # type: list[list[BaseException | None]]
        try:
            channel = await self._channel.get_underlay_channel()
        except LIBRARY_ERRORS as exc:
            for part, part_results in zip(parts, results):
                error = edge_error(exc, self._describe(part.exchange, ""))
                part_results[:] = [error] * len(part.messages)
            return self._answer(parts, results)
        number, frame_max = channel.number, channel.max_content_size
        payloads: list[bytes] = []
        slots: list[tuple[int, int]] = []  # (part, message) of each payload, in order
        for p, part in enumerate(parts):
            exchange = part.exchange
            for m, (key, body, properties) in enumerate(part.messages):
                try:
                    payloads.append(_frames(number, frame_max, exchange, key, body, properties))
                except Exception as exc:  # e.g. a routing key over 255 bytes: this message alone fails
                    results[p][m] = EndpointError(f"{self._describe(exchange, key)}: {exc}")
                    continue
                slots.append((p, m))
        if payloads:
            outcomes = await self._write(channel, payloads)
            for (p, m), outcome in zip(slots, outcomes):
                if isinstance(outcome, BaseException) or isinstance(outcome, (spec.Basic.Nack, spec.Basic.Reject)):
                    reason = outcome if isinstance(outcome, BaseException) else "the broker nacked it"
                    key = parts[p].messages[m][0]
                    results[p][m] = EndpointError(f"{self._describe(parts[p].exchange, key)}: {reason}")
        self._answer(parts, results)

    async def _write(self, channel: aiormq.abc.AbstractChannel, payloads: list[bytes]) -> list[Any]:
        """Write the round's messages as one frame sequence; their outcomes, in order."""
        confirms = channel.publisher_confirms
        loop = asyncio.get_running_loop()
        confirmations: list[asyncio.Future[Any]] = []
        drained = None if confirms else channel.create_future()  # the channel's: rejected if it closes
        try:
            async with channel.lock:  # the broker numbers publishes in the order they arrive
                first = channel.delivery_tag + 1
                if confirms:
                    table = channel.confirmations
                    for tag in range(first, first + len(payloads)):
                        future = loop.create_future()
                        table[tag] = future
                        confirmations.append(future)
                channel.delivery_tag += len(payloads)
                try:
                    await channel.write_queue.put(aiormq.abc.ChannelFrame(
                        payload=b"".join(payloads), should_close=False, drain_future=drained))
                except BaseException:  # not written: the broker never saw these tags
                    channel.delivery_tag = first - 1
                    for tag in range(first, first + len(confirmations)):
                        future = channel.confirmations.pop(tag, None)
                        if future is not None:
                            future.cancel()
                    raise
        except LIBRARY_ERRORS as exc:
            return [exc] * len(payloads)
        self.rounds += 1
        self.messages += len(payloads)
        if confirms:
            return await _confirmed(channel, confirmations)
        try:
            await drained  # type: ignore[misc]
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


async def _confirmed(channel: aiormq.abc.AbstractChannel, confirmations: list[asyncio.Future[Any]]) -> list[Any]:
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
    failure: BaseException | None = None
    if not confirmed.done():
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


def _frames(channel: int, frame_max: int, exchange: str, key: str, body: bytes, properties: spec.Basic.Properties) -> bytes:
    """One message's publish, content header and body frames, encoded (as aiormq's
    ``basic_publish`` encodes them, bodies split at the negotiated frame size)."""
    if len(key) > 255:
        raise ValueError("Routing key too long (max 255 bytes)")
    encoded = [pamqp_frame.marshal(spec.Basic.Publish(exchange=exchange, routing_key=key), channel),
               pamqp_frame.marshal(ContentHeader(properties=properties, body_size=len(body)), channel)]
    for start in range(0, len(body), frame_max):
        encoded.append(pamqp_frame.marshal(ContentBody(body[start:start + frame_max]), channel))
    return b"".join(encoded)
