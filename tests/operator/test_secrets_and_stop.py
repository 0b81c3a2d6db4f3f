"""Secrets never shown (check, JSON-schema errors, logs, status, dead-letter headers), and a
graceful stop (SIGTERM) that exits 0 and loses nothing, against a real RabbitMQ node with a
password-protected user."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import time
import uuid
from pathlib import Path

import aio_pika
import pytest

from engine.common.logs import JsonFormatter, LogfmtFormatter
from engine.common.redaction import Secret, redact_urls, reveal
from engine.endpoints.amqp.broker import LocalBroker
from tests.support.repo import REPO
from tests.support.engine_process import EngineProcess
from tests.support.amqp_helpers import Collector, message_count
from tests.support.outage_helpers import Tally, publish_reliably, robust
from tests.support.waiting import wait_for

PASSWORD = "S3cret-" + uuid.uuid4().hex[:10]
TOKEN = "tok-" + uuid.uuid4().hex[:10]


def _check(routes: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["timeout", "-s", "KILL", "60", sys.executable, "-m", "engine", "check", "--routes", str(routes),
         "--schemas", str(REPO / "schemas")],
        cwd=REPO, env={**os.environ, **env}, capture_output=True, text=True, timeout=70,
    )


def test_secret_type_never_shows_its_value() -> None:
    secret = Secret(f"amqp://farmer:{PASSWORD}@host:5672/")
    for shown in (str(secret), repr(secret), f"{secret}", "%s" % secret, json.dumps({"u": secret}, default=str)):
        assert PASSWORD not in shown and "***" in shown
    assert reveal(secret) == f"amqp://farmer:{PASSWORD}@host:5672/"
    assert secret == Secret(f"amqp://farmer:{PASSWORD}@host:5672/") and secret != Secret("amqp://farmer:x@host/")
    assert redact_urls(f"failed amqp://u:{PASSWORD}@h/ and amqps://v:w@h2") == "failed amqp://u:***@h/ and amqps://v:***@h2"
    assert Secret(TOKEN, "***").__format__("") == "***"


def test_log_lines_never_carry_a_url_password_whoever_logs_it() -> None:
    """A library (aiormq, aio-pika) may log a URL or an exception naming it."""
    import logging

    try:
        raise ConnectionError(f"cannot reach amqp://farmer:{PASSWORD}@gcs:5672/")
    except ConnectionError:
        import sys as _sys
        record = logging.LogRecord("aiormq", logging.ERROR, __file__, 1, "connect to %s failed", (f"amqp://farmer:{PASSWORD}@gcs/",), _sys.exc_info())
    record.url = Secret(f"amqp://farmer:{PASSWORD}@gcs/")
    for formatter in (LogfmtFormatter(), JsonFormatter()):
        line = formatter.format(record)
        assert PASSWORD not in line and "farmer:***@gcs" in line, line


def test_check_never_prints_a_password_or_a_secret_variable(tmp_path: Path) -> None:
    """The issue's example: a mistyped option beside the URL made the schema error print it."""
    (tmp_path / "a.yaml").write_text(f"""
connections:
  literal: {{amqp: {{url: "amqp://farmer:{PASSWORD}@localhost:5672/", heartbeat: x}}}}
  from_env: {{amqp: {{url: "amqp://farmer:${{RABBITMQ_PASSWORD}}@localhost:5672/", heartbeat: y}}}}
""")
    (tmp_path / "b.yaml").write_text("""
connections:
  token: {amqp: "amqp:/farmer@localhost:5672/?auth=${API_TOKEN}"}
  bad_url: {amqp: {url: "amqp://farmer:${RABBITMQ_PASSWORD}@/"}}
""")
    done = _check(tmp_path, {"RABBITMQ_PASSWORD": PASSWORD, "API_TOKEN": TOKEN})
    output = done.stdout + done.stderr
    assert done.returncode == 1
    assert "is not of type 'string'" in output and "'heartbeat': 'x'" in output, output
    assert output.count("not an amqp:// URL") == 2, output
    assert PASSWORD not in output and TOKEN not in output, output
    assert "amqp://farmer:***@localhost:5672/" in output, output


