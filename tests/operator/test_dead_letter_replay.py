"""Dead letters, sent again: a message dead-lettered by a bad mapping, the route fixed (its file
edited), ``rabbitros-engine dead-letters replay`` -> the sink receives it once; a letter that still
fails stays in its store; a second replay sends nothing twice. Both stores: the broker's queue
``rabbitros.dead-letter`` and the local spool.

Real parts: a private RabbitMQ node (tests/conftest.py), the engine in process, the command as an
operator runs it."""

from __future__ import annotations

import asyncio
import json
import uuid
from pathlib import Path

import aio_pika
import pytest

from engine.ops.cli import main
from engine.ops.dead_letter_tool import parse_time
from engine.running.dead_letters import DeadLetterSpool, default_spool_dir
from engine.running.runtime import Engine
from tests.support.amqp_helpers import Collector
from tests.support.repo import REPO
from tests.support.waiting import wait_for

ROUTES = """
connections:
  broker: {{amqp: "{url}"}}
{dead_letters}
routes:
  - name: weeds-{tag}
    source: {{amqp: {{exchange: {tag}-in, binding_key: "w.#", queue: {tag}-q}}}}
    mapping: "{{agent_id: {agent_field}, seq: seq, points: detections[].{{lat: lat, lon: lon, p: confidence}}}}"
    schema: weed_detection
    sink: {{amqp: {{exchange: {tag}-out, routing_key: "out.{{agent_id}}"}}}}
  - name: other-{tag}
    source: {{amqp: {{exchange: {tag}-in, binding_key: "o.#", queue: {tag}-o}}}}
    mapping: "{{agent_id: agnt, points: `[]`}}"
    schema: weed_detection
    sink: {{amqp: {{exchange: {tag}-out, routing_key: "other"}}}}
"""


def _body(seq: int, agent: str | None = "uav1") -> bytes:
    body = {"seq": seq, "detections": [{"lat": -22.0, "lon": -47.9, "confidence": 0.9}]}
    if agent is not None:
        body["agent"] = agent
    return json.dumps(body).encode()


@pytest.mark.fast
def test_times_are_iso_or_ago() -> None:
    assert parse_time("30m", now=10_000.0) == 8_200.0 and parse_time("1d", now=100_000.0) == 13_600.0
    assert parse_time("2026-11-27T14:00:00") == parse_time("2026-11-27T14:00:00+00:00")
    with pytest.raises(ValueError, match="not a time"):
        parse_time("yesterday")


@pytest.mark.parametrize("store", ["queue", "spool"])
def test_a_dead_letter_replayed_after_the_route_was_fixed_reaches_the_sink_once(
        tmp_path: Path, amqp_url: str, store: str, capsys: pytest.CaptureFixture[str]) -> None:
    tag = "r" + uuid.uuid4().hex[:8]
    routes = tmp_path / "routes"
    routes.mkdir()
    spool = tmp_path / "spool"
    dead_letters = f"dead_letters: {{spool_dir: {spool}}}" if store == "spool" else "dead_letters: {connection: broker}"
    route_file = routes / "r.yaml"
    route_file.write_text(ROUTES.format(url=amqp_url, tag=tag, dead_letters=dead_letters, agent_field="agnt"))  # misspelt
    cli = ["--routes", str(routes), "--schemas", str(REPO / "schemas")]

    async def dead_letter_them() -> None:
        """3 good messages and 1 without an agent to weeds (all dead-lettered by the misspelt
        mapping), 1 to the other route."""
        engine = Engine(routes, REPO / "schemas")
        await engine.start()
        try:
            connection = await aio_pika.connect(amqp_url)
            async with connection:
                channel = await connection.channel(publisher_confirms=True)
                exchange = await channel.declare_exchange(f"{tag}-in", aio_pika.ExchangeType.TOPIC, durable=True)
                for seq in range(3):
                    await exchange.publish(aio_pika.Message(_body(seq)), "w.x")
                await exchange.publish(aio_pika.Message(_body(3, agent=None)), "w.x")
                await exchange.publish(aio_pika.Message(_body(9)), "o.x")
                await wait_for(lambda: engine.observers.get(f"weeds-{tag}").failed == 4
                               and engine.observers.get(f"other-{tag}").failed == 1, 30, "5 dead letters")
        finally:
            await engine.stop()

    asyncio.run(dead_letter_them())
    assert main(["dead-letters", "list", *cli, "--route", f"weeds-{tag}", "--since", "10m"]) == 0
    listed = capsys.readouterr().out.splitlines()
    assert len(listed) == 4 and all(f"weeds-{tag}  schema  " in line for line in listed), listed
    assert main(["dead-letters", "show", *cli, "--route", f"other-{tag}"]) == 0
    shown = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [(s["route"], s["stage"], json.loads(s["body"])["seq"]) for s in shown] == [(f"other-{tag}", "schema", 9)]
    assert shown[0]["headers"]["x-rabbitros-route-file"].startswith(str(route_file))

    route_file.write_text(ROUTES.format(url=amqp_url, tag=tag, dead_letters=dead_letters, agent_field="agent"))  # fixed

    async def replay_twice() -> tuple[list[int], int, int, str, str]:
        connection = await aio_pika.connect(amqp_url)
        async with connection:
            out = await Collector.bind(await connection.channel(), f"{tag}-out")
            first = await asyncio.to_thread(main, ["dead-letters", "replay", *cli, "--route", f"weeds-{tag}"])
            first_out = capsys.readouterr().out
            await out.wait_for(3, 10)
            second = await asyncio.to_thread(main, ["dead-letters", "replay", *cli, "--route", f"weeds-{tag}"])
            second_out = capsys.readouterr().out
            await asyncio.sleep(0.5)  # quiet window: a second copy would arrive now (none may)
            return sorted(json.loads(m.body)["seq"] for m in out.messages), first, second, first_out, second_out

    received, first, second, first_out, second_out = asyncio.run(replay_twice())
    assert received == [0, 1, 2], received  # each once, through the fixed mapping
    assert first == 1 and "3 sent, 0 filtered, 1 kept" in first_out and "schema: " in first_out, first_out
    assert second == 1 and "0 sent, 0 filtered, 1 kept" in second_out, second_out
    assert main(["dead-letters", "list", *cli, "--route", f"weeds-{tag}", "--route", f"other-{tag}"]) == 0  # what is left
    left = capsys.readouterr().out.splitlines()
    assert sorted(line.split("  ")[2] for line in left) == sorted([f"weeds-{tag}", f"other-{tag}"]), left


