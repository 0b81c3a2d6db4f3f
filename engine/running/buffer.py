"""Messages a route holds while its sink is down, in memory or spilled to disk.

A ROS 2 or MAVLink source cannot have a message redelivered, so when the sink fails
transiently (the broker is down, a link is out) the route's runner hands the converted
message to its :class:`HoldingBuffer` and the source moves on. While the buffer holds
anything, new messages queue behind it, so order is kept. One task per buffer retries the
oldest messages with exponential backoff (and without trying at all while the sink's
connection reports itself unhealthy), in batches sent concurrently, and hands each
delivered message back to the route, which counts it. Which failures are retried and which
are dead-lettered is the delivery policy's classification (engine/running/delivery.py); the waits
between attempts are the engine's one backoff (engine/common/backoff.py). A buffer outlives a
reload that replaces its route's runner (:class:`Buffers`): the held messages move with the
route.

Freshness: a held message older than the route's ``max_age`` when its turn comes is not
sent but expired (the runner decides, ``stale``); with ``latest_only`` a held message for
which a newer one with the same key (the canonical field ``per``) is held too is not sent
but conflated. Both settle the message (it leaves the buffer) and are counted by the route.
Telemetry wants them: after an outage of minutes a position or a battery level from before
it is worthless, and replaying every one floods the link for as long as the outage lasted
(ros-foxglove-bridge#329). Events that must all arrive (detections, mission results,
commands) want neither: leave ``max_age`` and ``latest_only`` unset on their routes.

Calls (requests with a reply address, engine/running/replies.py) keep their way back through the
buffer: one read back from the spill files is bound to the route's replies again by the runner,
and one held in memory only when the buffer closes is answered with an ``error`` reply
(``on_lost``): it can no longer be delivered.

Bounded: at most ``max_messages`` are held; a full buffer makes ``hold`` wait (back-pressure
to the source, whose own bounded queue then applies its overflow policy).

Spill (``spill_dir``): every held message is appended as one JSON line to a segment file
in ``spill_dir/<route>/`` (``<first sequence number>.jsonl``, rolled every
``SEGMENT_MESSAGES``); ``cursor.json`` records how far delivery got (replaced atomically
after each delivered batch); a fully delivered segment is deleted. At start the buffer
replays what the files still hold, so an engine restart during an outage loses nothing that
was spilled.

Fsync policy: each message is written with one ``os.write`` before the source is
acknowledged, so it is in the kernel's page cache and survives the engine process dying
(SIGTERM, a crash, kill -9), which is the failure this buffer exists for. ``fsync`` runs at
most every ``fsync_interval`` seconds (default 1 s) while there are new writes, when a segment
is rolled and at close, so a power loss or kernel crash loses at most the last second. An
fsync per message would cost a disk flush per message (milliseconds on an SD card) and cap a
robot's throughput during the outage exactly when the backlog grows. A torn last line (a
write cut by a power loss) is skipped and counted as ``corrupt``. Delivery is at least once:
a crash between a delivered batch and its cursor update resends that batch.
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Awaitable, Callable, Protocol


from engine.common.backoff import Backoff
from engine.common.field_keys import slot_key
from engine.endpoints.base import EndpointError, Expired, NotSent, Outbound, Refused
from engine.language.stage_options import DEFAULT_MAX_MESSAGES, BufferSpec
from engine.running.buffer_stores import Held, MemoryStore, SpillStore
from engine.running.delivery import classify

log = logging.getLogger("engine.running.buffer")

BATCH = 64
RETRY_FIRST, RETRY_MAX = 0.1, 2.0
IDLE_POLL = 0.1
"""Seconds between looks at a sink that cannot take messages: a look costs nothing, and it
bounds the time from the sink's return to the first message sent."""

SendBatch = Callable[[list[Outbound]], Awaitable[list[BaseException | None]]]
"""Sends messages in order; ``result[i]`` is None when ``messages[i]`` was accepted."""


