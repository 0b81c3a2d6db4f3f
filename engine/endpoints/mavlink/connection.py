"""A MAVLink connection: one link shared by every route that names it.

It runs the link's :class:`~.port.MavlinkPort`, sends our HEARTBEAT (a SiK radio injects
RADIO_STATUS only after one, and a vehicle only talks to a GCS it hears), learns the vehicles it
hears (:attr:`MavlinkConnection.vehicles`), hands TUNNEL frames addressed to us to the JSON
tunnel, and every accepted message to the routes and transactions that subscribed to its type.

Split over the workers of ``run --workers N`` (``split_over_workers``, split.py), a connection
is given its worker's :class:`~engine.endpoints.workers.ConnectionShare`: the owner's link
holds the socket, the others' go through it; each reports only the vehicles of its own share
(liveness, ``vehicles_heard``, per-vehicle metrics), so the supervisor's merged status and
metrics name each vehicle once, from the worker that hears it.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Hashable, Mapping
from contextlib import AbstractAsyncContextManager
from dataclasses import asdict, dataclass
from typing import Any

from engine.common.shares import share_of
from engine.endpoints.base import Connection, ConnectionMetric, EndpointError, MessageRejected, Sink, Source, typed
from engine.endpoints.mavlink.checks import sink_options, source_options
from engine.endpoints.mavlink.codec import MESSAGES, TUNNEL, mavlink2
from engine.endpoints.mavlink.contract import Listener
from engine.endpoints.mavlink.enums import enum_name
from engine.endpoints.mavlink.framing import BAD_FRAME_REASONS, FrameReader
from engine.endpoints.mavlink.links import Link, OnBytes
from engine.endpoints.mavlink.liveness import VehicleLiveness, last_heard, vehicles
from engine.endpoints.mavlink.messages import MessageSource, sink_for
from engine.endpoints.mavlink.options import MavlinkConnectionOptions, MavlinkSinkOptions, MavlinkSourceOptions
from engine.endpoints.mavlink.port import PORT_STATS, MavlinkPort
from engine.endpoints.mavlink.settings import Address, settings_problems
from engine.endpoints.mavlink.split import PRESENCE, SplitOwnerLink, SplitWorkerLink
from engine.endpoints.mavlink.split_leases import SplitLock
from engine.endpoints.mavlink.tunnel import TunnelHub, TunnelSink, TunnelSource
from engine.endpoints.workers import ConnectionShare

HEARTBEAT = mavlink2.MAVLINK_MSG_ID_HEARTBEAT

_STATS = (*PORT_STATS, "not_for_us", "vehicles_heard")
"""Keys of :attr:`MavlinkConnection.stats` (see :data:`.port.PORT_STATS`); ``vehicles_heard``
counts the systems/components whose HEARTBEAT came in. Tunnel counters (``tunnel_sent``,
``tunnel_retransmissions``, ``tunnel_delivered``, ``tunnel_deliver_failed``,
``tunnel_malformed``), mission and command counters appear once used."""

REJECTION_STATS = (*BAD_FRAME_REASONS, "unsigned_rejected", "bad_signature", "replayed", "not_for_us")
"""What the link received and threw away, shown together in the status."""

@dataclass(slots=True)
class VehicleSeen:
    """A MAVLink component heard on the link, from its HEARTBEAT."""

    system_id: int
    component_id: int
    autopilot: str
    type: str
    last_heard: float
    """time.monotonic() of its last HEARTBEAT"""


class MavlinkConnection(Connection):
    """One MAVLink link shared by every route that names it (the
    :class:`~.contract.SharedLink` its route endpoints use)."""

    def __init__(self, name: str, settings: MavlinkConnectionOptions | Mapping[str, Any],
                 share: ConnectionShare | None = None) -> None:
        config, problems = settings_problems(settings)
        if config is None or problems:
            raise EndpointError(f"mavlink connection {name!r}: " + "; ".join(m for _, m in problems))
        super().__init__(name, typed(MavlinkConnectionOptions, settings, f"mavlink connection {name!r}"))
        self.config = config
        self.stats: dict[str, int] = dict.fromkeys(_STATS, 0)
        self.port = MavlinkPort(name, config, self._on_message, self.stats)
        self.hub = TunnelHub(self.port, config.tunnel)
        self.seen: dict[tuple[int, int], VehicleSeen] = {}
        self.agent_names: dict[int, str] = {}
        """System id -> the agent's name (engine/language/agents.py), from the routes' endpoints, for
        naming a vehicle in /healthz, the status and /metrics."""
        self.mission_refs: dict[tuple[int, int], str] = {}
        """Per vehicle, the id of the message whose mission was uploaded last: a MISSION_ACK
        source gives it as ``ref_id`` (MISSION_ACK itself carries no reference)."""
        self._heard: list[asyncio.Future[None]] = []
        self._listeners: dict[int | None, list[Listener]] = {}
        self._from_system: dict[tuple[int | None, int], list[Listener]] = {}
        """Listeners of one vehicle's messages (:meth:`listen` with a ``system_id``)."""
        self._locks: dict[Hashable, asyncio.Lock | SplitLock] = {}
        self._tasks: list[asyncio.Task[None]] = []
        self._answers: dict[int | None, list[Listener]] = {}
        """Listeners of transactions (``listen(answers=True)``), also called for the answers
        the owner of a split link copies to this worker (split.py)."""
        self.split = share if share is not None and config.split_over_workers and share.workers > 1 else None
        """This worker's place on a link split over the workers (split.py), else None."""
        self._owner_link: SplitOwnerLink | None = None
        self._split_end: SplitOwnerLink | SplitWorkerLink | None = None
        self._copies = FrameReader({})
        """Reads the owner's copies; they are counted by the vehicle's own worker."""
        if self.split is not None:
            self.port.make_link = self._split_link

    @property
    def address(self) -> tuple[str, int] | None:
        """Bound (host, port) of ``udpin``/``tcpin`` links; useful with port 0."""
        return self.port.address

    @property
    def signed(self) -> bool:
        return self.config.signing is not None

    @property
    def vehicles(self) -> list[dict[str, Any]]:
        """What the connection has heard, for the status view."""
        return [asdict(seen) for seen in self.seen.values() if self.mine(seen.system_id)]

    def health(self) -> dict[str, Any]:
        """For the status: the link's state, its counters (bad CRC, bad data and signature
        rejections among them; see :data:`.port.PORT_STATS`), the components heard and the
        vehicles' liveness (liveness.py)."""
        now = time.monotonic()
        split = {} if self.split is None else {"split": {
            "worker": self.split.index, "owner": self.split.owner, "workers": self.split.workers,
            **(self._split_end.split_status() if self._split_end is not None else {})}}
        return {
            **split,
            "state": "up" if self.port.ready else "waiting for a peer",
            "rejected": {key: self.stats[key] for key in REJECTION_STATS},
            "counters": dict(self.stats),
            "budget": self.port.budget.status(self.port.clock()),
            "heartbeat_timeout": self.config.heartbeat_timeout,
            "vehicles": [{"system_id": seen.system_id, "component_id": seen.component_id, "type": seen.type,
                          "agent": self.agent_names.get(seen.system_id),
                          "heard_s_ago": round(now - seen.last_heard, 1)}
                         for seen in self.seen.values() if self.mine(seen.system_id)],
            "liveness": [{"system_id": vehicle.system_id, "agent": vehicle.agent, "up": vehicle.up,
                          "heard_s_ago": round(vehicle.heard_s_ago, 1)} for vehicle in self.liveness(now)],
        }

    def liveness(self, now: float | None = None) -> list[VehicleLiveness]:
        """Each vehicle heard on the link, up or down (liveness.py); on a split link, those of
        this worker's share."""
        return vehicles((seen for seen in self.seen.values() if self.mine(seen.system_id)), self.agent_names,
                        self.config.heartbeat_timeout, self.config.source_system, now)

    def mine(self, system: int) -> bool:
        """Whether this worker reports ``system`` (every system, unless the link is split)."""
        return self.split is None or share_of(str(system), self.split.workers) == self.split.index

    def unavailable(self) -> list[str]:
        """The vehicles that are down, each named with how long it has been silent."""
        timeout = self.config.heartbeat_timeout
        return [vehicle.down_reason(timeout) for vehicle in self.liveness() if not vehicle.up]

    def metrics(self) -> list[ConnectionMetric]:
        """For /metrics, from the counters the reading path keeps: the link's frames (accepted,
        bad by reason (framing.py), lost from sequence gaps), what its radio's last RADIO_STATUS
        counted, and per vehicle its liveness and its lost frames."""
        stats = self.stats
        samples = [ConnectionMetric("link_bad_frames", "Received bytes thrown away as a bad frame, per reason",
                                    "counter", stats[reason], (("reason", reason),))
                   for reason in BAD_FRAME_REASONS]
        samples.append(ConnectionMetric("link_frames_accepted", "Frames received whole and accepted (CRC, signing)",
                                        "counter", stats["frames_accepted"]))
        samples.append(ConnectionMetric("link_frames_lost", "Frames missing from the senders' sequence numbers",
                                        "counter", stats["frames_lost"]))
        radio = self.port.budget.last
        if radio is not None:
            samples.append(ConnectionMetric("link_radio_rxerrors", "The SiK radio's RADIO_STATUS rxerrors (its own count, "
                                            "16 bits)", "gauge", radio.rxerrors))
            samples.append(ConnectionMetric("link_radio_fixed", "The SiK radio's RADIO_STATUS fixed: packets its error "
                                            "correction repaired", "gauge", radio.fixed))
        lost = self.port.lost_by_system
        for vehicle in self.liveness():
            labels = (("agent", vehicle.agent or str(vehicle.system_id)), ("system_id", str(vehicle.system_id)))
            samples.append(ConnectionMetric("vehicle_frames_lost", "Frames missing from the vehicle's sequence numbers",
                                            "counter", lost.get(vehicle.system_id, 0), labels))
            samples.append(ConnectionMetric("vehicle_up", "1 while the vehicle's HEARTBEATs come within heartbeat_timeout",
                                            "gauge", 1 if vehicle.up else 0, labels))
            samples.append(ConnectionMetric("vehicle_heard_seconds_ago", "Seconds since the vehicle's last HEARTBEAT",
                                            "gauge", vehicle.heard_s_ago, labels))
        return samples

    async def open(self) -> None:
        await self.port.open()
        if self.config.heartbeat > 0 and (self.split is None or self.split.index == self.split.owner):  # one ground station
            self._tasks.append(asyncio.create_task(self._heartbeat(), name=f"mavlink-heartbeat:{self.name}"))

    async def close(self) -> None:
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks = []
        await self.port.close()

    def _learn_agents(self, agents: Mapping[str, Mapping[str, Any]] | None) -> None:
        for name, entry in (agents or {}).items():
            if isinstance(entry.get("system_id"), int):
                self.agent_names[entry["system_id"]] = name

    def source(self, route: str, options: MavlinkSourceOptions | Mapping[str, Any]) -> Source:
        options = source_options(route, options)
        self._learn_agents(options.agents)
        system_id = options.system_id
        assert not isinstance(system_id, str)  # source_options refused an agent's name the loader did not resolve
        if options.json_tunnel:
            return TunnelSource(self.hub, route=route, payload_type=options.payload_type,
                                system_id=system_id, component_id=options.component_id)
        name = options.message
        return MessageSource(self, route, MESSAGES[name].id if name else None, system_id,
                             options.component_id, options.agents)

    def sink(self, route: str, options: MavlinkSinkOptions | Mapping[str, Any]) -> Sink:
        options = sink_options(route, options)
        self._learn_agents(options.agents)
        if options.json_tunnel:
            target_system, target_component = options.target_system or 0, options.target_component or 0
            assert isinstance(target_system, int) and isinstance(target_component, int)  # sink_options refused a name or {field}
            return TunnelSink(self.hub, payload_type=options.payload_type, target=(target_system, target_component), priority=options.priority,
                              max_age=options.max_age)
        return sink_for(self, route, options)

    # writing

    def enqueue(self, msg: mavlink2.MAVLink_message, *, bulk: bool = False, priority: str | None = None,
                key: Hashable | None = None) -> asyncio.Future[float]:
        self._opening(msg)
        return self.port.enqueue(msg, bulk=bulk, priority=priority, key=key)

    async def send_message(self, msg: mavlink2.MAVLink_message, *, bulk: bool = False,
                           priority: str | None = None) -> float:
        self._opening(msg)
        return await self.port.enqueue(msg, bulk=bulk, priority=priority)

    def post(self, msg: mavlink2.MAVLink_message) -> None:
        self._opening(msg)
        self.port.post(msg)

    def _opening(self, msg: mavlink2.MAVLink_message) -> None:
        """The owner of a split link notes its own commands as it notes the workers' (split.py)."""
        if self._owner_link is not None and self.split is not None:
            self._owner_link.opened(msg.get_msgId(), getattr(msg, "target_system", 0), self.split.index)

    # split over workers (split.py)

    def _split_link(self, address: Address, on_bytes: OnBytes, stats: dict[str, int]) -> Link:
        assert self.split is not None
        if self.split.index == self.split.owner:
            self._owner_link = self._split_end = SplitOwnerLink(address, on_bytes, stats, self.name, self.split, self._on_copy,
                                                                self._sent_by)
        else:
            self._split_end = SplitWorkerLink(address, on_bytes, stats, self.name, self.split, self._on_copy)
        return self._split_end

    def _sent_by(self, frame: bytes, worker: int) -> None:
        """A frame worker ``worker`` wrote: the owner's writer packs and sends it (split.py)."""
        assert self._owner_link is not None
        for msg in self._copies.datagram(frame):
            self._owner_link.opened(msg.get_msgId(), getattr(msg, "target_system", 0), worker)
            self.port.post(msg)

    def _on_copy(self, kind: bytes, frame: bytes) -> None:
        """Another worker's vehicle's HEARTBEAT (who is heard, for commands) or an answer to a
        transaction of this worker (its listeners only, never a route)."""
        for msg in self._copies.datagram(frame):
            msg_id = msg.get_msgId()
            if kind == PRESENCE:
                if msg_id == HEARTBEAT:
                    self._heard_from(msg)
                continue
            for listener in self._answers.get(msg_id, ()):
                listener(msg)

    async def _heartbeat(self) -> None:
        period = 1.0 / self.config.heartbeat
        while True:
            msg = mavlink2.MAVLink_heartbeat_message(self.config.mav_type, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0,
                                                     mavlink2.MAV_STATE_ACTIVE, 3)
            if self.port.ready:
                with contextlib.suppress(EndpointError):
                    await self.port.enqueue(msg)
            await asyncio.sleep(period)

    # reading

    def _on_message(self, msg: mavlink2.MAVLink_message) -> None:
        msg_id = msg.get_msgId()
        if msg_id == TUNNEL:
            if msg.target_system not in (0, self.config.source_system) or \
                    msg.target_component not in (0, self.config.source_component):
                self.stats["not_for_us"] += 1
                return
            header = msg.get_header()
            payload = bytes(msg.payload[:msg.payload_length])
            if self.hub.on_frame(msg.payload_type, (header.srcSystem, header.srcComponent), payload):
                return
        elif msg_id == HEARTBEAT:
            self._heard_from(msg)
        for key in (msg_id, None):
            for listener in self._listeners.get(key, ()):
                listener(msg)
        if self._from_system:
            system = msg.get_header().srcSystem
            for key in ((msg_id, system), (None, system)):
                for listener in self._from_system.get(key, ()):
                    listener(msg)

    def listen(self, msg_id: int | None, listener: Listener, system_id: int | None = None, answers: bool = False) -> None:
        """Call ``listener`` with every accepted message of ``msg_id`` (None: all), from
        vehicle ``system_id`` only when given; ``answers``: a transaction's, which also gets the
        answers a split link's owner copies to this worker (split.py).

        A link carries several vehicles (bench/fleet.py: 7 or 8 per ``udpin`` link), each with
        a route per message it sends: a listener that filtered by sender itself was called for
        every vehicle's message of its type, 8 calls where one is for it."""
        if answers:
            self._answers.setdefault(msg_id, []).append(listener)
        if system_id is None:
            self._listeners.setdefault(msg_id, []).append(listener)
        else:
            self._from_system.setdefault((msg_id, system_id), []).append(listener)

    def unlisten(self, msg_id: int | None, listener: Listener, system_id: int | None = None, answers: bool = False) -> None:
        if answers:
            with contextlib.suppress(KeyError, ValueError):
                self._answers[msg_id].remove(listener)
        with contextlib.suppress(KeyError, ValueError):
            if system_id is None:
                self._listeners[msg_id].remove(listener)
                return
            key = (msg_id, system_id)
            self._from_system[key].remove(listener)
            if not self._from_system[key]:
                del self._from_system[key]

    # presence

    def _heard_from(self, msg: mavlink2.MAVLink_message) -> None:
        header = msg.get_header()
        key = (header.srcSystem, header.srcComponent)
        seen = self.seen.get(key)
        if seen is None:
            self.stats["vehicles_heard"] += self.mine(key[0])
            self.seen[key] = VehicleSeen(key[0], key[1], enum_name("MAV_AUTOPILOT", msg.autopilot),
                                         enum_name("MAV_TYPE", msg.type), time.monotonic())
            waiters, self._heard = self._heard, []
            for waiter in waiters:
                if not waiter.done():
                    waiter.set_result(None)
        else:
            seen.last_heard = time.monotonic()

    def last_heard_text(self, system: int, component: int = 0) -> str:
        """``vehicle 1/1 (uav1)`` with when it was last heard, for a failure's reason:
        ``last heard 0.4 s ago`` or ``never heard (no HEARTBEAT)``."""
        agent = self.agent_names.get(system)
        heard_at = last_heard(self.seen.values(), system, component, self.config.source_system)
        heard = "never heard (no HEARTBEAT)" if heard_at is None else \
            f"last heard {time.monotonic() - heard_at:.1f} s ago"
        return f"vehicle {system}/{component}{f' ({agent})' if agent else ''}, {heard}"

    def has_heard(self, system: int, component: int = 0) -> bool:
        return any(s == system and component in (0, c) for s, c in self.seen)

    async def wait_for_vehicle(self, system: int, component: int, deadline: float) -> None:
        """Return once (system, component) sent a HEARTBEAT (component 0: any of the system);
        EndpointError at ``deadline`` (loop time): a vehicle that is not there yet is transient.
        A vehicle heard before but silent for ``heartbeat_timeout`` is down: MessageRejected at
        once, naming it and when it was last heard, so nothing is sent into the silence and a
        vehicle coming back later never acts on a stale command."""
        heard_at = last_heard(self.seen.values(), system, component, self.config.source_system)
        if heard_at is not None and time.monotonic() - heard_at > self.config.heartbeat_timeout:
            agent = self.agent_names.get(system)
            raise MessageRejected(
                f"mavlink connection {self.name!r}: vehicle {system}/{component}{f' ({agent})' if agent else ''} "
                f"is down: last heard {time.monotonic() - heard_at:.1f} s ago "
                f"(heartbeat_timeout {self.config.heartbeat_timeout:g} s)")
        loop = asyncio.get_running_loop()
        while not self.has_heard(system, component):
            left = deadline - loop.time()
            if left <= 0:
                raise EndpointError(f"mavlink connection {self.name!r}: vehicle {system}/{component} "
                                    "has not been heard (no HEARTBEAT)")
            heard = loop.create_future()
            self._heard = [waiter for waiter in self._heard if not waiter.done()] + [heard]
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(heard, left)

    def transaction_lock(self, key: Hashable) -> AbstractAsyncContextManager[Any]:
        """One mission upload (or command) at a time per target, as the protocols require; on a
        split link, across the workers (split_leases.py)."""
        lock = self._locks.get(key)
        if lock is None:
            lock = self._locks[key] = asyncio.Lock() if self._split_end is None else SplitLock(self._split_end, repr(key))
        return lock
