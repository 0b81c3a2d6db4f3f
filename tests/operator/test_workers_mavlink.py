"""``run --workers 2`` with one ``udpin`` link split over the workers by vehicle
(``split_over_workers: true``, engine/endpoints/mavlink/split.py; issue 34).

Real parts: the engine as an operator runs it (the supervisor and its two worker processes,
tests/support/engine_process.py), its admin endpoint over HTTP, a private RabbitMQ node
(tests/conftest.py) with an AMQP caller on direct reply-to, and eight vehicles on plain pymavlink
(tests/support/udp_vehicle.py ``FleetVehicle``), each sending HEARTBEAT and GLOBAL_POSITION_INT
at 10 Hz from its own UDP socket and acknowledging every COMMAND_LONG addressed to it.

- Every vehicle's telemetry reaches RabbitMQ, each from the worker its system id falls to; each
  worker reports (status: the link's liveness) exactly its share of the vehicles, the shares
  disjoint and both nonempty, and the merged status and ``/metrics`` (``rabbitros_vehicle_up``)
  name each vehicle once, from its own worker.
- Commands (AMQP -> acknowledged COMMAND_LONG, competing on both workers) reach each vehicle and
  only its peer, and every caller gets its MAV_RESULT_ACCEPTED, including for the commands a
  worker took for a vehicle of the other worker's share (the owner copied their COMMAND_ACKs:
  ``split_answers``).
- The worker holding the socket killed with -9 is started again by the supervisor, holds the
  socket again, the other worker connects to it again, and every vehicle's telemetry and
  commands flow again.
"""

from __future__ import annotations

import json
import os
import signal
import uuid
from pathlib import Path
from typing import Any

import aio_pika
import aiohttp
from prometheus_client.parser import text_string_to_metric_families

from engine.common.processes import listening_port
from engine.common.shares import share_of
from tests.support.amqp_helpers import Caller, Collector
from tests.support.engine_process import EngineProcess
from tests.support.udp_vehicle import FleetVehicle, free_udp_port
from tests.support.waiting import wait_for

ROUTES = """
connections:
  gcs: {{amqp: "{url}"}}
  fleet: {{mavlink: "udpin:127.0.0.1:{port}", heartbeat: 1, split_over_workers: true}}
routes:
  - name: position
    source: {{mavlink: {{connection: fleet, message: GLOBAL_POSITION_INT}}}}
    mapping: "{{vehicle: meta('system_id'), seq: time_boot_ms}}"
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: {tag}-out, routing_key: "uav.{{vehicle}}"}}}}
  - name: command
    source: {{amqp: {{connection: gcs, queue: {tag}-cmd, prefetch: 4}}}}
    schema: raw_json
    sink:
      mavlink: {{connection: fleet, message: COMMAND_LONG, acknowledged: true, target_system: "{{vehicle}}",
                target_component: 1}}
      mapping: "{{command: `400`, param1: `1`, param2: param}}"
    reply: {{mapping: "{{result: result}}"}}
"""
VEHICLES = range(1, 9)
ROUNDS = 3
"""Commands to each vehicle: with the broker handing them to either worker, some commands for
each share are taken by the other worker (asserted through ``split_answers``)."""


async def admin_status(port: int) -> dict[str, Any]:
    async with aiohttp.ClientSession() as session, session.get(f"http://127.0.0.1:{port}/status") as answer:
        assert answer.status == 200, await answer.text()
        return dict(await answer.json())


