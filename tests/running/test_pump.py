"""The engine's read loop (engine/endpoints/pump.py): a failure of the engine itself settles
nothing and never stops the loop; batches in flight are handed back in the order they were read; a
reader that does not overlap keeps one batch at a time whatever the sink allows."""

from __future__ import annotations

import ast
import asyncio
import logging
from collections.abc import Callable, Sequence
from pathlib import Path

import pytest

import engine.endpoints
from engine.endpoints.base import Inbound, Inbox
from engine.endpoints.pump import Pump, pump
from rabbitros_sim.deliver import FunctionDeliver

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier


class ListReader:
    """A source reading numbers from an inbox, remembering how each batch was settled."""

    def __init__(self, batch: int = 2) -> None:
        self.inbox: Inbox[int] = Inbox(1000)
        self.batch = batch
        self.settled: list[tuple[list[int], list[bool]]] = []
        self.changed = asyncio.Event()

    async def read_batch(self) -> list[int]:
        return await self.inbox.take(self.batch)

    def inbounds(self, batch: Sequence[int]) -> list[Inbound]:
        return [Inbound(body=str(number).encode()) for number in batch]

    async def settle(self, batch: Sequence[int], settled: list[bool]) -> None:
        self.settled.append((list(batch), settled))
        self.changed.set()


class Gated(FunctionDeliver):
    """Settles each batch once the test opens its gate; counts batches in the sink at once."""

    def __init__(self, batches_in_flight: int) -> None:
        super().__init__()
        self.batches_in_flight = batches_in_flight
        self.gates: list[asyncio.Event] = []
        self.inside = self.most_inside = 0
        self.changed = asyncio.Event()

    async def batch(self, inbounds: Sequence[Inbound]) -> list[bool]:
        gate = asyncio.Event()
        self.gates.append(gate)
        self.inside += 1
        self.most_inside = max(self.most_inside, self.inside)
        self.changed.set()
        try:
            await gate.wait()
        finally:
            self.inside -= 1
        return [True] * len(inbounds)


async def until(predicate: Callable[[], bool], changed: asyncio.Event, seconds: float = 5.0) -> None:
    """Wait until ``predicate`` holds, checking each time ``changed`` is set (no polling)."""
    while not predicate():
        changed.clear()
        await asyncio.wait_for(changed.wait(), seconds)


class FailsFirst(FunctionDeliver):
    """The engine itself fails on the first batch (a bug), then settles everything."""

    def __init__(self) -> None:
        super().__init__()
        self.calls = 0

    async def batch(self, inbounds: Sequence[Inbound]) -> list[bool]:
        self.calls += 1
        if self.calls == 1:
            raise RuntimeError("a bug in the engine")
        return [True] * len(inbounds)


def test_an_engine_failure_settles_nothing_and_the_loop_goes_on(caplog: pytest.LogCaptureFixture) -> None:
    async def scenario() -> None:
        reader = ListReader()
        task = asyncio.create_task(pump(reader, FailsFirst(), "route 'r', test source"))
        for number in range(4):
            reader.inbox.offer(number)
        reader.inbox.wake()
        await until(lambda: len(reader.settled) == 2, reader.changed)
        reader.inbox.close()
        await asyncio.wait_for(task, 5)
        assert reader.settled == [([0, 1], [False, False]), ([2, 3], [True, True])]

    with caplog.at_level(logging.ERROR, logger="engine.pump"):
        asyncio.run(scenario())
    assert [record.getMessage() for record in caplog.records] == ["route 'r', test source: settling a batch failed"]


def test_batches_in_flight_are_settled_in_the_order_they_were_read() -> None:
    async def scenario() -> None:
        reader, deliver = ListReader(), Gated(batches_in_flight=3)
        loop = Pump(reader, deliver, "route 'r'", overlapping=True)
        task = asyncio.create_task(loop.run())
        for number in range(8):
            reader.inbox.offer(number)
        reader.inbox.wake()
        await until(lambda: len(deliver.gates) == 3, deliver.changed)
        assert loop.in_flight == 3  # the fourth batch waits for room
        for gate in reversed(deliver.gates):  # the sink answers the last first
            gate.set()
        await until(lambda: len(deliver.gates) == 4, deliver.changed)
        deliver.gates[3].set()
        await until(lambda: len(reader.settled) == 4, reader.changed)
        reader.inbox.close()
        await asyncio.wait_for(task, 5)
        assert [batch for batch, _ in reader.settled] == [[0, 1], [2, 3], [4, 5], [6, 7]]
        assert deliver.most_inside == 3

    asyncio.run(scenario())


def test_a_reader_that_does_not_overlap_keeps_one_batch_at_a_time() -> None:
    async def scenario() -> None:
        reader, deliver = ListReader(), Gated(batches_in_flight=4)
        task = asyncio.create_task(pump(reader, deliver, "route 'r'"))
        for number in range(6):
            reader.inbox.offer(number)
        reader.inbox.wake()
        for count in (1, 2, 3):
            await until(lambda: len(deliver.gates) == count, deliver.changed)
            assert deliver.inside == 1
            deliver.gates[-1].set()
        await until(lambda: len(reader.settled) == 3, reader.changed)
        reader.inbox.close()
        await asyncio.wait_for(task, 5)
        assert deliver.most_inside == 1

    asyncio.run(scenario())


def test_no_source_hands_batches_to_its_route_itself() -> None:
    """Every source reads through the engine's loop: nothing under engine/endpoints/ but the
    loop (pump.py) calls a route's ``batch``, so no source has a delivery loop, nor a
    "settling a batch failed" handler, of its own."""
    root = Path(engine.endpoints.__file__).parent
    found = []
    for path in sorted(root.rglob("*.py")):
        if path == root / "pump.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "batch":
                found.append(f"{path.relative_to(root)}:{node.lineno}")
    assert not found, f"sources handing batches to their route outside engine/endpoints/pump.py: {found}"