ROUTES = """
connections:
  gcs: {{amqp: "amqp://farmer:${{RABBITMQ_PASSWORD}}@127.0.0.1:{port}/"}}
routes:
  - name: relay
    source:
      amqp: {{exchange: {inbox}, binding_key: "#", queue: {inbox}-q, prefetch: 64}}
    schema: raw_json
    sink:
      amqp: {{exchange: {outbox}, routing_key: out}}
"""


@pytest.mark.soak
def test_logs_status_and_dead_letters_never_show_the_password_and_sigterm_loses_nothing(tmp_path: Path) -> None:
    """A user with a password; debug logs; a dead letter; the broker killed with -9 while the
    engine runs (reconnect errors are logged); then 3,000 messages with a SIGTERM in the middle
    of them: the engine exits 0, the next engine delivers the rest, none lost."""
    tag = uuid.uuid4().hex[:8]
    names = {"inbox": f"in-{tag}", "outbox": f"out-{tag}"}
    routes = tmp_path / "routes"
    routes.mkdir()
    arrived = Tally("amqp->amqp across SIGTERM")
    expected = range(3_000)
    figures: dict[str, object] = {}

    async def scenario(broker: LocalBroker, env: dict[str, str]) -> list[EngineProcess]:
        url = f"amqp://farmer:{PASSWORD}@127.0.0.1:{broker.port}/"
        engines = [EngineProcess(routes, tmp_path / "first.json", env, "--log-level", "debug", "--drain-timeout", "5")]
        connection = await robust(url)
        try:
            await Collector.bind(await connection.channel(), names["outbox"], queue=f"collect-{tag}", ack=True, tally=arrived, prefetch=500)
            await asyncio.to_thread(engines[0].wait_started)
            channel = await connection.channel()
            inbox = await channel.declare_exchange(names["inbox"], aio_pika.ExchangeType.TOPIC, durable=True)
            await inbox.publish(aio_pika.Message(b"{not json"), "bad")
            dead = await channel.declare_queue("rabbitros.dead-letter", passive=True)
            letter = await wait_for(lambda: dead.get(no_ack=True, fail=False), 30, "the dead letter of '{not json'")
            figures["dead_letter_headers"] = json.dumps(dict(letter.headers), default=str)

            broker.kill()
            await wait_for(lambda: not (engines[0].status() or {}).get("connections", {}).get("gcs", {}).get("healthy", True),
                           30, "the engine to see the broker down")
            await asyncio.sleep(2.0)  # outage: the broker stays down 2 s, a few reconnection attempts logged
            await asyncio.to_thread(broker.start)
            await wait_for(lambda: (engines[0].status() or {}).get("connections", {}).get("gcs", {}).get("healthy", False),
                           60, "the engine to reconnect")

            publishing = asyncio.create_task(publish_reliably(connection, names["inbox"], "m", expected, 1000.0, arrived))
            await wait_for(lambda: arrived.delivered >= 1_000, 60, "1,000 delivered")
            began = time.monotonic()
            figures["first_exit"] = await asyncio.to_thread(engines[0].stop)
            figures["stop_s"] = time.monotonic() - began
            await publishing
            engines.append(EngineProcess(routes, tmp_path / "second.json", env))
            await asyncio.to_thread(engines[1].wait_started)
            await wait_for(lambda: not arrived.lost(expected), 60, "every message")
            figures["second_exit"] = await asyncio.to_thread(engines[1].stop)
        finally:
            await connection.close()
            for engine in engines:
                engine.stop()
        return engines

    broker = LocalBroker()
    try:
        broker.start()
        broker.ctl("add_user", "farmer", PASSWORD)
        broker.ctl("set_permissions", "-p", "/", "farmer", ".*", ".*", ".*")
        (routes / "relay.yaml").write_text(ROUTES.format(port=broker.port, **names))
        env = {"RABBITMQ_PASSWORD": PASSWORD}
        engines = asyncio.run(scenario(broker, env))
    finally:
        broker.stop()
    print(f"\n{arrived.figures(expected)}; SIGTERM took {figures['stop_s']:.2f}s")
    logs = "".join(engine.log_file.read_text() for engine in engines)
    statuses = "".join(engine.status_file.read_text() for engine in engines)
    assert "reconnect" in logs.lower() or "connection" in logs.lower()
    assert PASSWORD not in logs and PASSWORD not in statuses
    assert PASSWORD not in str(figures["dead_letter_headers"])
    assert "decode" in str(figures["dead_letter_headers"])
    assert figures["first_exit"] == 0 and figures["second_exit"] == 0
    assert not arrived.lost(expected)


