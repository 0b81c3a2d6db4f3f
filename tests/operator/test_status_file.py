"""The status file against a real engine and RabbitMQ: it keeps being written, whatever a route
carried (engine/ops/cli.py ``_write_status``)."""

from __future__ import annotations

import json
import uuid
from pathlib import Path

import aio_pika

from tests.support.amqp_helpers import Collector, publish
from tests.support.engine_process import EngineProcess
from tests.support.waiting import wait_for

ROUTES = """
routes:
  - name: relay
    source: {{amqp: {{exchange: {exchange}, binding_key: "in.#", queue: {exchange}-in}}}}
    mapping: "{{agent_id: agent, seq: seq, count: count}}"
    schema: raw_json
    sink: {{amqp: {{exchange: {exchange}, routing_key: "out.relay"}}}}
"""
LONG_COUNT = 2**70
"""An integer beyond 64 bits: the engine carries it exactly (engine/common/schemas.py), and
it is then the route's last canonical message in the status document."""


def test_a_message_with_an_integer_beyond_64_bits_leaves_the_status_file_written(amqp_url: str, tmp_path: Path) -> None:
    """orjson refuses integers beyond 64 bits (and lone surrogates): the status file is then
    encoded by the standard library, and the reporter goes on writing it (it stopped for
    good, and a reload's write stopped the reloader too)."""
    exchange = f"status-file-{uuid.uuid4().hex[:8]}"
    (tmp_path / "routes").mkdir()
    (tmp_path / "routes" / "relay.yaml").write_text(ROUTES.format(exchange=exchange))
    engine = EngineProcess(tmp_path / "routes", tmp_path / "status.json", {"RABBITROS_AMQP_URL": amqp_url})

    def delivered() -> int:
        return int(((engine.status() or {}).get("routes", {}).get("relay", {}).get("messages") or {}).get("delivered", 0))

    async def scenario() -> None:
        connection = await aio_pika.connect(amqp_url)
        try:
            channel = await connection.channel()
            collector = await Collector.bind(channel, exchange, "out.#")
            for seq, count in enumerate((1, LONG_COUNT, 1), 1):  # the long one the last canonical for a while
                await publish(channel, exchange, "in.a", [json.dumps({"agent": "uav1", "seq": seq, "count": count}).encode()])
                await wait_for(lambda: len(collector.messages) == seq, 30, f"message {seq} delivered")
                await wait_for(lambda: delivered() == seq, 30, f"the status file to count message {seq}", engine.status)
            assert json.loads(collector.messages[1].body)["count"] == LONG_COUNT
        finally:
            await connection.close()

    _, status = engine.run(scenario)
    assert status["routes"]["relay"]["messages"]["delivered"] == 3
