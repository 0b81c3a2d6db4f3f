"""A route's messages that end without being sent: dead letters stored together at the end
of a batch (stage 5 of engine/running/runner.py), the rate-limited reports of failures, and
the one ``error`` reply a caller gets when its request ends unsent (dead-lettered, expired
under ``max_age``, conflated).

Off the per-message path: the runner reaches it only for messages that failed or expired.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from engine.common.logs import ReportLimiter
from engine.endpoints.base import EndpointError, Inbound, Outbound
from engine.running.dead_letters import dead_letter_message
from engine.running.delivery import Failure
from engine.running.route_state import Dead, RunningRoute

log = logging.getLogger("engine.running.runtime")


class DeadLettering:
    """The dead letters and ended calls of one route (its runner's, read through ``route``)."""

    def __init__(self, route: RunningRoute) -> None:
        self.route = route
        self._report = ReportLimiter()
        self._retry_report = ReportLimiter()
        self._replying: set[asyncio.Task[None]] = set()
        """Error replies to calls settled without being sent (expired, conflated), on their way."""

    async def store(self, dead: list[Dead], settled: list[bool]) -> None:
        """Store the batch's dead letters together; each is settled once stored."""
        dead.sort(key=lambda message: message.index)
        route = self.route
        spec, host, observer = route.spec, route.host, route.observer
        limit = spec.delivery.max_message_bytes
        letters = [dead_letter_message(spec.name, f"{spec.file}:{spec.line}", m.inbound, m.failure, m.attempts, limit)
                   for m in dead]
        try:
            assert host.dead_letters is not None
            await host.dead_letters.put(spec.name, letters)
        except EndpointError as error:
            observer.dead_letter_errors += len(dead)
            self.report_failure(Failure("dead-letter", str(error), False))
            return
        for message in dead:
            settled[message.index] = True
            failure = message.failure
            observer.dead_letter(message.inbound, message.outbound, failure.stage, failure.error)
            remember = message.pipeline.remember
            if remember is not None:
                if message.outbound is not None:
                    remember.on_failed(message.outbound.canonical, message.outbound.meta, f"{failure.stage}: {failure.error}")
                elif message.canonical is not None:  # refused after its mapping (schema, when:, sink mapping)
                    remember.on_failed(message.canonical, message.inbound.meta, f"{failure.stage}: {failure.error}")
        self.report_failure(dead[-1].failure, len(dead))
        calls = [m for m in dead if m.inbound.meta.get("reply_to")]
        if calls:  # each request that failed for good: its caller gets one error reply, published together
            await asyncio.gather(*(route.replies.failed(m.outbound.reply if m.outbound is not None else None,
                                                        m.inbound.meta, m.failure.stage, m.failure.error)
                                   for m in calls))

    def report_retry(self, failure: Failure, count: int) -> None:
        if self._retry_report.ready():
            log.warning(
                "sink failed; retrying with backoff",
                extra={"route": self.route.spec.name, "error": failure.error, "messages": count,
                       "suppressed": self._retry_report.take_suppressed()},
            )

    def report_failure(self, failure: Failure, count: int = 1) -> None:
        if self._report.ready():
            spec = self.route.spec
            log.warning(
                "message dead-lettered" if failure.stage != "dead-letter" else "dead letters could not be stored",
                extra={
                    "route": spec.name,
                    "file": f"{spec.file}:{spec.line}",
                    "stage": failure.stage,
                    "error": failure.error[:500],
                    "messages": count,
                    "suppressed": self._report.take_suppressed(),
                },
            )

    def expired_call(self, outbound: Outbound) -> None:
        max_age_ns = self.route.spec.delivery.max_age_ns
        assert max_age_ns is not None  # only a route with a max_age expires messages (too_old)
        age = f"older than the route's max_age ({max_age_ns / 1e9:g} s) before it could be sent"
        self.ended_call(outbound, "max_age", age)

    def ended_call(self, outbound: Outbound, stage: str, error: str) -> None:
        """A request settled without being sent and without a dead letter (expired under
        ``max_age``, conflated by the throttle or ``latest_only``): its caller still hears the
        end, one ``error`` reply naming the stage, sent beside the route's work."""
        if not outbound.meta.get("reply_to"):
            return
        task = asyncio.create_task(self.route.replies.failed(self.reply_of(outbound), outbound.meta, stage, error))
        self._replying.add(task)
        task.add_done_callback(self._replying.discard)

    def filtered_call(self, inbound: Inbound) -> None:
        """A request the route's ``when:`` rejected: its caller hears one ``error`` reply."""
        if inbound.meta.get("reply_to"):
            task = asyncio.create_task(self.route.replies.failed(None, inbound.meta, "when", "filtered: the route's when: condition is false"))
            self._replying.add(task)
            task.add_done_callback(self._replying.discard)

    def reply_of(self, outbound: Outbound) -> Any:
        """The reply of a held message: a message read back from the buffer's spill files lost
        its ``Outbound.reply`` (an object, not JSON) but not its meta, so a call is bound again,
        through this runner's source (a reload's new runner included)."""
        if outbound.reply is None:
            outbound.reply = self.route.replies.bind(self.route.pipeline.reply_shape, outbound.meta)
        return outbound.reply
