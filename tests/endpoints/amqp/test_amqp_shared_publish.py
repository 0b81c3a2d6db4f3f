"""Every AMQP sink of a connection publishes through one shared round per loop turn
(engine/endpoints/amqp/publisher.py): many routes' batches go out as one write with one
confirm wait, yet each route hears exactly its own messages' outcomes."""

from __future__ import annotations

import asyncio
import uuid
from typing import Any

import aio_pika

from engine.endpoints.amqp.transport import TRANSPORT
from engine.endpoints.base import EndpointError, MessageRejected, Outbound
from tests.support.amqp_helpers import Collector
from tests.support.waiting import wait_for

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
            arrived = [str(m.routing_key) for m in await collector.wait_for(ok_count)]  # a delivery always has one
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


def test_frames_are_pamqps_bytes() -> None:
    """The publisher writes each message's frames with ``struct`` (engine/endpoints/amqp/
    publisher.py ``_frames``): byte for byte what pamqp encodes for aiormq's ``basic_publish``
    (channels, multi-byte keys, empty and split bodies, the sink's cached properties and plain
    ones), with pamqp's refusals and texts."""
    from aiormq import spec
    from pamqp import frame as pamqp_frame
    from pamqp.body import ContentBody
    from pamqp.header import ContentHeader

    from engine.endpoints.amqp.publisher import _frames
    from engine.endpoints.amqp.sink import PublishProperties

    def pamqps(channel: int, frame_max: int, exchange: str, key: str, body: bytes, properties: spec.Basic.Properties) -> bytes:
        """The encoding the publisher used before: pamqp's, after its own check of the key."""
        if len(key) > 255:
            raise ValueError("Routing key too long (max 255 bytes)")
        encoded = [pamqp_frame.marshal(spec.Basic.Publish(exchange=exchange, routing_key=key), channel),
                   pamqp_frame.marshal(ContentHeader(properties=properties, body_size=len(body)), channel)]
        encoded += [pamqp_frame.marshal(ContentBody(body[start:start + frame_max]), channel)
                    for start in range(0, len(body), frame_max)]
        return b"".join(encoded)

    fixed = PublishProperties.fixed("application/json", 2, {"x-rabbitros-route": "r", "x-rabbitros-generation": 3})
    cases = [(1, 131064, "fleet-out", "robot1.fix", b'{"seq": 1}', PublishProperties(fixed, "abc")),
             (7, 10, "", "k\u00e9y", b"x" * 35, spec.Basic.Properties(content_type="a", headers={"h": [1, "x"]}, delivery_mode=1)),
             (65535, 10, "a-b_c.d:e", "", b"", PublishProperties(fixed, None)),
             (2, 5, "ex", "z" * 255, b"0123456789", PublishProperties(fixed, "\u00e9" * 3))]
    for case in cases:
        assert _frames(*case) == pamqps(*case), case
    for exchange, key in (("e" * 128, "k"), ("bad exchange!", "k"), ("ex", "k" * 256), ("ex", "\u00e9" * 200)):
        outcomes: list[tuple[type[Exception], str] | None] = []
        for encode in (pamqps, _frames):
            try:
                encode(1, 100, exchange, key, b"x", PublishProperties(fixed, None))
                outcomes.append(None)
            except Exception as error:  # noqa: BLE001 - compared, type and text
                outcomes.append((type(error), str(error)))
        assert outcomes[0] is not None and outcomes[0] == outcomes[1], (exchange, key, outcomes)


def test_a_channel_closed_before_its_confirms_fails_every_route_of_the_round(amqp_url: str) -> None:
    """A round written at once (no task of its own: the channel was open, nothing else
    writing) whose channel the broker closes before confirming (a publish to an exchange that
    does not exist): every route of that round hears a failure naming its exchange and key,
    none is left waiting; the next round fetches the reopened channel and is confirmed."""
    from engine.endpoints.amqp.publisher import SharedPublisher
    from engine.endpoints.amqp.sink import PublishProperties

    tag = uuid.uuid4().hex[:8]
    exchange, missing = f"shared-ok-{tag}", f"shared-missing-{tag}"
    properties = PublishProperties(PublishProperties.fixed("application/json", 1, {}), None)

    async def scenario() -> tuple[list[BaseException | None], list[list[BaseException | None]], list[BaseException | None], int]:
        connection = await aio_pika.connect_robust(amqp_url)
        try:
            channel = await connection.channel(publisher_confirms=True)
            await channel.declare_exchange(exchange, aio_pika.ExchangeType.TOPIC, auto_delete=True)
            publisher = SharedPublisher(channel, "gcs")
            first = await publisher.publish(exchange, [("a", b"{}", properties)])  # fetches the channel (the task way)
            failed = await asyncio.wait_for(asyncio.gather(
                publisher.publish(missing, [("b", b"{}", properties), ("c", b"{}", properties)]),
                publisher.publish(exchange, [("d", b"{}", properties)])), 10)
            after: list[BaseException | None] = []

            async def published() -> bool:  # aio-pika reopens the robust channel
                after[:] = await asyncio.wait_for(publisher.publish(exchange, [("e", b"{}", properties)]), 10)
                return after == [None]

            await wait_for(published, 10, "a publish after the robust channel reopened", lambda: after)
            return first, list(failed), after, publisher.rounds
        finally:
            await connection.close()

    first, failed, after, rounds = asyncio.run(scenario())
    assert first == [None]
    assert [len(results) for results in failed] == [2, 1], failed
    for results, key in zip(failed, (("b", "c"), ("d",))):
        for result, name in zip(results, key):
            assert isinstance(result, EndpointError) and f"/{name!r} on 'gcs'" in str(result), result
    assert "NOT_FOUND" in str(failed[0][0]) or "closed" in str(failed[0][0]), failed
    assert after == [None], after
    assert rounds >= 3


