"""Throttling with conflation, on the real asyncio clock (no broker needed)."""

from __future__ import annotations

import asyncio

import pytest

from engine.running.throttle import Throttle

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier


class Runner:
    """The throttle's stage, as the route's runner is: records what is released and conflated."""

    def __init__(self) -> None:
        self.out: list[tuple[float, dict]] = []
        self.replaced: list[dict] = []
        self.arrived = asyncio.Event()

    def released(self, item: dict) -> None:
        self.out.append((asyncio.get_running_loop().time(), item))
        self.arrived.set()

    def conflated(self, item: dict) -> None:
        self.replaced.append(item)


def message(agent: str, seq: int) -> dict:
    return {"agent_id": agent, "seq": seq}


def test_latest_per_slot_is_kept_and_sent_when_the_slot_opens():
    async def scenario() -> None:
        throttle = Throttle.from_options({"max_rate": 5, "per": "agent_id"})
        assert throttle is not None and throttle.interval == 0.2
        runner = Runner()
        began = asyncio.get_running_loop().time()
        first = message("uav1", 0)
        assert throttle.admit(first, first, runner) is True
        burst = [message("uav1", seq) for seq in range(1, 6)]
        assert [throttle.admit(m, m, runner) for m in burst] == [False] * 5
        other = message("uav2", 0)
        assert throttle.admit(other, other, runner) is True, "another agent has its own slot"
        assert runner.replaced == burst[:4], "each newer one conflates the parked one"
        await asyncio.wait_for(runner.arrived.wait(), 2)
        at, item = runner.out[0]
        assert item is burst[-1], "the latest is the one released, as it was parked (converted once)"
        assert at - began >= 0.19
        later = message("uav1", 7)
        assert throttle.admit(later, later, runner) is False, "the slot closed again when it released one"
        throttle.close(runner)
        assert [item for _, item in runner.out] == [burst[-1], later], "what is parked at close goes out"
        assert runner.replaced == burst[:4]

    asyncio.run(scenario())


def test_without_per_one_slot_for_the_route():
    async def scenario() -> None:
        throttle = Throttle.from_options({"max_rate": 1})
        runner = Runner()
        a, b = message("a", 0), message("b", 0)
        assert throttle is not None and throttle.admit(a, a, runner) is True
        assert throttle.admit(b, b, runner) is False
        assert Throttle.from_options(None) is None
        throttle.close(runner)

    asyncio.run(scenario())
