"""MQTT: a private mosquitto per test (tests/conftest.py ``mosquitto``); the test's aiomqtt
clients inject on ``TAG/in/rN`` and observe ``TAG/out/+`` (QoS 1). The source's ``{robot}``
level is the metadata the mapping reads; the sink's topic is rendered from it."""

from __future__ import annotations

import asyncio
import json
from typing import Any, ClassVar

from tests.endpoints.conformance.harness import Harness, Seen


class MqttHarness(Harness):
    PROTOCOL = "mqtt"
    FIXTURES = ("mosquitto",)
    EXCLUDED: ClassVar[dict[str, str]] = {}  # every case: MQTT QoS 1 promises at-least-once, and a broker can drop a session

    async def open(self, fixtures: dict[str, Any], case: str) -> None:
        self.broker = fixtures["mosquitto"]
        self.messages: list[Seen] = []
        self.injector: Any = None
        self.observer: Any = None
        self.collecting: asyncio.Task[None] | None = None
        await self._connect()

    def _client(self) -> Any:
        import aiomqtt  # here, not at the top: the fast tier imports this module without the protocols' libraries

        return aiomqtt.Client("127.0.0.1", self.broker.port, protocol=aiomqtt.ProtocolVersion.V5, timeout=30)

    async def _connect(self) -> None:
        self.observer = self._client()
        await self.observer.__aenter__()
        await self.observer.subscribe(f"{self.tag}/out/+", qos=1)
        self.collecting = asyncio.create_task(self._collect(self.observer))
        self.injector = self._client()
        await self.injector.__aenter__()

    async def _collect(self, client: Any) -> None:
        async for message in client.messages:
            body = json.loads(bytes(message.payload))
            robot = int(str(message.topic).rsplit("/r", 1)[1])
            self.messages.append(Seen(robot, body["seq"], body["origin"], body["edition"]))

    async def _disconnect(self) -> None:
        if self.collecting is not None:
            self.collecting.cancel()
            await asyncio.gather(self.collecting, return_exceptions=True)
        for client in (self.observer, self.injector):
            if client is not None:
                try:
                    await client.__aexit__(None, None, None)
                except Exception:
                    pass  # the broker went first
        self.observer = self.injector = self.collecting = None

    async def close(self) -> None:
        await self._disconnect()

    def connection(self, case: str) -> str:
        # kill -9: a persistent session (client_id), so what arrives while no engine runs waits for the next one
        client_id = f", client_id: engine-{self.tag}" if case == "kill9" else ""
        return f'{{mqtt: {{url: "{self.broker.url}"{client_id}}}}}'

    def source(self) -> str:
        return f'topic: "{self.tag}/in/{{robot}}", qos: 1'

    def sink(self) -> str:
        return f'topic: "{self.tag}/out/{{origin}}", qos: 1'

    def origin_expression(self) -> str:
        return "meta('robot')"

    def expected_origin(self, robot: int) -> str:
        return f"r{robot}"

    async def inject(self, robot: int, seq: int) -> None:
        assert self.injector is not None
        await self.injector.publish(f"{self.tag}/in/r{robot}", json.dumps({"seq": seq}).encode(), qos=1)

    async def inject_bad(self, robot: int) -> None:
        assert self.injector is not None
        await self.injector.publish(f"{self.tag}/in/r{robot}", b"not json {", qos=1)

    def seen(self) -> list[Seen]:
        return list(self.messages)

    def session_of(self, connection: Any) -> Any:
        return connection._session  # the client session of the connection (engine/endpoints/mqtt/link.py)

    async def peer_down(self) -> None:
        await self._disconnect()
        await asyncio.to_thread(self.broker.halt)

    async def peer_back(self) -> None:
        await asyncio.to_thread(self.broker.start)
        await self._connect_again()

    async def _connect_again(self, timeout: float = 30.0, attempt_s: float = 5.0) -> None:
        """The test's own clients back on a restarted broker: a connection refused in the moment
        after it first accepted one (seen once under a loaded CI-like run) is tried again, and so
        is one the broker reset while connecting, after which the client waits for a CONNACK that
        never comes (its own timeout is 30 s: each attempt is bounded to ``attempt_s``); a broker
        that stays down still fails the case, naming the error."""
        import aiomqtt

        deadline = asyncio.get_running_loop().time() + timeout
        while True:
            try:
                await asyncio.wait_for(self._connect(), attempt_s)
                return
            except (aiomqtt.MqttError, asyncio.TimeoutError):
                await self._disconnect()  # whichever of the two clients got through: never two collectors
                if asyncio.get_running_loop().time() > deadline:
                    raise
                await asyncio.sleep(0.1)  # poll: the retry interval of a connect until its deadline

    async def cancel_subscription(self) -> None:
        """Killed and started again: the engine's clean session (no client_id) and its
        subscription are gone from the broker; the engine must subscribe again."""
        await self._disconnect()
        await asyncio.to_thread(self.broker.kill)
        await asyncio.to_thread(self.broker.start)
        await self._connect_again()


HARNESS = MqttHarness
