"""A batch for sinks that send each message as (address, bytes): an MQTT topic, a Zenoh key.

Both render the address from the message's fields, take the sink mapping's output (or the
canonical bytes when there is none), refuse for good a message whose fields make no address,
and hand the rest to their connection in one call; written once here so the two cannot drift.
"""

from __future__ import annotations

from typing import Any, Awaitable, Callable, Mapping, Sequence

from engine.common.schemas import SchemaError, canonical_bytes
from engine.endpoints.errors import MessageRejected
from engine.endpoints.messages import Outbound

Addressed = list[tuple[str, bytes]]
"""(address, body) per message the connection is to send, in the batch's order."""


async def send_addressed(messages: Sequence[Outbound], address: Callable[[Mapping[str, Any]], str], where: str,
                         send: Callable[[Addressed], Awaitable[Sequence[BaseException | None]]]) -> list[BaseException | None]:
    """One result per message (None: accepted): refused ones as MessageRejected, the others as
    ``send`` answered for them."""
    results: list[BaseException | None] = [None] * len(messages)
    sending: list[int] = []
    batch: Addressed = []
    for index, message in enumerate(messages):
        try:
            to = address(message.template_data)
            body = message.body if message.fields is message.canonical else canonical_bytes(message.fields)  # sink.mapping
        except MessageRejected as exc:
            results[index] = exc
            continue
        except SchemaError as exc:
            results[index] = MessageRejected(f"{where}: {exc}")
            continue
        sending.append(index)
        batch.append((to, body))
    if batch:
        for index, outcome in zip(sending, await send(batch)):
            results[index] = outcome
    return results
