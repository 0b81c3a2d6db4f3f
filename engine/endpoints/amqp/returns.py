"""The broker's returns of ``mandatory`` messages, matched to the publisher's rounds.

A sink publishes mandatory (sink.py says why): a message the exchange routes to no queue comes
back as ``basic.return`` (method, header and body), always before the publisher confirm of
that message, and the confirm (an ack) follows. A return carries no delivery tag, so it is
matched to its message by what it does carry: exchange, routing key, message id and body,
the first such message still unconfirmed in the rounds in flight. Returns come in the order
published, and two messages alike in all four route alike, so which of two such messages is
marked changes nothing. Only rounds with a mandatory message are entered (one dict entry per
round, none per message) and only a return walks them: while messages route, mandatory costs
the publisher nothing but a bit of the frame.

aiormq's own return handler finds the message through a ``message_id`` -> delivery tag table
only its ``basic_publish`` fills (and drops a message without an id); the publisher writes its
frames itself (publisher.py), so :meth:`Returns.watch` installs this handler on its channel,
as the publisher installs its confirm and close handlers.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any, Sequence

import aiormq.abc

log = logging.getLogger("engine.amqp")


class Awaiting:
    """A written round with mandatory messages, until its confirms arrived. ``parts``: the
    publisher's parts (``exchange``, ``messages``, ``mandatory``); ``slots``: (part, message) of
    each payload; ``returned``: payload index -> the broker's reply text (``NO_ROUTE``)."""

    __slots__ = ("confirmations", "parts", "returned", "slots")

    def __init__(self, parts: Sequence[Any], slots: list[tuple[int, int]]) -> None:
        self.parts = parts
        self.slots = slots
        self.confirmations: list[asyncio.Future[Any]] = []
        self.returned: dict[int, str] = {}


class Returns:
    """The rounds in flight with mandatory messages, and the returns matched to them."""

    def __init__(self, connection: str) -> None:
        self._connection = connection
        self._awaiting: dict[int, Awaiting] = {}
        """id -> round, in the order written."""
        self.count = 0
        """Messages the broker returned."""

    def enter(self, parts: Sequence[Any], slots: list[tuple[int, int]],
              confirmations: list[asyncio.Future[Any]] | None = None) -> Awaiting | None:
        """The round, entered where returns are matched when it has a mandatory message
        (its confirmations given now, or set before its frames are queued)."""
        for part in parts:
            if part.mandatory:
                awaiting = Awaiting(parts, slots)
                if confirmations is not None:
                    awaiting.confirmations = confirmations
                self._awaiting[id(awaiting)] = awaiting
                return awaiting
        return None

    def done(self, awaiting: Awaiting | None) -> dict[int, str]:
        """The round's returns (payload index -> reply text); the round leaves the table."""
        if awaiting is None:
            return {}
        self._awaiting.pop(id(awaiting), None)
        return awaiting.returned

    def returned(self, exchange: str, routing_key: str, body: bytes, message_id: str | None, reply_text: str) -> None:
        """Mark the returned message in its round (module docstring)."""
        self.count += 1
        for awaiting in self._awaiting.values():
            confirmations, returned = awaiting.confirmations, awaiting.returned
            for index, (p, m) in enumerate(awaiting.slots):
                part = awaiting.parts[p]
                if not part.mandatory or part.exchange != exchange or index in returned \
                        or index >= len(confirmations) or confirmations[index].done():
                    continue
                key, sent, properties = part.messages[m]
                if key == routing_key and (properties.message_id or None) == message_id and sent == body:
                    returned[index] = reply_text
                    return
        log.warning("the broker returned a message no publish in flight matches",
                    extra={"connection": self._connection, "exchange": exchange, "routing_key": routing_key})

    def watch(self, channel: aiormq.abc.AbstractChannel) -> None:
        """Read the broker's ``basic.return`` on ``channel`` with aiormq 7.2's own ``_get_frame``
        and ``_read_content`` (pinned ~=7.2.4). An aiormq without them keeps its handler:
        mandatory messages are then accepted as before, returned or not."""
        get_frame = getattr(channel, "_get_frame", None)
        read_content = getattr(channel, "_read_content", None)
        if get_frame is None or read_content is None or not hasattr(channel, "_on_return_frame"):
            return

        async def on_return_frame(frame: Any) -> None:
            header = await get_frame()
            message = await read_content(frame, header)
            self.returned(frame.exchange or "", frame.routing_key or "", message.body,
                          message.header.properties.message_id, frame.reply_text or "NO_ROUTE")

        channel._on_return_frame = on_return_frame
