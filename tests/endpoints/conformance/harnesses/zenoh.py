"""Zenoh: an eclipse-zenoh peer of the test's own, listening on a port drawn for it (multicast
scouting off, so parallel workers never meet), which the engine's connection connects to, as in
tests/endpoints/zenoh/test_zenoh.py. The test puts on ``TAG/in/rN`` and collects ``TAG/out/*``;
the source's ``{robot}`` chunk is the metadata the mapping reads, the sink's key is rendered
from it."""

from __future__ import annotations

import asyncio
import json
import threading
from typing import Any

from engine.common.processes import listening_port
from tests.endpoints.conformance.harness import Harness, Seen
from tests.support.waiting import wait_for


class ZenohHarness(Harness):
    PROTOCOL = "zenoh"
    EXCLUDED = {
        "kill9": "Zenoh pub/sub keeps nothing for an absent subscriber and has no acknowledgement, so it "
                 "promises no at-least-once across an engine's death (docs/route-keys.md routes[].source.zenoh, "
                 "engine/endpoints/zenoh/source.py; Transport.redelivers is False)",
        "cancel": "no broker holds Zenoh subscriptions to revoke: a peer gone and back (the health case) is how a "
                  "subscription is lost, and the session declares it again there",
    }

    async def open(self, fixtures: dict[str, Any], case: str) -> None:
        self.endpoint = f"tcp/127.0.0.1:{listening_port()}"
        self.samples: list[Seen] = []
        self.lock = threading.Lock()
        self.session: Any = None
        await self._open_peer()

    async def _open_peer(self) -> None:
        import zenoh

        config = zenoh.Config()
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("listen/endpoints", json.dumps([self.endpoint]))
        self.session = await asyncio.to_thread(zenoh.open, config)
        self.subscriber = self.session.declare_subscriber(f"{self.tag}/out/*", self._on_sample)
        self.publisher = self.session.declare_publisher(f"{self.tag}/in/r1")

    def _on_sample(self, sample: Any) -> None:  # on a Zenoh thread
        body = json.loads(sample.payload.to_bytes())
        robot = int(str(sample.key_expr).rsplit("/r", 1)[1])
        with self.lock:
            self.samples.append(Seen(robot, body["seq"], body["origin"], body["edition"]))

    async def _close_peer(self) -> None:
        if self.session is not None:
            self.subscriber.undeclare()
            self.publisher.undeclare()
            await asyncio.to_thread(self.session.close)
            self.session = None

    async def close(self) -> None:
        await self._close_peer()

    def connection(self, case: str) -> str:
        return f'{{zenoh: {{connect: ["{self.endpoint}"], multicast_scouting: false}}}}'

    def source(self) -> str:
        return f'key: "{self.tag}/in/{{robot}}"'

    def sink(self) -> str:
        return f'key: "{self.tag}/out/{{origin}}"'

    def origin_expression(self) -> str:
        return "meta('robot')"

    def expected_origin(self, robot: int) -> str:
        return f"r{robot}"

    async def ready(self) -> None:
        """Until the engine's subscriber matches the test's publisher (a put before is lost)."""
        await wait_for(lambda: self.publisher.matching_status.matching, 30, "the engine's subscriber")

    async def inject(self, robot: int, seq: int) -> None:
        self.session.put(f"{self.tag}/in/r{robot}", json.dumps({"seq": seq}).encode())

    async def inject_bad(self, robot: int) -> None:
        self.session.put(f"{self.tag}/in/r{robot}", b"not json {")

    def seen(self) -> list[Seen]:
        with self.lock:
            return list(self.samples)

    def session_of(self, connection: Any) -> Any:
        return connection._session  # the engine's zenoh.Session (engine/endpoints/zenoh/session.py)

    async def peer_down(self) -> None:
        await self._close_peer()

    async def peer_back(self) -> None:
        await self._open_peer()


HARNESS = ZenohHarness
