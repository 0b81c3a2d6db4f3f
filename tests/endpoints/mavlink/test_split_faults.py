"""A split link's local sockets under faults (engine/endpoints/mavlink/split.py): a worker's
socket full when a lock's grant or release must cross it, a successor owner's socket, the
runtime directory gone.

Real parts: the owner's :class:`MavlinkConnection` (its UDP socket and local socket), a worker's
end played by a plain ``AF_UNIX`` ``SOCK_SEQPACKET`` socket that reads only when the test says
so (a worker busy for a while), UDP datagrams of a vehicle of that worker's share.
"""

from __future__ import annotations

import asyncio
import os
import socket
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from engine.common.shares import share_of
from engine.endpoints.base import EndpointError
from engine.endpoints.mavlink.connection import MavlinkConnection
from engine.endpoints.mavlink.split import GRANT, LEASE, RECLAIMED, RELEASE
from engine.endpoints.mavlink.split_sockets import HELLO, OwnerSockets, socket_path
from engine.endpoints.mavlink.split_leases import lease_message, read_lease
from engine.endpoints.workers import ConnectionShare
from tests.support.udp_vehicle import free_udp_port
from tests.support.waiting import wait_for

pytestmark = pytest.mark.fast

KEY = ("command", (3, 1), 400)


def _settings(port: int) -> dict[str, object]:
    return {"url": f"udpin:127.0.0.1:{port}", "heartbeat": 0, "split_over_workers": True}


