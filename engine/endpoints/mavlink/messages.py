"""Route endpoints for single MAVLink messages: telemetry in (one type, or all, as field dicts)
and one message out per canonical message; ``sink_for`` picks the transactional sinks (mission
upload, acknowledged commands) where the options ask for them."""

from __future__ import annotations

import asyncio
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from engine.endpoints.base import Deliver, Inbound, Outbound, Sink, Source
from engine.endpoints.mavlink.codec import MESSAGES, build_message, message_fields, mavlink2
from engine.endpoints.mavlink.command import AcknowledgedCommandSink
from engine.endpoints.mavlink.mission import MissionUploadSink
from engine.endpoints.mavlink.transaction import TransactionOptions

if TYPE_CHECKING:
    from engine.endpoints.mavlink.connection import MavlinkConnection

SOURCE_QUEUE = 256
MISSION_ACK = mavlink2.MAVLINK_MSG_ID_MISSION_ACK



class MessageSource(Source):
    """Decoded messages of one type (or all) as field dicts, filtered by sender.

    Telemetry cannot be redelivered, so a slow route drops the oldest queued messages
    (counted as ``source_dropped``) rather than delaying the link for every other route.
    """

    def __init__(self, connection: MavlinkConnection, route: str, msg_id: int | None,
                 system_id: int | None = None, component_id: int | None = None) -> None:
        self.connection = connection
        self.route = route
        self.msg_id = msg_id
        self.system_id = system_id
        self.component_id = component_id
        self._queue: asyncio.Queue[Inbound | None] = asyncio.Queue(SOURCE_QUEUE)
        self._task: asyncio.Task[None] | None = None

    async def start(self, deliver: Deliver) -> None:
        self.connection.listen(self.msg_id, self.offer)
        self._task = asyncio.create_task(self._run(deliver), name=f"mavlink-source:{self.route}")

    async def stop(self) -> None:
        self.connection.unlisten(self.msg_id, self.offer)
        if self._task is None:
            return
        while not self._queue.empty():
            self._queue.get_nowait()
        self._queue.put_nowait(None)
        await asyncio.gather(self._task, return_exceptions=True)
        self._task = None

    def offer(self, msg: mavlink2.MAVLink_message) -> None:
        header = msg.get_header()
        if self.system_id is not None and header.srcSystem != self.system_id:
            return
        if self.component_id is not None and header.srcComponent != self.component_id:
            return
        if self._queue.full():
            self._queue.get_nowait()
            self.connection.stats["source_dropped"] += 1
        buf = msg.get_msgbuf()
        meta = {
            "message": msg.get_type(), "system_id": header.srcSystem, "component_id": header.srcComponent,
            "signed": bool(buf[0] == mavlink2.PROTOCOL_MARKER_V2 and buf[2] & mavlink2.MAVLINK_IFLAG_SIGNED),
        }
        fields = message_fields(msg)
        if self.msg_id == MISSION_ACK:
            ref = self.connection.mission_refs.get((header.srcSystem, header.srcComponent))
            if ref is not None:
                fields["ref_id"] = ref
        self._queue.put_nowait(Inbound(fields=fields, meta=meta))

    async def _run(self, deliver: Deliver) -> None:
        while (inbound := await self._queue.get()) is not None:
            try:
                await deliver(inbound)
            except Exception:
                self.connection.stats["source_dropped"] += 1


class MessageSink(Sink):
    """Encodes ``Outbound.fields`` as one message; accepted once written to the link."""

    def __init__(self, connection: MavlinkConnection, cls: type[mavlink2.MAVLink_message],
                 defaults: Mapping[str, Any]) -> None:
        self.connection = connection
        self.cls = cls
        self.defaults = dict(defaults)

    async def send(self, message: Outbound) -> None:
        await self.connection.send_message(build_message(self.cls, message.fields, self.defaults))



def sink_for(connection: MavlinkConnection, route: str, options: Mapping[str, Any]) -> Sink:
    """The sink the (already checked) options describe."""
    if "mission" in options:
        return MissionUploadSink(connection, TransactionOptions.parse(options)[0])
    cls = MESSAGES[options["message"]]
    if options.get("acknowledged"):
        return AcknowledgedCommandSink(connection, cls, TransactionOptions.parse(options)[0])
    defaults = {key: options[key] for key in ("target_system", "target_component") if key in options}
    return MessageSink(connection, cls, defaults)