@dataclass
class BufferStats:
    held: int = 0
    """Messages held now (memory or disk)."""
    held_total: int = 0
    delivered: int = 0
    rejected: int = 0
    replayed: int = 0
    """Messages found in the spill directory at start."""
    corrupt: int = 0
    lost: int = 0
    """Held in memory only and still undelivered when the buffer was closed."""
    retries: int = 0
    expired: int = 0
    """Older than the route's ``max_age`` when their turn came: not sent."""
    conflated: int = 0
    """``latest_only``: a newer message with the same key was held too: not sent."""
    refused: int = 0
    """Sent, and refused by the destination (an answer, replied to the caller): settled."""


class HoldingBuffer:
    """Holds a route's messages while its sink is down; see the module docstring."""

    def __init__(
        self,
        route: str,
        send: SendBatch,
        *,
        max_messages: int = DEFAULT_MAX_MESSAGES,
        spill_dir: Path | None = None,
        fsync_interval: float = 1.0,
        max_attempts: int | None = None,
        ready: Callable[[], bool] = lambda: True,
        on_delivered: Callable[[list[Held]], None] = lambda held: None,
        on_rejected: Callable[[Outbound, BaseException, int], Awaitable[None]] | None = None,
        latest_per: tuple[str, ...] | None = None,
        stale: Callable[[Held], bool] = lambda held: False,
        on_expired: Callable[[list[Held]], None] = lambda held: None,
        on_conflated: Callable[[list[Held]], None] = lambda held: None,
        on_refused: Callable[[list[Held]], None] = lambda held: None,
        on_lost: Callable[[list[Held]], Awaitable[None]] | None = None,
    ) -> None:
        self.route = route
        self._send = send
        self.max_messages = max(1, max_messages)
        self._ready = ready
        self.max_attempts = max_attempts
        """Failures of the oldest message while the sink's connection stays healthy after
        which it is handed to ``on_rejected`` (a message the far end never takes must not
        hold the route up for ever); failures while the connection is down do not count."""
        self._on_delivered = on_delivered
        self._on_rejected = on_rejected
        self._latest_per = latest_per
        self._stale = stale
        self._on_expired = on_expired
        self._on_conflated = on_conflated
        self._on_refused = on_refused
        self._on_lost = on_lost
        """Told of the messages held in memory only that a close lets go of (the route answers
        the calls among them with an error reply)."""
        self._latest: dict[Any, int] = {}
        """``latest_only``: key -> sequence number of the newest held message with that key."""
        self._head_seq = 0
        """Sequence number of the oldest held message (the next one held gets head + held)."""
        self.stats = BufferStats()
        self._store: MemoryStore | SpillStore = (
            SpillStore(spill_dir / route, fsync_interval) if spill_dir is not None else MemoryStore()
        )
        self._changed = asyncio.Event()
        self._closing = asyncio.Event()
        self._room = asyncio.Event()
        self._room.set()
        self._task: asyncio.Task[None] | None = None
        self._closed = False
        self._last_report = 0.0
        self._head_attempts = 0
        """Transient failures of the oldest message while the sink looked able to take it."""
        self._sent_ahead: set[int] = set()
        """Indexes (in the next batch) of messages accepted behind one that failed."""

    @property
    def spills(self) -> bool:
        return isinstance(self._store, SpillStore)

    @property
    def holding(self) -> bool:
        return self.stats.held > 0

    def __len__(self) -> int:
        return self.stats.held

    def start(self) -> None:
        """Replay what a previous run spilled, and begin delivering it."""
        if self._task is not None:
            return
        found, corrupt = self._store.load()
        self.stats.held = self.stats.replayed = found
        self.stats.corrupt += corrupt
        if found and self._latest_per is not None:
            for index, (message, _) in enumerate(self._store.peek(found)):
                self._latest[slot_key(message.canonical, self._latest_per)] = self._head_seq + index
        if found:
            log.info("replaying spilled messages", extra={"route": self.route, "messages": found, "corrupt": corrupt})
        self._update_room()
        self._task = asyncio.create_task(self._deliver_loop(), name=f"buffer-{self.route}")

    async def hold(self, message: Outbound, received_at_ns: int | None = None) -> None:
        """Keep ``message`` (received at ``received_at_ns``, wall clock) until the sink takes
        it; returns once it is held (written, when spilling), waiting while the buffer is full."""
        while self.stats.held >= self.max_messages:
            self._room.clear()
            await self._room.wait()
        self._store.append((message, received_at_ns))
        if self._latest_per is not None:
            self._latest[slot_key(message.canonical, self._latest_per)] = self._head_seq + self.stats.held
        self.stats.held += 1
        self.stats.held_total += 1
        self._update_room()
        self._changed.set()
        if self._task is None:
            self.start()

    async def close(self, timeout: float = 0.0) -> None:
        """Keep delivering for at most ``timeout`` seconds, then stop. Spilled messages stay
        on disk for the next start; messages held only in memory are counted as lost."""
        if self._task is None:
            return
        if timeout > 0 and self.holding and self._ready():
            deadline = time.monotonic() + timeout
            while self.holding and time.monotonic() < deadline and not self._task.done():
                await asyncio.sleep(0.02)
        self._closed = True
        self._closing.set()
        self._changed.set()
        try:  # a batch being sent finishes and is recorded, so the next start does not resend it
            await asyncio.wait_for(asyncio.shield(self._task), 5.0)
        except (asyncio.TimeoutError, asyncio.CancelledError):
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
        self._task = None
        self._store.close()
        if not self.spills and self.stats.held:
            self.stats.lost += self.stats.held
            log.error("buffer closed with undelivered messages", extra={"route": self.route, "lost": self.stats.held})
            if self._on_lost is not None:
                try:
                    await self._on_lost(self._store.peek(self.stats.held))
                except Exception as exc:  # telling the callers must not keep the engine from stopping
                    log.error("buffer: telling the lost messages' senders failed", extra={"route": self.route, "error": repr(exc)})
        elif self.stats.held:
            log.info("spilled messages kept for the next start", extra={"route": self.route, "messages": self.stats.held})

    def _update_room(self) -> None:
        if self.stats.held < self.max_messages:
            self._room.set()

    async def _deliver_loop(self) -> None:
        backoff = Backoff(RETRY_FIRST, RETRY_MAX)
        while not self._closed:
            if not self.holding:
                self._changed.clear()
                await self._changed.wait()
                continue
            if not self._ready():
                await self._pause(IDLE_POLL)
                continue
            batch = self._store.peek(BATCH)
            if not batch:  # the count says more than the files hold (corrupt lines)
                self.stats.held = 0
                continue
            failure = await self._send_batch(batch)
            if failure is None:
                backoff.reset()
            elif not await self._gave_up_on_head(failure):
                self._report_holding(failure)
                await self._pause(backoff.next())

    async def _send_batch(self, batch: list[Held]) -> BaseException | None:
        """Send the oldest messages; settle the accepted, the rejected, the expired and the
        conflated ones up to the first that failed transiently, and return that failure (None
        when all were settled)."""
        sent_ahead = self._sent_ahead
        skipped = {i: outcome for i, held in enumerate(batch) if i not in sent_ahead
                   for outcome in (self._not_sent(i, held),) if outcome is not None}
        to_send = [message for i, (message, _) in enumerate(batch) if i not in sent_ahead and i not in skipped]
        try:
            outcomes = iter(await self._send(to_send) if to_send else [])
        except Exception as error:  # the sink's contract is to return errors; be safe anyway
            outcomes = iter([error] * len(to_send))
        results = [None if i in sent_ahead or i in skipped else next(outcomes) for i in range(len(batch))]
        settled, failure = 0, None
        delivered: list[Held] = []
        dropped: dict[str, list[Held]] = {"expired": [], "conflated": [], "refused": []}
        for index, (held, result) in enumerate(zip(batch, results)):
            if index in skipped:
                dropped[skipped[index]].append(held)
            elif result is None:
                delivered.append(held)
            elif isinstance(result, NotSent):  # settled by the sink unsent; the route counts it
                kind = "expired" if isinstance(result, Expired) else "refused" if isinstance(result, Refused) else "conflated"
                dropped[kind].append(held)
            elif classify(result).permanent:
                await self._reject(held[0], result, self._head_attempts + 1)
            else:
                failure = result
                break
            settled += 1
        if settled:
            self._settled(settled, delivered, dropped)
        # accepted behind the failed one: not sent again while they wait for it
        self._sent_ahead = {i - settled for i in range(settled + 1, len(batch)) if results[i] is None and i not in skipped}
        return failure

    def _not_sent(self, index: int, held: Held) -> str | None:
        """Why the ``index``-th oldest held message is settled without being sent: "conflated"
        (``latest_only``: a newer one with its key is held), "expired" (the route says it is
        too old), or None: send it."""
        if self._latest_per is not None and \
                self._latest.get(slot_key(held[0].canonical, self._latest_per)) != self._head_seq + index:
            return "conflated"
        return "expired" if self._stale(held) else None

    def _settled(self, count: int, delivered: list[Held], dropped: dict[str, list[Held]] | None = None) -> None:
        self._pop(count)
        self.stats.held -= count
        self.stats.delivered += len(delivered)
        self._on_delivered(delivered)
        if dropped:
            self.stats.expired += len(dropped["expired"])
            self.stats.conflated += len(dropped["conflated"])
            self.stats.refused += len(dropped["refused"])
            if dropped["expired"]:
                self._on_expired(dropped["expired"])
            if dropped["conflated"]:
                self._on_conflated(dropped["conflated"])
            if dropped["refused"]:
                self._on_refused(dropped["refused"])
        self._update_room()
        self._head_attempts = 0

    def _pop(self, count: int) -> None:
        self._store.pop(count)
        self._head_seq += count

    async def _gave_up_on_head(self, failure: BaseException) -> bool:
        """Count a transient failure against the oldest message while the sink looks able to
        take messages; dead-letter it once it used ``max_attempts`` (True: go on at once)."""
        self.stats.retries += 1
        if not self._ready():  # the sink is down: not the message's fault
            return False
        self._head_attempts += 1
        if self.max_attempts is None or self._head_attempts < self.max_attempts:
            return False
        head = self._store.peek(1)[0][0]
        await self._reject(head, EndpointError(f"gave up after {self._head_attempts} attempts: {failure}"), self._head_attempts)
        self._pop(1)
        self.stats.held -= 1
        self._sent_ahead = {i - 1 for i in self._sent_ahead if i > 0}
        self._update_room()
        self._head_attempts = 0
        return True

    def _report_holding(self, failure: BaseException) -> None:
        now = time.monotonic()
        if now - self._last_report > 10.0:
            self._last_report = now
            log.warning("sink down; holding messages", extra={"route": self.route, "held": self.stats.held, "error": str(failure)})

    async def _reject(self, message: Outbound, error: BaseException, attempts: int) -> None:
        self.stats.rejected += 1
        if self._on_rejected is not None:
            try:
                await self._on_rejected(message, error, attempts)
            except Exception as failure:  # the dead letters are down too: say so, keep going
                log.error("buffer: could not dead-letter a rejected message",
                          extra={"route": self.route, "error": str(error), "dead_letter_error": str(failure)})

    async def _pause(self, seconds: float) -> None:
        """Sleep, but wake at once when the buffer is closed."""
        try:
            await asyncio.wait_for(self._closing.wait(), seconds)
        except asyncio.TimeoutError:
            pass


