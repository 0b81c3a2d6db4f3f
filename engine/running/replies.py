"""A route's replies: what a sink answers to a request goes back to the request's sender.

The reply path of the endpoint contract (engine/endpoints/base.py): a source that can answer
puts ``reply_to`` in a message's meta; the runner binds each converted message to a
:class:`ReplyTo` (its ``Outbound.reply``); the sink calls it with the answer; the answer is
shaped here by the route's ``reply: {mapping, schema}`` (compiled once, at load) and handed to
the source that received the request (``Source.reply``). A request that is dead-lettered gets
one ``error`` reply ``{kind: "error", stage, error, route}``, never passed through the mapping
(its input would not be the sink's answer), so no caller waits forever.

Per request: one small object and, per reply, one mapping, one validation and one publish. A
reply after the final one (``result``, ``rejected`` or ``error``: a late answer after a
timeout) is dropped and counted, as is one the source could not deliver; a reply to a request
that asked for none is only counted (fire-and-forget). Nothing is logged per reply: a
:class:`~engine.common.logs.ReportLimiter` reports failures at most once per second per route.
"""

from __future__ import annotations

import logging
from typing import Any, Mapping

from engine.common.logs import ReportLimiter
from engine.common.placeholders import MappingError
from engine.common.schemas import CanonicalSchema, SchemaError, canonical_bytes
from engine.endpoints.base import FINAL_REPLIES, REPLY_KINDS, EndpointError, Reply, Source
from engine.language.mapping import Mapper, compile_mapping
from engine.language.stage_options import ReplyOptions

log = logging.getLogger("engine.running.runtime")


class ReplyShape:
    """The route's reply mapping and schema, compiled once per pipeline generation."""

    def __init__(self, options: ReplyOptions | None, schema: CanonicalSchema | None) -> None:
        self.mapper: Mapper | None = compile_mapping(options.mapping) if options is not None else None
        self.schema = schema

    def body(self, data: Any) -> bytes:
        """The reply body; raise ReplyFailed naming the stage that refused it."""
        if self.mapper is not None:
            try:
                data = self.mapper(data)
            except MappingError as exc:
                raise ReplyFailed("reply mapping", str(exc)) from None
        try:
            if self.schema is not None:
                self.schema.validate(data)
            return canonical_bytes(data)
        except SchemaError as exc:
            raise ReplyFailed("reply schema", str(exc)) from None


class ReplyFailed(Exception):
    def __init__(self, stage: str, error: str) -> None:
        super().__init__(error)
        self.stage = stage
        self.error = error


class Replies:
    """One route's reply counters and its way back to the source (kept per runner)."""

    def __init__(self, route: str, source: Source) -> None:
        self.route = route
        self.source = source
        self.sent = 0
        """Replies handed to the source (every kind, errors included)."""
        self.errors = 0
        """``error`` replies among them."""
        self.unrequested = 0
        """Answers to requests that asked for no reply (fire-and-forget): counted, not sent."""
        self.late = 0
        """Replies after the request's final one (a late answer after a timeout): dropped."""
        self.undelivered = 0
        """Replies the source could not hand over (its connection down): dropped."""
        self._report = ReportLimiter()
        self._unrequested = Unrequested(self)

    def bind(self, shape: ReplyShape, meta: Mapping[str, Any]) -> Reply:
        """``Outbound.reply`` for a message with this meta: a :class:`ReplyTo` when it asks for
        replies, else the route's one :class:`Unrequested` (no object per message)."""
        if meta.get("reply_to"):
            return ReplyTo(self, shape, meta)
        return self._unrequested

    async def failed(self, reply: Any, meta: Mapping[str, Any], stage: str, error: str) -> None:
        """The request ended in a dead letter: its one ``error`` reply (unless a final reply
        went already, or it asked for none)."""
        if isinstance(reply, ReplyTo):
            await reply("error", {"stage": stage, "error": error})
        elif meta.get("reply_to"):  # failed before it was converted: no ReplyTo yet
            await self.deliver(meta, "error", self.error_body(stage, error))

    def error_body(self, stage: str, error: str) -> bytes:
        return canonical_bytes({"kind": "error", "stage": stage, "error": error[:2000], "route": self.route})

    async def deliver(self, meta: Mapping[str, Any], kind: str, body: bytes) -> None:
        try:
            await self.source.reply(meta, kind, body)
        except EndpointError as exc:
            self.undelivered += 1
            if self._report.ready():
                log.warning("reply not delivered", extra={"route": self.route, "kind": kind, "error": str(exc),
                                                          "suppressed": self._report.take_suppressed()})
            return
        self.sent += 1
        if kind == "error":
            self.errors += 1

    def counters(self) -> dict[str, int]:
        return {"sent": self.sent, "errors": self.errors, "unrequested": self.unrequested,
                "late": self.late, "undelivered": self.undelivered}


class Unrequested:
    """The ``Outbound.reply`` of every request of a route that asked for no reply: counts."""

    __slots__ = ("replies",)

    def __init__(self, replies: Replies) -> None:
        self.replies = replies

    async def __call__(self, kind: str, data: Any) -> None:
        self.replies.unrequested += 1

    def late(self) -> None:
        self.replies.late += 1


class ReplyTo:
    """The replies of one request (its ``Outbound.reply``): shaped, then delivered in order
    by the caller's awaiting; none after the final one."""

    __slots__ = ("replies", "shape", "meta", "finished")

    def __init__(self, replies: Replies, shape: ReplyShape, meta: Mapping[str, Any]) -> None:
        self.replies = replies
        self.shape = shape
        self.meta = meta
        self.finished = False

    def late(self) -> None:
        self.replies.late += 1

    async def __call__(self, kind: str, data: Any) -> None:
        replies = self.replies
        if self.finished:
            replies.late += 1
            return
        assert kind in REPLY_KINDS, kind
        if kind in FINAL_REPLIES:
            self.finished = True
        if kind == "error":
            body = replies.error_body(str(data.get("stage", "sink")), str(data.get("error", "")))
        else:
            try:
                body = self.shape.body(data)
            except ReplyFailed as exc:
                self.finished = True
                kind, body = "error", replies.error_body(exc.stage, exc.error)
        await replies.deliver(self.meta, kind, body)
