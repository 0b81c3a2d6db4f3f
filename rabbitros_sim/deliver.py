"""The engine's Deliver contract without an engine: for the simulated vehicle and endpoint tests
that start a source on its own."""

from __future__ import annotations

from typing import Any, Awaitable, Callable, Sequence

from engine.endpoints.base import Inbound, Inbox


class FunctionDeliver:
    """A :class:`~engine.endpoints.base.Deliver` around an async function: a message is settled
    unless the function raises. Subclasses may override ``__call__`` instead."""

    def __init__(self, function: Callable[[Inbound], Awaitable[Any]] | None = None,
                 overflow: str = "block", queue_limit: int = 10_000) -> None:
        self.function = function
        self.overflow = overflow
        self.queue_limit = queue_limit
        self.batches_in_flight = 1
        self.drops = 0

    async def __call__(self, inbound: Inbound) -> None:
        assert self.function is not None
        await self.function(inbound)

    async def batch(self, inbounds: Sequence[Inbound]) -> list[bool]:
        settled = []
        for inbound in inbounds:
            try:
                await self(inbound)
            except Exception:
                settled.append(False)
            else:
                settled.append(True)
        return settled

    def dropped(self, count: int = 1) -> None:
        self.drops += count

    def inbox(self, overflow: str) -> Inbox[Inbound]:
        """One FIFO (a route without ``fair:``)."""
        return Inbox(self.queue_limit, overflow)
