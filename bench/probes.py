"""What the benchmarks measure inside a running engine, attached from outside its package.

The engine keeps no benchmark hooks (issue 30): a route's runner tells its observer each
message's reception-to-acceptance time (``RouteObserver.accepted``), and hands its sink each
batch (``Sink.send_batch``) with every message's reception time (``Outbound.received_ns``).
A probe wraps one of those two calls on one runner's own objects, so only a benchmark that
attaches one pays for it, and :meth:`Probe.detach` puts the call back.
"""

from __future__ import annotations

import time
from typing import Any


class Probe:
    """Samples (ns) recorded from one runner until :meth:`detach`."""

    def __init__(self, owner: Any, method: str, wrapper: Any) -> None:
        self.samples: list[int] = []
        self._owner, self._method = owner, method
        self._own = vars(owner).get(method)  # an instance's own callable, else the class's method
        setattr(owner, method, wrapper(self.samples, getattr(owner, method)))

    def detach(self) -> list[int]:
        if self._own is not None:
            setattr(self._owner, self._method, self._own)
        else:
            vars(self._owner).pop(self._method, None)
        return self.samples


def latency(runner: Any) -> Probe:
    """Every message's reception-to-acceptance time (t2 - t1), as the route's counters get it."""

    def wrapper(samples: list[int], accepted: Any) -> Any:
        def recording(inbound: Any, outbound: Any, latency_ns: int | None) -> None:
            if latency_ns is not None:
                samples.append(latency_ns)
            accepted(inbound, outbound, latency_ns)
        return recording

    return Probe(runner.observer, "accepted", wrapper)


def handed(runner: Any) -> Probe:
    """Every message's reception-to-sink time, each time the runner hands it to its sink: the
    engine's own share, without the sink's wait for the broker's confirm or the vehicle's
    acknowledgement. Messages a route's buffer replays after an outage are left out, as they
    were when this was a hook of the runner (their time is the outage's)."""

    def wrapper(samples: list[int], send_batch: Any) -> Any:
        async def recording(messages: list[Any]) -> Any:
            buffer = runner.buffer
            if buffer is None or not buffer.holding:
                now = time.monotonic_ns()
                samples.extend(now - message.received_ns for message in messages if message.received_ns is not None)
            return await send_batch(messages)
        return recording

    return Probe(runner.pipeline.sink, "send_batch", wrapper)
