"""An independent Foxglove WebSocket client for the tests: plain ``websockets`` speaking the
protocol (JSON ``advertise`` and ``subscribe``; binary message data: opcode 1, subscription id
u32 LE, timestamp u64 LE, payload) under the SDK's name ``foxglove.sdk.v1``. Used by
tests/operator/test_foxglove.py and tests/operator/test_workers_foxglove.py."""

from __future__ import annotations

import asyncio
import json
import struct
from typing import Any

import websockets
from websockets.typing import Subprotocol

SUBPROTOCOL = Subprotocol("foxglove.sdk.v1")


class FoxgloveClient:
    """One connection: the channels advertised, subscriptions, and the message data received."""

    def __init__(self, ws: Any) -> None:
        self.ws = ws
        self.server_info: dict[str, Any] = {}
        self.channels: dict[str, dict[str, Any]] = {}
        self.statuses: list[dict[str, Any]] = []
        self.received: dict[int, list[tuple[int, bytes]]] = {}
        self.unadvertised: list[int] = []
        self._task = asyncio.create_task(self._read())

    async def _read(self) -> None:
        async for frame in self.ws:
            if isinstance(frame, bytes):
                assert frame[0] == 1, f"not message data: opcode {frame[0]}"
                subscription, timestamp = struct.unpack_from("<IQ", frame, 1)
                self.received.setdefault(subscription, []).append((timestamp, frame[13:]))
                continue
            message = json.loads(frame)
            if message["op"] == "serverInfo":
                self.server_info = message
            elif message["op"] == "advertise":
                self.channels.update((c["topic"], c) for c in message["channels"])
            elif message["op"] == "unadvertise":
                self.unadvertised.extend(message["channelIds"])
            elif message["op"] == "status":
                self.statuses.append(message)

    async def subscribe(self, topics: list[str]) -> dict[str, int]:
        """Subscribe to ``topics``; returns topic -> subscription id."""
        ids = {topic: index for index, topic in enumerate(topics, start=1)}
        await self.ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": ids[topic], "channelId": self.channels[topic]["id"]} for topic in topics]}))
        return ids

    def messages(self, subscription: int) -> list[Any]:
        return [json.loads(payload) for _, payload in self.received.get(subscription, [])]

    async def close(self) -> None:
        await self.ws.close()
        await asyncio.gather(self._task, return_exceptions=True)


async def connect(port: int) -> FoxgloveClient:
    ws = await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL])
    return FoxgloveClient(ws)
