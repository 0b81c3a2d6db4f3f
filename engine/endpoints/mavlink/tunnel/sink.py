"""The tunnel's sending side, on asyncio: :class:`TunnelSink` sends each message whole (alone
or bundled), drives a :class:`~.arq.Transfer` per transfer with the acknowledgements the hub
(hub.py) hands it, and returns once the receiver acknowledged delivery."""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

from engine.common.schemas import SchemaError, canonical_bytes
from engine.endpoints.base import EndpointError, Expired, MessageRejected, Outbound, Sink
from engine.endpoints.mavlink.tunnel.arq import Transfer
from engine.endpoints.mavlink.tunnel.frames import (
    CRC_SIZE, DEFAULT_PAYLOAD_TYPE, MAX_FRAGMENTS, Ack, bundle, bundled_size,
)
from engine.endpoints.mavlink.tunnel.hub import TunnelHub


@dataclass(slots=True)
class _Waiting:
    """A message handed to :meth:`TunnelSink.send_many`, until a transfer carries it."""

    body: bytes
    expires_ns: int | None
    outcome: asyncio.Future[BaseException | None]


class TunnelSink(Sink):
    """Sends ``Outbound.body`` whole; returns once the receiver acknowledged delivery.

    Up to four of a route's batches may be in flight (:attr:`Sink.batches_in_flight`): a
    batch is accepted only once the vehicle acknowledged its last transfer, a TDM round and
    more, seconds when a last fragment or its acknowledgement was lost, and with one batch at
    a time the radio stood idle for that long after every batch (measured on the emulated SiK
    radio at 5 % loss: 4 s of 22 after a batch of 128 messages; bench/results/2026-11-23/goodput/).
    Bundles are formed when a window slot frees, of every message then waiting, whichever
    batch it came in, so small batches in flight still travel as full bundles."""

    batches_in_flight = 4

    def __init__(self, hub: TunnelHub, *, payload_type: int = DEFAULT_PAYLOAD_TYPE,
                 target: tuple[int, int] = (0, 0), priority: str = "normal", max_age: float | None = None) -> None:
        self.hub = hub
        self.payload_type = payload_type
        self.target = target
        self.max_age_ns = None if max_age is None else int(max_age * 1e9)
        """The route's ``max_age``: a transfer still unacknowledged when its newest message is
        older than that is given up, each of its messages :class:`Expired` (never sent again)."""
        self.priority = priority
        """The route's ``priority``: the link's writer sends a ``high`` sink's fragments before
        the ``normal`` and ``low`` ones already queued (engine/endpoints/mavlink/port.py)."""
        self._window = asyncio.Semaphore(hub.settings.window)
        self._waiting: deque[_Waiting] = deque()
        """Messages of :meth:`send_many` not yet in a transfer, in the order they came."""
        self._arrived = asyncio.Event()
        self._dispatcher: asyncio.Task[None] | None = None
        self._transfers: set[asyncio.Task[None]] = set()
        hub.add_sender(payload_type)

    async def send(self, message: Outbound) -> None:
        await self.send_bytes(self._body(message), expires_ns=self._expiry(message.received_ns))

    def _expiry(self, received_ns: int | None) -> int | None:
        """``time.monotonic_ns()`` after which a message received at ``received_ns`` expired."""
        if self.max_age_ns is None or received_ns is None:
            return None
        return received_ns + self.max_age_ns

    @staticmethod
    def _body(message: Outbound) -> bytes:
        """The canonical bytes, or the JSON of what ``sink.mapping`` made of them."""
        if message.fields is message.canonical:
            return message.body
        try:
            return canonical_bytes(message.fields)
        except SchemaError as exc:
            raise MessageRejected(f"tunnel: {exc}") from None

    async def send_batch(self, messages: Sequence[Outbound]) -> list[BaseException | None]:
        results: list[BaseException | None] = [None] * len(messages)
        bodies: list[tuple[int, bytes]] = []
        for index, message in enumerate(messages):
            try:
                bodies.append((index, self._body(message)))
            except MessageRejected as exc:
                results[index] = exc
        expiries = [self._expiry(messages[index].received_ns) for index, _ in bodies]
        for (index, _), result in zip(bodies, await self.send_many([body for _, body in bodies], expiries)):
            results[index] = result
        return results

    async def send_many(self, bodies: Sequence[bytes],
                        expiries: Sequence[int | None] | None = None) -> list[BaseException | None]:
        """Send ``bodies`` in bundles (see the module's docstring), up to ``window`` of them
        in flight at once: a radio's round trip is a TDM round or more, so one transfer after
        another would leave it idle. ``result[i]`` is None once ``bodies[i]`` was delivered.
        ``expiries[i]``: ``time.monotonic_ns()`` after which ``bodies[i]`` is worthless (a
        bundle is given up once its newest message is). The messages wait in the sink's queue,
        behind those of earlier calls, until a window slot frees (:meth:`_dispatch`)."""
        loop = asyncio.get_running_loop()
        waiting = [_Waiting(body, None if expiries is None else expiries[index], loop.create_future())
                   for index, body in enumerate(bodies)]
        self._waiting.extend(waiting)
        self._arrived.set()
        if self._dispatcher is None or self._dispatcher.done():
            self._dispatcher = asyncio.create_task(self._dispatch(), name=f"tunnel-sink:{self.payload_type}")
        # cancelling this call cancels its outcomes: its messages not yet in a transfer are
        # skipped, and a transfer whose every message was cancelled is cancelled
        return list(await asyncio.gather(*(item.outcome for item in waiting)))

    async def _dispatch(self) -> None:
        """Start a transfer whenever a window slot is free and messages wait: one message, or
        a bundle of the consecutive ones that fit (:meth:`_next_group`)."""
        while True:
            while not self._pending():
                self._arrived.clear()
                await self._arrived.wait()
            await self._window.acquire()
            group = self._next_group()
            if not group:
                self._window.release()
                continue
            task = asyncio.create_task(self._transfer(group))
            self._transfers.add(task)
            task.add_done_callback(self._transfers.discard)

    def _pending(self) -> bool:
        waiting = self._waiting
        while waiting and waiting[0].outcome.done():  # its caller gave up
            waiting.popleft()
        return bool(waiting)

    def _next_group(self) -> list[_Waiting]:
        """The waiting messages at the head of the queue while their bundle stays within
        ``bundle`` bytes and the fragments a transfer can have (at least one message)."""
        settings = self.hub.settings
        limit = min(settings.bundle, MAX_FRAGMENTS * settings.fragment_size - CRC_SIZE)
        group: list[_Waiting] = []
        size = 0
        while self._pending():
            cost = bundled_size([len(self._waiting[0].body)])
            if group and size + cost > limit:
                break
            group.append(self._waiting.popleft())
            size += cost
        return group

    async def _transfer(self, group: list[_Waiting]) -> None:
        """One transfer of ``group`` in the window slot :meth:`_dispatch` took for it."""
        task = asyncio.current_task()
        assert task is not None

        def given_up(_: asyncio.Future[BaseException | None]) -> None:
            if all(item.outcome.cancelled() for item in group):
                task.cancel()

        for item in group:
            item.outcome.add_done_callback(given_up)
        expires_ns = _newest([item.expires_ns for item in group])
        outcome: BaseException | None = None
        try:
            if len(group) == 1:
                await self._send_transfer(group[0].body, expires_ns=expires_ns)
            else:
                await self._send_transfer(bundle([item.body for item in group]), bundled=True,
                                          messages=len(group), expires_ns=expires_ns)
        except Exception as exc:
            outcome = exc
        except BaseException:  # cancelled (every caller gave up, or the sink closes)
            for item in group:
                if not item.outcome.done():
                    item.outcome.cancel()
            raise
        finally:
            self._window.release()
        for item in group:
            if not item.outcome.done():
                item.outcome.set_result(outcome)

    async def close(self) -> None:
        """Stop the dispatcher and what it started (the route retired: nothing waits for them)."""
        tasks = [*self._transfers, *([self._dispatcher] if self._dispatcher is not None else [])]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        self._dispatcher = None

    async def send_bytes(self, body: bytes, *, bundled: bool = False, messages: int = 1,
                         expires_ns: int | None = None) -> None:
        """Send one transfer (one message, or a bundle of ``messages``); returns once the
        receiver acknowledged it DELIVERED. Raises :class:`Expired` once ``expires_ns``
        (``time.monotonic_ns()``) passed before that: before it was first sent (it waited
        for the window), or while its fragments were being sent again."""
        async with self._window:
            await self._send_transfer(body, bundled=bundled, messages=messages, expires_ns=expires_ns)

    async def _send_transfer(self, body: bytes, *, bundled: bool = False, messages: int = 1,
                             expires_ns: int | None = None) -> None:
        """:meth:`send_bytes` in a window slot already taken."""
        hub, settings = self.hub, self.hub.settings
        if expires_ns is not None and time.monotonic_ns() >= expires_ns:
            hub.count("tunnel_expired", messages)
            raise Expired("tunnel: older than the route's max_age before it could be sent")
        msg_id = hub.new_id(self.payload_type)
        try:
            transfer = Transfer(msg_id, body, fragment_size=settings.fragment_size,
                                rtt=hub.rtt(self.payload_type), retries=settings.retries, bundled=bundled)
        except ValueError as exc:  # larger than a tunnel message can be: never deliverable
            raise MessageRejected(f"tunnel: {exc}") from None
        acks: asyncio.Queue[Ack] = asyncio.Queue()
        hub.watch(self.payload_type, msg_id, acks.put_nowait)
        try:
            await self._run(transfer, acks, expires_ns)
        except Expired:
            hub.count("tunnel_expired", messages)
            raise
        finally:
            hub.unwatch(self.payload_type, msg_id)
            hub.count("tunnel_retransmissions", transfer.retransmissions)
        hub.count("tunnel_sent", messages)

    def _send_fragment(self, transfer: Transfer, index: int, *, first: bool = False) -> asyncio.Future[float]:
        return asyncio.ensure_future(self.hub.link.send_tunnel(self.payload_type, self.target, transfer.frames[index],
                                                               bulk=True, priority=self.priority, first=first))

    async def _run(self, transfer: Transfer, acks: asyncio.Queue[Ack], expires_ns: int | None = None) -> None:
        loop = asyncio.get_running_loop()
        pending: list[int] = list(range(transfer.count))

        def plan(indexes: list[int]) -> None:
            pending.extend(i for i in indexes if i not in pending)

        def expired() -> bool:
            return expires_ns is not None and time.monotonic_ns() >= expires_ns

        while True:
            if pending and not transfer.delivered and expired() and any(transfer.tx_count):
                raise Expired(f"tunnel message {transfer.msg_id}: older than the route's max_age while "
                              "being sent again; not sent any more")
            while pending and not transfer.delivered:
                # Every pending fragment is queued at once, so the writer sends a transfer's
                # fragments back to back: transfers in flight complete one after another (the
                # receiver can settle and answer the first while the next is on the air)
                # rather than all together at the end.
                # Fragments sent again go before every first transmission of their priority
                # (in order, at the front of the writer's lane): a loss is repaired in the time
                # of its fragments, not after the window of transfers queued behind it.
                wanted: list[int] = []
                while pending:
                    index = pending.pop(0)
                    if transfer.is_held(index) and index != transfer.probe:
                        continue
                    if index == transfer.probe:
                        transfer.probe = None
                    wanted.append(index)
                again = [i for i in wanted if transfer.tx_count[i]]
                queued: list[tuple[int, asyncio.Future[float]]] = [
                    (index, self._send_fragment(transfer, index, first=True)) for index in reversed(again)][::-1]
                queued += [(index, self._send_fragment(transfer, index)) for index in wanted if not transfer.tx_count[index]]
                try:
                    for index, written in queued:
                        transfer.on_sent(index, await written)
                        while not acks.empty():
                            plan(transfer.on_ack(acks.get_nowait(), loop.time()))
                        if transfer.delivered:
                            break
                finally:
                    for _, written in queued:  # not written yet and no longer wanted: the writer skips them
                        written.cancel()
            if transfer.delivered:
                return
            deadline = transfer.deadline()
            assert deadline is not None
            wait = deadline - loop.time()
            if expires_ns is not None:  # wake when it expires: a DELIVERED may still come until then
                wait = min(wait, (expires_ns - time.monotonic_ns()) / 1e9)
            try:
                ack = await asyncio.wait_for(acks.get(), max(0.0, wait))
            except TimeoutError:
                if expired():
                    raise Expired(f"tunnel message {transfer.msg_id}: older than the route's max_age before "
                                  "it was acknowledged; not sent again") from None
                plan(transfer.on_timeout(loop.time()))
                if transfer.failed:
                    raise EndpointError(
                        f"tunnel message {transfer.msg_id} not acknowledged after {transfer.max_retries} retries"
                    ) from None
            else:
                plan(transfer.on_ack(ack, loop.time()))


def _newest(expiries: Sequence[int | None]) -> int | None:
    """When a transfer of messages with these ``expiries`` is worthless: once its newest
    message is (None: one of them never expires)."""
    expiring = [value for value in expiries if value is not None]
    return None if len(expiring) < len(expiries) else max(expiring)
