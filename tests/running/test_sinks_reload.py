"""A reload that turns a route's ``sink:`` into ``sinks:`` (with a fallback on a connection of
its own) and back keeps its source, swaps its pipeline, and releases the connection only the
several sinks used: a real RabbitMQ node and a private mosquitto, the engine in process."""

from __future__ import annotations

import asyncio
import json
import uuid
from pathlib import Path
from typing import Any

import pytest

from engine.endpoints.mqtt.broker import LocalMosquitto
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector, publish, started_with_client
from tests.support.waiting import wait_for

pytestmark = pytest.mark.soak

ONE = """
connections:
  gcs: {{amqp: "{amqp}"}}
routes:
  - name: probe
    source: {{amqp: {{connection: gcs, exchange: in-{tag}, binding_key: "p.#", queue: q-{tag}}}}}
    schema: raw_json
    sink: {{amqp: {{connection: gcs, exchange: a-{tag}, routing_key: ok}}}}
"""
SEVERAL = """
connections:
  gcs: {{amqp: "{amqp}"}}
  local: {{mqtt: "{mqtt}"}}
routes:
  - name: probe
    source: {{amqp: {{connection: gcs, exchange: in-{tag}, binding_key: "p.#", queue: q-{tag}}}}}
    schema: raw_json
    sinks:
      - amqp: {{connection: gcs, exchange: a-{tag}, routing_key: ok}}
      - amqp: {{connection: gcs, exchange: b-{tag}, routing_key: ok}}
        mapping: "{{twice: n}}"
        when: "n > `1`"
        fallback:
          mqtt: {{connection: local, topic: spool}}
"""


def test_sink_to_sinks_and_back_swaps_the_pipeline_and_releases_what_only_the_sinks_used(
        tmp_path: Path, amqp_url: str, mosquitto: LocalMosquitto, schemas_dir: Path) -> None:
    tag = uuid.uuid4().hex[:8]
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "r.yaml").write_text(ONE.format(amqp=amqp_url, tag=tag))

    async def scenario() -> dict[str, Any]:
        engine = Engine(routes, schemas_dir)
        async with started_with_client(engine, amqp_url) as client:
            channel = await client.channel()
            a = await Collector.bind(channel, f"a-{tag}")
            b = await Collector.bind(channel, f"b-{tag}")
            runner = engine.runners["probe"]
            await publish(channel, f"in-{tag}", "p.x", [b'{"n": 1}'])
            await a.wait_for(1)
            (routes / "r.yaml").write_text(SEVERAL.format(amqp=amqp_url, mqtt=mosquitto.url, tag=tag))
            assert await engine.reload()
            several = {"same runner": engine.runners["probe"] is runner, "connections": [c.name for c in runner.connections],
                       "sinks": engine.status()["routes"]["probe"].get("sinks")}
            await publish(channel, f"in-{tag}", "p.x", [b'{"n": 1}', b'{"n": 2}'])
            await wait_for(lambda: len(a.messages) >= 3 and len(b.messages) >= 1, 30, "both sinks",
                           detail=lambda: engine.status()["routes"]["probe"])
            (routes / "r.yaml").write_text(ONE.format(amqp=amqp_url, tag=tag))
            assert await engine.reload()
            await publish(channel, f"in-{tag}", "p.x", [b'{"n": 3}'])
            await wait_for(lambda: len(a.messages) >= 4, 30, "the one sink again")
            return {**several, "after": [c.name for c in runner.connections], "open": sorted(c.name for _, c in engine.open_connections()),
                    "a": [json.loads(m.body) for m in a.messages], "b": [json.loads(m.body) for m in b.messages],
                    "status": engine.status()["routes"]["probe"]}

    result = asyncio.run(asyncio.wait_for(scenario(), 120))
    assert result["same runner"], "the source was kept: only the pipeline was swapped"
    assert result["connections"] == ["gcs", "gcs", "gcs", "local"], result
    assert set(result["sinks"]) == {"amqp.0", "amqp.1", "amqp.1.fallback"}, result["sinks"]
    assert result["a"] == [{"n": 1}, {"n": 1}, {"n": 2}, {"n": 3}] and result["b"] == [{"twice": 2}], result
    assert result["after"] == ["gcs", "gcs"] and result["open"] == ["gcs"], result
    assert "sinks" not in result["status"] and result["status"]["delivered"] == 4, result["status"]

