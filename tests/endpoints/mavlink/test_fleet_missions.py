"""Missions and commands to several vehicles on one link (issue 20): three simulated vehicles (systems 1-3,
rabbitros_sim) share one UDP link; a mission sink with ``target_system: "{vehicle}"`` uploads
each canonical mission to the vehicle its message names, one upload per target, the targets at
once. Each vehicle gets only its own mission (the link writes a targeted frame only to the peer
its system was heard from, and a vehicle counts what reaches it for another system), and each
call gets its own vehicle's reply."""

from __future__ import annotations

import asyncio
import json
import uuid
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import aio_pika

from engine.endpoints import mavlink
from engine.endpoints.base import MessageRejected, Outbound
from engine.endpoints.mavlink.connection import MavlinkConnection
from engine.running.runtime import Engine
from rabbitros_sim.vehicle import SimVehicle
from tests.support.amqp_helpers import Caller
from tests.endpoints.mavlink.test_mavlink_transactions import canonical_mission, free_udp_port, run
from tests.support.waiting import wait_for


def _points(system_id: int) -> list[tuple[float, float]]:
    """``system_id`` waypoints, each vehicle's own (its id in the latitude's last digits)."""
    return [(-22.0 - system_id / 1000 - n / 100_000, -47.9) for n in range(system_id)]


def _mission(system_id: Any, points: list[tuple[float, float]]) -> dict[str, Any]:
    return {**canonical_mission(points), "vehicle": system_id}


class _Watched:
    """A simulated vehicle that also counts the mission frames it received for another system
    (its autopilot ignores them, as MAVLink routing says; here they must not arrive at all)."""

    def __init__(self, port: int, system_id: int, **options: Any) -> None:
        self.sim = SimVehicle(f"udpout:127.0.0.1:{port}", system_id=system_id, **options)
        self.foreign = 0
        handle = self.sim.autopilot.handle

        def counted(msg: Any) -> None:
            if msg.get_type().startswith("MISSION_") and getattr(msg, "target_system", system_id) != system_id:
                self.foreign += 1
            handle(msg)

        self.sim.autopilot.handle = counted  # type: ignore[method-assign]  # deliberately wraps this simulated autopilot's handler

    def latitudes(self) -> list[float]:
        return [item["x"] / 1e7 for item in self.sim.autopilot.mission]


@asynccontextmanager
async def _fleet(port: int, silent: tuple[int, ...] = ()) -> AsyncIterator[dict[int, _Watched]]:
    vehicles = {system_id: _Watched(port, system_id, mission_result="silent" if system_id in silent else "MAV_MISSION_ACCEPTED")
                for system_id in (1, 2, 3)}
    stop = asyncio.Event()
    running = [asyncio.create_task(vehicle.sim.run(stop)) for vehicle in vehicles.values()]
    try:
        yield vehicles
    finally:
        stop.set()
        await asyncio.gather(*running)


def test_three_missions_as_calls_each_to_the_vehicle_it_names(tmp_path: Path, amqp_url: str, schemas_dir: Path) -> None:
    port = free_udp_port()
    tag = uuid.uuid4().hex[:8]
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "fleet.yaml").write_text(f"""\
connections:
  bus: {{amqp: "{amqp_url}"}}
  radio: {{mavlink: "udpin:127.0.0.1:{port}"}}
routes:
  - name: missions-{tag}
    source: {{amqp: {{connection: bus, queue: missions-{tag}}}}}
    schema: raw_json
    max_attempts: 1
    sink: {{mavlink: {{connection: radio, mission: upload, target_system: "{{vehicle}}", target_component: 1}}}}
    reply: {{mapping: "{{accepted: result == 'MAV_MISSION_ACCEPTED', items: items}}"}}
""")

    async def scenario() -> tuple[Caller, dict[Any, str], dict[int, list[float]], list[int]]:
        engine = Engine(routes, schemas_dir)
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        try:
            async with _fleet(port) as vehicles:
                channel = await connection.channel()
                caller = await Caller.open(channel)
                calls = {system_id: await caller.call("", f"missions-{tag}", json.dumps(_mission(system_id, _points(system_id if isinstance(system_id, int) else 1))).encode())
                         for system_id in (3, 1, 2, "uav2")}
                await caller.wait(lambda r: all(c in r for c in calls.values()), 40, "every mission's reply")
                await channel.queue_delete(f"missions-{tag}")
                return caller, calls, {s: v.latitudes() for s, v in vehicles.items()}, [v.foreign for v in vehicles.values()]
        finally:
            await engine.stop()
            await connection.close()

    caller, calls, missions, foreign = run(scenario(), 90)
    for system_id in (1, 2, 3):
        [reply] = caller.replies[calls[system_id]]
        assert (reply.headers["x-rabbitros-reply"], json.loads(reply.body)) == ("result", {"accepted": True, "items": system_id})
        assert missions[system_id] == [round(lat * 1e7) / 1e7 for lat, _ in _points(system_id)], (system_id, missions)
    [refused] = caller.replies[calls["uav2"]]  # not a system id (and no agents table to name it): never guessed
    error = json.loads(refused.body)
    assert refused.headers["x-rabbitros-reply"] == "error" and error["stage"] == "sink", error
    assert "target_system: field 'vehicle' is 'uav2'" in error["error"], error
    assert foreign == [0, 0, 0]


