"""A route's AMQP queue deleted while the engine consumes it (issue 30): the broker cancels the
consumer (``basic.cancel``); the source says so (the route's status, ``/healthz``), declares
again what the route declares (queue, exchange, binding) and consumes again, with the engine's
backoff while the broker refuses.

Before, aiormq logged ``Consumer ... cancelled by the broker`` and nothing else happened: the
route said running, ``/healthz`` 200, nothing was carried, and the queue declared and bound
again had 0 consumers. An engine process as an operator runs it, a real RabbitMQ, another
client deleting the queue."""

from __future__ import annotations

import asyncio
import json
import time
import urllib.error
import urllib.request
import uuid
from pathlib import Path
from typing import Any, Awaitable, Callable

import aio_pika
import aiormq
import pytest

from engine.common.processes import listening_port
from tests.support.amqp_helpers import Collector, consumer_count
from tests.support.engine_process import EngineProcess
from tests.support.waiting import wait_for

AFTER = 30
"""Messages published once the route consumes again: every one must arrive."""
DEADLINE_S = 30.0

ROUTES = """
routes:
  - name: kept
    source: {{amqp: {{exchange: {inbox}, queue: {queue}, binding_key: "in.#"}}}}
    schema: raw_json
    sink: {{amqp: {{exchange: {outbox}, routing_key: out}}}}
"""


def get(port: int, path: str) -> tuple[int, Any]:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=10) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read())


@pytest.mark.soak
def test_a_queue_deleted_while_consumed_is_declared_and_consumed_again(tmp_path: Path, amqp_url: str) -> None:
    tag = uuid.uuid4().hex[:8]
    inbox, outbox, queue = f"cancel-in-{tag}", f"cancel-out-{tag}", f"cancel-q-{tag}"
    (tmp_path / "routes").mkdir()
    (tmp_path / "routes" / "routes.yaml").write_text(ROUTES.format(inbox=inbox, outbox=outbox, queue=queue))
    port = listening_port()
    engine = EngineProcess(tmp_path / "routes", tmp_path / "status.json", {"RABBITROS_AMQP_URL": amqp_url},
                           "--admin", str(port))

    async def admin(path: str) -> tuple[int, Any]:
        return await asyncio.to_thread(get, port, path)

    async def route() -> dict[str, Any]:
        return (await admin("/status"))[1]["routes"]["kept"]

    async def scenario() -> dict[str, Any]:
        client = await aio_pika.connect(amqp_url)
        other = await aiormq.connect(amqp_url)  # another client: an operator deleting the queue
        try:
            channel = await client.channel()
            out = await Collector.bind(channel, outbox, "#")
            source = await channel.declare_exchange(inbox, aio_pika.ExchangeType.TOPIC, durable=True)

            async def carried(first: int, count: int) -> None:
                for seq in range(first, first + count):
                    await source.publish(aio_pika.Message(json.dumps({"seq": seq}).encode()), "in.x")
                await wait_for(lambda: len(out.messages) >= first + count, DEADLINE_S, f"{first + count} messages carried")

            async def consumers() -> int:
                """The queue's consumers (0 while it does not exist)."""
                admin_channel = await client.channel()
                try:
                    declared = await admin_channel.declare_queue(queue, passive=True)
                    return consumer_count(declared)
                except aio_pika.exceptions.ChannelClosed:  # 404: not there
                    return 0
                finally:
                    if not admin_channel.is_closed:
                        await admin_channel.close()

            await carried(0, 5)
            assert await consumers() == 1

            # 1. deleted: the route declares the queue and its binding again and consumes it at once
            deleting = await other.channel()
            deleted_at = time.monotonic()
            await deleting.queue_delete(queue)
            await wait_for(lambda: _when(consumers(), lambda n: n == 1), DEADLINE_S, "the queue declared again, with its consumer")
            consuming_after = time.monotonic() - deleted_at
            await carried(5, AFTER)
            first = await route()

            # 2. deleted while its exchange was replaced by one of another type: declaring it again
            # is refused (406) until the operator removes the wrong one; meanwhile the route's status
            # and /healthz say why, and the engine's backoff paces the attempts
            await deleting.exchange_delete(inbox)
            await deleting.exchange_declare(inbox, exchange_type="fanout", durable=True)
            await deleting.queue_delete(queue)
            code, health = await wait_for(lambda: _when(admin("/healthz"), lambda h: "PRECONDITION_FAILED" in str(h[1])),
                                          DEADLINE_S, "/healthz to say degraded, and why")
            degraded = await route()
            fixed_at = time.monotonic()
            await deleting.exchange_delete(inbox)
            await wait_for(lambda: _when(admin("/healthz"), lambda h: h[0] == 200), DEADLINE_S, "/healthz to say ok again")
            back = await route()
            healthy_after = time.monotonic() - fixed_at
            source = await channel.declare_exchange(inbox, aio_pika.ExchangeType.TOPIC, durable=True, passive=True)
            assert await consumers() == 1
            await carried(5 + AFTER, AFTER)
            return {"consuming_after_s": round(consuming_after, 3), "healthy_after_s": round(healthy_after, 3), "first": first, "health": health, "code": code, "degraded": degraded, "back": back,
                    "carried": [json.loads(m.body)["seq"] for m in out.messages]}
        finally:
            await other.close()
            await client.close()

    result, _ = engine.run(scenario)
    print({k: v for k, v in result.items() if k.endswith("_s")}, {k: v for k, v in result.items() if k != "carried"})
    assert result["first"]["source"]["cancelled_by_broker"] == 1 and result["first"]["source_degraded"] is None
    assert result["code"] == 503 and result["health"]["status"] == "degraded", result["health"]
    reason = result["health"]["degraded"]["kept"]
    assert f"queue {queue!r}" in reason and "cancelled" in reason and "PRECONDITION_FAILED" in reason, reason
    assert result["degraded"]["source_degraded"] == reason and result["degraded"]["state"] == "running"
    assert result["degraded"]["source"]["consuming"] is False
    back = result["back"]
    assert back["source_degraded"] is None and back["source"]["consuming"] is True
    assert back["source"]["cancelled_by_broker"] == 2 and back["source"]["taken_up_again"] == 2, back["source"]
    assert f"queue {queue!r}" in back["source"]["last_cancel"]
    assert sorted(set(result["carried"])) == list(range(5 + 2 * AFTER)), result["carried"]


async def _when(value: Awaitable[Any], condition: Callable[[Any], bool]) -> Any:
    got = await value
    return got if condition(got) else None
