"""A vehicle's liveness, as MAVROS shows it (``/mavros/state.connected``): a vehicle heard on a
link is *up* while its HEARTBEATs keep coming, *down* once none came for the connection's
``heartbeat_timeout``.

Issue 31: with the vehicle silent for 10 s ``/healthz`` stayed 200, and an acknowledged command
to it answered only after 16.7 s (five resends, about 30 COMMAND_LONGs on the air) while a
vehicle coming back late could act on the stale command. Now a down vehicle is named by
``/healthz`` (503), the status and ``rabbitros_vehicle_up``, and a command or mission to it
fails at once (connection.py ``wait_for_vehicle``).

Which systems count: every system that sent a HEARTBEAT on the link while routes use it,
except ground stations (``MAV_TYPE_GCS``: another QGroundControl closing is no vehicle down)
and ourselves; a vehicle never heard is waited for by a command (``vehicle_timeout``), not
reported down. Liveness is computed when asked (a scrape, a health probe, a command) from the
``time.monotonic()`` of the last HEARTBEAT, so the reading path only stores a float.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Protocol

NOT_VEHICLES = frozenset({"MAV_TYPE_GCS"})
"""HEARTBEAT types that are not vehicles (the names connection.py's VehicleSeen keeps)."""


class Heard(Protocol):
    system_id: int
    component_id: int
    type: str
    last_heard: float


@dataclass(frozen=True, slots=True)
class VehicleLiveness:
    system_id: int
    agent: str | None
    heard_s_ago: float
    up: bool

    @property
    def name(self) -> str:
        """``vehicle 1 (uav1)``, or ``vehicle 1`` where no agent names it."""
        return f"vehicle {self.system_id}" + (f" ({self.agent})" if self.agent else "")

    def down_reason(self, timeout: float) -> str:
        return f"{self.name}: not heard for {self.heard_s_ago:.1f} s (heartbeat_timeout {timeout:g} s)"


def last_heard(seen: Iterable[Heard], system: int, component: int = 0, us: int | None = None) -> float | None:
    """``time.monotonic()`` of the last HEARTBEAT of ``system`` (of ``component`` where not 0)
    from a component that is a vehicle's; None if never heard."""
    times = [heard.last_heard for heard in seen
             if heard.system_id == system and component in (0, heard.component_id)
             and heard.type not in NOT_VEHICLES and heard.system_id != us]
    return max(times) if times else None


def vehicles(seen: Iterable[Heard], agents: Mapping[int, str], timeout: float, us: int,
             now: float | None = None) -> list[VehicleLiveness]:
    """Every vehicle heard (one per system id, by its latest HEARTBEAT), in system id order."""
    now = time.monotonic() if now is None else now
    latest: dict[int, float] = {}
    for heard in seen:
        if heard.type in NOT_VEHICLES or heard.system_id == us:
            continue
        latest[heard.system_id] = max(latest.get(heard.system_id, heard.last_heard), heard.last_heard)
    return [VehicleLiveness(system, agents.get(system), now - at, now - at <= timeout)
            for system, at in sorted(latest.items())]
