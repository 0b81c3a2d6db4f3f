"""Throttling with conflation, for telemetry over slow radio links.

``throttle: {max_rate: 2, per: agent_id}`` lets at most ``max_rate`` messages per second
through for each distinct value of the canonical field ``per`` (one slot for the whole route
without ``per``). A message arriving while its slot is closed is parked; a newer one for
the same slot replaces it (conflation: the older one is counted as ``conflated``), and the
parked message is delivered when the slot opens. Only the latest value crosses the radio,
at the rate it can carry, and no backlog builds up.

Parking never blocks the source: sources that hand messages over one at a time (MAVLink,
ROS 2) go on reading, so conflation really keeps the latest. The price is that a parked
message is acknowledged to its source when parked, not when sent: a throttled route keeps
the latest value, not every value (what telemetry wants, and what ``conflated`` counts).
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field
from typing import Any, Mapping, Protocol

from engine.endpoints.base import Inbound, Outbound
from engine.observe import CONFLATED
from engine.options import option, parse


@dataclass(frozen=True, kw_only=True)
class ThrottleOptions:
    """A route's ``throttle:`` (see the module docstring)."""

    __schema_description__ = ("at most max_rate messages/s per value of the canonical field 'per'; "
                              "between slots only the latest is kept (conflation)")

    max_rate: float = option(exclusive_minimum=0, description="messages per second per slot")
    per: str | None = option(None, pattern=r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$",
                             description="canonical field (a.b) whose values get a slot each; none: one slot for the route")


class Redeliver(Protocol):
    def redeliver(self, inbound: Inbound) -> None: ...

    def observe(self, inbound: Inbound, outbound: Outbound | None, outcome: str, error: BaseException | None) -> None: ...


@dataclass
class _Slot:
    opens: float = 0.0
    parked: tuple[Inbound, Outbound] | None = None
    timer: asyncio.TimerHandle | None = None


@dataclass
class Throttle:
    max_rate: float
    per: tuple[str, ...] | None
    slots: dict[Any, _Slot] = field(default_factory=dict)
    _released: set[int] = field(default_factory=set)

    @classmethod
    def from_options(cls, options: ThrottleOptions | Mapping[str, Any] | None) -> Throttle | None:
        if not options:
            return None
        options = parse(ThrottleOptions, options)
        return cls(float(options.max_rate), tuple(options.per.split(".")) if options.per else None)

    @property
    def interval(self) -> float:
        return 1.0 / self.max_rate

    def key(self, canonical: Any) -> Any:
        if self.per is None:
            return None
        value = canonical
        for part in self.per:
            value = value.get(part) if isinstance(value, dict) else None
        return value if isinstance(value, (str, int, float, bool)) or value is None else repr(value)

    def admit(self, inbound: Inbound, outbound: Outbound, runner: Redeliver) -> bool:
        """True: send now. False: parked (sent when its slot opens) or conflated later."""
        if self._released and id(inbound) in self._released:
            self._released.discard(id(inbound))
            return True
        loop = asyncio.get_running_loop()
        now = loop.time()
        key = self.key(outbound.canonical)
        slot = self.slots.get(key)
        if slot is None:
            slot = self.slots[key] = _Slot()
        if slot.parked is None and now >= slot.opens:
            slot.opens = now + self.interval
            return True
        if slot.parked is not None:
            runner.observe(*slot.parked, CONFLATED, None)
        else:
            slot.timer = loop.call_at(slot.opens, self._open, slot, runner)
        slot.parked = (inbound, outbound)
        return False

    def _open(self, slot: _Slot, runner: Redeliver) -> None:
        parked, slot.parked, slot.timer = slot.parked, None, None
        if parked is None:
            return
        slot.opens = asyncio.get_running_loop().time() + self.interval
        self._released.add(id(parked[0]))
        runner.redeliver(parked[0])

    def close(self, runner: Redeliver) -> None:
        """The pipeline retires: what is parked goes out now rather than being lost."""
        for slot in self.slots.values():
            if slot.timer is not None:
                slot.timer.cancel()
            if slot.parked is not None:
                inbound = slot.parked[0]
                slot.parked = slot.timer = None
                self._released.add(id(inbound))
                runner.redeliver(inbound)
