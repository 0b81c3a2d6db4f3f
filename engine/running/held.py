"""The route's face to its buffer (engine/running/buffer.py's ``BufferOwner``): sending what the
buffer holds through the route's current pipeline, and counting (and answering the callers of)
what it delivered, expired, conflated, lost or had rejected.

A collaborator of the runner, not the runner itself, so the buffer sees only these calls; it
reads the runner through :class:`~engine.running.route_state.RunningRoute` (the current
pipeline: the buffer outlives a reload's runner).
"""

from __future__ import annotations

import asyncio
import time

from engine.endpoints.base import Inbound, Outbound, Unroutable
from engine.running.buffer_stores import Held
from engine.running.dead_lettering import DeadLettering
from engine.running.delivery import ConversionError, classify
from engine.running.fanout import mapped_for
from engine.running.pipeline import Pipeline
from engine.running.route_state import Dead, RunningRoute


class HeldMessages:
    """What a route's buffer calls back: see the module docstring."""

    def __init__(self, route: RunningRoute, dead_lettering: DeadLettering) -> None:
        self.route = route
        self.dead_lettering = dead_lettering

    def sink_can_take(self) -> bool:
        return self.route.sink_can_take()

    async def send_held(self, messages: list[Outbound]) -> list[BaseException | None]:
        pipeline = self.route.pipeline
        unmappable = self._mapped_again(pipeline, messages)
        to_send = [m for i, m in enumerate(messages) if i not in unmappable] if unmappable else messages
        pipeline.enter()
        try:
            results: list[BaseException | None] = await pipeline.sink.send_batch(to_send) if to_send else []
        finally:
            pipeline.leave()
        if unmappable:  # the buffer dead-letters those with their error
            sent = iter(results)
            results = [unmappable[i] if i in unmappable else next(sent) for i in range(len(messages))]
        if results.count(None) != len(results):
            self.route.observer.unroutable += sum(isinstance(result, Unroutable) for result in results)
        return results

    def _mapped_again(self, pipeline: Pipeline, messages: list[Outbound]) -> dict[int, BaseException] | None:
        """Register each message's reply, and map again those held across a reload that changed
        the route's sinks (``sink:`` to ``sinks:``, back, or to other sinks: their fields are for
        sinks the route no longer has); returns those the new mappings refuse, by index (None:
        none, the common case, with nothing made)."""
        names = pipeline.sink_names
        unmappable: dict[int, BaseException] | None = None
        for index, message in enumerate(messages):
            self.dead_lettering.reply_of(message)
            if not mapped_for(message.meta, names):
                try:
                    pipeline.remap(message)
                except ConversionError as error:
                    unmappable = unmappable or {}
                    unmappable[index] = error
        return unmappable

    def held_delivered(self, held: list[Held]) -> None:
        now_ns = time.time_ns()
        observer, remember, dedupe = self.route.observer, self.route.pipeline.remember, self.route.pipeline.dedupe
        keys = []
        for outbound, received_at_ns in held:
            observer.accepted(None, outbound, None if received_at_ns is None else now_ns - received_at_ns)
            if remember is not None:
                remember.on_accepted(outbound.canonical, outbound.meta)
            if dedupe is not None and (key := dedupe.key(outbound.canonical, outbound.meta)) is not None:
                keys.append(key)
        if keys and dedupe is not None:
            dedupe.keys.answered(keys)

    def held_stale(self, held: Held) -> bool:
        received_at_ns = held[1]
        return received_at_ns is not None and self.route.too_old(time.time_ns() - received_at_ns)

    def held_refused(self, held: list[Held]) -> None:
        """Sent from the buffer and refused by the destination: the sink replied already."""
        for outbound, _ in held:
            self.route.observer.refuse(None, outbound)

    def held_expired(self, held: list[Held]) -> None:
        for outbound, _ in held:
            self.route.observer.expire(None, outbound)
            self.dead_lettering.expired_call(outbound)

    def held_conflated(self, held: list[Held]) -> None:
        for outbound, _ in held:
            self.route.observer.conflate(None, outbound)
            self.dead_lettering.ended_call(outbound, "latest_only", "conflated: a newer message with the same key was held "
                                                                    "while the sink was down (buffer.latest_only)")

    async def held_lost(self, held: list[Held]) -> None:
        """The buffer closed (the route or the engine stopped) with calls held in memory only:
        they can no longer be delivered, so each caller gets its one ``error`` reply now."""
        error = "the route stopped before its sink could take it (held in memory, not spilled)"
        replies, reply_of = self.route.replies, self.dead_lettering.reply_of
        await asyncio.gather(*(replies.failed(reply_of(outbound), outbound.meta, "buffer", error)
                               for outbound, _ in held if outbound.meta.get("reply_to")))

    async def held_rejected(self, message: Outbound, error: BaseException, attempts: int) -> None:
        """A held message the sink rejected, or kept failing while it could take messages."""
        self.dead_lettering.reply_of(message)
        inbound = Inbound(body=message.body, meta=dict(message.meta))
        await self.dead_lettering.store([Dead(0, inbound, message, attempts, self.route.pipeline, classify(error, "sink"))], [False])
