"""The console's bounded views (engine/running/recent.py) as the observers feed them: the last
dead letters of every route, the last position of each agent from position routes only."""

from __future__ import annotations

import pytest

from engine.endpoints.base import Outbound
from engine.running.observe import Observers
from engine.running.recent import Fleet, RecentDeadLetters

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier


def sent(canonical: dict) -> Outbound:
    return Outbound(body=b"{}", canonical=canonical, fields=canonical, message_id="m", meta={})


def test_positions_are_kept_per_agent_from_position_routes_only() -> None:
    observers = Observers()
    position, weeds = observers.get("uav-position"), observers.get("weeds")
    position.carries("position")
    weeds.carries("weed_detection")
    position.accepted(None, sent({"agent_id": "uav1", "lat": 48.1, "lon": 11.5, "alt_rel": 30.0}), 1000)
    position.accepted(None, sent({"agent_id": "uav1", "lat": 48.2, "lon": 11.6}), 1000)
    weeds.accepted(None, sent({"agent_id": "robot1", "lat": 1.0, "lon": 2.0}), 1000)  # not a position route
    fleet = observers.fleet.view()
    assert [(a["agent_id"], a["lat"], a["lon"], a["route"]) for a in fleet] == [("uav1", 48.2, 11.6, "uav-position")]
    position.carries("weed_detection.v1")  # a reload changed the route's schema: no more positions from it
    position.accepted(None, sent({"agent_id": "uav2", "lat": 0.0, "lon": 0.0}), 1000)
    assert [a["agent_id"] for a in observers.fleet.view()] == ["uav1"]


def test_the_fleet_is_bounded_and_forgets_the_agent_heard_least_recently() -> None:
    fleet = Fleet(size=3)
    for agent in ("a", "b", "c", "a", "d"):
        fleet.heard({"agent_id": agent, "lat": 1.0, "lon": 2.0}, "r", 0.0)
    fleet.heard({"agent_id": "e", "lat": "north", "lon": 2.0}, "r", 0.0)  # kept, not drawn: no numeric lat
    fleet.heard({"lat": 1.0, "lon": 2.0}, "r", 0.0)  # no agent_id: not kept
    assert list(fleet.last) == ["a", "d", "e"]
    assert [a["agent_id"] for a in fleet.view()] == ["a", "d"]


def test_recent_dead_letters_are_bounded_newest_first_with_stage_and_reason() -> None:
    observers = Observers()
    observers.recent_dead_letters = RecentDeadLetters(size=2)
    route = observers.get("weeds")
    route.recent_dead_letters = observers.recent_dead_letters
    for n in range(3):
        route.dead_letter(None, None, "schema", f"p {n} is greater than the maximum of 1" + "x" * 1000)
    view = observers.recent_dead_letters.view()
    assert [(d["route"], d["stage"], d["reason"][:3]) for d in view] == [("weeds", "schema", "p 2"), ("weeds", "schema", "p 1")]
    assert len(view[0]["reason"]) == 500 and route.failed == 3
