"""The contract's values (engine/endpoints/base.py): a message as a source received it
(:class:`Inbound`), as a sink is given it (:class:`Outbound`, with its :class:`Reply`), as a
dead-letter store holds it (:class:`StoredLetter`), and a
push source's bounded queue (:class:`Inbox`). Protocol packages import them through
engine/endpoints/base.py, the contract's one face.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Generic, Mapping, Protocol, TypeVar

OVERFLOW_POLICIES = ("block", "drop_oldest", "drop_newest")
"""What a source does when its bounded queue towards the pipeline is full: stop taking from
its protocol until there is room (``block``: the protocol's own flow control or history
holds the rest), or drop the oldest / the newest message and count it."""


REPLY_KINDS = ("accepted", "feedback", "result", "rejected", "error")
"""What a reply says (the AMQP header ``x-rabbitros-reply``): a goal ``accepted`` (then each
``feedback``) or ``rejected``; the ``result`` that ends a call; an ``error`` that ends it too
(timeout, nobody serving it, a request that failed conversion). ``result``, ``rejected`` and
``error`` are final: nothing more is sent for that request (a later reply is dropped, counted)."""
FINAL_REPLIES = frozenset(("result", "rejected", "error"))

class Reply(Protocol):
    """``await outbound.reply(kind, data)``: one reply to the request ``outbound`` carries. ``data``
    is plain JSON data (the reply mapping's input); for ``error`` it is ``{stage, error}``. It never
    raises: a reply that cannot be delivered is counted by the route. For a message that asked for
    no reply it only counts the reply (fire-and-forget). ``outbound.reply.late()``: the sink's
    destination answered after the sink gave up on the call (its timeout): the answer is dropped
    and counted (``replies.late``), whether the request asked for replies or not."""

    async def __call__(self, kind: str, data: Any) -> None: ...

    def late(self) -> None: ...


def late_window(timeout: float) -> float:
    """How long after a call's timeout a sink still recognises its answer, to count it
    ``late``: one more ``timeout``, at least 5 s (a loaded machine answers a little late, and
    one more second of a few bytes per call is nothing); then the answer is forgotten. Bounded:
    calls time out at most as fast as they are sent, so at most that many seconds' worth wait."""
    return max(timeout, 5.0)


@dataclass(slots=True)
class Inbound:
    """One message as a source received it.

    Byte protocols (AMQP bodies, ROS ``std_msgs/String`` data, MAVLink JSON tunnels) fill
    ``body`` so an identity route can forward the bytes untouched; typed protocols (ROS
    messages, MAVLink telemetry) fill ``fields`` with a plain dict.
    """

    body: bytes | None = None
    fields: dict[str, Any] | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    received_ns: int = field(default_factory=time.monotonic_ns)
    undecodable: str | None = None
    """Set by a source that received something it could not turn into a message (why);
    the engine dead-letters it (stage ``decode``) with whatever ``body`` the source kept."""


@dataclass(slots=True)
class Outbound:
    """What a sink is given.

    ``body`` is the canonical JSON (the original bytes when the route maps by identity),
    ``canonical`` the validated canonical dict, ``fields`` the result of ``sink.mapping``
    (``canonical`` itself when there is none); ``meta`` carries the source's metadata.
    """

    body: bytes
    canonical: Any
    fields: Any
    message_id: str
    meta: Mapping[str, Any]
    reply: Reply | None = None
    """Set by the runner (see the reply contract in the module docstring); None outside a
    route (a test building an Outbound), where a sink's replies go nowhere."""
    received_ns: int | None = None
    """``time.monotonic_ns()`` when the route received the message, set by the runner: a sink
    that keeps trying to deliver it (a tunnel's retransmissions) gives it up as
    :class:`Expired` once it is older than the route's ``max_age`` (its options' ``max_age``)."""

    captured: Mapping[str, Any] | None = None
    """The values the source captured from where the message came (a ROS 2 source topic's
    ``{var}`` segments, :meth:`Transport.source_variables`), by name; None when there are none."""

    @property
    def template_data(self) -> Any:
        """What a sink's ``{name}`` templates (routing keys, topics) read: the canonical
        message, with the captured values over it (a captured variable wins over a canonical
        field of the same name, as a ``for_each`` variable does; ``check`` warns)."""
        if not self.captured:
            return self.canonical
        return {**self.canonical, **self.captured} if isinstance(self.canonical, dict) else dict(self.captured)


T = TypeVar("T")


class Inbox(Generic[T]):
    """A push source's bounded queue towards its batch loop (ROS 2 takes, MAVLink frames).

    ``offer`` applies the overflow policy and says how many it dropped; with ``block`` the
    source must stop taking from its protocol while ``full``. ``take`` waits for the first
    item and returns everything queued (at most ``most``); [] once closed and empty."""

    def __init__(self, limit: int, overflow: str = "block") -> None:
        self.items: deque[T] = deque()
        self.limit = max(1, limit)
        self.overflow = overflow
        self.closed = False
        self._arrived = asyncio.Event()

    @property
    def full(self) -> bool:
        return len(self.items) >= self.limit

    def offer(self, item: T) -> int:
        """Queue ``item`` (call :meth:`wake` after a burst); returns the number dropped."""
        items = self.items
        if len(items) >= self.limit:
            if self.overflow == "drop_newest":
                return 1
            if self.overflow == "drop_oldest":
                items.popleft()
                items.append(item)
                return 1
        items.append(item)
        return 0

    def wake(self) -> None:
        self._arrived.set()

    def clear(self) -> int:
        """Forget what is queued (a stopping source); returns how many."""
        left = len(self.items)
        self.items.clear()
        return left

    def close(self) -> None:
        self.closed = True
        self._arrived.set()

    async def arrival(self) -> None:
        """Wait for the next :meth:`wake` or :meth:`close` without taking anything (a loop
        that has something of its own to do when woken with nothing queued)."""
        self._arrived.clear()
        await self._arrived.wait()

    async def take(self, most: int) -> list[T]:
        items = self.items
        while not items:
            if self.closed:
                return []
            self._arrived.clear()
            await self._arrived.wait()
        return [items.popleft() for _ in range(min(len(items), most))]

    def __len__(self) -> int:
        return len(self.items)


@dataclass(eq=False)
class StoredLetter:
    """A dead letter as its store holds it: the body and headers :meth:`Connection.dead_letter`
    (or the engine's spool) was given, when it was stored (seconds since the epoch, None when the
    store does not say), and the store's handle for removing it."""

    body: bytes
    headers: Mapping[str, Any]
    at: float | None = None
    handle: Any = None
    where: str = ""
    """The store it is in, for operators (``amqp connection 'gcs'``, ``spool DIR``)."""
