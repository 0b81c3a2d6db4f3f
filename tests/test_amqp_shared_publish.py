"""Every AMQP sink of a connection publishes through one shared round per loop turn
(engine/endpoints/amqp/publisher.py): many routes' batches go out as one write with one
confirm wait, yet each route hears exactly its own messages' outcomes."""

from __future__ import annotations

import asyncio
import uuid

import aio_pika

from engine.endpoints.amqp.transport import TRANSPORT
from engine.endpoints.base import EndpointError, MessageRejected, Outbound
from tests.amqp_helpers import Collector

ROUTES = 20
PER_ROUTE = 3


def outbound(route: str, seq: int) -> Outbound:
    body = b'{"route": "%s", "seq": %d}' % (route.encode(), seq)
    canonical = {"route": route, "seq": seq}
    return Outbound(body=body, canonical=canonical, fields=canonical,
                    message_id=f"{route}-{seq}", meta={"route": route, "generation": 1})


def test_routes_share_one_round_and_each_hears_only_its_own_outcomes(amqp_url: str) -> None:
    """Twenty routes publish in the same loop turn: one round carries them all. One route's
    queue refuses all but one message (``x-overflow: reject-publish``, the broker nacks the
    rest, a transient failure the route retries) and one message's routing key is over AMQP's
    255 bytes (rejected: it can never be sent): those messages fail, each on its own route; every other message of every route is accepted and arrives."""
    tag = uuid.uuid4().hex[:8]
    exchange, full = f"shared-{tag}", f"shared-full-{tag}"

    async def scenario() -> tuple[list[list[BaseException | None]], dict[str, int], list[str], list[str]]:
        client = await aio_pika.connect(amqp_url)
        engine_side = TRANSPORT.connect("gcs", {"url": amqp_url})
        await engine_side.open()
        try:
            channel = await client.channel()
            collector = await Collector.bind(channel, exchange, "ok.#")
            target = await channel.declare_exchange(exchange, aio_pika.ExchangeType.TOPIC, durable=True)
            refusing = await channel.declare_queue(
                full, exclusive=True, arguments={"x-max-length": 1, "x-overflow": "reject-publish"})
            await refusing.bind(target, "full.#")
            names = [f"r{n}" for n in range(ROUTES)]
            keys = {name: "ok.{route}" for name in names}
            keys["r7"] = "full.{route}"  # the broker takes one of r7's messages and nacks the rest
            sinks = [engine_side.sink(name, {"exchange": exchange, "routing_key": keys[name]}) for name in names]
            await sinks[0].send_batch([outbound("r0", -1)])  # the exchange declared: what follows is one turn's work
            before = engine_side.health()
            batches = [[outbound(name, seq) for seq in range(PER_ROUTE)] for name in names]
            batches[3][1] = outbound("x" * 300, 1)  # r3's second message: a routing key of 302 bytes
            batches[3][1].meta = {"route": "r3", "generation": 1}
            sinks[3] = engine_side.sink("r3", {"exchange": exchange, "routing_key": "ok.{route}"})
            results = await asyncio.gather(*(sink.send_batch(batch) for sink, batch in zip(sinks, batches)))
            after = engine_side.health()
            ok_count = 1 + ROUTES * PER_ROUTE - PER_ROUTE - 1  # r0's first, all but r7's and r3's bad one
            arrived = [m.routing_key for m in await collector.wait_for(ok_count)]
            refused = []
            while (message := await refusing.get(no_ack=True, fail=False)) is not None:
                refused.append(message.body.decode())
            rounds = {"rounds": after["publish_rounds"] - before["publish_rounds"],
                      "published": after["published"] - before["published"]}
            return list(results), rounds, arrived, refused
        finally:
            await engine_side.close()
            await client.close()

    results, rounds, arrived, refused = asyncio.run(scenario())
    assert rounds == {"rounds": 1, "published": ROUTES * PER_ROUTE - 1}, rounds  # the bad key is never written
    for index, route_results in enumerate(results):
        if index == 7:
            assert route_results[0] is None and all(isinstance(r, EndpointError) and "Nack" in str(r)
                                                    for r in route_results[1:]), route_results
        elif index == 3:
            assert route_results[0] is None and route_results[2] is None, route_results
            error = route_results[1]
            assert isinstance(error, MessageRejected) and "255" in str(error), error  # never retried: dead-lettered
        else:
            assert route_results == [None] * PER_ROUTE, (index, route_results)
    assert refused == ['{"route": "r7", "seq": 0}']
    expected = ["ok.r0"] + [f"ok.r{n}" for n in range(ROUTES) if n != 7 for _ in range(PER_ROUTE - (n == 3))]
    assert sorted(arrived) == sorted(expected), arrived