DRAIN_ROUTES = """
connections:
  src: {{amqp: "{source_url}"}}
  dst: {{amqp: "{sink_url}"}}
dead_letters: {{connection: src}}
routes:
  - name: relay
    source:
      amqp: {{connection: src, exchange: {inbox}, binding_key: "#", queue: {inbox}-q, prefetch: 100}}
    schema: raw_json
    sink:
      amqp: {{connection: dst, exchange: out}}
"""


@pytest.mark.soak
def test_sigterm_with_the_sink_down_exits_0_within_the_drain_timeout_and_requeues(tmp_path: Path, amqp_url: str) -> None:
    """The sink's broker is killed; 500 messages wait in the source queue and the engine's
    prefetch; SIGTERM with --drain-timeout 2: exit 0 in about the drain timeout, and all 500
    are back in the source queue (nothing acked that was not delivered, nothing lost)."""
    tag = uuid.uuid4().hex[:8]
    inbox = f"drain-{tag}"
    routes = tmp_path / "routes"
    routes.mkdir()
    sink_broker = LocalBroker()
    figures: dict[str, float] = {}

    async def scenario() -> int:
        engine = EngineProcess(routes, tmp_path / "status.json", {}, "--drain-timeout", "2")
        connection = await aio_pika.connect(amqp_url)
        try:
            await asyncio.to_thread(engine.wait_started)
            sink_broker.kill()
            await wait_for(lambda: not (engine.status() or {}).get("connections", {}).get("dst", {}).get("healthy", True),
                           30, "the sink's connection to be down")
            channel = await connection.channel()
            await publish_reliably(connection, inbox, "m", range(500), 5000.0, Tally("published"))
            await wait_for(lambda: (engine.status() or {}).get("routes", {}).get("relay", {}).get("received", 0) >= 1,
                           30, "the engine to take its prefetch")
            began = time.monotonic()
            code = await asyncio.to_thread(engine.stop)
            figures["stop_s"] = time.monotonic() - began

            async def all_requeued() -> bool:
                queue = await channel.declare_queue(f"{inbox}-q", passive=True)
                figures["requeued"] = message_count(queue)
                return figures["requeued"] == 500

            await wait_for(all_requeued, 30, "all 500 back in the source queue", detail=lambda: figures.get("requeued"))
            return code
        finally:
            await connection.close()
            engine.stop()

    try:
        sink_broker.start()
        (routes / "relay.yaml").write_text(DRAIN_ROUTES.format(source_url=amqp_url, sink_url=sink_broker.url, inbox=inbox))
        code = asyncio.run(scenario())
    finally:
        sink_broker.stop()
    print(f"\nSIGTERM with the sink down: exit {code} after {figures['stop_s']:.2f}s, {figures['requeued']:.0f}/500 back in the queue")
    assert code == 0
    assert figures["stop_s"] < 2 + 2 + 6, "the drain timeout bounds the stop"
    assert figures["requeued"] == 500
