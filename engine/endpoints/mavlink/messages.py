"""Route endpoints for single MAVLink messages: telemetry in (one type, or all, as field dicts)
and one message out per canonical message; ``sink_for`` picks the transactional sinks (mission
upload, acknowledged commands) where the options ask for them.

What every kind of sink refuses before anything is sent (:func:`field_check`: a field set to
null) and how it builds what it sends (:func:`message_encoder`, :func:`dry_run`) are decided here
once, for the run and for ``rabbitros-engine test`` alike."""

from __future__ import annotations

import asyncio
import functools
import logging
import time
from collections.abc import Callable, Collection, Hashable, Mapping, Sequence
from typing import TYPE_CHECKING, Any

from engine.common.field_keys import slot_key
from engine.common.placeholders import TemplateError, whole_field
from engine.common.suggest import did_you_mean
from engine.endpoints.base import Deliver, Inbound, Inbox, MessageRejected, Outbound, Sink, Source
from engine.endpoints.mavlink.codec import MESSAGES, build_message, message_fields, mavlink2, refuse_nulls
from engine.endpoints.mavlink.command import AcknowledgedCommandSink, Encoder
from engine.endpoints.mavlink.contract import SharedLink
from engine.endpoints.mavlink.mission import MissionUploadSink, Targets, mission_items, mission_target, refuse_unguessed
from engine.endpoints.mavlink.transaction import TransactionOptions
from engine.endpoints.pump import pump

if TYPE_CHECKING:
    from engine.endpoints.mavlink.options import MavlinkSinkOptions

MISSION_ACK = mavlink2.MAVLINK_MSG_ID_MISSION_ACK
BATCH = 1024
"""Most messages handed to the route in one ``Deliver.batch``. A batch waits for its sink
(an AMQP sink: the broker's confirms) before the next one starts, so a backlogged route
carries at most BATCH per confirm round trip: 256 held the engine to ~3,300 msg/s where
the broker's round trip was ~80 ms under load, 1,024 keeps up with the plain pymavlink ->
aiormq reference (bench/throughput.py)."""
STOP_DRAIN = 2.0
"""Seconds :meth:`MessageSource.stop` keeps handing queued telemetry to the route; what is
still queued after that is dropped and counted (a reload must not wait on a stuck sink)."""

log = logging.getLogger(__name__)


class MessageSource(Source):
    """Decoded messages of one type (or all) as field dicts, filtered by sender.

    The link's reader hands messages to the route's bounded inbox (``Deliver.inbox``: one
    queue per agent with ``fair:``) and the engine's read loop (engine/endpoints/pump.py)
    settles them in batches. A radio link cannot be
    paused and telemetry cannot be redelivered, so a full inbox drops: ``drop_newest`` keeps
    what is queued, ``drop_oldest`` keeps the freshest, and ``block`` (the engine's default)
    is treated as ``drop_oldest`` (stalling the reader would stall every route on the link).
    Drops, and messages the route could not settle, are counted with ``Deliver.dropped``.
    """

    def __init__(self, connection: SharedLink, route: str, msg_id: int | None,
                 system_id: int | None = None, component_id: int | None = None,
                 agents: Mapping[str, Mapping[str, Any]] | None = None) -> None:
        self.connection = connection
        self.route = route
        self.agents = {entry["system_id"]: name for name, entry in (agents or {}).items() if "system_id" in entry}
        """System id -> the agent's name (``meta('agent')``), when the route reads it."""
        self.msg_id = msg_id
        self.system_id = system_id
        self.component_id = component_id
        self._inbox: Inbox[Inbound] = Inbox(1)
        self._deliver: Deliver | None = None
        self._task: asyncio.Task[None] | None = None
        self.received = 0
        self.dropped = 0
        self._drop_logged = 0.0

    async def start(self, deliver: Deliver) -> None:
        self._inbox = deliver.inbox("drop_oldest" if deliver.overflow == "block" else deliver.overflow)
        self._deliver = deliver
        self.connection.listen(self.msg_id, self.offer, self.system_id)  # only its vehicle's, when it names one
        self._task = asyncio.create_task(pump(self, deliver, f"mavlink route {self.route!r}"),
                                         name=f"mavlink-source:{self.route}")

    async def stop(self) -> None:
        """Stop listening, hand what is queued to the route (for at most :data:`STOP_DRAIN`
        seconds; the rest is dropped and counted), and return once the last batch settled."""
        self.connection.unlisten(self.msg_id, self.offer, self.system_id)
        task, self._task = self._task, None
        if task is None:
            return
        self._inbox.close()
        done, _ = await asyncio.wait({task}, timeout=STOP_DRAIN)
        if not done:
            left = self._inbox.clear()
            if left:
                self._count_dropped(left)
                log.warning("mavlink route %r: stopped with %d messages queued; dropped", self.route, left)
            await asyncio.gather(task, return_exceptions=True)

    def status(self) -> dict[str, Any]:
        return {"received": self.received, "dropped": self.dropped, "queued": len(self._inbox),
                "overflow": self._inbox.overflow}

    def offer(self, msg: mavlink2.MAVLink_message) -> None:
        header = msg.get_header()
        if self.system_id is not None and header.srcSystem != self.system_id:
            return
        if self.component_id is not None and header.srcComponent != self.component_id:
            return
        if self._inbox.closed:
            return
        self.received += 1
        buf = msg.get_msgbuf()
        meta = {
            "message": msg.get_type(), "system_id": header.srcSystem, "component_id": header.srcComponent,
            "connection": self.connection.name,
            "signed": bool(buf[0] == mavlink2.PROTOCOL_MARKER_V2 and buf[2] & mavlink2.MAVLINK_IFLAG_SIGNED),
        }
        if self.agents:
            meta["agent"] = self.agents.get(header.srcSystem)
        fields = message_fields(msg)
        if self.msg_id == MISSION_ACK:
            ref = self.connection.mission_refs.get((header.srcSystem, header.srcComponent))
            if ref is not None:
                fields["ref_id"] = ref
        if self._inbox.offer(Inbound(fields=fields, meta=meta)):
            self._count_dropped(1)
        self._inbox.wake()

    def _count_dropped(self, count: int) -> None:
        self.dropped += count
        if self._deliver is not None:
            self._deliver.dropped(count)
        now = time.monotonic()
        if now - self._drop_logged >= 10.0:
            self._drop_logged = now
            log.warning("mavlink route %r: queue full (%d, overflow %s), dropped %d messages so far",
                        self.route, self._inbox.limit, self._inbox.overflow, self.dropped)

    async def read_batch(self) -> list[Inbound]:
        """What the link's reader queued, up to :data:`BATCH`."""
        return await self._inbox.take(BATCH)

    def inbounds(self, batch: Sequence[Inbound]) -> Sequence[Inbound]:
        return batch

    async def settle(self, batch: Sequence[Inbound], settled: list[bool]) -> None:
        """Telemetry cannot be redelivered: what the route did not settle is counted lost."""
        lost = settled.count(False)
        if lost:
            self._count_dropped(lost)
        if len(self._inbox):  # a backlog must not hold the loop from other routes; an empty inbox waits in take()
            await asyncio.sleep(0)  # (at a robot's pace a yield per message is a loop round trip for nothing)


