"""Zenoh sink: each message put on its key, a batch in one worker thread (session.py).

The key may interpolate canonical fields and the source's captures (``farm/{agent_id}/cmd``,
rendered by keys.key_renderer); a message whose fields cannot make a key is refused for good
(MessageRejected: dead-lettered). A message is accepted once the session queued it for
sending: Zenoh's pub/sub has no acknowledgement from subscribers, so what a put promises is
that the session took it (with ``congestion_control: block`` it waits for room rather than
drop it). While the connection has no transport (health ``reconnecting``) the engine holds the
route's messages instead of putting them where nobody listens.
"""

from __future__ import annotations

from typing import Sequence

from engine.endpoints.addressed import send_addressed
from engine.endpoints.base import Outbound, Sink
from engine.endpoints.zenoh.keys import key_renderer
from engine.endpoints.zenoh.options import ZenohSinkOptions
from engine.endpoints.zenoh.session import ZenohLink


class ZenohSink(Sink):
    def __init__(self, connection: ZenohLink, route: str, options: ZenohSinkOptions) -> None:
        self._connection = connection
        self._options = options
        self._where = f"route {route!r}: zenoh sink"
        self._key = key_renderer(options.key, self._where)

    async def send(self, message: Outbound) -> None:
        error = (await self.send_batch((message,)))[0]
        if error is not None:
            raise error

    async def send_batch(self, messages: Sequence[Outbound]) -> list[BaseException | None]:
        return await send_addressed(messages, self._key, self._where, lambda batch: self._connection.put_batch(batch, self._options, self._where))