def test_confirms_settle_the_acknowledged_prefix_of_the_table(amqp_url: str) -> None:
    """The publisher's confirm handler (publisher.py ``_confirm_in_order``) on a real aiormq
    confirm channel, fed the broker's confirm frames: a multiple Ack settles exactly the tags up
    to its own (not the newer ones), a single Nack fails only its tag with aiormq's
    ``DeliveryError``, a multiple Nack fails the rest of its prefix, and an unknown tag changes
    nothing."""
    import aiormq
    from aiormq import spec
    from aiormq.exceptions import DeliveryError

    from engine.endpoints.amqp.publisher import _confirm_in_order

    async def scenario() -> None:
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await (await connection.channel(publisher_confirms=True)).get_underlay_channel()
            assert isinstance(channel, aiormq.Channel), "aio-pika's underlay is an aiormq Channel"
            _confirm_in_order(channel)
            loop = asyncio.get_running_loop()
            # aiormq's reader dispatches to the handler installed on the instance: a frame put
            # where the connection's reader puts it reaches it (else aiormq's own would answer)
            installed, seen = channel._on_confirm_frame, []

            async def counting(frame: Any) -> None:
                seen.append(frame)
                await installed(frame)

            channel._on_confirm_frame = counting  # type: ignore[method-assign]  # deliberately wraps this instance's handler (aiormq dispatches to it)
            probe = loop.create_future()
            channel.confirmations[100] = probe
            channel.frames.put_nowait((0, spec.Basic.Ack(delivery_tag=100, multiple=True)))
            await asyncio.wait_for(probe, 10)
            assert len(seen) == 1 and channel.confirmations == {}
            channel._on_confirm_frame = installed  # type: ignore[method-assign]  # puts the instance's own handler back
            futures = {tag: loop.create_future() for tag in range(1, 9)}
            channel.confirmations.update(futures)
            await channel._on_confirm_frame(spec.Basic.Ack(delivery_tag=3, multiple=True))
            assert [tag for tag, f in futures.items() if f.done()] == [1, 2, 3]
            assert all(isinstance(futures[tag].result(), spec.Basic.Ack) for tag in (1, 2, 3))
            await channel._on_confirm_frame(spec.Basic.Nack(delivery_tag=5, multiple=False))
            assert isinstance(futures[5].exception(), DeliveryError) and not futures[4].done()
            await channel._on_confirm_frame(spec.Basic.Ack(delivery_tag=42, multiple=True))  # not ours: ignored
            assert not futures[4].done() and list(channel.confirmations) == [4, 6, 7, 8]
            await channel._on_confirm_frame(spec.Basic.Nack(delivery_tag=7, multiple=True))
            assert isinstance(futures[4].exception(), DeliveryError) and isinstance(futures[6].exception(), DeliveryError)
            assert isinstance(futures[7].exception(), DeliveryError) and not futures[8].done()
            assert list(channel.confirmations) == [8]
            channel.confirmations.clear()
        finally:
            await connection.close()

    asyncio.run(scenario())


def test_a_frame_size_without_limit_still_sends_the_body() -> None:
    """A broker that negotiates frame_max 0 ("no limit") leaves aiormq's max_content_size at
    -8: the body goes as one frame, as aiormq's own split sends it, never dropped."""
    from aiormq import spec

    from engine.endpoints.amqp.publisher import _frames

    encoded = _frames(1, -8, "e", "k", b"abc", spec.Basic.Properties())
    assert encoded.endswith(b"\x03\x00\x01\x00\x00\x00\x03abc\xce"), encoded
