"""The event loop the engine runs on: uvloop where it is installed, asyncio's otherwise.

uvloop (libuv) cuts the loop's own cost per callback and per socket read/write: the batched
aiormq pass-through of issue 10 carried about 10 % more with it. It is an optional
dependency (``pip install rabbitros-engine[fast]``, Unix only); ``RABBITROS_LOOP=asyncio``
forces the standard loop, e.g. to compare the two.
"""

from __future__ import annotations

import asyncio
import os
from typing import Any, Callable, Coroutine, TypeVar

T = TypeVar("T")


def loop_factory() -> Callable[[], asyncio.AbstractEventLoop] | None:
    """uvloop's loop factory if installed and not disabled, else None (asyncio's default)."""
    if os.environ.get("RABBITROS_LOOP", "").lower() == "asyncio":
        return None
    try:
        import uvloop
    except ImportError:
        return None
    return uvloop.new_event_loop


def loop_name() -> str:
    return "uvloop" if loop_factory() is not None else "asyncio"


def run(main: Coroutine[Any, Any, T], **kwargs: Any) -> T:
    """``asyncio.run`` on the engine's loop."""
    with asyncio.Runner(loop_factory=loop_factory(), **kwargs) as runner:
        return runner.run(main)
