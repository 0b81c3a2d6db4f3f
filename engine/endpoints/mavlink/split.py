"""A ``udpin`` link's vehicles split over the workers of ``run --workers N``
(``split_over_workers: true``): one owner that hands frames on by system id.

One engine process uses one core; a ``udpin`` link carrying a fleet (many system ids on one
socket) was one process's (engine/running/placement.py rule 1), however many workers ran. With
the option, the worker placement gives the link to (its *owner*) holds the UDP socket and every
worker runs the link's routes; each worker is connected to the owner by a local socket
(``AF_UNIX``, ``SOCK_SEQPACKET``: one message per MAVLink datagram, nothing to frame; see
split_sockets.py for why not ``SOCK_DGRAM``) in the supervisor's private runtime
directory. Chosen over the kernel spreading one port over several
sockets (``SO_REUSEPORT``): the kernel hashes the sender's address, so a vehicle's replies and
its telemetry reach the same socket, but a command's sender cannot choose the socket its
vehicle's reply reaches, and a vehicle's address changing (a NAT, a router restarting) would
move it to another worker mid-transaction.

What crosses, and why (each datagram starts with its kind):

* :data:`VEHICLE`, owner to worker: a datagram of a vehicle whose share (engine/common/shares.py,
  ``share_of(str(system_id), N)``) is that worker's, read from the MAVLink headers without
  decoding (framing.py ``frame_headers``). Each vehicle's frames reach exactly one worker, whole
  and in order, which handles them as a single engine does (its telemetry routes, sequence
  gaps, liveness, status and metrics); the owner keeps its own share. A datagram holding frames
  of several systems is cut into frames.
* :data:`PRESENCE`, owner to every other worker: a copy of each HEARTBEAT, which the receiving
  worker only records (who is heard, and when) and reports nowhere: a worker that takes a command
  for a vehicle of another share waits for it and refuses it when it is down as a single engine
  does, while status and metrics report each vehicle from its own worker alone.
* :data:`SEND`, worker to owner: a frame a worker's sink or transaction wrote. The owner decodes
  it and queues it in its own writer, which packs it (so one sequence number stream goes out, as
  from one ground station) and writes it to the address it last heard the target system from, or
  to every peer for a frame with no target, as a single engine does: nothing that reaches a
  vehicle is guessed (an address is learnt only from a frame whose CRC holds, as a single
  engine learns it from the frames it accepts; a damaged header would otherwise send a
  vehicle's commands to another peer until its next frame). Our HEARTBEAT is the owner's alone.
* :data:`ANSWER`, owner to worker: a copy of a vehicle's COMMAND_ACK, MISSION_REQUEST(_INT) or
  MISSION_ACK for every worker that sent that vehicle a command (or a mission frame) in the last
  :data:`TRANSACTION_S`: a command route's source competes on every worker, and the worker that
  took a command for vehicle X waits for X's answer though X's frames are another worker's. The
  copy reaches only the transactions waiting (``listen(answers=True)``), never a route, so a
  telemetry route still carries the answer once, from X's own worker. Each transaction reads
  the answer as a single engine does (a COMMAND_ACK of another command is passed over). A
  transaction's lock (one mission upload, and one command of each kind, per vehicle at a time:
  two COMMAND_ACKs of one command cannot be told apart) is held at the owner for every worker
  (split_leases.py), so two workers taking commands for one vehicle take turns as in one process.

A worker that is down misses its vehicles' frames (counted ``split_dropped`` in the link's
counters: UDP telemetry is lost as over the air); a worker whose owner is down gets
EndpointError for what it sends, so its sinks retry. Not built: signed links (the owner would
hand frames on by headers it has not verified; settings.py refuses them) and JSON tunnel
sinks (their acknowledgements come as TUNNEL frames of the vehicle's worker; checked by the
transport's ``split_problems``).
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass
from collections.abc import Callable, Hashable
from typing import Any

from engine.common.shares import share_of
from engine.endpoints.base import EndpointError
from engine.endpoints.mavlink.dialect import mavlink2
from engine.endpoints.mavlink.framing import crc_holds, frame_headers, tiles
from engine.endpoints.mavlink.links import PEER_TTL, Link, OnBytes, UdpLink
from engine.endpoints.mavlink.settings import Address
from engine.endpoints.mavlink.split_leases import Claim, Leases, lease_message, read_lease
from engine.endpoints.mavlink.split_sockets import OwnerSockets, WorkerSocket, socket_path
from engine.endpoints.workers import ConnectionShare

VEHICLE, PRESENCE, ANSWER, SEND = b"V", b"H", b"A", b"S"
"""The kinds of datagram between the owner and the workers (see the module docstring; a
worker's connection starts with :data:`.split_sockets.HELLO`)."""
LEASE, RELEASE, GRANT, RECLAIM, RECLAIMED = b"L", b"R", b"G", b"C", b"D"
"""A transaction's lock across the workers (split_leases.py): asked, given back, granted; and
a worker's word to an owner started again: still held, and all that it holds said."""
RECLAIM_S = 2.0
"""How long an owner (started, or started again) waits for every worker to say which locks it
holds before it grants any: workers reconnect within a second (:data:`.split_sockets.CONNECT_CAP_S`);
a worker not up by then holds none."""
HEARTBEAT = mavlink2.MAVLINK_MSG_ID_HEARTBEAT
ANSWERS = {mavlink2.MAVLINK_MSG_ID_COMMAND_ACK: "command", mavlink2.MAVLINK_MSG_ID_MISSION_REQUEST: "mission",
           mavlink2.MAVLINK_MSG_ID_MISSION_REQUEST_INT: "mission", mavlink2.MAVLINK_MSG_ID_MISSION_ACK: "mission"}
"""A vehicle's answers, by the transaction they answer."""
REQUESTS = {mavlink2.MAVLINK_MSG_ID_COMMAND_LONG: "command", mavlink2.MAVLINK_MSG_ID_COMMAND_INT: "command",
            mavlink2.MAVLINK_MSG_ID_MISSION_COUNT: "mission", mavlink2.MAVLINK_MSG_ID_MISSION_ITEM: "mission",
            mavlink2.MAVLINK_MSG_ID_MISSION_ITEM_INT: "mission", mavlink2.MAVLINK_MSG_ID_MISSION_CLEAR_ALL: "mission"}
"""What a worker sends that opens (or goes on with) a transaction whose answers it waits for."""
TRANSACTION_S = 60.0
"""How long after a worker's last command (or mission frame) to a vehicle the vehicle's answers
are copied to it: beyond a command's bound with a MAV_RESULT_IN_PROGRESS (in_progress_timeout,
30 s by default). A copy after the transaction ended reaches no listener and costs a datagram."""
SPLIT_STATS = ("split_handed", "split_dropped", "split_answers", "split_lock_conflicts")
"""The owner's counters (the link's, in its status): datagrams handed to other workers, those
a worker could not take (down, starting, its socket full: lost, as UDP telemetry is), and
answers copied to a worker whose transaction waits for them (its own or another's), and locks
a worker said it still held that the owner had granted another meanwhile. A worker's
frames handed to the owner count ``split_sent`` there; the owner counts them ``frames_sent`` once
written, so the merged counters count each frame on the wire once."""
OWNER_PEER = "owner"
"""The peer a worker's frames come from (the owner heard the vehicle's address)."""


@dataclass(frozen=True)
class Unheard:
    """Where a frame for a system the owner has not heard goes: nowhere (:meth:`SplitOwnerLink.peer_for`)."""

    system: int


OnCopy = Callable[[bytes, bytes], None]
"""``(kind, frame)``: a :data:`PRESENCE` or :data:`ANSWER` copy for the connection."""


class SplitOwnerLink(UdpLink):
    """The ``udpin`` socket, held by the link's owner, which hands each vehicle's datagrams to
    its worker and writes what the workers send (see the module docstring)."""

    def __init__(self, address: Address, on_bytes: OnBytes, stats: dict[str, int], name: str, share: ConnectionShare,
                 on_copy: OnCopy, on_send: Callable[[bytes, int], None]) -> None:
        super().__init__(address, on_bytes, stats)
        self.share = share
        self.local = OwnerSockets(socket_path(share.runtime_dir, name), self._from_worker, self._gone)
        self.leases = Leases(self._grant, paused=True)
        self._reclaimed: set[int] = set()
        """The workers that said which locks they hold (see :data:`RECLAIM_S`)."""
        self._resuming: asyncio.TimerHandle | None = None
        self._own_grants: dict[int, asyncio.Future[None]] = {}
        self._requests = 0
        self.on_copy = on_copy
        self.on_send = on_send
        """``(frame, worker)``: a frame a worker wrote, for the owner's writer."""
        self.address_of: dict[int, Any] = {}
        """System id -> the address its last datagram came from (where its frames go)."""
        self.transactions: dict[tuple[int, str], dict[int, float]] = {}
        """(system id, command or mission) -> worker -> until when its answers are copied to it."""
        self._worker_of: dict[int, int] = {}
        for key in SPLIT_STATS:
            stats.setdefault(key, 0)

    def worker_of(self, system: int) -> int:
        worker = self._worker_of.get(system)
        if worker is None:
            worker = self._worker_of[system] = share_of(str(system), self.share.workers)
        return worker

    async def open(self) -> None:
        self.local.open()
        self._resuming = asyncio.get_running_loop().call_later(RECLAIM_S, self.leases.resume)
        try:
            await super().open()
        except BaseException:
            self._resuming.cancel()
            self.local.close()
            raise

    def split_status(self) -> dict[str, Any]:
        """For the connection's status: the workers connected to the owner now, the locks
        held (key -> worker) and how many claims wait for one (split_leases.py)."""
        return {"connected": sorted(self.local.workers),
                "locks": {key: worker for key, (worker, _) in sorted(self.leases.holder.items())},
                "locks_waiting": sum(map(len, self.leases.waiting.values()))}

    def peer_for(self, system: int, heard: dict[int, Hashable]) -> Hashable | None:
        """Every vehicle's address, not only those of the owner's own share; for a vehicle this
        owner has not heard, :class:`Unheard`: the workers may know it still (this owner started
        again meanwhile), and a frame for it must not go to every peer instead."""
        return self.address_of.get(system) or Unheard(system)

    async def transmit(self, data: bytes, peer: Hashable | None = None) -> None:
        if isinstance(peer, Unheard):
            raise EndpointError(f"udpin:{self.address.host}:{self.address.port}: system {peer.system} has not been heard "
                                "by the worker holding the link (started again since?); not written to the other peers")
        await super().transmit(data, peer)

    def received(self, data: bytes, addr: Any) -> None:
        self.heard(addr)
        headers = frame_headers(data)
        if not tiles(headers, len(data)):  # junk beside the frames: only frames whose CRC holds decide the worker
            headers = frame_headers(data, checked=True)
        if not headers:  # no frame at all: the owner's reader counts it
            self.on_bytes(data, addr)
            return
        first = headers[0][2]
        address_of = self.address_of
        for start, end, system, msg_id in headers:  # a damaged header never redirects a vehicle's frames
            if address_of.get(system) != addr and crc_holds(data, start, end, msg_id):
                address_of[system] = addr
        if all(system == first for _, _, system, _ in headers):
            self._hand(self.worker_of(first), VEHICLE, data, addr)
        else:
            for start, end, system, _ in headers:
                self._hand(self.worker_of(system), VEHICLE, data[start:end], addr)
        for start, end, system, msg_id in headers:
            if msg_id == HEARTBEAT:
                own = self.worker_of(system)
                for worker in range(self.share.workers):
                    if worker != own:
                        self._hand(worker, PRESENCE, data[start:end], addr)
            elif (kind := ANSWERS.get(msg_id)) is not None and (waiting := self.transactions.get((system, kind))):
                now, own = time.monotonic(), self.worker_of(system)
                for worker, until in list(waiting.items()):
                    if until < now:
                        del waiting[worker]
                    elif worker != own:
                        self.stats["split_answers"] += 1
                        self._hand(worker, ANSWER, data[start:end], addr)

    def _hand(self, worker: int, kind: bytes, data: bytes, addr: Any) -> None:
        if worker == self.share.index:
            if kind == VEHICLE:
                self.on_bytes(data, addr)
            else:
                self.on_copy(kind, data)
            return
        if self.local.send(worker, kind + data):
            self.stats["split_handed"] += 1
        else:
            self.stats["split_dropped"] += 1

    def opened(self, msg_id: int, target: int, worker: int) -> None:
        """A frame ``worker`` sends to ``target``: a command or mission frame opens (or renews) its
        transaction, whose answers the worker then gets (:data:`TRANSACTION_S`)."""
        kind = REQUESTS.get(msg_id)
        if kind is not None and target:
            self.transactions.setdefault((target, kind), {})[worker] = time.monotonic() + TRANSACTION_S

    def _from_worker(self, worker: int, data: bytes) -> None:
        kind = data[:1]
        if kind == SEND and len(data) > 1:
            self.on_send(data[1:], worker)
        elif kind in (LEASE, RELEASE):
            request, key = read_lease(data)
            (self.leases.acquire if kind == LEASE else self.leases.release)(key, (worker, request))
        elif kind == RECLAIM:
            request, key = read_lease(data)
            if not self.leases.reclaim(key, (worker, request)):
                self.stats["split_lock_conflicts"] += 1
        elif kind == RECLAIMED:
            self._reclaimed.add(worker)
            if self.leases.paused and self._reclaimed >= set(range(self.share.workers)) - {self.share.index}:
                self.leases.resume()

    def _gone(self, worker: int) -> None:
        self.leases.gone(worker)

    def _grant(self, claim: Claim, key: str) -> bool:
        worker, request = claim
        if worker != self.share.index:
            return self.local.send(worker, lease_message(GRANT, request, key), keep=True)
        waiter = self._own_grants.pop(request, None)
        if waiter is None or waiter.done():
            return False
        waiter.set_result(None)
        return True

    async def lease(self, key: str) -> int:
        """The owner's own transactions take their turn with the workers' (split_leases.py)."""
        self._requests += 1
        claim = (self.share.index, self._requests)
        waiter = self._own_grants[claim[1]] = asyncio.get_running_loop().create_future()
        self.leases.acquire(key, claim)
        try:
            await waiter
        except BaseException:
            self._own_grants.pop(claim[1], None)
            self.leases.release(key, claim)
            raise
        return claim[1]

    def unlease(self, key: str, request: int) -> None:
        self.leases.release(key, (self.share.index, request))

    async def close(self) -> None:
        if self._resuming is not None:
            self._resuming.cancel()
        self.local.close()
        await super().close()


class SplitWorkerLink(Link):
    """A worker's side of a split link: its vehicles' datagrams come from the owner, what it
    writes goes to the owner (see the module docstring)."""

    datagrams = True
    relayed = True

    def __init__(self, address: Address, on_bytes: OnBytes, stats: dict[str, int], name: str, share: ConnectionShare,
                 on_copy: OnCopy) -> None:
        super().__init__(address, on_bytes, stats)
        stats.setdefault("split_sent", 0)
        self.share = share
        self.local = WorkerSocket(socket_path(share.runtime_dir, name), share.index, self._from_owner, self._owner_lost,
                                  self._connected)
        self.on_copy = on_copy
        self._heard = -PEER_TTL
        self._grants: dict[int, asyncio.Future[None]] = {}
        self._held: dict[int, str] = {}
        """The locks this worker holds (request -> key), said again to an owner started again."""
        self._requests = 0

    async def open(self) -> None:
        self.local.open()

    def split_status(self) -> dict[str, Any]:
        """For the connection's status: whether this worker is connected to the owner now."""
        return {"connected": self.local.connected is not None}

    @property
    def ready(self) -> bool:
        """Whether the owner handed anything on lately (a vehicle's frame, a HEARTBEAT copy)."""
        return not self.closed and time.monotonic() - self._heard < PEER_TTL

    def _from_owner(self, data: bytes) -> None:
        self._heard = time.monotonic()
        kind, frame = data[:1], data[1:]
        if kind == VEHICLE:
            self.on_bytes(frame, OWNER_PEER)
        elif kind == GRANT:
            request, key = read_lease(data)
            waiter = self._grants.pop(request, None)
            if waiter is None or waiter.done():  # it gave up meanwhile: the next claim may have it
                self.local.send(lease_message(RELEASE, request, key), keep=True)
            else:
                waiter.set_result(None)
        else:
            self.on_copy(kind, frame)

    async def lease(self, key: str) -> int:
        """Wait for the owner's grant of ``key`` (split_leases.py); the request's number."""
        self._requests += 1
        request = self._requests
        waiter = self._grants[request] = asyncio.get_running_loop().create_future()
        if not self.local.send(lease_message(LEASE, request, key), keep=True):
            del self._grants[request]
            raise EndpointError(f"udpin:{self.address.host}:{self.address.port} is held by worker {self.share.owner} "
                                "(split_over_workers), which does not answer now (down or starting)")
        try:
            await waiter
        except BaseException:
            self._grants.pop(request, None)
            self.local.send(lease_message(RELEASE, request, key), keep=True)
            raise
        self._held[request] = key
        return request

    def unlease(self, key: str, request: int) -> None:
        self._held.pop(request, None)
        self.local.send(lease_message(RELEASE, request, key), keep=True)

    def _connected(self) -> None:
        """Connected to an owner (perhaps one started again, which knows nothing of the locks
        this worker holds): the locks held, then that this is all (split_leases.py)."""
        for request, key in self._held.items():
            self.local.send(lease_message(RECLAIM, request, key), keep=True)
        self.local.send(RECLAIMED, keep=True)

    def _owner_lost(self) -> None:
        """What waits for the owner's grant fails: the owner went away (its successor knows nothing of it)."""
        waiting, self._grants = self._grants, {}
        for waiter in waiting.values():
            if not waiter.done():
                waiter.set_exception(EndpointError("the worker holding the split link went away while a transaction "
                                                   "waited for its turn"))

    async def transmit(self, data: bytes, peer: Hashable | None = None) -> None:
        if self.closed:
            raise EndpointError("udp link is closed")
        if not self.local.send(SEND + data):
            raise EndpointError(f"udpin:{self.address.host}:{self.address.port} is held by worker {self.share.owner} "
                                "(split_over_workers), which does not take frames now (down, starting or busy)")

    async def close(self) -> None:
        await super().close()
        await self.local.close()
