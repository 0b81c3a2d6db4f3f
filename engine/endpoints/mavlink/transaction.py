"""What the mission upload and the acknowledged command share: the answers of one target,
queued while a transaction with it runs, and the typed options of both sinks.

Timeouts suit the link: a SiK radio's TDM round is ~237 ms, so the mission protocol's 250 ms
item timeout would fire on every item; serial links wait 1.5 s per answer (MAVROS: 1 s), networks
0.5 s. A timeout is not an error: the last message is sent again, ``retries`` times.

All of it within ``command_timeout`` seconds (:meth:`TransactionOptions.give_up_after`): a late
vehicle never acts on a stale command. Issue 31: a command to a silent vehicle was answered only
after 16.7 s, about 30 COMMAND_LONGs on the air: each send's retries, and then the route's
delivery attempts sent it all again. Now nothing is sent once the bound has passed, counted from
when the route received the message (a mission: from the vehicle's last answer, as an upload
that progresses is not stale), and the failure is permanent, so the route does not send it again.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable, Hashable, Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar

from engine.common.options import given
from engine.endpoints.base import EndpointError, MessageRejected
from engine.endpoints.mavlink.codec import mavlink2
from engine.endpoints.mavlink.contract import SharedLink

if TYPE_CHECKING:
    from engine.endpoints.mavlink.options import MavlinkSinkOptions

SERIAL_TIMEOUT = 1.5
NETWORK_TIMEOUT = 0.5
REFUSALS = ("reply", "dead_letter")
"""What an acknowledged command sink does with a refusal (DENIED, FAILED, UNSUPPORTED, ...)."""


@dataclass(frozen=True, slots=True)
class TransactionOptions:
    """Sink options of ``mission: upload`` and ``acknowledged: true`` sinks."""

    target_system: int = 1
    target_component: int = 1
    timeout: float | None = None
    """Seconds to wait for each answer before sending again; None: by link kind."""
    retries: int = 5
    vehicle_timeout: float = 10.0
    """How long a transaction waits for a target that has not sent a HEARTBEAT yet."""
    in_progress_timeout: float = 30.0
    """Commands: how long MAV_RESULT_IN_PROGRESS extends the wait for the final COMMAND_ACK."""
    retry_delay: float = 1.0
    """Commands: wait before resending after MAV_RESULT_TEMPORARILY_REJECTED."""
    command_timeout: float | None = None
    """Seconds after which nothing more is sent (see :meth:`give_up_after`); None: by link kind."""
    refusals: str = "reply"
    """Commands: ``reply`` (a refusal is an answer: replied, counted refused) or ``dead_letter``."""
    home_placeholder: bool = False
    mission_type: int = mavlink2.MAV_MISSION_TYPE_MISSION

    @classmethod
    def parse(cls, options: MavlinkSinkOptions) -> tuple[TransactionOptions, list[tuple[str | None, str]]]:
        """The transaction settings a sink's typed options give (what is not given keeps the
        defaults above), with the problems of the values out of range."""
        values: dict[str, Any] = {}
        problems: list[tuple[str | None, str]] = []
        written = given(options)
        for key, kind, low in (("timeout", float, 0.05), ("retries", int, 0), ("vehicle_timeout", float, 0.0),
                               ("in_progress_timeout", float, 0.0), ("retry_delay", float, 0.0),
                               ("command_timeout", float, 0.05),
                               ("target_system", int, 1), ("target_component", int, 0)):
            if key in written:
                value = getattr(options, key)
                if isinstance(value, str):
                    continue  # "{field}": read from each message (messages.targeted_fields)
                if value < low:
                    problems.append((key, f"{key} must be {'an integer' if kind is int else 'a number'} >= {low}"))
                else:
                    values[key] = kind(value)
        if options.refusals is not None:
            if options.refusals not in REFUSALS:
                problems.append(("refusals", f"refusals must be one of {', '.join(REFUSALS)}"))
            else:
                values["refusals"] = options.refusals
        if "home_placeholder" in written:
            values["home_placeholder"] = options.home_placeholder
        if options.mission_type is not None:
            names = {entry.name: value for value, entry in mavlink2.enums["MAV_MISSION_TYPE"].items()}
            value = options.mission_type
            value = names.get(value, names.get(f"MAV_MISSION_TYPE_{str(value).upper()}", value))
            if value not in (0, 1, 2):
                problems.append(("mission_type", "mission_type must be MAV_MISSION_TYPE_MISSION, _FENCE or _RALLY"))
            else:
                values["mission_type"] = value
        return cls(**values), problems

    def answer_timeout(self, connection: SharedLink) -> float:
        if self.timeout is not None:
            return self.timeout
        return SERIAL_TIMEOUT if connection.config.address.kind == "serial" else NETWORK_TIMEOUT

    def give_up_after(self, connection: SharedLink) -> float:
        """Seconds after which a command (or a mission upload without an answer) is given up:
        ``command_timeout``, else every send's wait, ``(retries + 1) x timeout`` (3 s on
        networks, 9 s on serial links with the defaults)."""
        if self.command_timeout is not None:
            return self.command_timeout
        return (self.retries + 1) * self.answer_timeout(connection)

    @property
    def target(self) -> tuple[int, int]:
        return self.target_system, self.target_component


def deadline(received_ns: int | None, seconds: float) -> float:
    """The loop time ``seconds`` after the route received a message (``Outbound.received_ns``,
    monotonic; now where it is not known)."""
    loop_now, now_ns = asyncio.get_running_loop().time(), time.monotonic_ns()
    age = 0.0 if received_ns is None else max(0.0, (now_ns - received_ns) / 1e9)
    return loop_now - age + seconds


async def heard_in_time(connection: SharedLink, target: tuple[int, int], vehicle_timeout: float, give_up: float) -> bool:
    """Wait until the vehicle ``target`` is heard, at most ``vehicle_timeout`` and never past
    ``give_up`` (loop time): True once heard; False when ``give_up`` passed unheard (the caller
    gives the message up, stale). A ``vehicle_timeout`` that ends before ``give_up`` raises the
    link's EndpointError (transient: the route tries again within the bound); a refusal
    (MessageRejected) passes as it is. One step of a command and a mission upload alike."""
    loop = asyncio.get_running_loop()
    try:
        await connection.wait_for_vehicle(*target, min(loop.time() + vehicle_timeout, give_up))
    except MessageRejected:
        raise
    except EndpointError:
        if loop.time() < give_up:
            raise
        return False
    return True


M = TypeVar("M")


async def per_target(messages: Sequence[M], target_of: Callable[[M], Hashable],
                     send: Callable[[M], Awaitable[None]]) -> list[BaseException | None]:
    """``send`` each message, the messages of one target in order and the targets at once: a
    batch of missions (or commands) for three vehicles on one link takes about as long as the
    slowest vehicle's, not the sum (one transaction per target, as the protocols require).
    ``result[i]`` is None once ``messages[i]`` was accepted, else its error; a message whose
    target cannot be read (``target_of`` raised) fails alone."""
    results: list[BaseException | None] = [None] * len(messages)
    groups: dict[Hashable, list[int]] = {}
    for index, message in enumerate(messages):
        try:
            groups.setdefault(target_of(message), []).append(index)
        except Exception as error:  # classified by the engine's delivery policy
            results[index] = error

    async def in_order(indexes: list[int]) -> None:
        for index in indexes:
            try:
                await send(messages[index])
            except Exception as error:
                results[index] = error

    await asyncio.gather(*(in_order(indexes) for indexes in groups.values()))
    return results


class Conversation:
    """Messages of ``msg_ids`` from ``target`` addressed to us (or to everyone), queued while open."""

    def __init__(self, connection: SharedLink, target: tuple[int, int], msg_ids: Iterable[int]) -> None:
        self.connection = connection
        self.target = target
        self.msg_ids = tuple(msg_ids)
        self.queue: asyncio.Queue[Any] = asyncio.Queue()
        self._us = connection.config.source_system

    def _offer(self, msg: Any) -> None:
        header = msg.get_header()
        if header.srcSystem != self.target[0] or self.target[1] not in (0, header.srcComponent):
            return
        if getattr(msg, "target_system", 0) not in (0, self._us):
            return
        self.queue.put_nowait(msg)

    async def __aenter__(self) -> Conversation:
        for msg_id in self.msg_ids:
            self.connection.listen(msg_id, self._offer, answers=True)
        return self

    async def __aexit__(self, *exc: object) -> None:
        for msg_id in self.msg_ids:
            self.connection.unlisten(msg_id, self._offer, answers=True)

    async def next(self, timeout: float) -> Any | None:
        """The next answer, or None after ``timeout`` seconds."""
        try:
            return await asyncio.wait_for(self.queue.get(), timeout)
        except TimeoutError:
            return None
