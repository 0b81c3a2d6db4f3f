"""What the web console shows beside the counters: recent dead letters and the fleet's positions.

Both are bounded and shared by every route (:class:`engine.running.observe.Observers` owns one
of each). The hot path pays one deque append per dead letter and, on routes whose canonical
schema is ``position``, one ordered-dict store per delivered message (a reference to the
canonical message, not a copy); the console's one-second snapshot picks the fields.
"""

from __future__ import annotations

import time
from collections import OrderedDict, deque
from typing import Any

RECENT_DEAD_LETTERS = 100
"""Dead letters the console lists (all routes together): enough for the last minute of a
misbehaving route, small enough to send every second."""
FLEET_AGENTS = 1000
"""Agents whose last position is kept; the least recently heard one goes first."""
DEAD_LETTER_REASON_CHARS = 500
"""A reason is cut to this many characters (a schema error can quote a whole message)."""
POSITION_SCHEMA = "position"
"""The canonical schema (schemas/position.v1.json: agent_id, lat, lon) whose messages draw the fleet."""


class RecentDeadLetters:
    """The last :data:`RECENT_DEAD_LETTERS` dead letters of every route: when, route, stage, reason."""

    def __init__(self, size: int = RECENT_DEAD_LETTERS) -> None:
        self.entries: deque[tuple[float, str, str, str]] = deque(maxlen=size)

    def add(self, route: str, stage: str, reason: str) -> None:
        self.entries.append((time.time(), route, stage, reason[:DEAD_LETTER_REASON_CHARS]))

    def view(self) -> list[dict[str, Any]]:
        """Newest first."""
        return [{"at": at, "route": route, "stage": stage, "reason": reason}
                for at, route, stage, reason in reversed(self.entries)]


class Fleet:
    """The last canonical position of each agent (at most :data:`FLEET_AGENTS`), kept as the
    message itself: the hot path stores a reference, :meth:`view` picks the fields."""

    def __init__(self, size: int = FLEET_AGENTS) -> None:
        self.size = size
        self.last: OrderedDict[str, tuple[Any, str, float]] = OrderedDict()

    def heard(self, canonical: Any, route: str, at: float) -> None:
        if not isinstance(canonical, dict):
            return
        agent = canonical.get("agent_id")
        if agent is None:
            return
        key = str(agent)
        last = self.last
        last[key] = (canonical, route, at)
        last.move_to_end(key)
        if len(last) > self.size:
            last.popitem(last=False)

    def view(self) -> list[dict[str, Any]]:
        """One entry per agent with a numeric lat/lon: agent_id, lat, lon, alt_rel, alt_msl,
        heading, stamp, route, at (``alt_msl`` and ``stamp``: what the Foxglove view of ``run
        --workers N`` draws a fix from, engine/ops/supervisor_foxglove.py)."""
        agents = []
        for agent, (canonical, route, at) in self.last.items():
            lat, lon = canonical.get("lat"), canonical.get("lon")
            if isinstance(lat, (int, float)) and isinstance(lon, (int, float)):
                agents.append({"agent_id": agent, "lat": lat, "lon": lon, "alt_rel": canonical.get("alt_rel"),
                               "alt_msl": canonical.get("alt_msl"), "heading": canonical.get("heading"),
                               "stamp": canonical.get("stamp"), "route": route, "at": at})
        return agents


def is_position_schema(name: str | None) -> bool:
    """``position`` or a version of it (``position.v1``)."""
    return name is not None and name.partition(".v")[0] == POSITION_SCHEMA