class BufferOwner(Protocol):
    """The runner that sends a shared buffer's messages: the route's live one."""

    async def send_held(self, messages: list[Outbound]) -> list[BaseException | None]: ...

    def sink_can_take(self) -> bool: ...

    def held_delivered(self, held: list[Held]) -> None: ...

    async def held_rejected(self, message: Outbound, error: BaseException, attempts: int) -> None: ...

    def held_stale(self, held: Held) -> bool: ...

    def held_expired(self, held: list[Held]) -> None: ...

    def held_conflated(self, held: list[Held]) -> None: ...

    def held_refused(self, held: list[Held]) -> None: ...

    async def held_lost(self, held: list[Held]) -> None: ...


class _Shared:
    __slots__ = ("buffer", "users", "owner")

    def __init__(self, buffer: HoldingBuffer, owner: BufferOwner) -> None:
        self.buffer, self.users, self.owner = buffer, 0, owner


class Buffers:
    """Every route's buffer by route name, shared by the runners of a route across a reload
    (the runner replacing another takes its held messages over); the buffer's messages are
    sent by the route's live runner (:meth:`hand_to`), and it closes with its last user."""

    def __init__(self) -> None:
        self._shared: dict[str, _Shared] = {}

    def acquire(self, route: str, spec: BufferSpec, max_attempts: int, owner: BufferOwner) -> HoldingBuffer:
        """The route's buffer (made for ``owner`` when it has none); its settings change at
        the next start."""
        shared = self._shared.get(route)
        if shared is None:
            shared = self._shared[route] = self._make(route, spec, max_attempts, owner)
        shared.users += 1
        return shared.buffer

    @staticmethod
    def _make(route: str, spec: BufferSpec, max_attempts: int, owner: BufferOwner) -> _Shared:
        def send(messages: list[Outbound]) -> Awaitable[list[BaseException | None]]:
            return shared.owner.send_held(messages)

        def rejected(message: Outbound, error: BaseException, attempts: int) -> Awaitable[None]:
            return shared.owner.held_rejected(message, error, attempts)

        buffer = HoldingBuffer(
            route, send, max_messages=spec.max_messages, spill_dir=spec.spill_dir,
            fsync_interval=spec.fsync_interval, max_attempts=max_attempts,
            ready=lambda: shared.owner.sink_can_take(),
            on_delivered=lambda held: shared.owner.held_delivered(held), on_rejected=rejected,
            latest_per=spec.latest_per, stale=lambda held: shared.owner.held_stale(held),
            on_expired=lambda held: shared.owner.held_expired(held),
            on_conflated=lambda held: shared.owner.held_conflated(held),
            on_refused=lambda held: shared.owner.held_refused(held),
            on_lost=lambda held: shared.owner.held_lost(held),
        )
        shared = _Shared(buffer, owner)
        return shared

    def hand_to(self, route: str, buffer: HoldingBuffer, owner: BufferOwner) -> None:
        """``owner`` is the route's live runner now: it sends what ``buffer`` holds."""
        shared = self._shared.get(route)
        if shared is not None and shared.buffer is buffer:
            shared.owner = owner

    def release(self, route: str, buffer: HoldingBuffer) -> bool:
        """True when no other runner uses ``buffer`` any more (the caller closes it)."""
        shared = self._shared.get(route)
        if shared is None or shared.buffer is not buffer:
            return False
        shared.users -= 1
        if shared.users > 0:
            return False
        del self._shared[route]
        return True

    def take_all(self) -> list[HoldingBuffer]:
        """Every buffer, forgotten here (the engine stops: the caller closes them)."""
        buffers = [shared.buffer for shared in self._shared.values()]
        self._shared.clear()
        return buffers


def stats_dict(buffer: HoldingBuffer) -> dict[str, Any]:
    return {**asdict(buffer.stats), "max_messages": buffer.max_messages, "spill": buffer.spills}
