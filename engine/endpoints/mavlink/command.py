"""Acknowledged command sink: COMMAND_LONG or COMMAND_INT, accepted once the target's COMMAND_ACK
says so.

    sink: {mavlink: {connection: radio, message: COMMAND_LONG, target_system: 1, acknowledged: true}}

Protocol (devguide ``services/command.md``): wait for the COMMAND_ACK of that command from the
target; on silence send again (COMMAND_LONG with ``confirmation`` incremented), ``retries``
times, then fail transiently (:class:`EndpointError`). MAV_RESULT_ACCEPTED completes;
IN_PROGRESS extends the wait to ``in_progress_timeout`` for the final ACK;
TEMPORARILY_REJECTED sends again after ``retry_delay`` (counted as a retry); any other result
(DENIED, FAILED, UNSUPPORTED, ...) is permanent: :class:`MessageRejected` naming it.

As a call (the request asked for replies, engine/running/replies.py): ACCEPTED replies
``{kind: "result", result: "MAV_RESULT_ACCEPTED", command: 400}``, each IN_PROGRESS a
``feedback`` with the ACK's ``progress``; a refusal or the silence ends in the runner's
``error`` reply (the silence only once the route's delivery attempts are spent).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Sequence
from typing import Any

from engine.endpoints.base import EndpointError, MessageRejected, Outbound, Reply, Sink
from engine.endpoints.mavlink.codec import mavlink2
from engine.endpoints.mavlink.contract import SharedLink
from engine.endpoints.mavlink.enums import enum_name
from engine.endpoints.mavlink.transaction import Conversation, TransactionOptions, per_target

_ACK = (mavlink2.MAVLINK_MSG_ID_COMMAND_ACK,)
COMMAND_ANSWER = ("kind", "result", "command", "progress")
"""The keys of what an acknowledged command answers a call (its reply mapping's input):
``result`` and ``feedback`` replies (``progress`` only in a ``feedback``); ``check`` knows them."""
Encoder = Callable[[Any], mavlink2.MAVLink_message]
"""The sink mapping's fields -> the message to send (engine/endpoints/mavlink/messages.py
``message_encoder``); raises MessageRejected for what the message cannot carry."""


class AcknowledgedCommandSink(Sink):
    """One command per message, retried until the target acknowledges it."""

    def __init__(self, connection: SharedLink, encode: Encoder, options: TransactionOptions,
                 fields: Callable[[Outbound], Any] | None = None) -> None:
        self.connection = connection
        self.encode = encode
        self.options = options
        self.fields = fields
        """The message's fields with its ``{field}`` targets filled in (messages.targeted_fields)."""

    def _build(self, fields: Any, confirmation: int) -> mavlink2.MAVLink_message:
        msg = self.encode(fields)
        if isinstance(msg, mavlink2.MAVLink_command_long_message):
            msg.confirmation = min(255, msg.confirmation + confirmation)
        return msg

    def target(self, message: Outbound) -> tuple[int, int]:
        """The (system, component) the message's command goes to."""
        msg = self.encode(message.fields if self.fields is None else self.fields(message))
        return msg.target_system, msg.target_component

    async def send_batch(self, messages: Sequence[Outbound]) -> list[BaseException | None]:
        """Commands to several vehicles at once, each vehicle's in order."""
        return await per_target(messages, self.target, self.send)

    async def send(self, message: Outbound) -> None:
        fields = message.fields if self.fields is None else self.fields(message)
        msg = self._build(fields, 0)
        target = (msg.target_system, msg.target_component)
        connection, options = self.connection, self.options
        loop = asyncio.get_running_loop()
        async with connection.transaction_lock(("command", target, msg.command)):
            await connection.wait_for_vehicle(*target, loop.time() + options.vehicle_timeout)
            async with Conversation(connection, target, _ACK) as answers:
                await self._exchange(answers, fields, message.reply, msg)

    async def _exchange(self, answers: Conversation, fields: Any, reply: Reply | None, msg: mavlink2.MAVLink_message) -> None:
        connection, options = self.connection, self.options
        stats = connection.stats
        loop = asyncio.get_running_loop()
        timeout = options.answer_timeout(connection)
        name = enum_name("MAV_CMD", msg.command)
        where = f"vehicle {msg.target_system}/{msg.target_component}"
        await connection.send_message(msg)
        sent, deadline = 0, loop.time() + timeout
        while True:
            ack = await answers.next(max(0.0, deadline - loop.time()))
            if ack is not None and ack.command != msg.command:
                continue
            if ack is not None and ack.result == mavlink2.MAV_RESULT_ACCEPTED:
                stats["commands_acknowledged"] = stats.get("commands_acknowledged", 0) + 1
                if reply is not None:
                    await reply("result", {"kind": "result", "result": "MAV_RESULT_ACCEPTED", "command": msg.command})
                return
            if ack is not None and ack.result == mavlink2.MAV_RESULT_IN_PROGRESS:
                deadline = loop.time() + options.in_progress_timeout
                if reply is not None:
                    await reply("feedback", {"kind": "feedback", "result": "MAV_RESULT_IN_PROGRESS",
                                             "command": msg.command, "progress": ack.progress})
                continue
            if ack is not None and ack.result != mavlink2.MAV_RESULT_TEMPORARILY_REJECTED:
                stats["commands_rejected"] = stats.get("commands_rejected", 0) + 1
                raise MessageRejected(f"{where} refused {name}: {enum_name('MAV_RESULT', ack.result)}")
            if ack is None and loop.time() < deadline:
                continue
            sent += 1
            if sent > options.retries:
                stats["command_timeouts"] = stats.get("command_timeouts", 0) + 1
                why = "kept answering MAV_RESULT_TEMPORARILY_REJECTED" if ack is not None else "did not acknowledge"
                raise EndpointError(f"mavlink connection {connection.name!r}: {where} {why} {name} "
                                    f"after {options.retries} retries")
            if ack is not None:
                await asyncio.sleep(options.retry_delay)
            stats["command_resends"] = stats.get("command_resends", 0) + 1
            msg = self._build(fields, sent)
            await connection.send_message(msg)
            deadline = loop.time() + timeout
