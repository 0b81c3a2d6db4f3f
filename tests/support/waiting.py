"""The one way tests wait: until a condition holds, or fail naming what they waited for.

Every wait has a deadline and polls a cheap predicate (a count, a status field, a file): the
test goes on the moment the condition holds instead of sleeping a fixed time and hoping, and a
condition that never holds fails with ``what`` (and ``detail()``, what was seen instead) rather
than a bare timeout. ``wait_for`` is for coroutines (it yields to the event loop between
polls), ``wait_for_sync`` for plain code (engines as processes, threads), ``probe_until`` for a
message that must be sent again until one gets through."""

from __future__ import annotations

import asyncio
import inspect
import time
from typing import Any, Awaitable, Callable, TypeVar, overload

T = TypeVar("T")

ASYNC_POLL_S = 0.02
"""Between two polls in a coroutine: short, as a poll there costs one predicate call."""
SYNC_POLL_S = 0.05
"""Between two polls in plain code, which often reads a file or asks an HTTP endpoint."""


def _timed_out(timeout: float, what: str, detail: Callable[[], object] | None) -> AssertionError:
    seen = f": {detail()}" if detail is not None else ""
    return AssertionError(f"timed out after {timeout:g} s waiting for {what}{seen}")


@overload
async def wait_for(predicate: Callable[[], Awaitable[T | None]], timeout: float = ..., what: str = ...,
                   detail: Callable[[], object] | None = ..., every: float = ...) -> T: ...
@overload
async def wait_for(predicate: Callable[[], T | None], timeout: float = ..., what: str = ...,
                   detail: Callable[[], object] | None = ..., every: float = ...) -> T: ...
async def wait_for(predicate: Callable[[], Any], timeout: float = 10.0, what: str = "the condition",
                   detail: Callable[[], object] | None = None, every: float = ASYNC_POLL_S) -> Any:
    """Until ``predicate()`` is truthy; returns that value. After ``timeout`` seconds, fails
    (AssertionError) naming ``what`` and ``detail()``. A predicate that returns an awaitable
    (a question to a broker or an HTTP endpoint) is awaited at each poll; one that costs more
    than a count (a channel opened, a request, a log read) polls less often (``every``)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    while True:
        value = predicate()
        if inspect.isawaitable(value):
            value = await value
        if value:
            return value
        if loop.time() > deadline:
            raise _timed_out(timeout, what, detail)
        await asyncio.sleep(every)  # poll: the interval between two checks of the predicate


def wait_for_sync(predicate: Callable[[], T | None], timeout: float = 10.0, what: str = "the condition",
                  detail: Callable[[], object] | None = None, every: float = SYNC_POLL_S) -> T:
    """:func:`wait_for` for plain (blocking) code."""
    deadline = time.monotonic() + timeout
    while not (value := predicate()):
        if time.monotonic() > deadline:
            raise _timed_out(timeout, what, detail)
        time.sleep(every)  # poll: the interval between two checks of the predicate
    return value


async def probe_until(arrived: Callable[[], object], probe: Callable[[], object], timeout: float = 30.0,
                      what: str = "a probe through", every: float = 0.2,
                      detail: Callable[[], object] | None = None) -> None:
    """Send a probe (``probe()``, awaited if it returns an awaitable) every ``every`` seconds
    until ``arrived()`` holds, or fail naming ``what`` after ``timeout`` seconds: for a peer that
    drops what it sends before the far end matched it (a volatile DDS writer, a datagram to a port
    not yet bound), where one message sent once could be lost and a fixed sleep only hopes."""
    loop = asyncio.get_running_loop()
    next_probe = loop.time()

    async def probed() -> bool:
        nonlocal next_probe
        if arrived():
            return True
        if loop.time() >= next_probe:
            sent = probe()
            if inspect.isawaitable(sent):
                await sent
            next_probe = loop.time() + every
        return False

    await wait_for(probed, timeout, what, detail)