async def _fill(owner: MavlinkConnection, port: int, system: int) -> None:
    """Datagrams of ``system`` (worker 1's share) until the owner cannot hand more to worker 1."""
    mav = mavlink2.MAVLink(None, srcSystem=system, srcComponent=1)
    frame = mav.global_position_int_encode(0, 0, 0, 0, 0, 0, 0, 0, 0).pack(mav)
    big = frame * (60000 // len(frame))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as vehicle:
        for _ in range(2000):
            if owner.stats["split_dropped"]:
                return
            handed = owner.stats["split_handed"]
            vehicle.sendto(big, ("127.0.0.1", port))
            await wait_for(lambda: owner.stats["split_handed"] > handed or owner.stats["split_dropped"], 5,
                           "the datagram handed on or dropped")
    raise AssertionError(f"worker 1's socket never filled: {owner.stats}")


async def _read_until(sock: socket.socket, kind: bytes, timeout: float) -> bytes:
    loop = asyncio.get_running_loop()

    async def read() -> bytes:
        while True:
            data = await loop.sock_recv(sock, 65536)
            if not data:
                raise AssertionError("the owner closed the connection")
            if data[:1] == kind:
                return data

    return await asyncio.wait_for(read(), timeout)


def test_a_lock_granted_while_the_workers_socket_is_full_still_reaches_it(tmp_path: Path) -> None:
    """The owner grants worker 1 a vehicle's command lock while worker 1's socket is full of its
    vehicles' frames (busy): the grant must wait for room, not be taken for the worker gone
    (worker 1 would wait for it for good, and the owner would give the lock to the next)."""
    system = next(s for s in range(1, 50) if share_of(str(s), 2) == 1)
    port = free_udp_port()

    async def scenario() -> list[str]:
        owner = MavlinkConnection("fleet", _settings(port), ConnectionShare(0, 2, 0, str(tmp_path)))
        await owner.open()
        worker = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        events: list[str] = []
        try:
            worker.setblocking(False)
            await asyncio.get_running_loop().sock_connect(worker, socket_path(str(tmp_path), "fleet"))
            worker.send(HELLO + (1).to_bytes(2, "big"))
            worker.send(RECLAIMED)  # it holds no lock (the owner grants once every worker said so)
            await wait_for(lambda: owner.health()["split"]["connected"] == [1], 10, "worker 1 connected")
            await _fill(owner, port, system)
            worker.send(lease_message(LEASE, 1, repr(KEY)))
            await wait_for(lambda: owner.health()["split"].get("locks") == {repr(KEY): 1}, 5,
                           "the lock granted to worker 1 (the grant waiting for room)", lambda: owner.health()["split"])
            theirs = asyncio.create_task(owner.transaction_lock(KEY).__aenter__())
            grant = await _read_until(worker, GRANT, 10)  # worker 1 reads again
            events.append(f"granted {read_lease(grant)}")
            events.append(f"owner waits: {not theirs.done()}")
            worker.send(lease_message(RELEASE, 1, repr(KEY)))
            await asyncio.wait_for(theirs, 5)
            events.append("owner holds")
        finally:
            worker.close()
            await owner.close()
        return events

    events = asyncio.run(asyncio.wait_for(scenario(), 60))
    assert events == [f"granted {(1, repr(KEY))}", "owner waits: True", "owner holds"], events


def test_a_release_sent_while_the_owners_socket_is_full_still_reaches_it(tmp_path: Path) -> None:
    """Worker 1 lets go of a lock while its socket to the owner is full (the owner busy, worker
    1's frames waiting): the release must wait for room, or the owner would hold the lock for
    worker 1 and every other worker wait for it for good. The owner is a plain socket here,
    which reads only when the test says so."""
    port = free_udp_port()

    async def scenario() -> bytes:
        loop = asyncio.get_running_loop()
        path = socket_path(str(tmp_path), "fleet")
        listening = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        listening.setblocking(False)
        listening.bind(path)
        listening.listen(4)
        worker = MavlinkConnection("fleet", _settings(port), ConnectionShare(1, 2, 0, str(tmp_path)))
        await worker.open()
        owner: socket.socket | None = None
        try:
            accepted, _ = await asyncio.wait_for(loop.sock_accept(listening), 10)
            owner = accepted  # closed in finally
            accepted.setblocking(False)
            assert await _read_until(accepted, HELLO, 5) == HELLO + (1).to_bytes(2, "big")
            lock = worker.transaction_lock(KEY)
            asking = asyncio.create_task(lock.__aenter__())
            request, key = read_lease(await _read_until(accepted, LEASE, 5))
            accepted.send(lease_message(GRANT, request, key))
            await asyncio.wait_for(asking, 5)
            frame = mavlink2.MAVLink_command_long_message(3, 1, 511, 0, 0, 0, 0, 0, 0, 0, 0)
            for _ in range(100000):  # the owner reads nothing meanwhile: worker 1's socket fills
                try:
                    await worker.send_message(frame)
                except EndpointError:
                    break
            else:
                raise AssertionError("worker 1's socket to the owner never filled")
            await lock.__aexit__(None, None, None)
            return await _read_until(accepted, RELEASE, 10)
        finally:
            if owner is not None:
                owner.close()
            listening.close()
            await worker.close()

    released = asyncio.run(asyncio.wait_for(scenario(), 60))
    assert read_lease(released)[1] == repr(KEY)


def test_a_worker_named_again_frees_what_its_predecessor_held(tmp_path: Path) -> None:
    """A worker's new connection names itself while its predecessor's is still open (started
    again before the owner read the old one's end): what the old one held is freed, as when it
    closes; else the lock stays held by a process that is gone."""
    port = free_udp_port()

    async def scenario() -> None:
        loop = asyncio.get_running_loop()
        path = socket_path(str(tmp_path), "fleet")
        owner = MavlinkConnection("fleet", _settings(port), ConnectionShare(0, 2, 0, str(tmp_path)))
        await owner.open()
        old = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        new = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        try:
            for sock in (old, new):
                sock.setblocking(False)
            await loop.sock_connect(old, path)
            old.send(HELLO + (1).to_bytes(2, "big"))
            old.send(RECLAIMED)
            old.send(lease_message(LEASE, 1, repr(KEY)))
            await _read_until(old, GRANT, 5)
            await loop.sock_connect(new, path)
            new.send(HELLO + (1).to_bytes(2, "big"))
            lock = owner.transaction_lock(KEY)
            await asyncio.wait_for(lock.__aenter__(), 5)
            await lock.__aexit__(None, None, None)
        finally:
            old.close()
            new.close()
            await owner.close()

    asyncio.run(asyncio.wait_for(scenario(), 30))


def test_a_lock_held_across_the_owners_restart_is_granted_to_no_other(tmp_path: Path) -> None:
    """Worker 1 holds a vehicle's command lock (its COMMAND_ACK awaited) when the owner goes away
    and starts again, knowing nothing of it: worker 1 says it still holds it once connected
    again, and the new owner grants it to no other (here its own transaction of the same
    command) before worker 1 lets go; else both would send the command, and one would take the
    other's COMMAND_ACK for its own."""
    port = free_udp_port()

    async def scenario() -> list[str]:
        owner = MavlinkConnection("fleet", _settings(port), ConnectionShare(0, 2, 0, str(tmp_path)))
        other = MavlinkConnection("fleet", _settings(port), ConnectionShare(1, 2, 0, str(tmp_path)))
        await owner.open()
        await other.open()
        events: list[str] = []
        try:
            await wait_for(lambda: owner.health()["split"]["connected"] == [1], 10, "worker 1 connected")
            held = other.transaction_lock(KEY)
            await asyncio.wait_for(held.__aenter__(), 10)
            await owner.close()
            await wait_for(lambda: not other.health()["split"]["connected"], 10, "worker 1 saw the owner go")
            owner = MavlinkConnection("fleet", _settings(port), ConnectionShare(0, 2, 0, str(tmp_path)))  # started again
            await owner.open()
            theirs = asyncio.create_task(owner.transaction_lock(KEY).__aenter__())
            await wait_for(lambda: owner.health()["split"].get("locks") == {repr(KEY): 1}, 10,
                           "worker 1's lock known to the new owner", lambda: owner.health()["split"])
            events.append(f"owner waits: {not theirs.done()}")
            await held.__aexit__(None, None, None)
            await asyncio.wait_for(theirs, 5)
            events.append("owner holds")
        finally:
            await other.close()
            await owner.close()
        return events

    events = asyncio.run(asyncio.wait_for(scenario(), 60))
    assert events == ["owner waits: True", "owner holds"], events


def test_a_frame_for_a_vehicle_the_restarted_owner_has_not_heard_goes_to_no_other_peer(tmp_path: Path) -> None:
    """The owner starts again; worker 1 still knows vehicle 1 (heard before) and commands it
    before vehicle 1 is heard again, while vehicle 3 is: the command must not go to vehicle 3's
    address (nor any other peer's), as the owner's address of vehicle 1 is not known yet."""
    port = free_udp_port()

    async def scenario() -> bytes | None:
        owner = MavlinkConnection("fleet", _settings(port), ConnectionShare(0, 2, 0, str(tmp_path)))
        other = MavlinkConnection("fleet", _settings(port), ConnectionShare(1, 2, 0, str(tmp_path)))
        one, three = (socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2))
        mavs = {one: mavlink2.MAVLink(None, srcSystem=1, srcComponent=1), three: mavlink2.MAVLink(None, srcSystem=3, srcComponent=1)}

        def beat(vehicle: socket.socket) -> None:
            mav = mavs[vehicle]
            vehicle.sendto(mav.heartbeat_encode(2, 3, 0, 0, 4).pack(mav), ("127.0.0.1", port))

        for vehicle in (one, three):
            vehicle.bind(("127.0.0.1", 0))
            vehicle.setblocking(False)
        await owner.open()
        await other.open()
        try:
            await wait_for(lambda: owner.health()["split"]["connected"] == [1], 10, "worker 1 connected")
            beat(one)
            beat(three)
            await wait_for(lambda: other.has_heard(1, 1) and other.has_heard(3, 1), 10, "both vehicles heard by worker 1")
            await owner.close()
            await wait_for(lambda: not other.health()["split"]["connected"], 10, "worker 1 saw the owner go")
            owner = MavlinkConnection("fleet", _settings(port), ConnectionShare(0, 2, 0, str(tmp_path)))  # started again
            await owner.open()
            await wait_for(lambda: owner.health()["split"]["connected"] == [1], 10, "worker 1 connected again")
            beat(three)
            await wait_for(lambda: owner.has_heard(3, 1), 10, "vehicle 3 heard by the new owner")
            before = owner.stats["frames_sent"] + owner.stats["send_errors"]
            await other.send_message(mavlink2.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0))
            await wait_for(lambda: owner.stats["frames_sent"] + owner.stats["send_errors"] > before, 10,
                           "the owner wrote the command or refused it")
            try:
                return three.recv(1024)
            except BlockingIOError:
                return None
        finally:
            one.close()
            three.close()
            await other.close()
            await owner.close()

    assert asyncio.run(asyncio.wait_for(scenario(), 60)) is None


