"""Acknowledged command sink: COMMAND_LONG or COMMAND_INT, accepted once the target's COMMAND_ACK
says so.

    sink: {mavlink: {connection: radio, message: COMMAND_LONG, target_system: 1, acknowledged: true}}

Protocol (devguide ``services/command.md``): wait for the COMMAND_ACK of that command from the
target; on silence send again (COMMAND_LONG with ``confirmation`` incremented), ``retries``
times, all within ``command_timeout`` seconds of the route receiving the message
(transaction.py): then the command fails for good (:class:`MessageRejected`, a dead letter)
naming the vehicle and when it was last heard, and it is never sent again: a vehicle that comes
back late does not act on a stale arm. MAV_RESULT_ACCEPTED completes; IN_PROGRESS extends the
wait to ``in_progress_timeout`` for the final ACK; TEMPORARILY_REJECTED sends again after
``retry_delay`` (counted as a retry) until the bound, then is a refusal; any other result
(DENIED, FAILED, UNSUPPORTED, ...) is a refusal at once.

A refusal is an answer (``refusals: reply``, the default): replied like an acceptance,
``{kind: "result", result: "MAV_RESULT_DENIED", command: 400}`` through the route's
``reply.mapping``, and settled :class:`Refused` (counted ``refused``), not dead-lettered: a
caller handles one reply shape, and operator refusals do not fill the dead-letter queue.
``refusals: dead_letter`` keeps it a dead letter (:class:`MessageRejected` naming the result).

As a call (the request asked for replies, engine/running/replies.py): ACCEPTED replies
``{kind: "result", result: "MAV_RESULT_ACCEPTED", command: 400}``, each IN_PROGRESS a
``feedback`` with the ACK's ``progress``; the silence ends in the runner's ``error`` reply.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Sequence
from typing import Any

from engine.endpoints.base import MessageRejected, Outbound, Refused, Reply, Sink
from engine.endpoints.mavlink.codec import mavlink2
from engine.endpoints.mavlink.contract import SharedLink
from engine.endpoints.mavlink.enums import enum_name
from engine.endpoints.mavlink.transaction import Conversation, TransactionOptions, deadline, heard_in_time, per_target

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
        bound = options.give_up_after(connection)
        give_up = deadline(message.received_ns, bound)
        async with connection.transaction_lock(("command", target, msg.command)):
            if loop.time() >= give_up:  # it waited behind the vehicle's previous command that long
                raise self._stale(msg, bound, "not sent: it waited for the previous one to the vehicle")
            if not await heard_in_time(connection, target, options.vehicle_timeout, give_up):
                raise self._stale(msg, bound, "not sent: the vehicle was not heard")
            async with Conversation(connection, target, _ACK) as answers:
                await self._exchange(answers, fields, message.reply, msg, give_up, bound)

    def _stale(self, msg: mavlink2.MAVLink_message, bound: float, what: str) -> MessageRejected:
        """The command given up at its bound: permanent, so it is never sent again."""
        connection = self.connection
        connection.stats["command_timeouts"] = connection.stats.get("command_timeouts", 0) + 1
        return MessageRejected(f"mavlink connection {connection.name!r}: "
                               f"{connection.last_heard_text(msg.target_system, msg.target_component)}: "
                               f"{enum_name('MAV_CMD', msg.command)} {what} within command_timeout {bound:g} s; "
                               "not sent again (a late vehicle must not act on a stale command)")

    async def _refused(self, msg: mavlink2.MAVLink_message, result: int, reply: Reply | None) -> Refused | MessageRejected:
        """The vehicle's refusal: an answer (replied, :class:`Refused`), or with ``refusals:
        dead_letter`` a dead letter naming it."""
        stats = self.connection.stats
        stats["commands_rejected"] = stats.get("commands_rejected", 0) + 1
        name = enum_name("MAV_RESULT", result)
        why = f"vehicle {msg.target_system}/{msg.target_component} refused {enum_name('MAV_CMD', msg.command)}: {name}"
        if self.options.refusals == "dead_letter":
            return MessageRejected(why)
        if reply is not None:
            await reply("result", {"kind": "result", "result": name, "command": msg.command})
        return Refused(why)

    async def _exchange(self, answers: Conversation, fields: Any, reply: Reply | None, msg: mavlink2.MAVLink_message,
                        give_up: float, bound: float) -> None:
        """Send, and send again on silence or TEMPORARILY_REJECTED, until an answer or
        ``give_up`` (loop time); nothing is sent at or after it."""
        connection, options = self.connection, self.options
        stats = connection.stats
        loop = asyncio.get_running_loop()
        timeout = options.answer_timeout(connection)
        await connection.send_message(msg)
        sends, in_progress = 1, False
        wait_until = min(loop.time() + timeout, give_up)
        while True:
            ack = await answers.next(max(0.0, wait_until - loop.time()))
            if ack is not None and ack.command != msg.command:
                continue
            if ack is not None and ack.result == mavlink2.MAV_RESULT_ACCEPTED:
                stats["commands_acknowledged"] = stats.get("commands_acknowledged", 0) + 1
                if reply is not None:
                    await reply("result", {"kind": "result", "result": "MAV_RESULT_ACCEPTED", "command": msg.command})
                return
            if ack is not None and ack.result == mavlink2.MAV_RESULT_IN_PROGRESS:
                in_progress, wait_until = True, loop.time() + options.in_progress_timeout
                if reply is not None:
                    await reply("feedback", {"kind": "feedback", "result": "MAV_RESULT_IN_PROGRESS",
                                             "command": msg.command, "progress": ack.progress})
                continue
            if ack is not None and ack.result != mavlink2.MAV_RESULT_TEMPORARILY_REJECTED:
                raise await self._refused(msg, ack.result, reply)
            if ack is None and loop.time() < wait_until:
                continue
            resend_at = loop.time() + (options.retry_delay if ack is not None else 0.0)
            if sends > options.retries or resend_at >= give_up:
                if ack is not None:  # the vehicle is there, and still says not now
                    raise await self._refused(msg, ack.result, reply)
                if in_progress:
                    stats["command_timeouts"] = stats.get("command_timeouts", 0) + 1
                    raise MessageRejected(f"mavlink connection {connection.name!r}: "
                                          f"{connection.last_heard_text(msg.target_system, msg.target_component)}: "
                                          f"{enum_name('MAV_CMD', msg.command)} was IN_PROGRESS, and no final "
                                          f"COMMAND_ACK came within in_progress_timeout {options.in_progress_timeout:g} s")
                raise self._stale(msg, bound, f"not acknowledged after {sends} send{'s' if sends > 1 else ''}")
            if ack is not None:
                await asyncio.sleep(resend_at - loop.time())
            stats["command_resends"] = stats.get("command_resends", 0) + 1
            msg = self._build(fields, sends)
            await connection.send_message(msg)
            sends += 1
            wait_until = min(loop.time() + timeout, give_up)
