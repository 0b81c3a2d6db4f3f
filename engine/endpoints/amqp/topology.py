"""AMQP topology follows the configuration: what a retired source leaves behind goes.

A source declares its queue and binds it when it starts (engine/endpoints/amqp/source.py). When a
route is removed, or its source replaced (say its ``binding_key`` changed), the broker would
otherwise keep the old binding for ever: messages published with the old key keep flowing,
and a removed route's durable queue fills. So, once the old source has stopped:

* each binding it made that no remaining source of the same connection makes is unbound;
* its queue, when auto-named (``rabbitros.<route>``) and no remaining source consumes it,
  is deleted if empty (a queue still holding messages is kept and reported); a named queue
  is kept, since other programs may share it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Iterable


from engine.endpoints.base import Connection
from engine.endpoints.amqp.errors import LIBRARY_ERRORS
from engine.endpoints.amqp.options import AmqpSourceOptions
from engine.endpoints.amqp.partitions import retire_partitions

log = logging.getLogger("engine.amqp")


@dataclass(frozen=True)
class Binding:
    queue: str
    exchange: str
    key: str


def queue_name(route: str, options: AmqpSourceOptions) -> str:
    return options.queue or f"rabbitros.{route}"


def bindings(route: str, options: AmqpSourceOptions) -> set[Binding]:
    """The bindings an AMQP source with these options makes when it starts."""
    if not options.exchange:
        return set()
    return {Binding(queue_name(route, options), options.exchange, options.binding_key)}


async def retire_source(
    connection: Connection, route: str, options: AmqpSourceOptions, remaining: Iterable[tuple[str, AmqpSourceOptions]]
) -> dict[str, list[str]]:
    """Undo what the stopped source of ``route`` made and no ``remaining`` (route, options)
    source on this connection needs; returns what was done, for the log and tests."""
    remaining = list(remaining)
    factory = getattr(connection, "channel_factory", None)
    if options.partitions > 1 and factory is not None:
        return await retire_partitions(factory, route, options, remaining)
    wanted = set().union(*(bindings(r, o) for r, o in remaining))
    queues_in_use = {queue_name(r, o) for r, o in remaining}
    stale = sorted(bindings(route, options) - wanted, key=lambda b: (b.queue, b.exchange, b.key))
    queue = queue_name(route, options)
    auto_named = not options.queue and queue not in queues_in_use
    done: dict[str, list[str]] = {"unbound": [], "deleted": [], "kept": []}
    if not stale and not auto_named:
        return done
    if factory is None:
        return done
    channel = await factory().channel()
    try:
        for binding in stale:
            try:
                declared = await channel.declare_queue(binding.queue, passive=True)
                await declared.unbind(binding.exchange, binding.key)
                done["unbound"].append(f"{binding.queue} <- {binding.exchange} [{binding.key}]")
            except LIBRARY_ERRORS as exc:  # the queue or exchange is already gone: nothing to undo
                log.info("binding already gone", extra={"route": route, "queue": binding.queue, "error": str(exc)})
                channel = await _fresh(channel, factory)
        if auto_named:
            try:
                declared = await channel.declare_queue(queue, passive=True)
                await declared.delete(if_unused=False, if_empty=True)
                done["deleted"].append(queue)
            except LIBRARY_ERRORS as exc:  # not empty (PRECONDITION_FAILED) or already gone
                done["kept"].append(f"{queue}: {exc}")
                channel = await _fresh(channel, factory)
    finally:
        try:
            await channel.close()
        except LIBRARY_ERRORS:
            pass
    if any(done.values()):
        log.info("amqp topology follows the routes", extra={"route": route, **done})
    return done


async def _fresh(channel: Any, factory: Any) -> Any:
    """A failed passive declare or delete closes the channel (AMQP channel error)."""
    if channel.is_closed:
        return await factory().channel()
    return channel
