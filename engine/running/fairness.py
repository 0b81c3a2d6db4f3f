"""Fairness on a route many agents share: one agent's flood does not delay or drop the others'.

``fair: {per: system_id}`` gives each agent (each value of the source's metadata ``per``: a
MAVLink ``system_id``, a ROS 2 ``topic``) its own queue inside the source's inbox (engine/endpoints/base.py
``Inbox``) and takes a batch from them round-robin, at most ``batch`` messages of one agent
per batch. Without it the inbox is one FIFO: a vehicle sending 100x its rate into a sink that
cannot keep up fills it, every other vehicle's message waits behind the flood (seconds, growing)
and, once the FIFO is full, is dropped with it.

What it bounds (the sink is the bottleneck, ``rate`` messages/s, ``K`` agents with something
queued): a batch holds at most ``batch`` messages of each agent, so an agent below its share
of the sink waits at most for the batch being sent and its place in the next one, about
``2 * batch * K / rate`` s in the worst case, and in practice ``2 * (batch + K) / rate`` (the
quiet agents have one or two messages queued, the flooder ``batch``): with the defaults, 10
agents at 10 msg/s and one at 1,000 msg/s through a ~500 msg/s sink, the others' p99 was 408 ms
with none lost, 12.7 s without (bench/bench_fairness.py; all figures in docs/route-language.md).
A small ``batch`` keeps a slow sink's batches short; a sink that confirms per batch (AMQP)
pays a round trip per ``batch x K`` messages.
An agent's queue holds at most ``queue`` messages; beyond it that agent's oldest is dropped
(its newest with ``overflow: drop_newest``), counted in the route's ``dropped`` and per agent in
``dropped_by_agent`` (engine/running/observe.py), never another agent's. ``block`` cannot hold one
agent back on a shared link, so with ``fair`` it drops too.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from collections.abc import Callable, Hashable
from typing import Any

from engine.endpoints.base import Inbound, Inbox
from engine.language.stage_options import FairOptions

class FairInbox(Inbox[Inbound]):
    """The per-agent queues of one source, taken round-robin (see the module docstring)."""

    def __init__(self, options: FairOptions, overflow: str, dropped: Callable[[Any, int], None]) -> None:
        super().__init__(options.queue, "drop_newest" if overflow == "drop_newest" else "drop_oldest")
        self.per = options.per
        self.batch = options.batch
        self.queues: OrderedDict[Hashable, deque[Inbound]] = OrderedDict()
        """Agents with something queued, in the order they are served next."""
        self.count = 0
        self._dropped = dropped

    @property
    def full(self) -> bool:
        return False  # one agent's queue full drops its own messages; the source never stops for it

    def offer(self, item: Inbound) -> int:
        agent = item.meta.get(self.per)
        queue = self.queues.get(agent)
        if queue is None:
            queue = self.queues[agent] = deque()
        if len(queue) >= self.limit:
            self._dropped(agent, 1)
            if self.overflow == "drop_newest":
                return 1
            queue.popleft()
            queue.append(item)
            return 1
        queue.append(item)
        self.count += 1
        return 0

    async def take(self, most: int) -> list[Inbound]:
        while not self.count:
            if self.closed:
                return []
            self._arrived.clear()
            await self._arrived.wait()
        taken: list[Inbound] = []
        queues = self.queues
        for _ in range(self.batch):
            for agent in list(queues):
                queue = queues[agent]
                taken.append(queue.popleft())
                if not queue:
                    del queues[agent]
                else:
                    queues.move_to_end(agent)  # served: behind the others for the next message
                if len(taken) >= most:
                    break
            if not queues or len(taken) >= most:
                break
        self.count -= len(taken)
        return taken

    def clear(self) -> int:
        left, self.count = self.count, 0
        self.queues.clear()
        return left

    def __len__(self) -> int:
        return self.count


def route_inbox(fair: FairOptions | None, queue_limit: int, overflow: str,
                agent_dropped: Callable[[Any, int], None]) -> Inbox[Inbound]:
    """The inbox a push source queues its route's messages in (what the route answers
    ``Deliver.inbox``): one FIFO of ``queue_limit``, or with the route's ``fair:`` one queue per
    agent, whose drops are also counted per agent (``agent_dropped``)."""
    if fair is None:
        return Inbox(queue_limit, overflow)
    return FairInbox(fair, overflow, agent_dropped)