def test_a_fleet_on_one_udp_link_is_split_over_two_workers_by_vehicle(tmp_path: Path, amqp_url: str) -> None:
    shares = {system: share_of(str(system), 2) for system in VEHICLES}
    assert set(shares.values()) == {0, 1}, shares  # both workers have vehicles
    tag = "m" + uuid.uuid4().hex[:8]
    udp = free_udp_port()
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "fleet.yaml").write_text(ROUTES.format(url=amqp_url, port=udp, tag=tag))
    admin = listening_port()
    engine = EngineProcess(routes, tmp_path / "status.json", {}, "--workers", "2", "--admin", str(admin))
    vehicles = {system: FleetVehicle(system, udp, rate=10.0) for system in VEHICLES}

    async def scenario() -> dict[str, Any]:
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            positions = await Collector.bind(channel, f"{tag}-out", "uav.#")
            caller = await Caller.open(await connection.channel())
            await channel.declare_queue(f"{tag}-cmd", durable=True)

            async def connected() -> bool:
                workers = (await admin_status(admin))["workers"]
                splits = [(w.get("status") or {}).get("connections", {}).get("fleet", {}).get("split") for w in workers]
                if None in splits:
                    return False
                owner = splits[0]["owner"]
                return bool(splits[owner]["connected"] == [1 - owner])

            await wait_for(connected, 30, "the other worker connected to the link's owner")
            for vehicle in vehicles.values():
                vehicle.start()

            def heard() -> set[int]:
                return {json.loads(m.body)["vehicle"] for m in positions.messages}

            await wait_for(lambda: heard() == set(VEHICLES), 60, "telemetry of every vehicle at RabbitMQ",
                           lambda: f"heard {sorted(heard())}; {engine.log()}")

            async def every_vehicle_reported() -> dict[str, Any] | None:
                status = await admin_status(admin)
                link = status["connections"].get("fleet", {})
                return status if sorted(v["system_id"] for v in link.get("liveness", [])) == list(VEHICLES) else None

            status = await wait_for(every_vehicle_reported, 30, "each vehicle's liveness in the merged status")
            async with aiohttp.ClientSession() as session, session.get(f"http://127.0.0.1:{admin}/metrics") as answer:
                metrics = await answer.text()
            calls = {}
            for round_ in range(ROUNDS):
                for system in VEHICLES:
                    body = json.dumps({"vehicle": system, "param": round_ * 100 + system}).encode()
                    calls[await caller.call("", f"{tag}-cmd", body)] = system
            await caller.wait(lambda replies: all(call in replies for call in calls), 60, "every command's reply")

            async def every_command_counted() -> dict[str, Any] | None:
                """The reply goes out before the route counts the command delivered: wait for the counts."""
                status = await admin_status(admin)
                taken = [status["workers"][w]["status"]["routes"]["command"]["delivered"] for w in (0, 1)]
                return status if sum(taken) >= ROUNDS * len(VEHICLES) else None

            after = await wait_for(every_command_counted, 30, "every command counted delivered by the workers")
            # the worker holding the socket killed: started again, it holds it again, and the other reconnects
            owner = after["workers"][0]["status"]["connections"]["fleet"]["split"]["owner"]
            victim = after["workers"][owner]["pid"]
            os.kill(victim, signal.SIGKILL)

            async def back() -> bool:
                worker = (await admin_status(admin))["workers"][owner]
                return bool(worker["up"] and worker["restarts"] == 1 and worker["pid"] != victim)

            await wait_for(back, 90, "the link's owner started again", lambda: engine.log())
            await wait_for(connected, 30, "the other worker connected to the new owner")
            mark = len(positions.messages)
            await wait_for(lambda: {json.loads(m.body)["vehicle"] for m in positions.messages[mark:]} == set(VEHICLES), 60,
                           "telemetry of every vehicle again")
            again = {await caller.call("", f"{tag}-cmd", json.dumps({"vehicle": system, "param": 1000 + system}).encode()): system
                     for system in VEHICLES}
            await caller.wait(lambda replies: all(call in replies for call in again), 60, "every command's reply after the restart")
            calls.update(again)
            return {"status": status, "after": after, "victim": victim, "metrics": metrics, "positions": [json.loads(m.body) | {"key": m.routing_key}
                                                                      for m in positions.messages],
                    "replies": {call: (caller.replies[call][0].headers.get("x-rabbitros-reply"), json.loads(caller.replies[call][0].body))
                                for call in calls}}
        finally:
            for vehicle in vehicles.values():
                vehicle.stop.set()
            await connection.close()

    try:
        result, _ = engine.run(scenario)
    finally:
        for vehicle in vehicles.values():
            vehicle.stop.set()
            vehicle.join(5)
    status, after = result["status"], result["after"]
    assert status["placement"] == {"command": [0, 1], "position": [0, 1]}, status["placement"]
    assert status["split_connections"] == {"fleet": status["workers"][0]["status"]["connections"]["fleet"]["split"]["owner"]}
    for worker in (0, 1):  # each worker reports exactly the vehicles whose system id falls to it
        link = status["workers"][worker]["status"]["connections"]["fleet"]
        own = sorted(v["system_id"] for v in link["liveness"])
        assert own == [s for s in VEHICLES if shares[s] == worker], (worker, own)
        assert all(v["up"] for v in link["liveness"]), link["liveness"]
        assert link["split"]["worker"] == worker and link["split"]["workers"] == 2
        received = status["workers"][worker]["status"]["routes"]["position"]["received"]
        assert received > 0, (worker, received)
    for position in result["positions"]:
        assert position["key"] == f"uav.{position['vehicle']}"
    up = {s.labels["system_id"]: s.value for family in text_string_to_metric_families(result["metrics"]) for s in family.samples
          if s.name == "rabbitros_vehicle_up"}  # the merged series: one per vehicle, from its worker
    assert up == {str(system): 1.0 for system in VEHICLES}, up
    per_worker = [s.labels for family in text_string_to_metric_families(result["metrics"]) for s in family.samples
                  if s.name == "rabbitros_worker_vehicle_up"]
    assert sorted((labels["worker"], int(labels["system_id"])) for labels in per_worker) == sorted(
        (str(shares[system]), system) for system in VEHICLES), per_worker
    merged = after["connections"]["fleet"]
    assert sorted(v["system_id"] for v in merged["liveness"]) == list(VEHICLES)  # once each, from its own worker
    assert merged["counters"]["split_dropped"] == 0, merged["counters"]
    # every command acknowledged, through whichever worker took it
    assert {kind for kind, _ in result["replies"].values()} == {"result"}, result["replies"]
    assert all(body == {"result": "MAV_RESULT_ACCEPTED"} for _, body in result["replies"].values()), result["replies"]
    assert merged["counters"]["split_answers"] >= 1, merged["counters"]  # some were taken by the other share's worker
    taken = [after["workers"][w]["status"]["routes"]["command"]["delivered"] for w in (0, 1)]
    assert sum(taken) >= ROUNDS * len(VEHICLES), taken
    for system, vehicle in vehicles.items():
        params = sorted(int(msg.param2) for msg in vehicle.received())
        assert set(params) == {round_ * 100 + system for round_ in range(ROUNDS)} | {1000 + system}, (system, params)
        assert vehicle.foreign == 0  # each command went only to the peer its vehicle was heard from

