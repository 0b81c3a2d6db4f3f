"""The one way tests wait: until a condition holds, or fail naming what they waited for.

Every wait has a deadline and polls a cheap predicate (a count, a status field, a file): the
test goes on the moment the condition holds instead of sleeping a fixed time and hoping, and a
condition that never holds fails with ``what`` (and ``detail()``, what was seen instead) rather
than a bare timeout. ``wait_for`` is for coroutines (it yields to the event loop between
polls), ``wait_for_sync`` for plain code (engines as processes, threads)."""

from __future__ import annotations

import asyncio
import inspect
import time
from typing import Awaitable, Callable, TypeVar

T = TypeVar("T")

ASYNC_POLL_S = 0.02
"""Between two polls in a coroutine: short, as a poll there costs one predicate call."""
SYNC_POLL_S = 0.05
"""Between two polls in plain code, which often reads a file or asks an HTTP endpoint."""


def _timed_out(timeout: float, what: str, detail: Callable[[], object] | None) -> AssertionError:
    seen = f": {detail()}" if detail is not None else ""
    return AssertionError(f"timed out after {timeout:g} s waiting for {what}{seen}")


async def wait_for(predicate: Callable[[], T | Awaitable[T]], timeout: float = 10.0, what: str = "the condition",
                   detail: Callable[[], object] | None = None) -> T:
    """Until ``predicate()`` is truthy; returns that value. After ``timeout`` seconds, fails
    (AssertionError) naming ``what`` and ``detail()``. A predicate that returns an awaitable
    (a question to a broker or an HTTP endpoint) is awaited at each poll."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while True:
        value = predicate()
        if inspect.isawaitable(value):
            value = await value
        if value:
            return value  # type: ignore[return-value]
        if loop.time() > deadline:
            raise _timed_out(timeout, what, detail)
        await asyncio.sleep(ASYNC_POLL_S)


def wait_for_sync(predicate: Callable[[], T], timeout: float = 10.0, what: str = "the condition",
                  detail: Callable[[], object] | None = None) -> T:
    """:func:`wait_for` for plain (blocking) code."""
    deadline = time.monotonic() + timeout
    while not (value := predicate()):
        if time.monotonic() > deadline:
            raise _timed_out(timeout, what, detail)
        time.sleep(SYNC_POLL_S)
    return value