class MessageSink(Sink):
    """Encodes ``Outbound.fields`` as one message; accepted once written to the link.

    A batch is queued at once, so the link's writer holds what does not fit the radio's
    budget (engine/endpoints/mavlink/budget.py); for a telemetry route (``latest_per``: its
    ``buffer.latest_only`` key) a waiting message is replaced by a newer one with the same key
    and reported :class:`~engine.endpoints.base.Conflated`."""

    def __init__(self, connection: SharedLink, encode: Encoder, priority: str = "normal",
                 fields: Callable[[Outbound], Any] | None = None, latest_per: tuple[str, ...] | None = None) -> None:
        self.connection = connection
        self.encode = encode
        self.priority = priority
        """The route's ``priority``: the link's writer sends by it (engine/endpoints/mavlink/port.py)."""
        self.fields = fields or _sink_fields
        self.latest_per = latest_per

    def _key(self, message: Outbound) -> Hashable | None:
        return None if self.latest_per is None else (id(self), slot_key(message.canonical, self.latest_per))

    async def send(self, message: Outbound) -> None:
        await self.connection.enqueue(self.encode(self.fields(message)), priority=self.priority, key=self._key(message))

    async def send_batch(self, messages: Sequence[Outbound]) -> list[BaseException | None]:
        queued: list[asyncio.Future[float] | BaseException] = []
        for message in messages:
            try:
                queued.append(self.connection.enqueue(self.encode(self.fields(message)), priority=self.priority,
                                                      key=self._key(message)))
            except Exception as error:  # refused before anything was queued: MessageRejected
                queued.append(error)
        results: list[BaseException | None] = []
        for item in queued:
            if isinstance(item, BaseException):
                results.append(item)
                continue
            try:
                await item
            except Exception as error:  # Conflated, or the link's EndpointError
                results.append(error)
            else:
                results.append(None)
        return results


def _sink_fields(message: Outbound) -> Any:
    return message.fields


def sink_for(connection: SharedLink, route: str, options: MavlinkSinkOptions) -> Sink:
    """The sink the (already checked) options describe."""
    if options.mission is not None:
        return MissionUploadSink(connection, TransactionOptions.parse(options)[0], message_targets(options))
    if options.acknowledged:
        return AcknowledgedCommandSink(connection, message_encoder(options), TransactionOptions.parse(options)[0],
                                       fields=targeted_fields(options))
    return MessageSink(connection, message_encoder(options), options.priority, targeted_fields(options),
                       options.latest_per)


def target_fields(options: MavlinkSinkOptions) -> list[tuple[str, str]]:
    """``(target key, canonical field path)`` of each target a sink reads from the message
    (``target_system: "{vehicle}"``), read by the engine's one template grammar; a value it
    refuses is left out here and reported by ``check`` (checks.py)."""
    fields = []
    for key in ("target_system", "target_component"):
        value = getattr(options, key)
        if isinstance(value, str) and value.startswith("{"):
            try:
                fields.append((key, ".".join(whole_field(value, key))))
            except TemplateError:
                continue
    return fields


