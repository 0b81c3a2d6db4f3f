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



HELD = """
connections:
  gcs: {{amqp: "{amqp}"}}
  relay: {{mqtt: "{mqtt}"}}
routes:
  - name: held
    source: {{amqp: {{connection: gcs, exchange: in-{tag}, binding_key: "p.#", queue: q-{tag}}}}}
    schema: raw_json
    buffer: {{max_messages: 100}}
"""
ONE_RELAY = """
    sink: {{mqtt: {{connection: relay, topic: relayed}}}}
"""
CLOUD_AND_RELAY = """
    sinks:
      - name: cloud
        amqp: {{connection: gcs, exchange: cloud-{tag}, routing_key: ok}}
        mapping: "{{{field}: n}}"
      - name: relay
        mqtt: {{connection: relay, topic: relayed}}
"""
RELAY_FALLBACK = """
        fallback:
          after: 0
          amqp: {{connection: gcs, exchange: spool-{tag}, routing_key: spool}}
"""
ONE_CLOUD = """
    sink:
      amqp: {{connection: gcs, exchange: cloud-{tag}, routing_key: ok}}
      mapping: "{{m: n}}"
"""


def held_then_reloaded(tmp_path: Path, amqp_url: str, mosquitto: LocalMosquitto, schemas_dir: Path,
                       before: str, after: str) -> dict[str, Any]:
    """Three messages held by the route's buffer while the relay's mosquitto is stopped (the
    route ``before``), then a reload to ``after`` with the relay still stopped: what the cloud and
    the spool exchanges got once the route counted the three delivered, and its status."""
    tag = uuid.uuid4().hex[:8]
    routes = tmp_path / "routes"
    routes.mkdir()

    def write(sinks: str) -> None:
        (routes / "r.yaml").write_text((HELD + sinks).format(amqp=amqp_url, mqtt=mosquitto.url, tag=tag))

    async def scenario() -> dict[str, Any]:
        write(before)
        engine = Engine(routes, schemas_dir)
        async with started_with_client(engine, amqp_url) as client:
            channel = await client.channel()
            cloud = await Collector.bind(channel, f"cloud-{tag}")
            spool = await Collector.bind(channel, f"spool-{tag}")

            def route() -> dict[str, Any]:
                return engine.status()["routes"]["held"]

            await asyncio.to_thread(mosquitto.halt)  # held: seen down, or failed once and handed to the buffer
            await publish(channel, f"in-{tag}", "p.x", [b'{"n": %d}' % n for n in range(3)])
            await wait_for(lambda: route()["buffer"]["held"] == 3, 30, "three held", detail=route)
            write(after)
            assert await engine.reload()
            await wait_for(lambda: route()["delivered"] == 3 and route()["buffer"]["held"] == 0 and len(cloud.messages) >= 3,
                           30, "the held three", detail=route)
            return {"cloud": [json.loads(m.body) for m in cloud.messages], "spool": [json.loads(m.body) for m in spool.messages],
                    "status": route()}

    return asyncio.run(asyncio.wait_for(scenario(), 120))


def test_messages_held_by_one_sink_go_to_every_sink_after_a_reload_to_several(
        tmp_path: Path, amqp_url: str, mosquitto: LocalMosquitto, schemas_dir: Path) -> None:
    """The buffer holds what the one sink (the relay, stopped) could not take; a reload to
    ``sinks:`` keeps the buffer, and what it held was mapped for the one sink: the new sinks map
    it again, so each gets its copy (it used to be sent to no sink and counted delivered)."""
    several = CLOUD_AND_RELAY.replace("{field}", "m") + RELAY_FALLBACK
    result = held_then_reloaded(tmp_path, amqp_url, mosquitto, schemas_dir, ONE_RELAY, several)
    assert sorted(body["m"] for body in result["cloud"]) == [0, 1, 2], result
    assert sorted(body["n"] for body in result["spool"]) == [0, 1, 2], result
    sinks = result["status"]["sinks"]
    assert sinks["cloud"]["delivered"] == 3 and sinks["relay"]["to_fallback"] == 3 and sinks["relay.fallback"]["delivered"] == 3, sinks


def test_messages_held_by_several_sinks_get_the_one_sinks_mapping_after_a_reload_to_one(
        tmp_path: Path, amqp_url: str, mosquitto: LocalMosquitto, schemas_dir: Path) -> None:
    """The reverse: held while one of several sinks (the relay, stopped, no fallback) could not
    take them, then a reload to one ``sink:``: each held message is mapped by the one sink's
    mapping (it used to be sent as the several sinks' ``{name: fields}``)."""
    result = held_then_reloaded(tmp_path, amqp_url, mosquitto, schemas_dir, CLOUD_AND_RELAY.replace("{field}", "old"), ONE_CLOUD)
    assert sorted(result["cloud"], key=lambda body: body.get("m", -1)) == [{"m": 0}, {"m": 1}, {"m": 2}], result