def test_an_owner_closing_leaves_its_successors_socket(tmp_path: Path) -> None:
    """Two owners of one link meet when the owner moves (a reload places it on another worker:
    the new one opens while the old one closes): the one closing last must not unlink the
    socket the other listens on, or no worker could connect again."""

    async def scenario() -> tuple[bool, bool]:
        path = socket_path(str(tmp_path), "fleet")
        old = OwnerSockets(path, lambda worker, data: None, lambda worker: None)
        new = OwnerSockets(path, lambda worker, data: None, lambda worker: None)
        old.open()
        new.open()
        old.close()
        exists = os.path.exists(path)
        with socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET) as worker:
            worker.setblocking(False)
            try:
                await asyncio.get_running_loop().sock_connect(worker, path)
                reached = True
            except OSError:
                reached = False
        new.close()
        return exists, reached

    assert asyncio.run(scenario()) == (True, True)


def test_the_owner_opens_where_the_runtime_directory_was_removed(tmp_path: Path) -> None:
    """The runtime directory removed under a running supervisor (a /tmp cleaner): the owner,
    started again, makes it (private) rather than failing to open for good."""
    runtime = tmp_path / "gone"
    port = free_udp_port()

    async def scenario() -> list[int]:
        owner = MavlinkConnection("fleet", _settings(port), ConnectionShare(0, 2, 0, str(runtime)))
        await owner.open()
        try:
            return [os.stat(runtime).st_mode & 0o777]
        finally:
            await owner.close()

    assert asyncio.run(asyncio.wait_for(scenario(), 30)) == [0o700]
