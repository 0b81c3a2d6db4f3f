"""One transaction per vehicle (and command) across the workers of a split link (split.py).

A single engine runs one mission upload, and one command of each kind, at a time per vehicle
(``transaction_lock``: the mission protocol allows one upload, and two COMMAND_ACKs of one
command cannot be told apart). On a link split over the workers a command route's source
competes on every worker, so two workers could take two commands of one kind for one vehicle
at once: the lock is then held at the link's owner, which grants it to one worker at a time,
in the order asked (:class:`Leases`), as the process's lock does; each worker's
:class:`SplitLock` asks for it after its own process's lock. A lock held by a worker that goes
away (killed: its connection to the owner closes) is granted to the next; a worker whose owner
goes away fails what it waits for (EndpointError: its route tries again), and tells the
owner started again which locks it still holds (``reclaim``) before that owner grants any: a
transaction in flight across an owner's restart (waiting for its COMMAND_ACK) keeps its lock,
so no other worker sends the same command meanwhile and takes its acknowledgement.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable
from typing import Protocol


Claim = tuple[int, int]
"""Who asks for a lock: (worker index, that worker's request number). The number tells a late
grant of a request given up from the grant of the next request for the same key."""


class Leases:
    """At the owner: each key's holder and the claims waiting, in order. ``grant(claim, key)``
    tells a worker its claim holds ``key``; False: the worker is gone (the next claim waits)."""

    def __init__(self, grant: Callable[[Claim, str], bool], paused: bool = False) -> None:
        self.grant = grant
        self.holder: dict[str, Claim] = {}
        self.waiting: dict[str, deque[Claim]] = {}
        self.paused = paused
        """Nothing is granted meanwhile: an owner started again waits for the workers to say
        what its predecessor granted them (:meth:`reclaim`) before it grants anything."""

    def acquire(self, key: str, claim: Claim) -> None:
        if key in self.holder or self.paused:
            self.waiting.setdefault(key, deque()).append(claim)
            return
        self._hand(key, claim)

    def reclaim(self, key: str, claim: Claim) -> bool:
        """``claim`` holds ``key`` still, granted by this owner's predecessor: recorded as
        holding it. False where another claim holds it already (granted in between: two
        transactions may then meet; the caller counts it)."""
        held = self.holder.setdefault(key, claim)
        return held == claim

    def resume(self) -> None:
        """Every worker said what it holds (or the wait for them is over): the claims waiting
        for a free key are granted."""
        self.paused = False
        for key in [key for key in self.waiting if key not in self.holder]:
            self._next(key)

    def release(self, key: str, claim: Claim) -> None:
        """``claim`` is done with ``key``, or no longer waits for it (its worker gave up)."""
        if self.holder.get(key) == claim:
            del self.holder[key]
            self._next(key)
            return
        queue = self.waiting.get(key)
        if queue is not None and claim in queue:
            queue.remove(claim)
            if not queue:
                del self.waiting[key]

    def gone(self, worker: int) -> None:
        """A worker went away: what it held goes to the next, what it waited for is forgotten."""
        for key, queue in list(self.waiting.items()):
            for claim in [claim for claim in queue if claim[0] == worker]:
                queue.remove(claim)
            if not queue:
                del self.waiting[key]
        for key, claim in [(key, claim) for key, claim in self.holder.items() if claim[0] == worker]:
            self.release(key, claim)

    def _hand(self, key: str, claim: Claim) -> None:
        self.holder[key] = claim
        if not self.grant(claim, key):
            del self.holder[key]
            self._next(key)

    def _next(self, key: str) -> None:
        if self.paused:
            return
        queue = self.waiting.get(key)
        if not queue:
            self.waiting.pop(key, None)
            return
        claim = queue.popleft()
        if not queue:
            del self.waiting[key]
        self._hand(key, claim)


def lease_message(kind: bytes, request: int, key: str) -> bytes:
    """``kind`` (ask, give back, grant), the request number, the key."""
    return kind + request.to_bytes(4, "big") + key.encode()


def read_lease(data: bytes) -> tuple[int, str]:
    """The request number and key of a :func:`lease_message` (its kind byte included)."""
    return int.from_bytes(data[1:5], "big"), data[5:].decode()


class LeaseHolder(Protocol):
    """A worker's end of a split link, as a lock asks it (split.py's two links)."""

    async def lease(self, key: str) -> int:
        """Return once the owner granted ``key`` to this worker (the request's number);
        EndpointError if it cannot."""

    def unlease(self, key: str, request: int) -> None: ...


class SplitLock:
    """The transaction lock of a split link: this process's own, then the owner's grant."""

    def __init__(self, end: LeaseHolder, key: str) -> None:
        self.end = end
        self.key = key
        self.local = asyncio.Lock()
        self.request = 0

    async def __aenter__(self) -> SplitLock:
        await self.local.acquire()
        try:
            self.request = await self.end.lease(self.key)
        except BaseException:
            self.local.release()
            raise
        return self

    async def __aexit__(self, *exc: object) -> None:
        try:
            self.end.unlease(self.key, self.request)
        finally:
            self.local.release()
