"""What a source under test delivers, without an engine: the one collector of the endpoint tests
(what a broker's queue receives is tests/support/amqp_helpers.py ``Collector``)."""

from __future__ import annotations

from typing import Any

from engine.endpoints.base import Inbound
from rabbitros_sim.deliver import FunctionDeliver
from tests.support.waiting import wait_for


def decoded(inbound: Inbound) -> dict[str, Any]:
    """The fields of a message from a source that decodes (MAVLink, ROS 2); asserts it has them."""
    assert inbound.fields is not None, "a delivered message came without its fields"
    return inbound.fields


class CollectingDeliver(FunctionDeliver):
    """A Deliver that records every message it settles in ``items``; its first ``fail_first``
    calls raise (a sink that is down), and ``calls`` counts every attempt. ``deliver``: the
    FunctionDeliver options (``overflow``, ``queue_limit``)."""

    def __init__(self, fail_first: int = 0, **deliver: Any) -> None:
        super().__init__(**deliver)
        self.items: list[Inbound] = []
        self.calls = 0
        self.fail_first = fail_first

    async def __call__(self, inbound: Inbound) -> None:
        self.calls += 1
        if self.calls <= self.fail_first:
            raise RuntimeError("sink down")
        self.items.append(inbound)

    async def wait_for(self, count: int, timeout: float = 10.0) -> list[Inbound]:
        """Until ``count`` messages were delivered; fails naming how many came."""
        await wait_for(lambda: len(self.items) >= count, timeout, f"{count} deliveries", detail=lambda: f"{len(self.items)} came")
        return self.items

    def fields(self) -> list[dict[str, Any]]:
        """The decoded fields of each message delivered, in order; asserts every one has them
        (a source that decodes, as MAVLink's and ROS 2's do)."""
        return [decoded(inbound) for inbound in self.items]

    def bodies(self) -> list[bytes]:
        """The raw body of each message delivered, in order; asserts every one kept its body
        (a source that forwards bytes)."""
        bodies = [inbound.body for inbound in self.items]
        assert all(body is not None for body in bodies), "a delivered message came without its raw body"
        return [body for body in bodies if body is not None]