def message_targets(options: MavlinkSinkOptions) -> Targets | None:
    """How a sink with ``{field}`` targets reads each message's receiver from its canonical
    message (the one vehicle the message names): a missing field, or a value that is no system
    or component id (an integer 0-255), is refused (MessageRejected, stage ``sink``), never
    guessed. Keys in ``skip`` are not read (the sink mapping names them itself). None: no
    target is read from the message (nothing to do per message)."""
    targets = [(key, tuple(path.split("."))) for key, path in target_fields(options)]
    if not targets:
        return None
    agents = options.agents or {}
    ids = {key: {name: entry[entry_key] for name, entry in agents.items() if entry_key in entry}
           for key, entry_key in AGENT_IDS.items()}

    def read(message: Outbound, skip: Collection[str] = ()) -> dict[str, int]:
        out: dict[str, int] = {}
        for key, path in targets:
            if key in skip:
                continue
            value = message.canonical
            for step in path:
                if not isinstance(value, dict) or step not in value:
                    raise MessageRejected(f"{key}: the canonical message has no field {'.'.join(path)!r}")
                value = value[step]
            if isinstance(value, str) and agents:
                value = _agent_id(key, path, value, ids[key])
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 255:
                raise MessageRejected(f"{key}: field {'.'.join(path)!r} is {value!r}, not a MAVLink id (an integer 0-255)"
                                      + (" nor an agent's name" if agents else ""))
            out[key] = value
        return out

    return read


AGENT_IDS = {"target_system": "system_id", "target_component": "component_id"}
"""The agent entry's key that gives each target, for a ``{field}`` holding an agent's name."""


def _agent_id(key: str, path: tuple[str, ...], name: str, ids: dict[str, Any]) -> Any:
    """The id of the agent ``name`` for target ``key``; a name the table (on this connection)
    does not hold is refused naming the field, never sent to a guessed vehicle."""
    if name in ids:
        return ids[name]
    known = ", ".join(ids) or "none"
    raise MessageRejected(f"{key}: field {'.'.join(path)!r} is {name!r}, which is no agent on this connection with "
                          f"a {AGENT_IDS[key]}{did_you_mean(name, ids) or f' (agents: {known})'}")


def targeted_fields(options: MavlinkSinkOptions) -> Callable[[Outbound], Any] | None:
    """How a message or command sink with ``{field}`` targets gets its message's fields: the
    sink mapping's output with each target the mapping leaves out read from the canonical
    message (:func:`message_targets`). None: no target is read from the message."""
    targets = message_targets(options)
    if targets is None:
        return None

    def fields(message: Outbound) -> Any:
        out = dict(message.fields)
        out.update(targets(message, skip=out))
        return out

    return fields


def message_encoder(options: MavlinkSinkOptions) -> Encoder:
    """How a message sink (plain or acknowledged) builds its message from the sink mapping's
    fields: the target fields the mapping leaves out come from the sink's options (an
    acknowledged command's default to 1/1, the vehicle that acknowledges), the rest are 0."""
    if options.acknowledged:
        transaction = TransactionOptions.parse(options)[0]
        defaults = {"target_system": transaction.target_system, "target_component": transaction.target_component}
    else:
        defaults = message_defaults(options)
    name = options.message
    assert name is not None  # a message sink names its message (checks.sink_problems)
    return functools.partial(build_message, MESSAGES[name], defaults=defaults)


def message_defaults(options: MavlinkSinkOptions) -> dict[str, int]:
    """The target fields a message sink fills in when the mapping does not (a ``{field}``
    target is read from each message: :func:`targeted_fields`)."""
    return {key: value for key in ("target_system", "target_component") if isinstance(value := getattr(options, key), int)}


def field_check(options: MavlinkSinkOptions) -> Callable[[Any], None] | None:
    """What the sink refuses in the sink mapping's output before anything is sent: a field set
    to null, and for a mission a waypoint without exactly one altitude (MessageRejected naming
    it; the pipeline reports it at its ``sink mapping`` stage). A JSON tunnel carries JSON,
    where null is a value like any other: nothing to refuse."""
    if options.json_tunnel:
        return None
    if options.mission is not None:
        return refuse_unguessed
    name = options.message
    assert name is not None  # a message sink names its message (checks.sink_problems)
    return functools.partial(refuse_nulls, name)


def dry_run(options: MavlinkSinkOptions) -> Callable[[Outbound], object]:
    """What the sink would send for a message, built and thrown away (``rabbitros-engine
    test``): raises MessageRejected where the sink would. A JSON tunnel sends the canonical JSON
    as it is."""
    if options.json_tunnel:
        return lambda outbound: None
    if options.mission is not None:
        transaction = TransactionOptions.parse(options)[0]
        targets = message_targets(options)
        return lambda outbound: mission_items(outbound.fields, transaction, mission_target(transaction, targets, outbound))
    encode = message_encoder(options)
    fields_of = targeted_fields(options) or _sink_fields
    return lambda outbound: encode(fields_of(outbound))
