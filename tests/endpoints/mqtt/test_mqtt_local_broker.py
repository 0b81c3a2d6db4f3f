"""``run --local-broker`` asks each protocol for its private broker: routes with an MQTT
connection that names no url get a private mosquitto (its own port and data directory), which
stops with the engine; the AMQP node starts as always."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import ssl
import subprocess
import sys
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import aiomqtt
from tests.support.repo import REPO
from tests.support.waiting import wait_for_sync

ROUTES = """
routes:
  - {name: relay, source: {mqtt: {topic: "farm/+/weather", qos: 1}}, schema: raw_json, sink: {mqtt: {topic: farm/weather, qos: 1}}}
"""


def start_engine(tmp_path: Path, routes_text: str, env: dict[str, str], *flags: str) -> tuple[subprocess.Popen[str], list[str]]:
    """``rabbitros-engine --local-broker FLAGS`` on ``routes_text``, waited for until it writes
    its status; the process and the brokers' URLs from its URL file."""
    url_file, status_file, routes = tmp_path / "broker-url", tmp_path / "status.json", tmp_path / "routes"
    routes.mkdir()
    (routes / "field.yaml").write_text(routes_text)
    process = subprocess.Popen(
        ["timeout", "-s", "KILL", "180", sys.executable, "-m", "engine", "--routes", str(routes), "--schemas", "schemas",
         "--local-broker", *flags, "--broker-url-file", str(url_file), "--status-file", str(status_file),
         "--log-format", "json"],
        cwd=REPO, stderr=subprocess.PIPE, text=True, start_new_session=True, env={**env, "PYTHONPATH": str(REPO)},
    )
    wait_for_sync(lambda: status_file.exists() or process.poll() is not None, 120, "the engine to start or exit")
    if not status_file.exists():
        os.killpg(process.pid, signal.SIGKILL)
        raise AssertionError("engine did not start")
    return process, url_file.read_text().split()


def local_broker_started(process: subprocess.Popen[str]) -> dict[str, Any]:
    """The engine's ``local broker started`` log line (read from its stderr as it runs)."""
    assert process.stderr is not None, "the engine's stderr is a pipe"
    while process.poll() is None:
        line = process.stderr.readline()
        if line.startswith("{") and json.loads(line)["msg"] == "local broker started":
            return json.loads(line)
    raise AssertionError("no 'local broker started' line")


async def weather_through_the_engine(host: str, port: int, tls_context: ssl.SSLContext | None = None) -> bytes:
    """Publish a station's weather until the engine's route has carried one to ``farm/weather``
    (it subscribes once its connection is up), and return what arrived there."""
    async with aiomqtt.Client(host, port, identifier="test-reader", tls_context=tls_context) as reader:
        await reader.subscribe("farm/weather", qos=1)
        async with aiomqtt.Client(host, port, identifier="test-writer", tls_context=tls_context) as writer:
            async def publish_until_answered() -> None:
                while True:
                    await writer.publish("farm/station1/weather", b'{"t": 21.5}', qos=1)
                    await asyncio.sleep(0.5)  # pacing: one message each 0.5 s until the engine answers
            publishing = asyncio.create_task(publish_until_answered())
            try:
                async with asyncio.timeout(30):
                    async for message in reader.messages:
                        return bytes(message.payload)
            finally:
                publishing.cancel()
    raise AssertionError("no message")


def test_run_local_broker_starts_a_private_mosquitto_for_an_mqtt_connection_without_url(tmp_path: Path):
    env = {k: v for k, v in os.environ.items() if k not in ("RABBITROS_MQTT_URL", "RABBITROS_AMQP_URL")}
    process, urls = start_engine(tmp_path, ROUTES, env)
    try:
        mqtt_url = next(url for url in urls if url.startswith("mqtt://"))
        host, port = urlsplit(mqtt_url).hostname, urlsplit(mqtt_url).port
        assert host is not None and port is not None, f"the URL names a host and a port: {mqtt_url}"
        assert port != 1883  # its own port, not a system broker's
        started = local_broker_started(process)
        assert any("mosquitto" in node for node in started["nodes"]), started

        assert json.loads(asyncio.run(weather_through_the_engine(host, port))) == {"t": 21.5}
        process.send_signal(signal.SIGTERM)
        _, stderr = process.communicate(timeout=60)
        assert process.returncode == 0, stderr
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    with socket.socket() as probe:
        assert probe.connect_ex((host, port)) != 0, "the private mosquitto outlived the engine"


TLS_ROUTES = """
connections:
  field: {mqtt: {client_id: tls-engine}}      # no url: the private broker, over mqtts://
routes:
  - {name: relay, source: {mqtt: {topic: "farm/+/weather", qos: 1}}, schema: raw_json, sink: {mqtt: {topic: farm/weather, qos: 1}}}
"""


def test_run_local_broker_tls_gives_a_private_mosquitto_with_a_tls_listener(tmp_path: Path):
    """``--local-broker --local-broker-tls`` with a named MQTT connection without url: the URL
    file names mqtts://localhost:PORT, a plain MQTT client cannot talk to that port, a client
    without the run's CA is refused, and one verifying it gets its message carried by a route
    (the engine connected over TLS, verifying the same CA)."""

    env = {k: v for k, v in os.environ.items() if not k.startswith("RABBITROS_")}
    process, urls = start_engine(tmp_path, TLS_ROUTES, env, "--local-broker-tls")
    status_file = tmp_path / "status.json"
    try:
        mqtt_url = next(url for url in urls if url.startswith("mqtt"))
        assert mqtt_url.startswith("mqtts://localhost:"), mqtt_url
        port = urlsplit(mqtt_url).port
        assert port is not None, f"the URL names a port: {mqtt_url}"
        started = local_broker_started(process)
        ca_file = Path(started["environment"]["RABBITROS_MQTT_CA_FILE"])
        verified = ssl.create_default_context(cafile=str(ca_file))

        async def roundtrip() -> bytes:
            try:  # a CONNECT in plain MQTT is no TLS ClientHello: no CONNACK
                async with aiomqtt.Client("localhost", port, identifier="plain", timeout=5):
                    raise AssertionError("a plain MQTT client talked to the TLS port")
            except aiomqtt.MqttError:
                pass
            try:  # the system's CAs do not know the run's throwaway CA
                async with aiomqtt.Client("localhost", port, identifier="unverified", timeout=5,
                                          tls_context=ssl.create_default_context()):
                    raise AssertionError("a client without the run's CA trusted the broker")
            except aiomqtt.MqttError:
                pass
            return await weather_through_the_engine("localhost", port, tls_context=verified)

        assert json.loads(asyncio.run(roundtrip())) == {"t": 21.5}
        status = json.loads(status_file.read_text())
        assert status["connections"]["field"]["healthy"], status["connections"]
        process.send_signal(signal.SIGTERM)
        _, stderr = process.communicate(timeout=60)
        assert process.returncode == 0, stderr
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    assert not ca_file.exists(), "the throwaway CA outlived the private mosquitto"