def _outbound(canonical: dict[str, Any]) -> Outbound:
    return Outbound(json.dumps(canonical).encode(), canonical, canonical, uuid.uuid4().hex, {})


def test_a_silent_vehicle_does_not_hold_the_others_missions() -> None:
    """One batch of three missions, vehicle 1 silent: vehicles 2 and 3 have theirs while vehicle
    1's upload still waits (one after the other, they would wait 4 s behind it); then vehicle 1's
    fails alone."""
    port = free_udp_port()

    async def scenario() -> list[BaseException | None]:
        gcs: MavlinkConnection = mavlink.TRANSPORT.connect("gcs", {"url": f"udpin:127.0.0.1:{port}"})
        await gcs.open()
        try:
            async with _fleet(port, silent=(1,)) as vehicles:
                sink = gcs.sink("missions", {"mission": "upload", "target_system": "{vehicle}", "timeout": 1.0, "retries": 3})
                await wait_for(lambda: all(gcs.has_heard(s) for s in vehicles), 10, "every vehicle's HEARTBEAT")
                batch = asyncio.create_task(sink.send_batch([_outbound(_mission(s, _points(s))) for s in (1, 2, 3)]))
                await wait_for(lambda: all(vehicles[s].sim.autopilot.stats["missions_accepted"] == 1 for s in (2, 3)), 3.0,
                            "vehicles 2 and 3 accepting theirs while vehicle 1 is silent")
                assert not batch.done()
                return await batch
        finally:
            await gcs.close()

    results = run(scenario(), 30)
    assert isinstance(results[0], MessageRejected) and "the mission upload (1 items) got no answer to MISSION_COUNT after 4 sends" in str(results[0]), results
    assert results[1:] == [None, None]


def test_a_silent_vehicle_does_not_hold_the_others_commands() -> None:
    """The same for acknowledged commands: one batch of arm commands to vehicles 1-3, vehicle 1
    never acknowledging; 2 and 3 acknowledge theirs while 1's is still being retried."""
    port = free_udp_port()

    async def scenario() -> list[BaseException | None]:
        gcs: MavlinkConnection = mavlink.TRANSPORT.connect("gcs", {"url": f"udpin:127.0.0.1:{port}"})
        await gcs.open()
        vehicles = {s: SimVehicle(f"udpout:127.0.0.1:{port}", system_id=s,
                                  command_results=["silent"] if s == 1 else ["MAV_RESULT_ACCEPTED"]) for s in (1, 2, 3)}
        stop = asyncio.Event()
        running = [asyncio.create_task(v.run(stop)) for v in vehicles.values()]
        try:
            sink = gcs.sink("arm", {"message": "COMMAND_LONG", "acknowledged": True, "target_system": "{vehicle}",
                                    "timeout": 1.0, "retries": 3})
            await wait_for(lambda: all(gcs.has_heard(s) for s in vehicles), 10, "every vehicle's HEARTBEAT")
            batch = asyncio.create_task(sink.send_batch([
                Outbound(b"", {"vehicle": s}, {"command": 400, "param1": 1}, uuid.uuid4().hex, {}) for s in (1, 2, 3)]))
            await wait_for(lambda: gcs.stats.get("commands_acknowledged", 0) == 2, 3.0,
                        "vehicles 2 and 3 acknowledging theirs while vehicle 1 is silent")
            assert not batch.done()
            assert [len(vehicles[s].autopilot.commands) >= 1 for s in (1, 2, 3)] == [True, True, True]
            return await batch
        finally:
            stop.set()
            await asyncio.gather(*running)
            await gcs.close()

    results = run(scenario(), 30)
    assert isinstance(results[0], MessageRejected) and "MAV_CMD_COMPONENT_ARM_DISARM not acknowledged after 4 sends" \
        in str(results[0]), results
    assert results[1:] == [None, None]
