"""Zenoh queries answered as calls: a queryable as a route's source, the route's reply its answer.

    source: {zenoh: {key: "farm/{robot}/plan", queryable: true}}
    sink: {amqp: {exchange: plans, routing_key: "plan.{robot}", timeout: 5}}

Each query (a ``get`` whose key intersects the source's key) becomes one request message: its
payload, or when it has none its selector's parameters as a JSON object (``get
farm/r1/plan?depth=3`` gives ``{"depth": "3"}``), with ``meta('key')`` (the query's key),
``meta('parameters')`` (the selector's parameters as written), the key's captures, and a
``reply_to`` of its own (engine/endpoints/base.py, reply contract). The sink's answer, shaped
by the route's ``reply:`` mapping, goes back as the query's reply:

- ``result`` (and ``accepted``, ``feedback``): a reply on the query's key, JSON, its
  attachment naming the kind; ``result`` finalizes the query (the querier's ``get`` ends);
- ``error`` and ``rejected``: an error reply (``ReplyError``) with the JSON error body, final.

A querier that wants feedback asks with ``consolidation: NONE``: Zenoh's default keeps only the
latest reply per key, so it sees the result alone. A query is never left hanging: one the
route's queue drops (overflow), does not settle (the route stops), or dead-letters gets an
error reply; the querier's own ``timeout`` (Zenoh's default 10 s) bounds the rest.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import logging
from typing import Any, Mapping, Sequence

import zenoh

from engine.endpoints.base import FINAL_REPLIES, Deliver, EndpointError, Inbound, Source
from engine.endpoints.pump import pump
from engine.endpoints.zenoh.errors import mapped
from engine.endpoints.zenoh.handoff import Handoff, stop_receiving
from engine.endpoints.zenoh.keys import parse_pattern
from engine.endpoints.zenoh.options import ZenohSourceOptions
from engine.endpoints.zenoh.session import ZenohLink

log = logging.getLogger("engine.zenoh")

BATCH = 256
"""Most queries handed to the route at once (each may wait for its sink's answer)."""
JSON = "application/json"


class QuerySource(Source):
    def __init__(self, connection: ZenohLink, route: str, options: ZenohSourceOptions) -> None:
        self._connection = connection
        self.route = route
        self._where = f"route {route!r}: zenoh queryable {options.key!r}"
        try:
            self.pattern = parse_pattern(options.key)
        except ValueError as exc:
            raise EndpointError(f"{self._where}: {exc}") from None
        self._pending: dict[str, zenoh.Query] = {}
        """Queries waiting for their final reply, by reply_to token."""
        self._serial = itertools.count(1)
        self._handoff: Handoff[Inbound] | None = None
        self._queryable: Any = None
        self._loop: asyncio.Task[None] | None = None
        self.counters = {"queries": 0, "answered": 0, "failed": 0}

    async def start(self, deliver: Deliver) -> None:
        handoff: Handoff[Inbound] = Handoff(asyncio.get_running_loop(), deliver.queue_limit, deliver.overflow,
                                            on_drop=self._dropped)
        self._handoff = handoff

        def on_query(query: zenoh.Query) -> None:  # a Zenoh thread
            token = f"zenoh-query-{next(self._serial)}"
            self._pending[token] = query
            handoff.put(self._inbound(query, token))

        with mapped(f"{self._where}: declare"):
            self._queryable = self._connection.session.declare_queryable(self.pattern.subscription, on_query)
        self._loop = asyncio.create_task(pump(self, deliver, self._where), name=f"zenoh-queryable:{self.route}")

    def _dropped(self, inbound: Inbound) -> None:
        """A query the queue did not take (any thread): answered now, never left to time out."""
        stopping = self._handoff is not None and self._handoff.closed
        self._end(str(inbound.meta["reply_to"]), "the route is stopping" if stopping else "the route's queue is full")

    def _inbound(self, query: zenoh.Query, token: str) -> Inbound:
        key = str(query.key_expr)
        parameters = query.parameters
        meta: dict[str, Any] = {"key": key, "parameters": str(parameters), "reply_to": token, "correlation_id": token}
        meta.update(self.pattern.captured(key))
        payload = query.payload
        if payload is not None:
            meta["encoding"] = str(query.encoding)
            return Inbound(body=payload.to_bytes(), meta=meta)
        pairs = iter(parameters)  # type: ignore[type-var]  # eclipse-zenoh's stub says __iter__ returns a list; it returns an iterator
        return Inbound(body=json.dumps(dict(pairs)).encode(), meta=meta)

    async def read_batch(self) -> list[Inbound]:
        handoff = self._handoff
        assert handoff is not None
        batch = await handoff.take(BATCH)
        self.counters["queries"] += len(batch)
        return batch

    @staticmethod
    def inbounds(batch: Sequence[Inbound]) -> Sequence[Inbound]:
        return batch

    async def settle(self, batch: Sequence[Inbound], settled: list[bool]) -> None:
        """A query the route did not settle (it is stopping) is answered with an error now."""
        for inbound, done in zip(batch, settled):
            if not done:
                self._end(str(inbound.meta["reply_to"]), "not settled (the route is stopping)")

    async def reply(self, meta: Mapping[str, Any], kind: str, body: bytes) -> None:
        token = str(meta["reply_to"])
        query = self._pending.get(token)
        if query is None:
            raise EndpointError(f"{self._where}: the query was answered or ended already")
        final = kind in FINAL_REPLIES
        if final:
            del self._pending[token]
        try:
            with mapped(f"{self._where}: reply"):
                if kind in ("error", "rejected"):
                    query.reply_err(body, encoding=JSON)
                else:
                    query.reply(query.key_expr, body, encoding=JSON, attachment=kind.encode())
        finally:
            if final:
                self._finish(query)
        if final:
            self.counters["answered" if kind == "result" else "failed"] += 1

    def _end(self, token: str, why: str) -> None:
        """Answer the query with an error now (any thread) and finalize it."""
        query = self._pending.pop(token, None)
        if query is None:
            return
        self.counters["failed"] += 1
        try:
            query.reply_err(json.dumps({"kind": "error", "stage": "source", "error": why, "route": self.route}).encode(),
                            encoding=JSON)
        except zenoh.ZError as exc:  # the session closed meanwhile
            log.debug("%s: error reply: %s", self._where, exc)
        self._finish(query)

    @staticmethod
    def _finish(query: zenoh.Query) -> None:
        """Finalize: the querier's ``get`` ends once every queryable it reached let go of its
        query: ``drop()`` where the library has it (1.0 has not: there the last reference going,
        ours, as the caller took it out of ``_pending``, does it)."""
        drop = getattr(query, "drop", None)
        if drop is None:
            return
        try:
            drop()
        except zenoh.ZError:
            pass

    async def stop(self) -> None:
        """Take no more queries (those coming meanwhile get an error reply), undeclare the
        queryable, settle what was queued, and end what is still waiting for an answer."""
        queryable, self._queryable = self._queryable, None
        await stop_receiving(self._handoff, queryable, self._loop, self._where)
        for token in list(self._pending):
            self._end(token, "the route stopped")

    def status(self) -> dict[str, Any]:
        return {"queryable": self.pattern.subscription, "pending": len(self._pending), **self.counters}
