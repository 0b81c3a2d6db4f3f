"""Zenoh source: one subscriber on the route's key expression, messages handed to the route in batches.

Each sample becomes a message with its payload's bytes untouched, ``meta('key')`` (the key it
was put on), ``meta('encoding')``, and one ``meta(name)`` per ``{name}`` capture of the key
(keys.py). Samples come on Zenoh's threads into a bounded queue (handoff.py); the engine's
read loop (engine/endpoints/pump.py) hands everything queued to the route as one batch.

Zenoh's pub/sub keeps no message for a subscriber and has no acknowledgement: a message the
route did not settle (only while it stops) is gone, and counted as dropped, as a ROS 2 topic's
is. The route therefore holds messages in its buffer while its sink is down
(``Transport.redelivers`` is False). A DELETE sample (a ``delete`` on a key) carries no
payload and is skipped.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any, Sequence

import zenoh

from engine.endpoints.base import Deliver, EndpointError, Inbound, Source
from engine.endpoints.pump import pump
from engine.endpoints.zenoh.errors import mapped
from engine.endpoints.zenoh.handoff import Handoff, stop_receiving
from engine.endpoints.zenoh.keys import parse_pattern
from engine.endpoints.zenoh.options import ZenohSourceOptions
from engine.endpoints.zenoh.session import ZenohLink

log = logging.getLogger("engine.zenoh")

BATCH = 1024
"""Most messages handed to the route in one ``Deliver.batch`` (as the ROS 2 and MAVLink sources)."""


class ZenohSource(Source):
    def __init__(self, connection: ZenohLink, route: str, options: ZenohSourceOptions) -> None:
        self._connection = connection
        self.route = route
        self._where = f"route {route!r}: zenoh source {options.key!r}"
        try:
            self.pattern = parse_pattern(options.key)
        except ValueError as exc:
            raise EndpointError(f"{self._where}: {exc}") from None
        self._handoff: Handoff[Inbound] | None = None
        self._deliver: Deliver | None = None
        self._subscriber: Any = None
        self._loop: asyncio.Task[None] | None = None
        self._reported_drops = 0
        self.received = 0
        self.dropped = 0

    async def start(self, deliver: Deliver) -> None:
        handoff: Handoff[Inbound] = Handoff(asyncio.get_running_loop(), deliver.queue_limit, deliver.overflow)
        self._handoff, self._deliver = handoff, deliver
        captured = self.pattern.captured

        def on_sample(sample: zenoh.Sample) -> None:  # a Zenoh thread
            if sample.kind != zenoh.SampleKind.PUT:
                return
            key = str(sample.key_expr)
            meta: dict[str, Any] = {"key": key, "encoding": str(sample.encoding)}
            meta.update(captured(key))
            handoff.put(Inbound(body=sample.payload.to_bytes(), meta=meta))

        with mapped(f"{self._where}: subscribe"):
            self._subscriber = self._connection.session.declare_subscriber(self.pattern.subscription, on_sample)
        self._loop = asyncio.create_task(self._run(deliver), name=f"zenoh-source:{self.route}")

    async def _run(self, deliver: Deliver) -> None:
        """The engine's read loop (engine/endpoints/pump.py) over :meth:`read_batch`,
        :meth:`inbounds` and :meth:`settle`; then the queue's last drops are counted."""
        await pump(self, deliver, self._where)
        self._report_drops(deliver)

    async def read_batch(self) -> list[Inbound]:
        """Everything queued (at most BATCH), once there is something; [] once stopped."""
        handoff, deliver = self._handoff, self._deliver
        assert handoff is not None and deliver is not None
        batch = await handoff.take(BATCH)
        self.received += len(batch)
        self._report_drops(deliver)
        return batch

    @staticmethod
    def inbounds(batch: Sequence[Inbound]) -> Sequence[Inbound]:
        return batch

    async def settle(self, batch: Sequence[Inbound], settled: list[bool]) -> None:
        """A message not settled is lost (Zenoh keeps nothing to redeliver): counted."""
        deliver, handoff = self._deliver, self._handoff
        assert deliver is not None and handoff is not None
        lost = settled.count(False)
        if lost:
            self.dropped += lost
            deliver.dropped(lost)
        if len(handoff):  # a backlog must not hold the loop from other routes
            await asyncio.sleep(0)

    def _report_drops(self, deliver: Deliver) -> None:
        """Count the messages the queue dropped since the last report (overflow)."""
        handoff = self._handoff
        if handoff is not None and handoff.dropped != self._reported_drops:
            increase, self._reported_drops = handoff.dropped - self._reported_drops, handoff.dropped
            self.dropped += increase
            deliver.dropped(increase)

    async def stop(self) -> None:
        """Take no more samples, undeclare the subscriber, settle what was queued, then end.
        The queue closes first: a callback waiting for room (``overflow: block``) is let go
        (its sample dropped and counted), so undeclaring never waits on a route that cannot
        take more (its sink down)."""
        subscriber, self._subscriber = self._subscriber, None
        await stop_receiving(self._handoff, subscriber, self._loop, self._where)

    def status(self) -> dict[str, Any]:
        return {"subscription": self.pattern.subscription, "received": self.received, "dropped": self.dropped}
