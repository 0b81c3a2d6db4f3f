"""A source's held acknowledgements: one ``basic_ack(multiple=True)`` for many settled messages.

A batch's settled prefix joins the held acknowledgement, which goes out once it covers a
quarter of the prefetch, once the source goes idle (:data:`ACK_IDLE_NS` without a message),
after :data:`ACK_HOLD_NS` at most, and at a stop or reload (:meth:`HeldAcks.acknowledge` says
why). Batches are acknowledged in order, so every earlier tag is already acked or nacked and
at-least-once holds: a crash redelivers instead of losing. The source (source.py) decides when
a batch is acknowledged; this module, how.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any, Callable

import aiormq.abc

from engine.endpoints.amqp.errors import LIBRARY_ERRORS

ACK_IDLE_NS = 5_000_000
"""The source is idle once no message arrived for this long: the acknowledgement it holds
(see :meth:`HeldAcks.acknowledge`) goes out then. Its timer fires about once per this
while a burst lasts (at 1 ms it was 0.8 % of the engine's samples in a drain); a message at a
robot's pace (5-10 ms apart) does not wait for it: one settled alone is acknowledged at once."""
ACK_HOLD_NS = 50_000_000
"""The longest an acknowledgement is held while messages keep arriving (50 ms: at 6,000 msg/s
fewer messages than a quarter of the bench's prefetch, which flushes it first)."""


class HeldAcks:
    """The acknowledgement one source holds, per channel.

    ``last_received_ns`` tells when the source's last message arrived (is it idle?); ``wake``
    wakes its batch loop, which sends what is held once :attr:`due` (see the source's ``_park``:
    every acknowledgement leaves from one place at a time, in order)."""

    def __init__(self, prefetch: int, last_received_ns: Callable[[], int], wake: Callable[[], None]) -> None:
        self._last_received_ns = last_received_ns
        self._wake = wake
        self._acks: dict[int, tuple[aiormq.abc.AbstractChannel, int | None]] = {}
        """Per channel, the highest delivery tag whose whole prefix was settled and not
        acknowledged yet (see :meth:`acknowledge`)."""
        self.held = 0
        """Messages the held acknowledgements cover."""
        self._since_ns = 0
        """When the oldest of them was settled."""
        self._every = max(1, prefetch // 4)
        """Held acknowledgements go out once they cover this many messages: the broker keeps
        three quarters of the prefetch streaming meanwhile."""
        self.due = False
        """The source went idle (or :data:`ACK_HOLD_NS` passed): what is held goes out now."""
        self._timer: asyncio.TimerHandle | None = None

    @property
    def holding(self) -> bool:
        """Some settled message is not acknowledged yet."""
        return bool(self._acks)

    def arm_timer(self) -> None:
        if self._timer is None:
            self._timer = asyncio.get_running_loop().call_later(ACK_IDLE_NS / 1e9, self._idle)

    def cancel_timer(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _idle(self) -> None:
        """The timer the source's ``_park`` armed: is the source idle (or the hold over)? Then wake it."""
        self._timer = None
        if not self._acks:
            return
        now = time.monotonic_ns()
        quiet = now - self._last_received_ns()
        if quiet >= ACK_IDLE_NS or now - self._since_ns >= ACK_HOLD_NS:
            self.due = True
            self._wake()
        else:
            self._timer = asyncio.get_running_loop().call_later((ACK_IDLE_NS - quiet) / 1e9, self._idle)

    async def acknowledge(self, messages: list[aiormq.abc.DeliveredMessage], settled: list[bool],
                          hold: bool = True) -> None:
        """The settled prefix of the batch joins the held acknowledgement: one
        ``basic_ack(multiple=True)`` per channel, sent once it covers a quarter of the
        prefetch, once the source goes idle (the source's ``_park``), after :data:`ACK_HOLD_NS`, at
        once for a message settled alone with nothing held (``hold`` False: at a robot's pace
        every message is alone), and before anything else is acked or nacked: single acks and
        requeueing nacks for the rest of the batch, after it, so no frame names a tag a later
        ``multiple`` ack already covered. Only settled messages are ever acked.

        Why held: a batch is whatever arrived since the last one, a few messages when the
        route keeps up with the broker (3,960 batches for 13,200 messages measured before
        source.py's ``FRAME_BUFFER``, and still small whenever the engine is faster than the stream),
        and an ack per batch was a tenth of the engine's CPU time in py-spy (a frame, a writer
        task wake-up and a socket write each), besides the broker's own work per ack; held,
        ~2 %. The cost: a crash (not a stop or reload, which send what is held) redelivers up
        to a quarter of the prefetch more messages that had reached the sink, within the
        at-least-once contract a crash already has."""
        prefix = 0
        while prefix < len(settled) and settled[prefix]:
            prefix += 1
        acks = self._acks
        if prefix:
            if not acks:
                self._since_ns = time.monotonic_ns()
            first, last = messages[0], messages[prefix - 1]
            if first.channel is last.channel:
                acks[id(last.channel)] = (last.channel, last.delivery_tag)
            else:  # the batch spans a reconnect: the old channel's tags are requeued by the broker anyway
                for message in messages[:prefix]:
                    acks[id(message.channel)] = (message.channel, message.delivery_tag)
            self.held += prefix
        if acks and (not hold or prefix < len(messages) or self.due or self.held >= self._every
                     or time.monotonic_ns() - self._since_ns >= ACK_HOLD_NS):
            await self.flush()
        elif acks:
            self.arm_timer()  # the settler's batches too, while the loop may be parked already
        for message, ok in zip(messages[prefix:], settled[prefix:]):
            if ok:
                await _settle_frame(message.channel.basic_ack, message.delivery_tag)
            else:
                await _settle_frame(message.channel.basic_nack, message.delivery_tag, requeue=True)

    async def flush(self) -> None:
        """Send the held acknowledgement (one ``multiple`` ack per channel)."""
        self.due = False
        if not self._acks:
            return
        acks, self._acks, self.held = self._acks, {}, 0
        for channel, tag in acks.values():
            await _settle_frame(channel.basic_ack, tag, multiple=True)


async def _settle_frame(method: Any, tag: int | None, **kwargs: Any) -> None:
    """An ack or nack queued for the connection's writer, not waited for (``wait=False``):
    the source moves on to its next batch at once instead of sleeping until the frame is on
    the socket (a loop round trip per batch, which at a robot's pace is one per message).
    Frames leave in the order they were queued; one lost with its connection changes nothing,
    as the broker requeues whatever was not acknowledged."""
    try:
        await method(tag, wait=False, **kwargs)
    except LIBRARY_ERRORS:
        pass  # the channel is gone: the broker requeues whatever was not acked
