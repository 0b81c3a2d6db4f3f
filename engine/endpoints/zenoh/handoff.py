"""Messages from Zenoh's threads to the engine's event loop, bounded, in batches.

eclipse-zenoh calls a subscriber's or queryable's callback on a thread of its own runtime.
Each callback appends to this queue under a lock and wakes the loop only when it was not
woken already, so a burst costs one ``call_soon_threadsafe`` (a write to the loop's
self-pipe), not one per message. Full (the route's ``queue_limit``), it follows the route's
``overflow``: ``drop_newest`` / ``drop_oldest`` drop and count; ``block`` makes the callback
wait for room, which stops Zenoh reading from that peer: its reliable link then fills and the
publisher's congestion control applies (a put with ``block`` waits, one with ``drop`` drops,
Zenoh's default). A callback on the loop's own thread (a put of this session that matches its
own subscription runs the callback inline) never waits: it could not be given room.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections import deque
from typing import Any, Callable, Generic, TypeVar

T = TypeVar("T")

log = logging.getLogger("engine.zenoh")


async def stop_receiving(handoff: Handoff[Any] | None, entity: Any, loop: asyncio.Task[None] | None, where: str) -> None:
    """A subscriber's or queryable's stop, in its order: the queue closes first (a callback
    waiting for room is let go, so undeclaring never waits on a route that cannot take more),
    the entity is undeclared (off the event loop: it blocks), then what was queued is settled."""
    if handoff is not None:
        handoff.close()
    if entity is not None:
        try:
            await asyncio.to_thread(entity.undeclare)
        except Exception as exc:  # a closed session undeclared it already
            log.debug("%s: undeclare: %s", where, exc)
    if loop is not None:
        await loop


class Handoff(Generic[T]):
    def __init__(self, loop: asyncio.AbstractEventLoop, limit: int, overflow: str,
                 on_drop: Callable[[T], None] | None = None) -> None:
        self._loop = loop
        self._on_drop = on_drop
        """Called with each item dropped (on the putting thread): a query must still be answered."""
        self._loop_thread = threading.get_ident()
        self._items: deque[T] = deque()
        self._limit = max(1, limit)
        self._overflow = overflow
        self._lock = threading.Lock()
        self._room = threading.Condition(self._lock)
        self._woken = False
        self._arrived = asyncio.Event()
        self.closed = False
        self.dropped = 0
        """Messages dropped so far (read on the loop; the source reports the increase)."""

    def put(self, item: T) -> None:
        """Called on a Zenoh thread (or inline on the loop's): queue ``item`` by the overflow policy."""
        dropped: list[T] = []
        wake = False
        with self._lock:
            items = self._items
            while not self.closed and len(items) >= self._limit:
                if self._overflow == "drop_oldest":
                    dropped.append(items.popleft())
                    break
                if self._overflow != "block" or threading.get_ident() == self._loop_thread:
                    break
                self._room.wait()
            if self.closed or len(items) >= self._limit:
                dropped.append(item)
            else:
                items.append(item)
                wake, self._woken = not self._woken, True
            self.dropped += len(dropped)
        if self._on_drop is not None:
            for lost in dropped:
                self._on_drop(lost)
        if wake:
            try:
                self._loop.call_soon_threadsafe(self._arrived.set)
            except RuntimeError:  # the loop is closed: the engine is gone
                pass

    async def take(self, most: int) -> list[T]:
        """Everything queued (at most ``most``), once there is something; [] once closed and empty."""
        while True:
            with self._lock:
                items = self._items
                if items:
                    count = min(most, len(items))
                    batch = [items.popleft() for _ in range(count)]
                    if not items:
                        self._woken = False
                        self._arrived.clear()
                    self._room.notify_all()
                    return batch
                if self.closed:
                    return []
                self._woken = False
                self._arrived.clear()
            await self._arrived.wait()

    def close(self) -> None:
        """Take nothing more and release a waiting callback; :meth:`take` still returns what
        is queued, then []."""
        with self._lock:
            self.closed = True
            self._room.notify_all()
        self._arrived.set()

    def __len__(self) -> int:
        return len(self._items)
