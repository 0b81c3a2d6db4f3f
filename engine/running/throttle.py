"""Throttling with conflation, for telemetry over slow radio links: a stage of the route.

``throttle: {max_rate: 2, per: agent_id}`` lets at most ``max_rate`` messages per second
through for each distinct value of the canonical field ``per`` (one slot for the whole route
without ``per``). The stage sits between conversion and the sink (engine/running/runner.py): a
converted message arriving while its slot is closed is parked; a newer one for the same slot
replaces it (conflation: the older one is counted as ``conflated``), and the parked message
goes to the sink when the slot opens. Only the latest value crosses the radio, at the rate
it can carry, and no backlog builds up. A parked message is converted and counted once: what
the slot releases is the message already converted, handed to the route's sink path.

Parking never blocks the source: sources that hand messages over one at a time (MAVLink,
ROS 2) go on reading, so conflation really keeps the latest. The price is that a parked
message is acknowledged to its source when parked, not when sent: a throttled route keeps
the latest value, not every value (what telemetry wants, and what ``conflated`` counts).
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field
from typing import Any, Generic, Mapping, Protocol, TypeVar

from engine.common.field_keys import slot_key
from engine.common.options import parse
from engine.language.stage_options import ThrottleOptions

T = TypeVar("T")
T_contra = TypeVar("T_contra", contravariant=True)


class ThrottleStage(Protocol[T_contra]):
    """What the throttle hands parked messages back to (the route's runner)."""

    def released(self, item: T_contra) -> None:
        """The item's slot opened (or the throttle closed): send it now."""

    def conflated(self, item: T_contra) -> None:
        """A newer item replaced this parked one."""


@dataclass
class _Slot(Generic[T]):
    opens: float = 0.0
    parked: T | None = None
    timer: asyncio.TimerHandle | None = None


@dataclass
class Throttle(Generic[T]):
    max_rate: float
    per: tuple[str, ...] | None
    slots: dict[Any, _Slot[T]] = field(default_factory=dict)

    @classmethod
    def from_options(cls, options: ThrottleOptions | Mapping[str, Any] | None) -> Throttle[Any] | None:
        if not options:
            return None
        options = parse(ThrottleOptions, options)
        return cls(float(options.max_rate), tuple(options.per.split(".")) if options.per else None)

    @property
    def interval(self) -> float:
        return 1.0 / self.max_rate

    def key(self, canonical: Any) -> Any:
        return slot_key(canonical, self.per)

    def admit(self, item: T, canonical: Any, stage: ThrottleStage[T]) -> bool:
        """True: send ``item`` now. False: parked, handed to ``stage.released`` when its slot
        opens unless a newer item replaces it first (``stage.conflated``)."""
        loop = asyncio.get_running_loop()
        now = loop.time()
        key = self.key(canonical)
        slot = self.slots.get(key)
        if slot is None:
            slot = self.slots[key] = _Slot()
        if slot.parked is None and now >= slot.opens:
            slot.opens = now + self.interval
            return True
        if slot.parked is not None:
            stage.conflated(slot.parked)
        else:
            slot.timer = loop.call_at(slot.opens, self._open, slot, stage)
        slot.parked = item
        return False

    def _open(self, slot: _Slot[T], stage: ThrottleStage[T]) -> None:
        parked, slot.parked, slot.timer = slot.parked, None, None
        if parked is None:
            return
        slot.opens = asyncio.get_running_loop().time() + self.interval
        stage.released(parked)

    def close(self, stage: ThrottleStage[T]) -> None:
        """The pipeline retires: what is parked goes out now rather than being lost."""
        for slot in self.slots.values():
            if slot.timer is not None:
                slot.timer.cancel()
            parked, slot.parked, slot.timer = slot.parked, None, None
            if parked is not None:
                stage.released(parked)
