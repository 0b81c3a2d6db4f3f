"""Per-sink counts of a route with several sinks (issue 32), and a fallback's ``after`` counted
from the outage at hand: a real RabbitMQ node and a private mosquitto, the engine in process.

* the per-sink counts live in the route's one set of counters (engine/running/observe.py), so
  the status' ``sinks`` and ``/metrics``' ``rabbitros_sink_messages_total`` say the same, and
  both keep counting across a reload that swaps the route's pipeline (Prometheus counters never
  go back);
* a sink that refuses returned messages for good (``unroutable: dead_letter``, no fallback)
  counts each return ``unroutable`` on the route and on the sink, as one plain sink does
  (the fan-out used to count only the returns a fallback took);
* an outage of a sink with a fallback that ended long ago does not count toward the next one:
  the next outage waits its ``after`` seconds again before the fallback takes over (it used to
  take over at once when no message had reached the sink between the two);
* a send the broker refuses while the sink is up (a negative confirm) goes to the fallback at
  once instead of spending the route's attempts and being dead-lettered before ``after``."""

from __future__ import annotations

import asyncio
import time
import uuid
from pathlib import Path
from typing import Any

import pytest
from prometheus_client import generate_latest
from prometheus_client.parser import text_string_to_metric_families

from engine.endpoints.mqtt.broker import LocalMosquitto
from engine.ops.admin import AdminServer
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector, publish, started_with_client
from tests.support.waiting import wait_for

pytestmark = pytest.mark.soak

DEADLINE_S = 30.0
COUNTED = """
connections:
  gcs: {{amqp: "{amqp}"}}
dead_letters: {{connection: gcs}}
routes:
  - name: counted
    source: {{amqp: {{connection: gcs, exchange: in-{tag}, binding_key: "p.#", queue: q-{tag}}}}}
    schema: raw_json
    sinks:
      - name: kept
        amqp: {{connection: gcs, exchange: kept-{tag}, routing_key: ok}}
        mapping: "{mapping}"
      - name: nobody
        amqp: {{connection: gcs, exchange: nobody-{tag}, routing_key: unbound, unroutable: dead_letter}}
"""


def sink_metrics(engine: Engine) -> dict[tuple[str, str], float]:
    """``(sink, outcome) -> value`` of the route's ``rabbitros_sink_messages_total``, as /metrics renders it."""
    text = generate_latest(AdminServer(engine, "127.0.0.1", 0).registry).decode()
    return {(sample.labels["sink"], sample.labels["outcome"]): sample.value
            for family in text_string_to_metric_families(text) if family.name == "rabbitros_sink_messages"
            for sample in family.samples if sample.name.endswith("_total") and sample.labels["route"] == "counted"}