@pytest.mark.fast
def test_the_spool_is_listed_while_the_broker_is_unreachable(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    """Dead letters spooled while the broker was down are listed while it still is: the broker's
    queue is said not read (exit 1), the spool's letters are printed."""
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "r.yaml").write_text(ROUTES.format(url="amqp://127.0.0.1:1", tag="t", dead_letters="dead_letters: {connection: broker}",
                                                 agent_field="agnt"))
    DeadLetterSpool(default_spool_dir()).write("weeds-t", [(_body(5), {"x-rabbitros-route": "weeds-t", "x-rabbitros-stage": "schema",
                                                                       "x-rabbitros-error": "agent_id: None is not of type 'string'"})])
    assert main(["dead-letters", "list", "--routes", str(routes), "--schemas", str(REPO / "schemas")]) == 1
    captured = capsys.readouterr()
    assert "weeds-t  schema  agent_id: None is not of type 'string'" in captured.out
    assert "its dead letters are not read; the local spool is" in captured.err


FAN = """
connections:
  broker: {{amqp: "{url}"}}
dead_letters: {{spool_dir: {spool}}}
routes:
  - name: fan-{tag}
    source: {{amqp: {{exchange: {tag}-in, binding_key: "f.#", queue: {tag}-f}}}}
    schema: raw_json
    sinks:
      - name: a
        amqp: {{exchange: {tag}-a, routing_key: "a.{{agent}}"}}
      - name: b
        amqp: {{exchange: {tag}-b, routing_key: "b.{{{b_field}}}"}}
"""


def test_a_dead_letter_of_one_sink_among_several_is_replayed_to_that_sink_only(
        tmp_path: Path, amqp_url: str, capsys: pytest.CaptureFixture[str]) -> None:
    """Sink ``b``'s routing key reads a field the messages lack: ``a`` takes each message, ``b``
    refuses it for good, one dead letter each naming ``b``; the route fixed, ``replay`` sends them
    to ``b`` alone (``a`` has them: no second copy)."""
    tag = "s" + uuid.uuid4().hex[:8]
    routes = tmp_path / "routes"
    routes.mkdir()
    route_file = routes / "r.yaml"
    route_file.write_text(FAN.format(url=amqp_url, tag=tag, spool=tmp_path / "spool", b_field="agnt"))  # misspelt
    cli = ["--routes", str(routes), "--schemas", str(REPO / "schemas")]

    async def scenario() -> tuple[list[int], list[int], int, str]:
        engine = Engine(routes, REPO / "schemas")
        await engine.start()
        connection = await aio_pika.connect(amqp_url)
        async with connection:
            channel = await connection.channel(publisher_confirms=True)
            a = await Collector.bind(channel, f"{tag}-a")
            b = await Collector.bind(channel, f"{tag}-b")
            try:
                exchange = await channel.declare_exchange(f"{tag}-in", aio_pika.ExchangeType.TOPIC, durable=True)
                for seq in range(3):
                    await exchange.publish(aio_pika.Message(_body(seq)), "f.x")
                await wait_for(lambda: engine.observers.get(f"fan-{tag}").failed == 3, 30, "3 dead letters")
                await a.wait_for(3)
            finally:
                await engine.stop()
            assert await asyncio.to_thread(main, ["dead-letters", "show", *cli, "--route", f"fan-{tag}"]) == 0
            shown = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
            assert [(s["stage"], s["headers"]["x-source-sinks_unsent"]) for s in shown] == [("sink", "b")] * 3, shown
            assert all(s["headers"]["x-rabbitros-error"].startswith("sink 'b': ") for s in shown), shown
            route_file.write_text(FAN.format(url=amqp_url, tag=tag, spool=tmp_path / "spool", b_field="agent"))  # fixed
            replayed = await asyncio.to_thread(main, ["dead-letters", "replay", *cli, "--route", f"fan-{tag}"])
            out = capsys.readouterr().out
            await b.wait_for(3, 10)
            await asyncio.sleep(0.5)  # quiet window: a second copy to a would arrive now (none may)
            return (sorted(json.loads(m.body)["seq"] for m in a.messages), sorted(json.loads(m.body)["seq"] for m in b.messages),
                    replayed, out)

    a, b, replayed, out = asyncio.run(scenario())
    assert a == [0, 1, 2] and b == [0, 1, 2], (a, b)  # each once at each sink
    assert replayed == 0 and "3 sent, 0 filtered, 0 kept" in out, out
