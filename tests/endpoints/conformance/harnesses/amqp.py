"""AMQP: the session's RabbitMQ (tests/conftest.py ``amqp_url``), or for ``health`` a private
node the test can stop and start (engine/endpoints/amqp/broker.py ``LocalBroker``). The test's
aio-pika client publishes to ``in-TAG`` with routing key ``in.rN`` and collects ``out-TAG``
(tests/support/amqp_helpers.py ``Collector``). The routing key the message came with is the
metadata the mapping reads; the sink's routing key is rendered from it."""

from __future__ import annotations

import asyncio
import json
from typing import Any, ClassVar

from tests.endpoints.conformance.harness import Harness, Seen
from tests.support.waiting import wait_for


class AmqpHarness(Harness):
    PROTOCOL = "amqp"
    FIXTURES = ("amqp_url",)
    EXCLUDED: ClassVar[dict[str, str]] = {}  # every case: AMQP acknowledges after the sink, and a broker can cancel a consumer

    async def open(self, fixtures: dict[str, Any], case: str) -> None:
        self.private = None
        self.url = fixtures["amqp_url"]
        if case == "health":  # the session's node is shared: stop only a node of this test's own
            from engine.endpoints.amqp.broker import LocalBroker

            self.private = LocalBroker(lifetime=900)
            await asyncio.to_thread(self.private.start)
            self.url = self.private.url
        self.client: Any = None
        self.collectors: list[Any] = []
        await self._connect()

    async def _connect(self) -> None:
        import aio_pika  # here, not at the top: the fast tier imports this module without the protocols' libraries

        from tests.support.amqp_helpers import Collector

        self.client = await aio_pika.connect(self.url)
        self.channel = await self.client.channel()
        self.collectors.append(await Collector.bind(self.channel, f"out-{self.tag}", "#"))
        self.inbox = await self.channel.declare_exchange(f"in-{self.tag}", aio_pika.ExchangeType.TOPIC, durable=True)

    async def _disconnect(self) -> None:
        if self.client is not None:
            await self.client.close()
            self.client = None

    async def close(self) -> None:
        await self._disconnect()
        if self.private is not None:
            await asyncio.to_thread(self.private.stop)

    def connection(self, case: str) -> str:
        return f'{{amqp: "{self.url}"}}'

    def source(self) -> str:
        return f'exchange: in-{self.tag}, binding_key: "in.*", queue: in-{self.tag}-q'

    def sink(self) -> str:
        return f'exchange: out-{self.tag}, routing_key: "out.{{origin}}"'

    def origin_expression(self) -> str:
        return "meta('routing_key')"

    def expected_origin(self, robot: int) -> str:
        return f"in.r{robot}"

    async def ready(self) -> None:
        """Until the route consumes its queue (the engine declares and binds it at start)."""

        from aio_pika.exceptions import ChannelClosed

        async def consumers() -> int:
            assert self.client is not None
            channel = await self.client.channel()
            try:
                queue = await channel.declare_queue(f"in-{self.tag}-q", passive=True)
                return queue.declaration_result.consumer_count or 0
            except ChannelClosed:
                return 0
            finally:
                if not channel.is_closed:
                    await channel.close()

        await wait_for(consumers, 30, "a consumer on the route's queue", every=0.1)  # a channel a poll

    async def _publish(self, robot: int, body: bytes) -> None:
        import aio_pika

        await self.inbox.publish(aio_pika.Message(body, content_type="application/json", delivery_mode=2), f"in.r{robot}")

    async def inject(self, robot: int, seq: int) -> None:
        await self._publish(robot, json.dumps({"seq": seq}).encode())

    async def inject_bad(self, robot: int) -> None:
        await self._publish(robot, b"not json {")

    def seen(self) -> list[Seen]:
        seen = []
        for collector in self.collectors:
            for message in collector.messages:
                body = json.loads(message.body)
                robot = int((message.routing_key or "").rsplit(".r", 1)[1])
                seen.append(Seen(robot, body["seq"], body["origin"], body["edition"]))
        return seen

    def session_of(self, connection: Any) -> Any:
        # aio-pika's robust connection keeps its object across reconnections; its transport's
        # aiormq connection is the AMQP connection itself (a new one after each reconnection)
        return connection._connection.transport.connection

    async def peer_down(self) -> None:
        assert self.private is not None
        await self._disconnect()
        await asyncio.to_thread(self.private.halt)

    async def peer_back(self) -> None:
        assert self.private is not None
        await asyncio.to_thread(self.private.start)
        await self._connect()

    async def cancel_subscription(self) -> None:
        """The route's queue deleted under it: the broker cancels the engine's consumer."""
        assert self.client is not None
        channel = await self.client.channel()
        await channel.queue_delete(f"in-{self.tag}-q")
        await channel.close()


HARNESS = AmqpHarness
