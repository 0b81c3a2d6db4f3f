"""Plain (not robust) channels, opened within a bound.

The engine opens its own channels where aio-pika's robust restore would race it (the publish
channel, the declare channel: engine/endpoints/amqp/link.py; the calls channel:
engine/endpoints/amqp/calls.py) and opens them again itself. aio-pika's
``Channel.initialize(timeout=...)`` ignores its timeout (aio-pika 10.2 calls ``_open()`` without
it), so a broker that never answers Channel.Open (a connection blocked by a resource alarm)
held the opener, and every route queued behind its lock, for ever; the bound is put around
the whole open here instead. (The channels aio-pika's robust connection opens and restores,
the sources', dead letters' and topology's, still open without this bound: left alone.)"""

from __future__ import annotations

import asyncio

import aio_pika
import aio_pika.abc

from engine.endpoints.amqp.errors import ignored

OPEN_TIMEOUT = 10.0
"""Seconds to open a channel (as long as a connection gets: transport.CONNECT_TIMEOUT)."""


async def open_plain_channel(connection: aio_pika.abc.AbstractConnection, *, publisher_confirms: bool,
                             timeout: float = OPEN_TIMEOUT) -> aio_pika.Channel:
    """An open channel of ``connection``; on any failure (``asyncio.TimeoutError`` after
    ``timeout``) the half-open channel is closed (bounded too) and the failure raised."""
    channel = aio_pika.Channel(connection, publisher_confirms=publisher_confirms)
    try:
        await asyncio.wait_for(channel.initialize(), timeout)
    except BaseException:
        with ignored():  # asyncio.TimeoutError is one of the library errors it ignores
            await asyncio.wait_for(channel.close(), 1.0)
        raise
    return channel
