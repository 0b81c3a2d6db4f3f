"""A ``udpin`` link split over two workers (``split_over_workers``, engine/endpoints/mavlink/split.py),
both ends in one process: the owner's connection (worker 0, holding the UDP socket) and worker
1's, connected by the local socket in a runtime directory, as ``run --workers 2`` opens them.

Real parts: eight vehicles on plain pymavlink behind their own UDP sockets
(tests/support/udp_vehicle.py ``FleetVehicle``: HEARTBEAT and GLOBAL_POSITION_INT at 20 Hz,
each COMMAND_LONG addressed to it acknowledged), the engine's two connections with their local
sockets. Each vehicle's frames reach exactly its worker (its system id's share); each worker
reports its own vehicles' liveness and hears every vehicle's HEARTBEAT (a command waits for its
vehicle); a command worker 1 sends to a vehicle of worker 0's share goes out through the owner
to that vehicle alone and worker 1's transaction gets the COMMAND_ACK, which no route of worker 1
sees; once worker 1 is gone, the owner counts what it could not hand on (``split_dropped``) and
its own vehicles' frames still flow.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import uuid
from collections import Counter
from pathlib import Path
from functools import partial
from typing import Any, AsyncIterator

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from engine.common.shares import share_of
from engine.endpoints.base import Outbound
from engine.endpoints.mavlink.connection import MavlinkConnection
from engine.endpoints.mavlink.split_leases import Leases
from engine.endpoints.mavlink.transaction import Conversation
from engine.endpoints.workers import ConnectionShare
from tests.support.udp_vehicle import FleetVehicle, free_udp_port
from tests.support.waiting import wait_for

VEHICLES = range(1, 9)
POSITION = mavlink2.MAVLINK_MSG_ID_GLOBAL_POSITION_INT
ACK = mavlink2.MAVLINK_MSG_ID_COMMAND_ACK


def test_each_vehicle_reaches_its_worker_and_a_command_from_the_other_worker_gets_its_answer(tmp_path: Path) -> None:
    shares = {system: share_of(str(system), 2) for system in VEHICLES}
    assert set(shares.values()) == {0, 1}, shares
    target = next(system for system in VEHICLES if shares[system] == 0)  # commanded by worker 1, heard by worker 0
    port = free_udp_port()
    settings = {"url": f"udpin:127.0.0.1:{port}", "heartbeat": 1, "split_over_workers": True}
    vehicles = {system: FleetVehicle(system, port, rate=20.0) for system in VEHICLES}
    found: dict[str, Any] = {}

    async def scenario() -> None:
        owner = MavlinkConnection("fleet", settings, ConnectionShare(0, 2, 0, str(tmp_path)))
        other = MavlinkConnection("fleet", settings, ConnectionShare(1, 2, 0, str(tmp_path)))
        heard: dict[int, Counter[int]] = {0: Counter(), 1: Counter()}
        acks_to_routes: list[int] = []

        def tally(index: int, msg: Any) -> None:
            heard[index].update([msg.get_srcSystem()])

        for index, connection in ((0, owner), (1, other)):
            connection.listen(POSITION, partial(tally, index))
        other.listen(ACK, lambda msg: acks_to_routes.append(msg.get_srcSystem()))  # a route's listener
        await owner.open()
        await other.open()
        try:
            await wait_for(lambda: owner.health()["split"]["connected"] == [1] and other.health()["split"]["connected"], 10,
                           "worker 1 connected to the owner")
            for vehicle in vehicles.values():
                vehicle.start()
            await wait_for(lambda: all(heard[shares[s]][s] >= 20 for s in VEHICLES), 30, "20 positions of every vehicle",
                           lambda: heard)
            found["heard"] = {index: dict(counts) for index, counts in heard.items()}
            found["liveness"] = {index: sorted(v.system_id for v in c.liveness()) for index, c in ((0, owner), (1, other))}
            found["other_heard_target"] = other.has_heard(target, 1)
            loop = asyncio.get_running_loop()
            await other.wait_for_vehicle(target, 1, loop.time() + 10)  # from the owner's HEARTBEAT copies
            async with Conversation(other, (target, 1), (ACK,)) as answers:
                await other.send_message(mavlink2.MAVLink_command_long_message(target, 1, 400, 0, 1, 77, 0, 0, 0, 0, 0))
                found["ack"] = await answers.next(10)
            found["acks_to_routes"] = list(acks_to_routes)
            found["owner_counters"] = dict(owner.stats)
            found["other_sent"] = (other.stats["split_sent"], other.stats["frames_sent"])
            await other.close()
            dropped = owner.stats["split_dropped"]
            before = heard[0].copy()
            await wait_for(lambda: owner.stats["split_dropped"] > dropped + 20, 10, "frames for the closed worker dropped")
            await wait_for(lambda: all(heard[0][s] > before[s] + 5 for s in VEHICLES if shares[s] == 0), 10,
                           "the owner's own vehicles still carried")
        finally:
            for vehicle in vehicles.values():
                vehicle.stop.set()
            await other.close()
            await owner.close()

    try:
        asyncio.run(asyncio.wait_for(scenario(), 90))
    finally:
        for vehicle in vehicles.values():
            vehicle.stop.set()
            vehicle.join(5)
    for index in (0, 1):  # each vehicle's frames at its own worker only
        assert set(found["heard"][index]) == {s for s in VEHICLES if shares[s] == index}, found["heard"]
        assert found["liveness"][index] == [s for s in VEHICLES if shares[s] == index], found["liveness"]
    assert found["other_heard_target"] is True
    ack = found["ack"]
    assert ack is not None and ack.command == 400 and ack.result == mavlink2.MAV_RESULT_ACCEPTED, ack
    assert found["acks_to_routes"] == []  # the copy reached the transaction, no route
    assert found["other_sent"] == (1, 0)  # handed to the owner (no HEARTBEAT of its own); the owner counts it written
    counters = found["owner_counters"]
    assert counters["split_answers"] == 1 and counters["split_dropped"] == 0, counters
    commanded = vehicles[target].received()
    assert [(msg.command, msg.param2, msg.get_srcSystem()) for msg in commanded] == [(400, 77.0, 255)]
    assert all(not vehicle.received() for system, vehicle in vehicles.items() if system != target)
    assert all(vehicle.foreign == 0 for vehicle in vehicles.values())  # written to the target's address alone
    assert all(vehicle.heartbeats > 0 for vehicle in vehicles.values())  # the owner's HEARTBEAT, to every peer


def test_missions_from_either_worker_reach_a_vehicle_of_the_other_share(tmp_path: Path) -> None:
    """Mission uploads across the split: worker 1 uploads to vehicle 1 (worker 0's share) and the
    owner, worker 0, to vehicle 3 (worker 1's); the vehicles (rabbitros_sim, their own UDP sockets)
    answer MISSION_REQUEST_INT and MISSION_ACK, which the owner copies to the uploading worker.
    Each vehicle has exactly its own mission, and nothing for another system reached it."""
    from tests.endpoints.mavlink.test_fleet_missions import _mission, _points, _Watched

    assert (share_of("1", 2), share_of("3", 2)) == (0, 1)
    port = free_udp_port()
    settings = {"url": f"udpin:127.0.0.1:{port}", "heartbeat": 1, "split_over_workers": True}

    async def scenario() -> tuple[list[BaseException | None], list[BaseException | None], dict[int, _Watched], dict[str, int]]:
        owner = MavlinkConnection("fleet", settings, ConnectionShare(0, 2, 0, str(tmp_path)))
        other = MavlinkConnection("fleet", settings, ConnectionShare(1, 2, 0, str(tmp_path)))
        await owner.open()
        await other.open()
        await wait_for(lambda: owner.health()["split"]["connected"] == [1], 10, "worker 1 connected to the owner")
        vehicles = {system: _Watched(port, system) for system in (1, 3)}
        stop = asyncio.Event()
        running = [asyncio.create_task(vehicle.sim.run(stop)) for vehicle in vehicles.values()]
        try:
            await wait_for(lambda: all(c.has_heard(s) for c in (owner, other) for s in vehicles), 10, "both vehicles heard by both workers")
            options = {"mission": "upload", "target_system": "{vehicle}", "timeout": 1.0, "retries": 3}
            from_other = other.sink("missions", options).send_batch([_outbound(_mission(1, _points(1)))])
            from_owner = owner.sink("missions", options).send_batch([_outbound(_mission(3, _points(3)))])
            results = await asyncio.gather(from_other, from_owner)
            return results[0], results[1], vehicles, dict(owner.stats)
        finally:
            stop.set()
            await asyncio.gather(*running)
            await other.close()
            await owner.close()

    by_other, by_owner, vehicles, counters = asyncio.run(asyncio.wait_for(scenario(), 60))
    assert by_other == [None] and by_owner == [None], (by_other, by_owner)
    for system in (1, 3):
        assert vehicles[system].latitudes() == [round(lat * 1e7) / 1e7 for lat, _ in _points(system)], system
        assert vehicles[system].foreign == 0
    assert counters["split_answers"] >= 2 and counters["split_dropped"] == 0, counters


def _outbound(canonical: dict[str, object]) -> Outbound:
    return Outbound(json.dumps(canonical).encode(), canonical, canonical, uuid.uuid4().hex, {})


def test_a_transactions_lock_is_held_across_the_workers_and_freed_when_its_holder_goes(tmp_path: Path) -> None:
    """``transaction_lock`` of a split link (split_leases.py): worker 1 holds a vehicle's command
    lock, the owner's transaction for the same key waits until worker 1 lets go; then worker 1
    waits for the owner's, and the owner gets it back at once when worker 1's end closes (a
    worker killed while it held a lock does not hold it for good). Another key is never held up."""
    port = free_udp_port()
    settings = {"url": f"udpin:127.0.0.1:{port}", "heartbeat": 0, "split_over_workers": True}
    key = ("command", (3, 1), 400)

    async def scenario() -> list[str]:
        owner = MavlinkConnection("fleet", settings, ConnectionShare(0, 2, 0, str(tmp_path)))
        other = MavlinkConnection("fleet", settings, ConnectionShare(1, 2, 0, str(tmp_path)))
        await owner.open()
        await other.open()
        events: list[str] = []
        try:
            await wait_for(lambda: owner.health()["split"]["connected"] == [1], 10, "worker 1 connected to the owner")
            held, let_go = asyncio.Event(), asyncio.Event()

            def owner_waiting() -> int:
                return int(owner.health()["split"]["locks_waiting"])

            async def worker_one() -> None:
                async with other.transaction_lock(key):
                    events.append("1 holds")
                    held.set()
                    await let_go.wait()
                    events.append("1 lets go")

            async def let_go_once_the_owner_waits() -> None:
                await wait_for(lambda: owner_waiting() == 1, 5, "the owner's claim queued behind worker 1's")
                let_go.set()

            first = asyncio.create_task(worker_one())
            await held.wait()
            async with owner.transaction_lock(("command", (3, 1), 176)):  # another command: not held up
                events.append("0 holds another")
            helper = asyncio.create_task(let_go_once_the_owner_waits())
            async with owner.transaction_lock(key):
                events.append("0 holds")
                waiting = asyncio.create_task(other.transaction_lock(key).__aenter__())
                await wait_for(lambda: owner_waiting() == 1, 5, "worker 1's claim queued behind the owner's")
                events.append(f"1 waits: {not waiting.done()}")
            await asyncio.wait_for(waiting, 5)
            events.append("1 holds again")
            await first
            await helper
            third = asyncio.create_task(owner.transaction_lock(key).__aenter__())
            await wait_for(lambda: owner_waiting() == 1, 5, "the owner's claim queued behind worker 1's")
            events.append(f"0 waits: {not third.done()}")
            await other.close()  # worker 1 goes away holding it
            await asyncio.wait_for(third, 5)
            events.append("0 holds after 1 went away")
        finally:
            await other.close()
            await owner.close()
        return events

    events = asyncio.run(asyncio.wait_for(scenario(), 30))
    assert events == ["1 holds", "0 holds another", "1 lets go", "0 holds", "1 waits: True", "1 holds again", "0 waits: True",
                      "0 holds after 1 went away"], events


@pytest.mark.fast
def test_leases_go_in_order_and_a_late_grant_is_told_from_the_next_request() -> None:
    """The owner's table (split_leases.py ``Leases``) alone: claims are (worker, request)."""
    granted: list[tuple[tuple[int, int], str]] = []
    away: set[int] = set()

    def grant(claim: tuple[int, int], key: str) -> bool:
        if claim[0] in away:
            return False
        granted.append((claim, key))
        return True

    leases = Leases(grant)
    leases.acquire("k", (1, 1))
    leases.acquire("k", (0, 1))
    leases.acquire("k", (2, 1))
    leases.acquire("j", (0, 2))
    assert granted == [((1, 1), "k"), ((0, 2), "j")]
    leases.release("k", (1, 7))  # a stale release of another request: nothing
    assert leases.holder["k"] == (1, 1)
    away.add(0)
    leases.release("k", (1, 1))  # worker 0 is gone: its claim is passed over
    assert granted[-1] == ((2, 1), "k")
    leases.gone(2)
    assert "k" not in leases.holder and "k" not in leases.waiting
    leases.gone(0)
    assert leases.holder == {} and leases.waiting == {}


@contextlib.asynccontextmanager
async def two_workers_hearing_positions(tmp_path: Path, port: int) -> AsyncIterator[dict[int, list[tuple[int, int]]]]:
    """Worker 0 (holding a split ``udpin`` link on ``port``) and worker 1, connected to it; yields
    what each worker's GLOBAL_POSITION_INT listener heard, (system id, time_boot_ms) in order."""
    settings = {"url": f"udpin:127.0.0.1:{port}", "heartbeat": 0, "split_over_workers": True}
    owner = MavlinkConnection("fleet", settings, ConnectionShare(0, 2, 0, str(tmp_path)))
    other = MavlinkConnection("fleet", settings, ConnectionShare(1, 2, 0, str(tmp_path)))
    heard: dict[int, list[tuple[int, int]]] = {0: [], 1: []}

    def note(index: int, msg: Any) -> None:
        heard[index].append((msg.get_srcSystem(), msg.time_boot_ms))

    for index, connection in ((0, owner), (1, other)):
        connection.listen(POSITION, partial(note, index))
    await owner.open()
    await other.open()
    try:
        await wait_for(lambda: owner.health()["split"]["connected"] == [1], 10, "worker 1 connected to the owner")
        yield heard
    finally:
        await other.close()
        await owner.close()


def test_a_datagram_with_frames_of_two_vehicles_is_cut_between_their_workers(tmp_path: Path) -> None:
    """A router may put frames of several systems in one datagram: each frame goes to its own
    system's worker (system 1: worker 0, system 3: worker 1), none twice."""
    import socket

    port = free_udp_port()
    one, three = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1), mavlink2.MAVLink(None, srcSystem=3, srcComponent=1)

    async def scenario() -> dict[int, list[tuple[int, int]]]:
        async with two_workers_hearing_positions(tmp_path, port) as heard:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as router:
                for n in range(5):
                    frames = [mav.global_position_int_encode(n, 0, 0, 0, 0, 0, 0, 0, 0).pack(mav) for mav in (one, three, one)]
                    router.sendto(b"".join(frames), ("127.0.0.1", port))
                await wait_for(lambda: len(heard[0]) == 10 and len(heard[1]) == 5, 10, "every frame at its worker", lambda: heard)
        return heard

    heard = asyncio.run(asyncio.wait_for(scenario(), 30))
    assert heard[0] == [(1, n) for n in range(5) for _ in range(2)], heard
    assert heard[1] == [(3, n) for n in range(5)], heard


def test_junk_before_a_frame_does_not_send_it_to_another_systems_worker(tmp_path: Path) -> None:
    """A datagram whose leading junk reads as a MAVLink 2 header of system 1 (worker 0), whose
    claimed length covers the start of the real frame of system 3 after it: the owner hands it by the frame whose
    CRC holds, to system 3's worker (1); worker 0 gets nothing of it. Before, the false header
    decided, and worker 0's parser then found system 3's frame: a vehicle carried by two workers."""
    import socket

    port = free_udp_port()
    one, three = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1), mavlink2.MAVLink(None, srcSystem=3, srcComponent=1)
    fake = bytes([0xFD, 2, 0, 0, 0, 1, 1, 33, 0, 0])  # v2, 2 bytes of payload, system 1, GLOBAL_POSITION_INT: 14 bytes claimed

    async def scenario() -> dict[int, list[tuple[int, int]]]:
        async with two_workers_hearing_positions(tmp_path, port) as heard:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
                for n in range(5):
                    sender.sendto(fake + three.global_position_int_encode(n, 0, 0, 0, 0, 0, 0, 0, 0).pack(three), ("127.0.0.1", port))
                await wait_for(lambda: len(heard[1]) == 5, 10, "system 3's frames at worker 1", lambda: heard)
                # a clean frame of system 1 after them: worker 0 has had whatever the owner handed it before
                sender.sendto(one.global_position_int_encode(99, 0, 0, 0, 0, 0, 0, 0, 0).pack(one), ("127.0.0.1", port))
                await wait_for(lambda: (1, 99) in heard[0], 10, "system 1's frame at worker 0", lambda: heard)
        return heard

    heard = asyncio.run(asyncio.wait_for(scenario(), 30))
    assert heard[1] == [(3, n) for n in range(5)], heard
    assert heard[0] == [(1, 99)], heard
