"""The engine's one backoff: exponential, capped, with jitter.

Every retry loop in the engine (a sink's transient failures, a buffer's held messages, a
connection that cannot be opened, a route waiting to start, a TCP link to reconnect) waits
with this, so they share one shape: the n-th wait is ``first * 2**(n-1)`` capped at ``cap``,
then scaled by a random factor in [0.5, 1) so that routes or links that failed together (a
broker restart fails them all at once) do not retry together and hit it in step.
"""

from __future__ import annotations

import random
from typing import Callable

FIRST_S = 0.1
CAP_S = 5.0


def backoff_delay(attempt: int, first: float = FIRST_S, cap: float = CAP_S,
                  rand: Callable[[], float] = random.random) -> float:
    """Seconds to wait after failed attempt ``attempt`` (1-based)."""
    delay = min(cap, first * 2 ** max(0, attempt - 1))
    return delay * (0.5 + rand() / 2)


class Backoff:
    """The waits of one retry loop: :meth:`next` after each failure, :meth:`reset` after a
    success (the next failure starts from ``first`` again)."""

    __slots__ = ("first", "cap", "failures", "_rand")

    def __init__(self, first: float = FIRST_S, cap: float = CAP_S, rand: Callable[[], float] = random.random) -> None:
        self.first = first
        self.cap = cap
        self.failures = 0
        self._rand = rand

    def next(self) -> float:
        """The wait after one more failure."""
        self.failures += 1
        return backoff_delay(self.failures, self.first, self.cap, self._rand)

    def reset(self) -> None:
        self.failures = 0