def test_per_sink_counts_agree_in_status_and_metrics_count_refused_returns_and_survive_a_reload(
        tmp_path: Path, amqp_url: str, schemas_dir: Path) -> None:
    tag = uuid.uuid4().hex[:8]
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "r.yaml").write_text(COUNTED.format(amqp=amqp_url, tag=tag, mapping="@"))

    async def scenario() -> dict[str, Any]:
        engine = Engine(routes, schemas_dir)
        async with started_with_client(engine, amqp_url) as client:
            channel = await client.channel()
            kept = await Collector.bind(channel, f"kept-{tag}")
            dead = await Collector.bind(channel, "rabbitros.dead-letter", "counted")

            def route() -> dict[str, Any]:
                return engine.status()["routes"]["counted"]

            await publish(channel, f"in-{tag}", "p.x", [b'{"n": %d}' % n for n in range(5)])
            await wait_for(lambda: len(kept.messages) >= 5 and len(dead.messages) >= 5
                           and route()["dead_lettered"].get("sink", 0) >= 5, DEADLINE_S, "the first five", detail=route)
            first = {"route": route(), "metrics": sink_metrics(engine)}
            (routes / "r.yaml").write_text(COUNTED.format(amqp=amqp_url, tag=tag, mapping="{m: n}"))
            assert await engine.reload()
            await publish(channel, f"in-{tag}", "p.x", [b'{"n": %d}' % n for n in range(5, 7)])
            await wait_for(lambda: len(kept.messages) >= 7 and route()["dead_lettered"].get("sink", 0) >= 7, DEADLINE_S,
                           "two more after the reload", detail=route)
            return {"first": first, "route": route(), "metrics": sink_metrics(engine),
                    "letters": [dict(m.headers) for m in dead.messages]}

    result = asyncio.run(asyncio.wait_for(scenario(), 120))
    first, route, metrics = result["first"], result["route"], result["metrics"]
    # each message: the kept sink took its copy, the nobody sink refused the return for good (one dead letter naming it)
    assert first["route"]["sinks"]["kept"] == {"delivered": 5, "refused": 0, "to_fallback": 0, "unroutable": 0, "can_take": True}
    assert first["route"]["sinks"]["nobody"] == {"delivered": 0, "refused": 5, "to_fallback": 0, "unroutable": 5, "can_take": True}
    assert first["route"]["unroutable"] == 5, first["route"]
    assert all("sink 'nobody'" in letter["x-rabbitros-error"] and letter["x-source-sinks_unsent"] == "nobody"
               for letter in result["letters"]), result["letters"]
    # /metrics says what the status says, from the same counters
    assert first["metrics"] == {(sink, outcome): float(count) for sink in ("kept", "nobody")
                                for outcome, count in first["route"]["sinks"][sink].items() if outcome != "can_take"}
    # a reload swapped the pipeline (a new fan-out): the counts go on from where they were
    assert route["sinks"]["kept"]["delivered"] == 7 and route["sinks"]["nobody"]["refused"] == 7, route["sinks"]
    assert metrics[("kept", "delivered")] == 7.0 and metrics[("nobody", "unroutable")] == 7.0, metrics
    assert route["unroutable"] == 7 and route["dead_lettered"] == {"sink": 7}, route


AFTER_S = 1.5
RELAYED = """
connections:
  gcs: {{amqp: "{amqp}"}}
  relay: {{mqtt: "{relay}"}}
routes:
  - name: relayed
    source: {{amqp: {{connection: gcs, exchange: in-{tag}, binding_key: "p.#", queue: q-{tag}}}}}
    schema: raw_json
    sinks:
      - name: relay
        mqtt: {{connection: relay, topic: relayed}}
        fallback:
          after: {after}
          amqp: {{connection: gcs, exchange: spool-{tag}, routing_key: spool}}
"""


def test_an_outage_long_past_does_not_count_toward_the_next_ones_after(
        tmp_path: Path, amqp_url: str, mosquitto: LocalMosquitto, schemas_dir: Path) -> None:
    tag = uuid.uuid4().hex[:8]
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "r.yaml").write_text(RELAYED.format(amqp=amqp_url, relay=mosquitto.url, tag=tag, after=AFTER_S))

    async def scenario() -> dict[str, Any]:
        engine = Engine(routes, schemas_dir)
        async with started_with_client(engine, amqp_url) as client:
            channel = await client.channel()
            spool = await Collector.bind(channel, f"spool-{tag}")

            def route() -> dict[str, Any]:
                return engine.status()["routes"]["relayed"]

            def relay_can_take() -> bool:
                return bool((route().get("sinks") or {}).get("relay", {}).get("can_take"))

            await wait_for(relay_can_take, DEADLINE_S, "the relay", detail=route)
            # the first outage: seen (the status asks, as an operator's dashboard does), then over, and no message meanwhile
            await asyncio.to_thread(mosquitto.halt)
            await wait_for(lambda: not relay_can_take(), DEADLINE_S, "the relay seen down", detail=route)
            first_seen_down = time.monotonic()
            await asyncio.to_thread(mosquitto.start)
            await wait_for(relay_can_take, DEADLINE_S, "the relay seen back", detail=route)
            # the first outage is older than 'after' now (waiting on the clock is the condition itself)
            await wait_for(lambda: time.monotonic() - first_seen_down > 2 * AFTER_S, DEADLINE_S, "the first outage to age")
            # the second outage: the route waits 'after' seconds before the fallback takes over
            await asyncio.to_thread(mosquitto.halt)
            await wait_for(lambda: not relay_can_take(), DEADLINE_S, "the relay seen down again", detail=route)
            waiting = route()["sink_not_ready"]
            second_seen_down = time.monotonic()
            await publish(channel, f"in-{tag}", "p.x", [b'{"n": 1}'])
            await spool.wait_for(1, DEADLINE_S)
            return {"waiting": waiting, "taken_over_after_s": time.monotonic() - second_seen_down, "route": route()}

    result = asyncio.run(asyncio.wait_for(scenario(), 120))
    print(result)
    assert result["waiting"] is not None and "fallback 'relay.fallback' in" in result["waiting"], result
    assert result["taken_over_after_s"] >= AFTER_S * 0.5, result  # not at once: (nearly) 'after' from this outage
    assert result["route"]["sinks"]["relay"]["to_fallback"] == 1 and result["route"]["sinks"]["relay.fallback"]["delivered"] == 1


