"""Throttling with conflation, on the real asyncio clock (no broker needed)."""

from __future__ import annotations

import asyncio

from engine.endpoints.base import Inbound, Outbound
from engine.observe import CONFLATED
from engine.throttle import Throttle


class Runner:
    """Records what the throttle hands back, as RouteRunner would redeliver it."""

    def __init__(self) -> None:
        self.redelivered: list[tuple[float, Inbound]] = []
        self.observed: list[tuple[Inbound, str]] = []
        self.arrived = asyncio.Event()

    def redeliver(self, inbound: Inbound) -> None:
        self.redelivered.append((asyncio.get_running_loop().time(), inbound))
        self.arrived.set()

    def observe(self, inbound: Inbound, outbound: Outbound | None, outcome: str, error: BaseException | None) -> None:
        self.observed.append((inbound, outcome))


def message(agent: str, seq: int) -> tuple[Inbound, Outbound]:
    canonical = {"agent_id": agent, "seq": seq}
    return Inbound(body=b"{}"), Outbound(b"{}", canonical, canonical, str(seq), {})


def test_latest_per_slot_is_kept_and_sent_when_the_slot_opens():
    async def scenario() -> None:
        throttle = Throttle.from_options({"max_rate": 5, "per": "agent_id"})
        assert throttle is not None and throttle.interval == 0.2
        runner = Runner()
        first = message("uav1", 0)
        began = asyncio.get_running_loop().time()
        assert throttle.admit(*first, runner) is True
        burst = [message("uav1", seq) for seq in range(1, 6)]
        assert [throttle.admit(*m, runner) for m in burst] == [False] * 5
        assert throttle.admit(*message("uav2", 0), runner) is True, "another agent has its own slot"
        assert [outcome for _, outcome in runner.observed] == [CONFLATED] * 4
        assert [inbound for inbound, _ in runner.observed] == [m[0] for m in burst[:4]]
        await asyncio.wait_for(runner.arrived.wait(), 2)
        at, inbound = runner.redelivered[0]
        assert inbound is burst[-1][0], "the latest is the one sent"
        assert at - began >= 0.19
        assert throttle.admit(inbound, burst[-1][1], runner) is True, "a released message goes through"
        assert throttle.admit(*message("uav1", 7), runner) is False, "the slot closed again"
        throttle.close(runner)
        assert len(runner.redelivered) == 2, "what is parked at close goes out"
        assert throttle.admit(runner.redelivered[1][1], message("uav1", 7)[1], runner) is True

    asyncio.run(scenario())


def test_without_per_one_slot_for_the_route():
    async def scenario() -> None:
        throttle = Throttle.from_options({"max_rate": 1})
        runner = Runner()
        assert throttle is not None and throttle.admit(*message("a", 0), runner) is True
        assert throttle.admit(*message("b", 0), runner) is False
        assert Throttle.from_options(None) is None

    asyncio.run(scenario())
