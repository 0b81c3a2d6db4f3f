"""The event loop the engine runs on: asyncio's own, or uvloop when asked.

``RABBITROS_LOOP=uvloop`` runs the engine on uvloop (libuv; the optional extra ``fast``,
``pip install rabbitros-engine[fast]``, Unix only); unset or ``asyncio``, on asyncio's loop.

asyncio's loop is the default because uvloop saves nothing measurable here any more (issue 34
asked to keep it only for at least 15 % less CPU per message, measured in the same run). It
carried about 10 % more in the batched aiormq pass-through of issue 10; since then the engine
writes a round of publishes as one write and takes ROS 2 messages in batches, and the loop's
own cost per callback is a small part of a message's. Measured on the 2-core machine, shared,
2026-11-27 (bench/results/2026-11-27/session4-loops/):

- a backlog drain AMQP -> AMQP, one engine, 4 rounds alternating: 52.75 µs of CPU a message
  on either loop (median), asyncio / uvloop 0.92-1.15 round by round; AMQP -> ROS 2: 59.7 /
  58.75 µs (1.6 % more on asyncio's), 0.68-1.3 round by round;
- the fleet (bench/fleet.py, 100 agents, 2,100 msg/s; session4-fleet-loops), 3 rounds
  alternating: 257, 257, 266 µs of CPU a message on asyncio's loop, 245, 252, 237 on uvloop
  (4.7 % less, median); telemetry p99 25.6 / 13.4 / 14.8 ms and 11.4 / 12.9 / 25.1 ms. (The
  rounds of session4-status-ab named "1 worker asyncio" ran on uvloop: bench/bench_fleet_workers.py
  did not pass the system's environment on then.)

One loop less to reason about (signal handling, ``add_reader`` and subprocess support differ
in corner cases) and one native dependency less on a robot's computer.
"""

from __future__ import annotations

import asyncio
import os
from typing import Any, Callable, Coroutine, TypeVar

T = TypeVar("T")

LOOPS = ("asyncio", "uvloop")
"""The values ``RABBITROS_LOOP`` takes."""


class LoopChoiceError(RuntimeError):
    """``RABBITROS_LOOP`` names a loop that is unknown or not installed."""


def loop_factory() -> Callable[[], asyncio.AbstractEventLoop] | None:
    """uvloop's loop factory when ``RABBITROS_LOOP=uvloop``, else None (asyncio's default)."""
    chosen = os.environ.get("RABBITROS_LOOP", "").strip().lower() or "asyncio"
    if chosen not in LOOPS:
        raise LoopChoiceError(f"RABBITROS_LOOP={chosen!r}: use one of {', '.join(LOOPS)}")
    if chosen == "asyncio":
        return None
    try:
        import uvloop
    except ImportError as error:
        raise LoopChoiceError("RABBITROS_LOOP=uvloop: uvloop is not installed (pip install 'rabbitros-engine[fast]')") from error
    return uvloop.new_event_loop


def loop_name() -> str:
    return "uvloop" if loop_factory() is not None else "asyncio"


def run(main: Coroutine[Any, Any, T], **kwargs: Any) -> T:
    """``asyncio.run`` on the engine's loop."""
    with asyncio.Runner(loop_factory=loop_factory(), **kwargs) as runner:
        return runner.run(main)