NACKED = """
connections:
  gcs: {{amqp: "{amqp}"}}
dead_letters: {{connection: gcs}}
routes:
  - name: nacked
    source: {{amqp: {{connection: gcs, exchange: in-{tag}, binding_key: "p.#", queue: q-{tag}}}}}
    schema: raw_json
    sinks:
      - name: full
        amqp: {{connection: gcs, exchange: full-{tag}, routing_key: x}}
        fallback:
          after: 60
          amqp: {{connection: gcs, exchange: spool-{tag}, routing_key: spool}}
"""


def test_a_send_the_broker_refuses_while_the_sink_is_up_goes_to_the_fallback_at_once(
        tmp_path: Path, amqp_url: str, schemas_dir: Path) -> None:
    """A queue full under ``x-overflow: reject-publish`` makes RabbitMQ nack each publish (a
    transient failure, the connection healthy): the route would spend its 5 attempts (about 1.5 s)
    and dead-letter the message long before an ``after`` of 60 s; it goes to the fallback at once."""
    tag = uuid.uuid4().hex[:8]
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "r.yaml").write_text(NACKED.format(amqp=amqp_url, tag=tag))

    async def scenario() -> dict[str, Any]:
        engine = Engine(routes, schemas_dir)
        async with started_with_client(engine, amqp_url) as client:
            channel = await client.channel()
            full = await channel.declare_exchange(f"full-{tag}", "topic", durable=True)
            queue = await channel.declare_queue(f"full-{tag}", exclusive=True,
                                                arguments={"x-max-length": 2, "x-overflow": "reject-publish"})
            await queue.bind(full, "#")
            spool = await Collector.bind(channel, f"spool-{tag}")

            def route() -> dict[str, Any]:
                return engine.status()["routes"]["nacked"]

            began = time.monotonic()
            await publish(channel, f"in-{tag}", "p.x", [b'{"n": %d}' % n for n in range(6)])
            await spool.wait_for(4, DEADLINE_S)
            await wait_for(lambda: route()["delivered"] == 6, DEADLINE_S, "six delivered", detail=route)
            declared = await channel.declare_queue(f"full-{tag}", passive=True)
            return {"route": route(), "seconds": time.monotonic() - began, "in_full": declared.declaration_result.message_count,
                    "spooled": sorted(int(m.body.decode().split(":")[1].strip(" }")) for m in spool.messages)}

    result = asyncio.run(asyncio.wait_for(scenario(), 120))
    print(result)
    route = result["route"]
    assert result["in_full"] == 2 and result["spooled"] == [2, 3, 4, 5], result
    assert route["sinks"]["full"]["to_fallback"] == 4 and route["sinks"]["full.fallback"]["delivered"] == 4, route["sinks"]
    assert route["dead_lettered"] == {} and route["failed"] == 0, route
    assert result["seconds"] < 30, result  # well before 'after' (60 s): the fallback took them at once
